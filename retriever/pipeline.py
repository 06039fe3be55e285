"""``Pipeline``: declare flows and edges, compile them, run them on a backend.

    with Pipeline("agent") as pipe:
        cam.then(policy, sync=Latest()).then(ctrl, sync=ActionChunking(control_hz=200))
    ir = pipe.build_ir()            # validate everything, raise once
    trace = pipe.run(duration=10)   # default backend: retriever.init(backend=...) or "inproc"

``run`` and ``step`` continue from where the last call stopped; ``reset`` returns to T0.
``pipe.session`` is the run going on (its backend's ``Session``), for watching it; ``pipe.open()``
opens it before the first run.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import warnings
import weakref
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from . import declaring
from .backends import Session, open_backend
from .errors import (BackendError, GraphError, Interrupted, IRError, Problem, RetrieverWarning, SetupError,
                     StarvedFlowWarning)
from .flow.core import Flow, settings_of
from .graph import DeclaredEdge, Graph, compile_graph
from .ir import DEFAULT_DEADLINE, DEFAULT_MAX_MICROSTEPS, IR, REALTIME_MODES
from .log.format import RunEnd
from .log.reader import LoggedTrace
from .rebuild import check_node, construct_node
from .starved import describe_starved, starved_flows
from .sync import Latest, SyncPolicy, policy_from_ir
from .time import MAX_SECONDS, MAX_TIME_NS, NS_PER_S, max_microsteps_problem, seconds_problem, seconds_to_ns
from .trace import Trace


class Pipeline:
    """A graph of flows. Use as a context manager so ``a.then(b)`` knows where to add the edge."""

    def __init__(self, name: str = "pipeline", *, max_microsteps: int = DEFAULT_MAX_MICROSTEPS,
                 realtime: str = "soft", deadline: float = DEFAULT_DEADLINE):
        """``realtime`` and ``deadline`` matter on real-time backends (docs/realtime.md): ``deadline``
        is how long a tick waits for an input edge that is not complete up to its tag (edges may
        override it), ``realtime`` how misses escalate: ``"hard"`` stops the run at the first
        overrun, deadline miss or incomplete edge; ``"soft"`` applies each flow's ``on_overrun`` /
        ``on_deadline_miss``; ``"best_effort"`` counts and logs misses and never stops."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"a pipeline name must be a non-empty string, got {name!r}")
        problem = max_microsteps_problem(max_microsteps)
        if problem is not None:
            raise ValueError(f"Pipeline(max_microsteps={max_microsteps!r}): {problem}")
        if realtime not in REALTIME_MODES:
            raise ValueError(f"Pipeline(realtime={realtime!r}): expected one of {', '.join(map(repr, REALTIME_MODES))}")
        problem = seconds_problem("deadline", deadline)
        if problem is not None:
            raise ValueError(f"Pipeline(deadline={deadline!r}): {problem}")
        self.name = name
        self.max_microsteps = max_microsteps
        self.realtime = realtime
        self.deadline = deadline
        self._flows: list[Flow] = []
        self._edges: list[DeclaredEdge] = []
        self._graph: Graph | None = None
        self._session: Session | None = None

    # -- declaring ---------------------------------------------------------------------------
    def __enter__(self) -> "Pipeline":
        declaring.push(self)
        return self

    def __exit__(self, *exc: Any) -> None:
        declaring.pop(self)

    def add(self, flow: Flow, name: str | None = None) -> Flow:
        """Add a flow (flows join automatically when created inside ``with`` or wired)."""
        if not isinstance(flow, Flow):
            raise TypeError(f"Pipeline.add expects a Flow, got {type(flow).__qualname__}")
        settings = settings_of(flow)
        owner = settings.pipeline() if settings.pipeline is not None else None
        if owner is not None and owner is not self:
            raise GraphError(self.name, [Problem(
                f"{flow!r} belongs to pipeline '{owner.name}', where it was created or first wired, so it cannot "
                f"join pipeline '{self.name}'",
                f"a flow belongs to one pipeline: make a new instance for '{self.name}', e.g. "
                f"{type(flow).__qualname__}(...) @ Rate(hz=...)")])
        if name is not None:
            flow.configure(name=name)
        if owner is None:
            settings.pipeline = weakref.ref(self)
            self._flows.append(flow)
            self._changed()
        return flow

    def connect(self, src: Flow, dst: Flow, sync: SyncPolicy | None = None, map: dict[str, str] | None = None,
                delay: float = 0.0, qsize: int = 10, deadline: float | None = None, *,
                _stacklevel: int = 2) -> Flow:
        """Add an edge ``src → dst``; returns ``dst``. Ports are matched when the graph compiles.
        ``deadline`` (seconds, real-time backends) overrides the pipeline's for this edge."""
        for role, f in (("source", src), ("destination", dst)):
            if isinstance(f, type):
                raise TypeError(f"connect(): the {role} must be a Flow instance, got the class {f.__qualname__}\n"
                                f"    hint: instantiate it: {f.__qualname__}() @ Rate(hz=...)")
            if not isinstance(f, Flow):
                raise TypeError(f"connect(): the {role} must be a Flow instance, got {type(f).__qualname__}")
        if sync is None:
            sync = Latest()
        if not isinstance(sync, SyncPolicy):
            hint = "\n    hint: instantiate it: sync=Latest()" if isinstance(sync, type) else ""
            raise TypeError(f"connect(): sync must be a sync policy such as Latest(), got {sync!r}{hint}")
        if map is not None and (not isinstance(map, dict) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in map.items())):
            raise TypeError(f"connect(): map must be a dict {{output_port: input_port}} of str, got {map!r}")
        edge = f"edge {type(src).__qualname__} → {type(dst).__qualname__}"
        problem = seconds_problem("delay", delay)
        if problem is not None:
            raise ValueError(f"connect(): {edge}: {problem}\n    hint: delay is the seconds an event takes along "
                             "the edge")
        if not isinstance(qsize, int) or isinstance(qsize, bool) or qsize < 1:
            raise ValueError(f"connect(): qsize must be an integer >= 1, got {qsize!r}")
        problem = None if deadline is None else seconds_problem("deadline", deadline)
        if problem is not None:
            raise ValueError(f"connect(): {edge}: {problem} (or None: the pipeline's)")
        self.add(src)
        self.add(dst)
        frame = sys._getframe(_stacklevel - 1)
        where = f"{Path(frame.f_code.co_filename).name}:{frame.f_lineno}"
        self._edges.append(DeclaredEdge(src, dst, sync, dict(map) if map is not None else None, delay, qsize, where,
                                        deadline))
        self._changed()
        return dst

    def _changed(self) -> None:
        self._graph = None
        if self._session is not None:
            self._session.close()
            self._session = None

    @property
    def flows(self) -> list[Flow]:
        return list(self._flows)

    # -- compiling ---------------------------------------------------------------------------
    def compile(self) -> Graph:
        """Resolve and validate the graph (cached until the pipeline changes)."""
        if self._graph is None:
            self._graph = compile_graph(self.name, self._flows, self._edges, self.max_microsteps,
                                        self.realtime, self.deadline)
            for w in self._graph.declaration_warnings + self._graph.warnings:
                warnings.warn(f"pipeline '{self.name}': {w}", RetrieverWarning, stacklevel=_user_stacklevel())
        return self._graph

    def build_ir(self) -> IR:
        """Validate the graph, reporting every problem in one GraphError, and return its IR."""
        return self.compile().to_ir()

    @classmethod
    def from_ir(cls, ir: IR) -> "Pipeline":
        """Rebuild a runnable pipeline from an IR alone: import each ``type``, call it with ``params``."""
        meta = ir.doc["metadata"]
        pipe = cls(ir.name, max_microsteps=meta.get("max_microsteps", DEFAULT_MAX_MICROSTEPS),
                   realtime=meta.get("realtime", "soft"), deadline=meta.get("deadline", DEFAULT_DEADLINE))
        flows: dict[str, Flow] = {}
        problems: list[str] = []
        # everything that can be checked without importing, for every node, before importing any
        folders = meta.get("module_folders", {})
        params = {node["id"]: check_node(node, problems, folders) for node in ir.nodes}
        if not problems:
            with pipe:  # flows join this pipeline, not whatever `with` block encloses the call
                for node in ir.nodes:
                    construct_node(node, params[node["id"]], flows, problems)
        if problems:
            raise IRError(f"IR '{ir.name}'", problems)
        for e in ir.edges:
            src, dst = flows[e["source"]["node"]], flows[e["destination"]["node"]]
            pipe.connect(src, dst, sync=policy_from_ir(e["adapter"]), map={e["source"]["port"]: e["destination"]["port"]},
                         delay=e.get("delay", 0.0), qsize=e.get("qsize", 10), deadline=e.get("deadline"))
        return pipe

    # -- running -----------------------------------------------------------------------------
    @property
    def session(self) -> Session | None:
        """The current run: the backend's :class:`~retriever.backends.Session` that the last
        ``run``/``step`` (or :meth:`open`) opened and the next one goes on with; None before the
        first and after :meth:`reset` or a change to the pipeline.

        It is for watching a run, from the thread that runs it or another one: its ``trace``,
        ``stats()``, ``counts``, ``starved``, ``produced_counts()``, ``keep``, ``log_metadata()``,
        ``stop_signal``, ``retained_peak`` (:class:`~retriever.backends.base.Session` says what
        each is); a real-time backend's adds its own (``t0``, the run's start in HLC Unix ns once it
        is set, ``worker_pids()``, and ``hosting``: where its processes run, of a deployment its
        ``placed``, ``workers`` and ``status()``).
        The pipeline's own methods (``stats()``, ``counts()``, ``trace``) read the same run."""
        return self._session

    def open(self, backend: str | None = None, **options: Any) -> Session:
        """Open the run's session now, without running it, and return it (:attr:`session`): a
        real-time backend starts its processes here, which the first ``run`` would otherwise do.
        The next ``run``/``step`` goes on with it; ``reset()`` closes it. With a session already
        open, that one is returned (``backend`` must then name its backend, and ``options`` be
        empty: they are given once, to the run they open)."""
        return self._session_for(backend, options)

    def _session_for(self, backend: str | None, options: dict) -> Session:
        from .backends import canonical, default_backend

        name = canonical(backend or default_backend())
        if self._session is not None:
            if backend is not None and self._session.backend_name != name:
                raise BackendError(
                    f"pipeline '{self.name}' is already running on backend '{self._session.backend_name}', "
                    f"not '{name}'\n    hint: call pipe.reset() before switching backends")
            if options:
                raise BackendError(f"backend options {sorted(options)} can only be given on the first run/step "
                                   "after construction or pipe.reset()")
            if self._session.logged_to is not None:
                raise BackendError(f"this run of pipeline '{self.name}' was logged to {self._session.logged_to}, "
                                   "and that log is finished\n    hint: call pipe.reset() to start a new run")
            return self._session
        self._session = open_backend(name, self.compile(), **options)
        return self._session

    def run(self, duration: float | None = None, backend: str | None = None, log: str | Path | None = None,
            overwrite: bool = False, blocking: bool = True, **options: Any) -> Trace | RunHandle:
        """Run for ``duration`` seconds (every tick with ``t < now + duration``); returns the trace.

        ``log="run.mcap"`` records the run, from T0, in an MCAP event log that is complete when
        ``run`` returns (or raises); ``retriever replay run.mcap`` re-executes it. An existing
        file is refused unless ``overwrite=True``; a path that cannot be written is refused
        before the run starts, and a write that fails during the run stops it (``LogWriteError``).
        ``blocking=False`` runs it on a thread of its own and returns a :class:`RunHandle` at once.
        """
        if not blocking:
            return RunHandle(self, duration=duration, backend=backend, log=log, overwrite=overwrite, **options)
        if duration is not None:
            _check_seconds("run", "duration", duration, self._now_ns())
        run_log = None if log is None else RunLog(log, overwrite)  # before any worker starts
        fresh = self._session is None
        if fresh and log is not None and "keep" not in options and _realtime(backend):
            options["keep"] = "counters"  # a logged real-time run may run for hours: the log holds it
        session, begun = None, False
        try:
            session = self._session_for(backend, options)
            # a signal stops a logged run between ticks (its log then ends "interrupted") from
            # before the log is begun until after it is closed: one that comes while the header
            # or the end is being written does not tear the file
            with _stop_between_ticks(session, logged=run_log is not None):
                if duration is None and type(session).run_to_end is Session.run_to_end:
                    session.run_to_end()  # raises: this backend needs a duration
                if run_log is not None:
                    run_log.begin(session)
                begun = True
                try:
                    if duration is None:
                        session.run_to_end()
                    else:
                        session.advance(session.now_ns + seconds_to_ns(duration))
                except BaseException as exc:
                    if run_log is not None:
                        run_log.end(session, exc)
                    _forget(session)
                    raise
                if run_log is not None:
                    run_log.end(session)
        except BaseException as exc:
            if begun:
                raise
            # refused before it started: the pipeline is left as it was (a zenoh session has
            # workers: one interrupted as it started may be set on the pipeline, not yet returned),
            # and no file claims to hold the run
            opened = self._session if fresh else None
            if opened is not None:
                self._session = None
                opened.close()
            if session is not None:
                session.log = None  # (a writer begun on the file being discarded)
            if run_log is not None:
                run_log.discard()
            if session is not None and session.stop_requested and not isinstance(exc, KeyboardInterrupt):
                raise KeyboardInterrupt from exc  # a stop (Ctrl-C, RunHandle.stop) came as it failed
            raise
        finally:
            if session is not None:
                session.stop_requested = False  # asked as a run ended by itself: not the next one's
        _forget(session)
        for line in self.starved():
            warnings.warn(f"pipeline '{self.name}': {line}", StarvedFlowWarning, stacklevel=_user_stacklevel())
        return session.trace

    def step(self, dt: float, **options: Any) -> Trace:
        """Advance virtual time by ``dt`` seconds (in-process backend) and return the trace so far."""
        _check_seconds("step", "dt", dt, self._now_ns())
        session = self._session_for("inproc" if self._session is None else None, options)
        if not session.steppable:
            raise BackendError(f"pipe.step() needs the in-process backend; this pipeline runs on '{session.backend_name}'")
        session.advance(session.now_ns + seconds_to_ns(dt))
        _forget(session)
        return session.trace

    def reset(self) -> None:
        """Return to T0: drop the run's state and trace and reset every flow."""
        if self._session is not None:
            self._session.close()
            self._session = None
        for f in self._flows:
            f.reset()

    @property
    def trace(self) -> Trace:
        """The trace of the current run (empty before the first run/step)."""
        return self._session.trace if self._session is not None else Trace()

    @property
    def now(self) -> float:
        """Current virtual time in seconds since T0: where the last run ended, or, for one that
        raised (a step's error, a stop), the time of the instant it got to; the next run goes on
        from there."""
        return self._now_ns() / NS_PER_S

    def _now_ns(self) -> int:
        return 0 if self._session is None else self._session.now_ns

    def stats(self) -> dict[str, Any]:
        """Per-node counters of the current run: ticks, steps, skips, errors, mean step time, and
        what a real-time backend counted for the node (``.counts``, see :meth:`counts`)."""
        return {} if self._session is None else self._session.stats()

    def starved(self) -> list[str]:
        """What the current run's counters say a miswired port starved: each flow that skipped
        (nearly) every tick, or never ticked, for an input that never had an event, and each edge
        a typo left empty; and each input a real-time run saw starve to its end, its producers
        making events all along (see :mod:`retriever.starved`). ``run`` warns with these at its end."""
        if self._session is None:
            return []
        lines = starved_flows(self._session.graph, self._session.stats(), self._session.produced_counts())
        # and each input that a real-time run saw starve until its end, if its flow is not named yet
        # (one that stepped for a while first: its counters alone do not tell)
        named = {line.split(" ", 1)[0] for line in lines}
        return lines + [f"{describe_starved(e)} (starved during the run)" for e in self._session.starved
                        if e["until_ns"] is None and e["node"] not in named]

    def counts(self) -> dict[str, int]:
        """What the current run counted, summed over its nodes (and the coordinator): events that
        arrived late, incomplete edges, overruns, ticks skipped during restarts, LET deadline
        misses, unrun ticks, dropped garbage messages, waits for the log, time spent busy-waiting for
        ticks (``spin_ns``: ``configure(spin=)``) (``retriever.backends.base.COUNTERS`` says which
        is which). Only real-time backends count these; what was never counted is absent."""
        return {} if self._session is None else {name: n for name, n in self._session.counts.items() if n}

    def __repr__(self) -> str:
        return f"<Pipeline '{self.name}': {len(self._flows)} flows, {len(self._edges)} edges>"


