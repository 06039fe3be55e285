"""Where an export of a log may be written: the checks every export to another tool's file makes
before it writes a byte (Foxglove, ROS 2, Rerun)."""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import LogError


def export_path(log_path: str | os.PathLike, out: str | os.PathLike, overwrite: bool) -> Path:
    """``out`` as a path an export may write: a file name, not a folder, not the log itself, not
    a file that exists unless ``overwrite``, never a device or FIFO (it would be replaced by a
    file, /dev/null for root); a LogError that says which, and what to do."""
    out = Path(out)
    if not out.name or out.is_dir():
        raise LogError(f"{str(out) or repr('')} is a folder, not a file", "give the export a file name: -o view.mcap")
    if out.exists() and not overwrite:
        raise LogError(f"{out} exists", "pass --force (overwrite=True) to replace it")
    if out.exists() and not out.is_file():  # an export is written aside, then renamed over it
        raise LogError(f"{out} is no regular file (a device, a FIFO or a socket): an export would replace it",
                       "write the export to a file")
    if out.resolve() == Path(log_path).resolve() or (out.exists() and os.path.samefile(out, log_path)):
        raise LogError(f"{out} is the log being exported", "write the export to another file")
    return out
