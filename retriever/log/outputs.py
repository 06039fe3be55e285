"""Where an export of a log may be written: the checks every export to another tool's file makes
before it writes a byte (Foxglove, ROS 2, Rerun)."""

from __future__ import annotations

import errno
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
    if sys.stdout is None or not _fd_open(1):  # `>&-`: Python leaves sys.stdout None
        raise LogError("standard output is closed",
                       f"pipe it into a program ({PIPED[format]}), redirect it (> FILE) or give a path: -o FILE")
    if sys.stdout.isatty():
        raise LogError(f"-o - writes the {format} export to standard output, which is a terminal",
                       f"pipe it into a program ({PIPED[format]}), redirect it (> FILE) or give a path: -o FILE")
    return sys.stdout.buffer


def _fd_open(fd: int) -> bool:
    try:
        os.fstat(fd)
    except OSError:
        return False
    return True


#: bytes an export wrote to standard output in this process (a :class:`CountedStream` on it), or
#: None if none did, and those of the write under way: what an export stopped half-way says it
#: left there
_stdout = {"written": None, "under_way": 0}


def stdout_written() -> tuple[int, int] | None:
    """``(at least, at most)`` bytes exports wrote to standard output in this process, None if
    none wrote there through a :class:`CountedStream` (Rerun's SDK writes it itself: unknown).
    The two differ only when a signal stopped it during a write, which may have gone out in part
    (a write is counted when it returns; the signal may come just before)."""
    if _stdout["written"] is None:
        return None
    return _stdout["written"], _stdout["written"] + _stdout["under_way"]


def stdout_reader_gone() -> bool:
    """Whether standard output is a pipe whose reader went away (``| head`` had enough): what a
    writer that does not say EPIPE itself (Rerun's SDK: its file writer's thread "shut down
    prematurely") failed of."""
    import select

    poll = select.poll()
    poll.register(1, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poll.poll(0))


def abandon_stdout() -> None:
    """Point file descriptor 1 at /dev/null: after a write to it failed (a reader gone, a disk
    full), so that what Python still holds for it is not tried again at exit, which would print
    a second error."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
    finally:
        os.close(devnull)


class CountedStream:
    """Standard output for a writer (mcap's) that asks where it is (``tell``), written front to
    back straight to its file descriptor (no buffer left to flush at exit, after an error or a
    Ctrl-C), each byte counted once it is out (``stdout_written``). A reader that went away
    (``| head``) is the BrokenPipeError it is (a command exits quietly on it, as Unix tools do);
    any other failure (a full disk: ``> /dev/full``) is a LogError saying so."""

    def __init__(self, stream):
        stream.flush()
        self._fd, self._written = stream.fileno(), 0
        _stdout["written"] = _stdout["written"] or 0

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        while view:
            _stdout["under_way"] = len(view)  # set before: a count that missed a write is said as a range
            try:
                done = os.write(self._fd, view)
            except BrokenPipeError:
                raise
            except OSError as e:
                trouble = "is full" if e.errno == errno.ENOSPC else "failed"
                raise LogError(f"standard output {trouble}: {e.strerror or e} ({self._written} bytes were written "
                               "before; not a whole export)", "write the export to a file with room: -o FILE") from None
            _stdout["written"] += done
            self._written += done
            view = view[done:]
        _stdout["under_way"] = 0
        return len(data)

    def tell(self) -> int:
        return self._written

    def flush(self) -> None:
        pass  # nothing is held


def export_path(log_path: str | os.PathLike, out: str | os.PathLike, overwrite: bool) -> Path:
    """``out`` as a path an export may write: a file name, not a folder, not the log itself, not
    a file that exists unless ``overwrite``, never a device or FIFO (it would be replaced by a
    file, /dev/null for root); a LogError that says which, and what to do."""
    if to_stdout(out):  # the exports that may, take "-" before (stdout_stream)
        raise LogError("this export cannot be written to standard output (-o -)", "give it a path: -o FILE")
    text, out = os.fspath(out), Path(out)
    if not out.name or out.is_dir() or text.endswith(("/", os.sep)):  # (Path drops a trailing /: "bag/" names a folder)
        raise LogError(f"{text or repr('')} is a folder, not a file", "give the export a file name: -o view.mcap")
    if out.exists() and not overwrite:
        raise LogError(f"{out} exists", "pass --force (overwrite=True) to replace it")
    if out.exists() and not out.is_file():  # an export is written aside, then renamed over it
        raise LogError(f"{out} is no regular file (a device, a FIFO or a socket): an export would replace it",
                       "write the export to a file")
    if out.resolve() == Path(log_path).resolve() or (out.exists() and os.path.samefile(out, log_path)):
        raise LogError(f"{out} is the log being exported", "write the export to another file")
    return out
