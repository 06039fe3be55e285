"""``pipe.run(..., rerun=TARGET)``, ``retriever run|deploy --rerun [TARGET]``: a running
pipeline shown live in the Rerun viewer, from the coordinating process, as the log's Rerun export
shows it afterwards (log/rerun.py's writer: the same entities, archetypes and timelines).

TARGET is the gRPC URL of a running viewer (``rerun+http://HOST:PORT/proxy``; by default the
local viewer that ``rerun`` starts) or a path ending in ``.rrd``, where the stream is saved as it
goes (a file that ``rerun FILE.rrd`` opens, during the run or after it). Nothing else: a folder
is no target (the view writes no file of its own naming into one), nor a path whose folder does
not exist, nor a file that exists; :func:`check_target` says so before the run starts (the
backends and the command call it before any worker starts or the pipeline is loaded).

A viewer that stops taking the stream (frozen, suspended, on a slow machine or link) must not
grow the run's process without bound: Rerun's SDK (0.26) queues what it is handed without bound
and has no knob to bound it. The view knows how far its sink is behind (:class:`SinkWatch`: a
thread of its own flushes the stream, with a timeout, and counts what the last flush that
completed took) and, while more than BEHIND_BYTES is not known taken, drops what it is handed:
large values (frames) first, then, past SMALL_BYTES more, numbers and step records too. What it
dropped is counted and said (a warning when it starts, the count at the run's end); the log keeps
everything. A viewer that goes away (killed, closed) stops the view with a warning.

A viewer that takes nothing (suspended) holds the SDK's disconnect, and its at-exit shutdown,
which disconnects every stream of the process, for as long: the view's close gives up after
CLOSE_S and says so, and :func:`skip_rerun_shutdown_if_stuck` lets the process's owner (the
command line) exit without that shutdown. A library user's process keeps it.
"""

from __future__ import annotations

import os
import socket
import threading
import warnings
from collections import Counter
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from ..errors import LogError, RetrieverWarning, ViewDroppedWarning
from ..trace import NOT_KEPT, StepRecord
from .rerun import RECORD_BYTES, RERUN_VIEWER_URL, RerunRecording, event_time_blueprint, new_stream, rerun_sdk
from .views import value_leaves

TARGET_HINT = f"give a Rerun gRPC URL (default {RERUN_VIEWER_URL}) or a path ending in .rrd"
#: the schemes of the URLs Rerun's SDK connects to
URL_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")
#: how long a viewer's port may take to accept a TCP connection before the run is refused
VIEWER_CONNECT_TIMEOUT_S = 1.0
#: the live view's stream is flushed by Rerun's SDK's tick, every LIVE_FLUSH_S seconds, and by an
#: entity's bytes only past LIVE_FLUSH_BYTES (a tick's worth of 1.3 GB/s of frames). The SDK's
#: default, 1 MiB, flushed a camera of big frames for its bytes several times a tick, and the SDK
#: skips its tick whenever an entity did since the last: the numbers and step records beside it
#: reached the viewer only in 1 MiB lumps, seconds to minutes late (benchmarks/reports/export_memory.md).
#: A flush of our own (``stream.flush(timeout_sec=0)``) would also flush the sink, which logs an
#: error on stderr each time once a viewer is gone
LIVE_FLUSH_S = 0.1
LIVE_FLUSH_BYTES = 128 << 20
#: while more than this (in bytes of values, a row counting RECORD_BYTES more: what the SDK holds
#: of it, log/rerun.py) was handed to the SDK and not yet taken by its sink, the view drops large
#: values. 64 MiB is a few seconds of a camera (9 s of 30 Hz 320x240 RGB, 2.4 s of VGA) for a
#: viewer that stalls for a moment (a window dragged, a GC pause, a busy machine) before it
#: drops a frame, and what the process grows by (the SDK holds 1.6-1.7 bytes a byte handed,
#: benchmarks/reports/export_memory.md) stays about 110 MB however long the viewer stalls
BEHIND_BYTES = 64 << 20
#: a value of at most this many bytes (a number, a short array or text) is small: past
#: BEHIND_BYTES small values and step records are still sent (the viewer's plots and step logs
#: go on while frames are dropped), until SMALL_BYTES more (4,096 rows) are behind too
SMALL_VALUE_BYTES = 1024
SMALL_BYTES = 16 << 20
#: how long the view's watch waits for one flush of the stream before it starts the next (a
#: flush that times out says the sink is behind; the next one waits for all before it), twice as
#: long each time it times out, up to WATCH_FLUSH_MAX_S: each flush is a command the SDK holds
#: until its sink takes what came before, and says an error for on stderr if the sink dies first
WATCH_FLUSH_S = 0.5
WATCH_FLUSH_MAX_S = 4.0
#: how long closing the view waits for its sink to take what is left, then to disconnect
CLOSE_S = 5.0
#: the start of the error Rerun's SDK (0.26.2) raises when a flush's timeout passes: a
#: RuntimeError as for a sink that failed (both are its SinkFlushError, told apart in Python by
#: the text only: SinkFlushError::Timeout's message, crates/top/re_sdk/src/log_sink.rs), pinned by
#: tests/backends/zenoh/test_rerun_live.py
FLUSH_TIMED_OUT = "Flush timed out"
#: how to have a viewer listen where a URL points
START_VIEWER_HINT = (f"start a viewer first: `rerun` (the desktop viewer, listening on {RERUN_VIEWER_URL}), or "
                     "`rerun --serve-web` (a web viewer, its gRPC port the same); `--port PORT` for another port; "
                     "or give a path ending in .rrd to save the stream to a file")


