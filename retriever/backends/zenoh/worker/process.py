"""A worker's OS process: the parent whose end is its end, its settings, and its exit.

A worker process dies with its parent (PARENT_DIED), and a thread watches that parent
(watch_parent) to exit within ORPHAN_GRACE_S once it is gone, removing the run's folders no
one else will; its exit codes say how its node ended (the package's docstring).
"""

from __future__ import annotations

import ctypes
import faulthandler
import gc
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from ..command import FIRST, StartMode
from ..hub import await_segments_released

#: The signal a worker gets when the thread that started it dies (PR_SET_PDEATHSIG): its own, not
#: SIGTERM, which a coordinator or daemon sends to stop a worker that goes on finishing. Told
#: apart, a worker whose parent was SIGKILLed ends without a word, whatever ``_orphaned`` sees:
#: a parent's threads die one by one, and the one that started it may be gone while
#: /proc still shows the process alive (a daemon's worker then said "done" with a final
#: frontier, and its consumer finished before the node's restart elsewhere could reach it).
PARENT_DIED = signal.SIGUSR2


def _die_with_parent() -> None:
    """Linux: PARENT_DIED to this process when its parent dies, so no worker outlives its run."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, PARENT_DIED)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


#: after its coordinator died, a worker's loop has this long to stop by itself (SIGTERM asks it
#: to), then the process exits anyway: a flow stuck in its step never looks at the request
ORPHAN_GRACE_S = 3.0


@dataclass(frozen=True)
class Parent:
    """The process whose end is this worker's end: the one that started it (a coordinator, a
    worker daemon), or, ``adopted``, a coordinator that is not its parent (dora's nodes are
    dora's children): no kernel tells an adopted worker that its coordinator died, so it tells
    itself, as the kernel would (PARENT_DIED)."""

    pid: int
    adopted: bool = False

    def gone(self, stat: int | None = None) -> bool:
        """Whether it is dead or dying. Its main thread's exit sends PR_SET_PDEATHSIG, and may
        leave its other threads, and our ppid, for a moment longer: the main thread's state (that
        of /proc/<pid>) is then already Z. ``stat``: a descriptor of that file, opened while the
        parent lived (it then names that process, whatever process gets its pid later: a read
        fails once it is gone)."""
        if not self.adopted and os.getppid() != self.pid:
            return True
        try:
            if stat is None:
                text = Path(f"/proc/{self.pid}/stat").read_bytes()
            else:
                text = os.pread(stat, 4096, 0)
        except OSError:
            return True
        return chr(text[text.rindex(b")") + 2]) in "ZX"


@dataclass
class Launch:
    """How this worker process was started, and what its starter hands it: the command line
    (worker.main), or dora's node module (backends/dora/node.py)."""

    spec_path: Path
    node: str
    parent: Parent
    #: the key it signs its statuses and reports with (origin.py); None: it signs nothing
    key: bytes | None
    mode: StartMode = FIRST
    #: ``(session, node) -> Transport``: how a node's events travel (dora's: backends/dora/link.py);
    #: None: on the process's Zenoh session (node/transport.py, ZenohTransport)
    transport: Callable | None = None
    #: folders of the run besides its run directory, removed with it once the parent is gone
    folders: tuple[Path, ...] = ()

    @property
    def run_dir(self) -> Path:
        return self.spec_path.parent

    def remove_folders(self) -> None:
        """Remove the run's folders, which no one else will once its coordinator is gone."""
        if self.run_dir.name.startswith("retriever-run-"):
            for folder in self.folders:
                shutil.rmtree(folder, ignore_errors=True)
            shutil.rmtree(self.run_dir, ignore_errors=True)


def watch_parent(launch: Launch) -> None:
    """Watch the parent from a thread of its own, from now on (:func:`_watch_parent`)."""
    threading.Thread(target=_watch_parent, args=(launch,), name="retriever-watch-parent", daemon=True).start()


def _watch_parent(launch: Launch) -> None:
    """Once the parent is gone, exit within ORPHAN_GRACE_S, with every thread's stack on
    stderr, even when the step never returns (faulthandler's timer needs no GIL); and remove the
    run's folders, which no one else will."""
    parent = launch.parent
    try:  # read through one descriptor: a pread a look (an idle worker's thread wakes twice a second)
        stat = os.open(f"/proc/{parent.pid}/stat", os.O_RDONLY)
    except OSError:
        stat = None
    while not parent.gone(stat):
        time.sleep(0.5)
    faulthandler.dump_traceback_later(ORPHAN_GRACE_S, exit=True)
    launch.remove_folders()
    if parent.adopted:
        os.kill(os.getpid(), PARENT_DIED)


def _keep_freed_memory() -> None:
    """glibc: serve blocks up to 32 MiB from the heap and keep freed memory mapped. A worker
    allocates and frees a message-sized buffer per event; by default glibc returns big blocks to
    the kernel at once, so every event paid a page fault per 4 KiB again (a 16 MiB frame: 4096
    faults, which cost more than the copy itself)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD (the most glibc allows)
        libc.mallopt(-1, 512 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def prepare_process() -> bool:
    """This process's settings, before anything else; False when its parent is already gone."""
    _die_with_parent()
    _keep_freed_memory()
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # `kill -USR1 PID`: where is a stuck worker?
    sys.stdout.reconfigure(line_buffering=True)  # a pipe to the coordinator: a flow's print shows at once
    if os.getppid() == 1:
        return False
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the coordinator, which stops us
    return True


def exit_process(code: int) -> NoReturn:
    """End this process with ``code``, as Python ends: ``atexit`` functions, then the C library's
    exit handlers, in which Zenoh removes the shared-memory segments this process was the last to
    map. Collecting what a flow held (a torch model, object by object) may take seconds: a worker
    that said ``done`` has the coordinator's REAP_GRACE_S for it, not the stop grace of a stuck one."""
    sys.exit(code)


def let_go_of(pool: set[str]) -> None:
    """Once the session closed, until Zenoh let go of the shared-memory pool it made (``pool``:
    its /dev/shm segments), at most hub.SEGMENT_RELEASE_S: Zenoh unlinks a segment when the last
    process that maps it lets go, and the exit handlers skip a segment this process still maps.
    The loop, which holds the session, goes first: the signal handlers held it (a stop has
    nothing left to stop: the process ends)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(PARENT_DIED, signal.SIG_IGN)
    if pool:
        gc.collect()  # the loop's cycles (its threads, callbacks) hold the session too
        await_segments_released(pool)


PR_SET_TIMERSLACK = 29  # <linux/prctl.h>


def no_timer_slack() -> None:
    """Let this thread's timed waits end on time: Linux may end each one up to its timer slack
    late (50 µs unless set) to wake threads together; the loop waits for ticks, so it asks for
    1 ns (benchmarks/control_jitter.py measures a tick's lateness). Per thread: call it
    on the thread that runs the loop. Elsewhere than Linux, or if refused, nothing changes."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None).prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass
