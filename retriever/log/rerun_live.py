"""``pipe.run(..., rerun=TARGET)``, ``retriever run|deploy --rerun [TARGET]``: a running
pipeline shown live in the Rerun viewer, from the coordinating process, as the log's Rerun export
shows it afterwards (log/rerun.py's writer: the same entities, archetypes and timelines).

TARGET is the gRPC URL of a running viewer (``rerun+http://HOST:PORT/proxy``; by default the
local viewer that ``rerun`` starts) or a path ending in ``.rrd``, where the stream is saved as it
goes (a file that ``rerun FILE.rrd`` opens, during the run or after it). Nothing else: a folder
is no target (the view writes no file of its own naming into one), nor a path whose folder does
not exist, nor a file that exists; :func:`check_target` says so before the run starts (the
backends and the command call it before any worker starts or the pipeline is loaded).
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ..errors import LogError
from ..trace import NOT_KEPT, StepRecord
from .rerun import RERUN_VIEWER_URL, RerunRecording, event_time_blueprint, new_stream, rerun_sdk

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


class RerunLiveView:
    """One recording stream, to a viewer or an ``.rrd`` file, fed with the run's events (at their
    tags on ``event_time``, their seqs on ``seq`` and their publish times on ``wall_time``) and
    step records, batched by Rerun's SDK for at most LIVE_FLUSH_S: what was logged reaches the
    sink within about that."""

    title = "the Rerun live view"

    def __init__(self, target: str | os.PathLike, pipeline: str):
        check_target(target)
        rr = rerun_sdk(self.title)
        self.target = str(target)
        self._stream = new_stream(rr, rr.ChunkBatcherConfig(flush_tick=LIVE_FLUSH_S,
                                                             flush_num_bytes=LIVE_FLUSH_BYTES))
        try:
            self._open(target, rr)
        except Exception as e:  # the SDK's own error: a path it cannot create, a URL it cannot reach
            self._stream.disconnect()
            raise LogError(f"cannot stream the run to Rerun at {self.target}: {e}", self._hint()) from None
        self._stream.send_recording_name(pipeline)
        self._recording = RerunRecording(rr, self._stream)

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
    def written(self):
        """The rows sent so far, per entity."""
        return self._recording.written

    def event(self, node: str, port: str, tag, seq: int, value: Any, wall_ns: int) -> None:
        if value is not NOT_KEPT:
            self._recording.log_event(node, port, tag[0], wall_ns, seq, value)

    def step(self, node: str, tag, consumed, produced, status: str, detail, start_ns: int, wall_ns: int) -> None:
        self._recording.log_step(StepRecord(node, tag, consumed, produced, status, detail, start_ns, wall_ns))

    def close(self) -> None:
        try:
            self._stream.flush()
        finally:
            self._stream.disconnect()