def is_rrd_path(target: str | os.PathLike) -> bool:
    """Whether ``target`` names a file to save the stream to rather than a viewer's URL."""
    return isinstance(target, os.PathLike) or str(target).lower().endswith(".rrd")


def check_target(target: str | os.PathLike) -> None:
    """A LogError unless ``target`` is the URL of a viewer that listens (:func:`check_viewer`) or
    a new file's path in a folder that exists (what can be told without the SDK): said before a
    run starts, with the forms a target takes."""
    if not isinstance(target, (str, os.PathLike)) or isinstance(target, bytes):
        refuse_target_type(target)
    text = str(target)
    if not is_rrd_path(target) and text.lower().startswith(URL_SCHEMES):
        check_viewer(text)
        return
    path = Path(target)
    folder = path.parent if str(path.parent) != "" else Path(".")
    either = f"or a running viewer's URL ({RERUN_VIEWER_URL})"
    if text == "":  # Path("") is ".": a folder, which it was not given as
        raise LogError("cannot stream the run to Rerun at '': it is empty",
                       f"give a path ending in .rrd, the file to save the stream to (live.rrd), {either}")
    if path.is_dir():
        raise LogError(f"cannot stream the run to Rerun at {text}: it is a folder",
                       f"give a path ending in .rrd, the file to save the stream to ({path / 'live.rrd'}), {either}")
    if not is_rrd_path(target):
        raise LogError(f"cannot stream the run to Rerun at {text}: it is neither a Rerun viewer's URL "
                       f"({', '.join(s + '…' for s in URL_SCHEMES)}) nor a path ending in .rrd", TARGET_HINT)
    if os.path.lexists(path):  # never over a file: it may be this run's log, or another's
        raise LogError(f"cannot stream the run to Rerun at {text}: the file exists; a live view never replaces a file",
                       "give a new path (none that exists: remove it first) in a folder you may write to")
    if not folder.is_dir():
        why = "is not a folder" if folder.exists() else "does not exist"
        raise LogError(f"cannot stream the run to Rerun at {text}: its folder {folder} {why}",
                       f"give a path ending in .rrd in a folder that exists (or create {folder} first), {either}")


def refuse_target_type(target: Any) -> None:
    """The LogError for a ``rerun=`` that is neither a str nor a path (``True``, a port number...):
    it names the forms a target takes, and the URL a port number or True meant."""
    if isinstance(target, int) and not isinstance(target, bool):
        meant = f"for a viewer listening on port {target}, rerun='rerun+http://127.0.0.1:{target}/proxy'"
    else:
        meant = f"for the local viewer, rerun={RERUN_VIEWER_URL!r}"
    raise LogError(f"rerun={target!r} is no Rerun target: it takes a viewer's gRPC URL (a str: rerun://…, "
                   f"rerun+http://…, rerun+https://…) or a path ending in .rrd (a str or a pathlib.Path), "
                   f"the file to save the stream to", f"{meant}; or rerun='live.rrd'")


