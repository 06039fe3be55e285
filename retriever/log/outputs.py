"""Where an export of a log may be written: the checks every export to another tool's file makes
before it writes a byte (Foxglove, ROS 2, Rerun)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..errors import LogError


#: ``-o -``: the export on standard output, for a pipe (``| rerun -``); only where the format is
#: written front to back, and never onto a terminal
STDOUT = "-"
#: what writes onto standard output, and why the others do not
STREAMED_FORMATS = ("ros2", "rerun")
PIPED = {"ros2": "| mcap info /dev/stdin", "rerun": "| rerun -"}  # what a pipe into the terminal's user may run
NOT_STREAMED = {
    "foxglove": "Foxglove's SDK writes its MCAP only to a file it opens by name",
    "lerobot": "a dataset is a folder of files",
    "npz": "a dataset is a folder of files",
}


def to_stdout(out: str | os.PathLike) -> bool:
    """Whether ``out`` asks for standard output (``-``)."""
    return os.fspath(out) == STDOUT


def stdout_stream(format: str):
    """Standard output as the binary stream an export of ``format`` writes to, or a LogError:
    for a format not written front to back (NOT_STREAMED), or a terminal (binary is no text)."""
    if format not in STREAMED_FORMATS:
        raise LogError(f"--format {format} cannot be written to standard output (-o -): {NOT_STREAMED[format]}",
                       "give it a path: -o FILE")
    if sys.stdout.isatty():
        raise LogError(f"-o - writes the {format} export to standard output, which is a terminal",
                       f"pipe it into a program ({PIPED[format]}), redirect it (> FILE) or give a path: -o FILE")
    return sys.stdout.buffer


class CountedStream:
    """A stream written front to back that says how much it took (``tell``): a pipe, for a
    writer (mcap's) that asks where it is."""

    def __init__(self, stream):
        self._stream, self._written = stream, 0

    def write(self, data) -> int:
        self._stream.write(data)
        self._written += len(data)
        return len(data)

    def tell(self) -> int:
        return self._written

    def flush(self) -> None:
        self._stream.flush()


def export_path(log_path: str | os.PathLike, out: str | os.PathLike, overwrite: bool) -> Path:
    """``out`` as a path an export may write: a file name, not a folder, not the log itself, not
    a file that exists unless ``overwrite``, never a device or FIFO (it would be replaced by a
    file, /dev/null for root); a LogError that says which, and what to do."""
    if to_stdout(out):  # the exports that may, take "-" before (stdout_stream)
        raise LogError("this export cannot be written to standard output (-o -)", "give it a path: -o FILE")
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