class RunHandle:
    """A run going on in the background (``pipe.run(..., blocking=False)``): ``wait()`` for its
    trace (it raises what the run raised), ``done``, and ``stop()``, which ends it between two
    ticks as Ctrl-C would (``wait()`` then raises ``KeyboardInterrupt``)."""

    def __init__(self, pipe: "Pipeline", **run: Any):
        self._pipe = pipe
        self._trace: Trace | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, kwargs=run, name=f"retriever-run-{pipe.name}", daemon=True)
        self._thread.start()

    def _run(self, **run: Any) -> None:
        try:
            self._trace = self._pipe.run(**run)
        except BaseException as exc:  # handed to wait()
            self._error = exc

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> Trace:
        """The run's trace once it is over (at most ``timeout`` s: TimeoutError if it is not)."""
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise TimeoutError(f"the run of pipeline '{self._pipe.name}' is still going after {timeout:g} s")
        if self._error is not None:
            raise self._error
        assert self._trace is not None
        return self._trace

    def stop(self) -> None:
        """Ask the run to stop between two ticks (a no-op once it is over)."""
        session = self._pipe.session
        if session is not None and not self.done:  # (a request left on the session would stop the next run)
            session.stop_requested = True
            session.look_between_ticks()


def _user_stacklevel() -> int:
    """The warnings stacklevel of the first frame outside this package (the user's line)."""
    package = str(Path(__file__).parent)
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(package):
        frame, level = frame.f_back, level + 1
    return level