def viewer_address(url: str) -> tuple[str, int]:
    """``(host, port)`` of a viewer's URL (``rerun+http://HOST:PORT/proxy``), or a LogError for
    one Rerun's SDK would not take (no host, a port past 65535, a path other than ``/proxy``,
    an unclosed ``[``): without a port, the one its scheme's transport has (http 80, else 443)."""
    def refuse(why: str) -> LogError:
        return LogError(f"cannot stream the run to Rerun at {url}: {why}", TARGET_HINT)

    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:  # an unclosed '[', a port that is no number or past 65535
        raise refuse(f"it is not a valid URL ({e})") from None
    if not parts.hostname:
        raise refuse("it names no host")
    if parts.path != "/proxy" or parts.query or parts.fragment:
        raise refuse("a Rerun viewer's URL ends in /proxy after its host and port")
    if port is None:
        port = 80 if parts.scheme.lower() == "rerun+http" else 443
    return parts.hostname, port


def check_viewer(url: str, timeout: float = VIEWER_CONNECT_TIMEOUT_S) -> None:
    """A LogError unless ``url`` is well formed and something accepts a TCP connection at its
    host and port within ``timeout`` seconds: a run is refused before any worker starts (or its
    log is made), not after its workers did and Rerun's SDK gave up seconds later."""
    host, port = viewer_address(url)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as e:
        why = "no answer" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise LogError(f"cannot stream the run to Rerun at {url}: no viewer listens at {host}:{port} ({why})",
                       START_VIEWER_HINT) from None


