"""Private folders named by the process that made them, and the reaping of those it left behind.

A run's folder (the coordinator's ``retriever-run-PID-…``, in /dev/shm when there is one) and a
worker daemon's (``retriever-worker-PID-…``, its runs' ``retriever-worker-PID-run-…``) hold the
passwords of Zenoh sessions (mode 0700). Their process removes them when it ends; a SIGKILLed one
cannot, so whoever makes a folder of that kind next first removes this user's folders of the
kind whose process is gone.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

#: the kinds of folder: a run's (its coordinator's process), a worker daemon's and its runs'
RUN_FOLDER = "retriever-run"
DAEMON_FOLDER = "retriever-worker"
#: the dora backend's folder for dora's own files (its dataflow, its logs), on disk
DORA_FOLDER = "retriever-dora"


def private_folder(kind: str, base: str | None = None) -> Path:
    """A new folder ``KIND-PID-…`` in ``base`` (the temporary folder if None) that only this
    user may enter (mode 0700), after the stale ones of its kind there were reaped."""
    reap_stale(kind, base)
    return Path(tempfile.mkdtemp(prefix=f"{kind}-{os.getpid()}-", dir=base))


def reap_stale(kind: str, base: str | None = None) -> list[Path]:
    """Remove this user's ``KIND-PID-…`` folders in ``base`` whose process ``PID`` is gone;
    those removed. A folder of a live process, of another user, or without a pid is kept."""
    removed = []
    for folder in Path(base or tempfile.gettempdir()).glob(f"{kind}-*-*"):
        pid = folder.name[len(kind) + 1:].split("-")[0]
        try:
            if not pid.isdigit() or folder.lstat().st_uid != os.getuid() or not folder.is_dir():
                continue
            os.kill(int(pid), 0)  # raises if no such process
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
        except OSError:  # another user's process (EPERM), or the folder went meanwhile
            continue
    return removed