@contextmanager
def _stop_between_ticks(session: Session, logged: bool) -> Iterator[None]:
    """While a logged run goes, Ctrl-C and SIGTERM ask it to stop at the next hand-over to the log
    writer (between two ticks) instead of raising wherever the interpreter happens to be, which
    could leave a tick half recorded. A second signal stops at once, but while the log's end is
    written, where raising would tear the file, it is ignored, and a third ends the process at once
    by the signal's default (an end that hangs is not a trap). SIGTERM, unless the program
    handles it itself, then ends the program with SystemExit(143), as it does a run that holds
    processes, logged or not."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    session.signal_ignored = False  # (a run before this one's, on the same session)

    def request_stop(signum, frame) -> None:
        if session.stop_requested and session.ending_log and not session.signal_ignored:
            session.signal_ignored = True  # the log's end is being written: raised there, it would tear the file
            return
        if session.stop_requested and session.ending_log:  # asked a third time: the end hangs; end at once
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        if session.stop_requested:
            raise Interrupted(signum)  # (not a bare KeyboardInterrupt: see Interrupted)
        session.stop_requested = True
        session.stop_signal = signum

    def terminate(signum, frame) -> None:
        raise SystemExit(128 + signum)  # what a shell reports for a process SIGTERM ended

    if logged:
        handlers = {signal.SIGINT: request_stop, signal.SIGTERM: request_stop}
    elif session.holds_processes and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        handlers = {signal.SIGTERM: terminate}
    else:
        handlers = {}
    previous = {sig: signal.signal(sig, handler) for sig, handler in handlers.items()}
    try:
        yield
    except KeyboardInterrupt:
        if logged and session.stop_signal == signal.SIGTERM and previous[signal.SIGTERM] is signal.SIG_DFL:
            # the log is ended ("interrupted"); the program ends as SIGTERM's default would have
            # it, through exit(): an uncaught KeyboardInterrupt ends it with SIGINT instead,
            # past the exit() in which Zenoh removes its shared memory
            raise SystemExit(128 + signal.SIGTERM) from None
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class RunLog:
    """The log that ``pipe.run(log=...)`` records: its file is created before any worker starts
    (a path that cannot be written refuses the run), begun on the session at T0, and ended with
    the run's status; or discarded, for a run refused before it began, or stopped by a flow's
    ``setup()`` before its first tick (a log of no step would only claim to hold a run)."""

    def __init__(self, path: str | Path, overwrite: bool):
        from .log.writer import LogFile

        self.file = LogFile(path, overwrite=overwrite)

    def begin(self, session: Session) -> None:
        """Set the writer of this log on the session: from here on, the run hands it its records."""
        from .log.writer import LogWriter

        if session.now_ns != 0 or session.trace.raw_steps:
            raise BackendError("log= records a run from T0: give it on the first run after construction or "
                               "pipe.reset()")
        session.log = LogWriter(self.file, session.graph, backend=session.backend_name, seeds=session.seeds(),
                                extra=session.log_metadata())

    def discard(self) -> None:
        """Remove the file of a run that never began."""
        self.file.discard()

    def end(self, session: Session, exc: BaseException | None = None) -> None:
        """Finish the log, once begun, with how the run ended (``exc``: what stopped it). A
        SetupError before any step removes the file instead, and adds a note that says so to
        ``exc`` (what ``retriever run`` prints under the error)."""
        writer = session.log
        if writer is None:
            return
        session.log = None
        steps = session.trace.raw_steps
        unstarted = isinstance(exc, SetupError) and writer.steps_total == 0 and not steps
        if not unstarted:
            # absolute: pipe.trace reads the log back later, maybe from another working directory
            session.logged_to = session.trace.log_path = os.path.abspath(writer.path)
        if exc is None:
            status, error = RunEnd.FINISHED, ""
        elif isinstance(exc, KeyboardInterrupt):
            status, error = RunEnd.INTERRUPTED, "stopped by Ctrl-C or SIGTERM"
        else:
            status, error = RunEnd.ERROR, f"{type(exc).__name__}: {exc}"
        # a stopped run ends at its last tick: the writer ends the log at the latest of its step records
        session.ending_log = True  # a second stop signal now waits for the end (_stop_between_ticks)
        try:
            writer.close(session.trace, session.now_ns, status=status, error=error, stats=session.stats(),
                         counts=session.counts)
        finally:
            session.ending_log = False
            if unstarted:
                self.file.discard()
        if unstarted:
            exc.add_note(f"no log is left: the run did not start, so {writer.path} was removed")
        elif session.keep == "counters":  # the log has the records: pipe.trace reads them back from it
            session.trace = LoggedTrace(session.logged_to)


def _realtime(backend: str | None) -> bool:
    from .backends import canonical, default_backend

    try:
        return canonical(backend or default_backend()) != "inproc"
    except BackendError:
        return False  # an unknown backend: _session_for says so


def _forget(session: Session) -> None:
    """What the run keeps no more at its end: the values (keep="records"), the records of an
    unlogged run (keep="counters"); the log has them, or nothing does."""
    if not isinstance(session.trace, LoggedTrace):
        session.drop_records()
        session.trace.forget_values()


def _check_seconds(method: str, name: str, value: Any, now_ns: int) -> None:
    problem = seconds_problem(name, value)
    if problem is None and now_ns + seconds_to_ns(value) > MAX_TIME_NS:
        problem = (f"the run is at {now_ns / NS_PER_S:g} s, and {name} would take it past {MAX_SECONDS:.4g} s "
                   "(about 292 years: times are int64 nanoseconds)")
    if problem is not None:
        raise ValueError(f"pipe.{method}({name}={value!r}): {problem}\n    hint: run for a number of seconds "
                         "that ends within 292 years of T0, e.g. duration=10")