def value_bytes(value: Any) -> int:
    """About how many bytes ``value``'s leaves hand Rerun's SDK: an array's, a text's or a
    list's of numbers (8 each); 8 for anything else (a number, a flag)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (int, float)):
        return 8
    size = 0
    for _, leaf in value_leaves(value):
        if isinstance(leaf, np.ndarray):
            size += leaf.nbytes
        elif isinstance(leaf, (str, bytes, bytearray)):
            size += len(leaf)
        elif isinstance(leaf, (list, tuple)):
            size += 8 * len(leaf)
        else:
            size += 8
    return size


def flush_timed_out(error: BaseException) -> bool:
    """Whether ``error``, raised by a stream's ``flush(timeout_sec=...)``, says its timeout
    passed (the sink is behind) rather than that the sink failed."""
    return isinstance(error, RuntimeError) and str(error).startswith(FLUSH_TIMED_OUT)


#: the SDK's disconnects that a view's close left waiting, in a thread each, on a sink that took
#: nothing: Rerun's at-exit shutdown disconnects every stream again, and would wait on those too
_left_disconnects: list[threading.Thread] = []


def skip_rerun_shutdown_if_stuck() -> bool:
    """If a live view's close gave up on its sink (a viewer that took nothing, suspended), drop
    Rerun's at-exit shutdown, which would wait on that sink for ever, and say True. Process-wide:
    every stream of the process loses its at-exit flush; for the process's owner only (the
    command line, once its run is over), never called by the library."""
    if not any(disconnect.is_alive() for disconnect in _left_disconnects):
        return False  # none, or each ended since (the viewer resumed, or went away)
    import rerun

    rerun.unregister_shutdown()
    return True


class SinkWatch:
    """How far a recording stream's sink is behind: ``handed`` (bytes the run's thread gave the
    SDK, added by it) less ``taken`` (of those, the ones handed before the start of the last
    flush that completed). A thread of its own flushes the stream whenever something was handed
    since, waiting at most WATCH_FLUSH_S a flush (the SDK releases the GIL meanwhile): the
    run's thread never waits for the sink. A flush that fails other than by its timeout means
    the sink is gone (a viewer closed or killed): ``gone`` says why, and the watch stops; any
    other error stops it too, said in ``failed`` (its class and message)."""

    def __init__(self, stream, period: float = LIVE_FLUSH_S):
        self._stream, self._period = stream, period
        self.handed = 0
        self.taken = 0
        #: why the sink is gone (the SDK's error), or None
        self.gone: str | None = None
        #: the error, other than the SDK's for its sink, that stopped the watch ("ValueError: ..."), or None
        self.failed: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="retriever-rerun-watch", daemon=True)
        self._thread.start()

    @property
    def behind(self) -> int:
        """Bytes handed that the sink is not known to have taken."""
        return self.handed - self.taken

    def _watch(self) -> None:
        try:
            self._flush_while_handed()
        except BaseException as e:  # noqa: BLE001 - said by the view's next call (a Rust panic is a BaseException)
            self.failed = f"{type(e).__name__}: {e}"

    def _flush_while_handed(self) -> None:
        timeout = WATCH_FLUSH_S
        while not self._stop.is_set():
            mark = self.handed
            if mark != self.taken:
                try:
                    self._stream.flush(timeout_sec=timeout)
                except RuntimeError as e:  # the SDK's, for both: its timeout passed, or its sink failed
                    if flush_timed_out(e):
                        timeout = min(2 * timeout, WATCH_FLUSH_MAX_S)
                        continue  # still behind: flush again (it waits for all before it)
                    self.gone = str(e)
                    return
                self.taken, timeout = mark, WATCH_FLUSH_S
            self._stop.wait(self._period)

    def stop(self) -> None:
        """Stop the watch; its thread ends on its own once the flush under way, if any, is over."""
        self._stop.set()


class RerunLiveView:
    """One recording stream, to a viewer or an ``.rrd`` file, fed with the run's events (at their
    tags on ``event_time``, their seqs on ``seq`` and their publish times on ``wall_time``) and
    step records, batched by Rerun's SDK for at most LIVE_FLUSH_S: what was logged reaches the
    sink within about that. While the sink is more than ``behind_bytes`` behind (SinkWatch),
    large values are dropped, and past ``small_bytes`` more every value and step record:
    counted in ``dropped``, said once when it starts and, at close, how much."""

    title = "the Rerun live view"

    def __init__(self, target: str | os.PathLike, pipeline: str, *, behind_bytes: int = BEHIND_BYTES,
                 small_bytes: int = SMALL_BYTES):
        check_target(target)
        rr = rerun_sdk(self.title)
        self.target = str(target)
        self.behind_bytes, self.small_bytes = behind_bytes, small_bytes
        #: what was not sent because the sink was behind: "values", "bytes" (theirs), "records"
        #: (step records), "spells" (times it began to drop after sending)
        self.dropped: Counter = Counter()
        self._dropping = False
        self._stream = new_stream(rr, rr.ChunkBatcherConfig(flush_tick=LIVE_FLUSH_S,
                                                             flush_num_bytes=LIVE_FLUSH_BYTES))
        try:
            self._open(target, rr)
        except Exception as e:  # the SDK's own error: a path it cannot create, a URL it cannot reach
            self._stream.disconnect()
            raise LogError(f"cannot stream the run to Rerun at {self.target}: {e}", self._hint()) from None
        self._stream.send_recording_name(pipeline)
        self._recording = RerunRecording(rr, self._stream)
        self._watch = SinkWatch(self._stream)

    def _open(self, target: str | os.PathLike, rr) -> None:
        if is_rrd_path(target):
            if os.path.lexists(target):  # made since check_target: still never over a file
                raise FileExistsError("the file exists; a live view never replaces a file")
            self._stream.save(Path(target), default_blueprint=event_time_blueprint(rr))
            return
        self._stream.connect_grpc(str(target), default_blueprint=event_time_blueprint(rr))
        self._stream.flush()  # raises when no viewer answers there: said now, not once the run is over

    def _hint(self) -> str:
        if is_rrd_path(self.target):
            return "give a new path (none that exists: remove it first) in a folder you may write to"
        return START_VIEWER_HINT

    @property
    def sink(self) -> str:
        """The sink, as said: ``the viewer at URL`` or ``the file PATH``."""
        return f"the file {self.target}" if is_rrd_path(self.target) else f"the viewer at {self.target}"

    @property
    def written(self):
        """The rows sent so far, per entity."""
        return self._recording.written

    @property
    def behind(self) -> int:
        """Bytes handed to the SDK that its sink is not known to have taken (SinkWatch)."""
        return self._watch.behind

    def _admit(self, size: int, small: bool) -> bool:
        """Whether a row of ``size`` bytes is sent (counted as handed) rather than dropped."""
        watch = self._watch
        if watch.gone is not None or watch.failed is not None:
            why = f"went away: {watch.gone}" if watch.gone is not None else f"cannot be watched: {watch.failed}"
            raise LogError(f"{self.sink} {why}", "the run goes on without the view; a log of the run (--log) "
                           "keeps it all: retriever log export LOG --format rerun")
        behind = watch.handed - watch.taken
        if behind <= self.behind_bytes:
            self._dropping = False  # caught up (or never behind): a spell of drops is over
        if behind <= self.behind_bytes or (small and behind <= self.behind_bytes + self.small_bytes):
            watch.handed += size
            return True
        if not self._dropping:
            self._dropping = True
            self.dropped["spells"] += 1
            if self.dropped["spells"] == 1:
                warnings.warn(f"{self.title}: {self.sink} is not taking the stream ({behind / 2**20:.0f} MiB sent "
                              f"it has not taken): frames and other large values are dropped from the view until "
                              f"it catches up, numbers and step records too past {self.small_bytes / 2**20:.0f} "
                              f"MiB more (a log of the run keeps them all; how many is said at the run's end)",
                              RetrieverWarning, stacklevel=4)
        return False

    def event(self, node: str, port: str, tag, seq: int, value: Any, wall_ns: int) -> None:
        if value is NOT_KEPT:
            return
        size = value_bytes(value)
        if self._admit(RECORD_BYTES + size, size <= SMALL_VALUE_BYTES):
            self._recording.log_event(node, port, tag[0], wall_ns, seq, value)
        else:
            self.dropped["values"] += 1
            self.dropped["bytes"] += size

    def step(self, node: str, tag, consumed, produced, status: str, detail, start_ns: int, wall_ns: int) -> None:
        if self._admit(RECORD_BYTES, True):
            self._recording.log_step(StepRecord(node, tag, consumed, produced, status, detail, start_ns, wall_ns))
        else:
            self.dropped["records"] += 1

    def close(self) -> None:
        """What is left is sent, waiting at most CLOSE_S for the sink to take it and as long to
        disconnect (a viewer that takes nothing, suspended, holds the SDK's disconnect until it
        takes it or is gone: that is left to a thread of its own, kept for
        :func:`skip_rerun_shutdown_if_stuck`); what was dropped is said."""
        self._watch.stop()  # its flush under way, if any, ends on its own; this one waits for it too
        dropped = self.dropped
        if dropped["values"] or dropped["records"]:
            warnings.warn(f"{self.title} dropped {dropped['values']} values ({dropped['bytes'] / 1e6:.1f} MB) and "
                          f"{dropped['records']} step records that {self.sink} did not take in time "
                          f"(behind by more than {self.behind_bytes / 2**20:.0f} MiB {dropped['spells']} "
                          f"time{'s' if dropped['spells'] != 1 else ''}); a log of the run keeps them all", ViewDroppedWarning,
                          stacklevel=3)
        left = None
        try:
            self._stream.flush(timeout_sec=CLOSE_S)
        except RuntimeError as e:  # timed out (a viewer that takes nothing) or gone
            left = str(e)
        disconnect = threading.Thread(target=self._stream.disconnect, name="retriever-rerun-disconnect", daemon=True)
        disconnect.start()
        if left is None:
            disconnect.join(CLOSE_S)
            if disconnect.is_alive():
                left = f"its disconnect did not end within {CLOSE_S:g} s"
        if left is not None:  # the sink takes nothing: the SDK's disconnect waits for it (or its end) in its thread
            _left_disconnects.append(disconnect)
            raise LogError(f"{self.sink} did not take the end of the stream: {left}",
                           "a log of the run (--log) keeps every event and step record")
