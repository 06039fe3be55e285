"""Exceptions and warnings raised by Retriever.

    RetrieverError                 base of everything Retriever raises on purpose
    ├── GraphError                 build_ir() found problems; all of them, one per line
    ├── ClockError (ValueError)    a clock was declared with an impossible value
    ├── IRError                    an IR document is malformed, of another version, or names unknown things
    ├── PlacementError             a placement file is malformed, or the nodes cannot go on the workers up
    ├── LoadError                  retriever run FILE[:ATTR]: the file or the attribute gives no Pipeline
    ├── CodecError (TypeError)     a value cannot be encoded for the wire, the log or a trace digest
    │   └── UnregisteredTypeError  ... or decoded: it names a class this process registered no value type for
    ├── OutputError (TypeError)    a step returned what its declared output cannot be read from (a StepError's cause)
    ├── BackendError               an unknown backend, or a backend that cannot run this graph
    ├── SetupError                 a flow's setup() raised, before its first tick: the run did not start
    ├── StepError                  a flow's step() raised; names the node and the tick, chains the cause
    │   └── RestartLimitError      ... once more than max_restarts within restart_window (on_error="restart")
    ├── RemoteError                a worker process's exception, carried back as text (a StepError's cause)
    ├── CausalityError             an instant ran past max_microsteps (a Zeno loop); names the cycle
    ├── ValuesNotKeptError         a trace of a run with keep="records" was asked for its values
    ├── FeatureError (ValueError)  a port's value no dataset feature holds, or keys that name no feature
    ├── LogError                   an event log cannot be written, read or replayed as asked
    │   ├── LogWriteError          the OS refused a write to the log: the run stopped, the file is no record of it
    │   ├── ChunkTooLargeError (ValueError)  a log's chunk would decompress past what a log is read with
    │   └── UnmappableError        export_dataset: a port's value that no dataset feature can hold
    ├── AccessError (ValueError)   zenoh: a deployment secret that cannot be read, used or written
    ├── WireError                  zenoh: a message on the key space is no Retriever message of this version
    │   └── OtherProtocolReply     ... a daemon's answer in another protocol version: which, and its Retriever's
    ├── LinkError                  zenoh: a same-host link refused a peer (what it sent, which peer), or a send waited too long
    ├── ReportError                zenoh: a report could not be sent; the coordinator will not get its records
    ├── WorkerError                zenoh: a worker that cannot start as asked, or a worker query with no answer
    │   └── OtherProtocolError     ... a worker that speaks another protocol version than this process
    ├── RouterError                zenoh: a router (retriever router) that cannot start as asked
    ├── RunEnded                   a step called sys.exit(0): the run ends at that tick, cleanly (caught inside)
    ├── StopRun                    a node loop must stop the run (zenoh; caught inside, the coordinator reports why)
    ├── ReplayedError              replay: a logged step's error raised again at its tick (caught inside)
    └── InternalError              a bug in Retriever itself; please report it

    RetrieverWarning (UserWarning) instantaneous cycles, required ports nothing feeds
    ├── StarvedFlowWarning         after a run: a flow skipped (nearly) every tick, and the input that starved it
    └── ViewDroppedWarning         after a run: what a live view dropped because its viewer did not take it in time

    Interrupted (KeyboardInterrupt)  a command stopped by SIGTERM or Ctrl-C (retriever.cli.stop_on_signals)

Every exception class of ``retriever/`` is defined here and drawn above (tests/test_errors.py
checks it); the modules that raise them re-export the ones their users import from there.
Every message names the thing (by its qualified name, ``node.port``), says what was expected
and what arrived, and where a common misuse is likely, ends with a one-line ``hint:``.
"""

from __future__ import annotations

from dataclasses import dataclass


class RetrieverError(Exception):
    """Base class of every error Retriever raises on purpose."""


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a graph or a placement: what and where, plus how to fix it."""

    message: str
    hint: str | None = None

    def __str__(self) -> str:
        return self.message if self.hint is None else f"{self.message}\n    hint: {self.hint}"


class GraphError(RetrieverError):
    """The graph cannot be compiled; ``problems`` lists every reason at once."""

    def __init__(self, pipeline: str, problems: list[Problem]):
        self.pipeline = pipeline
        self.problems = list(problems)
        count = len(self.problems)
        lines = [f"pipeline '{pipeline}' has {count} problem{'s' if count != 1 else ''}:"]
        lines += [f"  - {p}" for p in self.problems]
        super().__init__("\n".join(lines))


class ClockError(RetrieverError, ValueError):
    """A clock was declared with a value no schedule can follow."""


class IRError(RetrieverError):
    """An IR document is malformed, of an unsupported version, or names unknown things."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = list(problems)
        lines = [f"invalid IR ({source}):"] + [f"  - {p}" for p in self.problems]
        super().__init__("\n".join(lines))


class PlacementError(RetrieverError):
    """A placement cannot be read or met (``retriever deploy``); ``problems`` lists every reason at once.

    ``source`` is the placement file, or None for an automatic placement (no ``--placement``)."""

    def __init__(self, source: str | None, problems: list[Problem]):
        self.source = source
        self.problems = list(problems)
        count = len(self.problems)
        what = f"placement {source}" if source is not None else "automatic placement (no --placement file)"
        lines = [f"{what} has {count} problem{'s' if count != 1 else ''}:"]
        lines += [f"  - {p}" for p in self.problems]
        super().__init__("\n".join(lines))


class LoadError(RetrieverError):
    """The file or attribute named on the command line does not give a Pipeline."""


class CodecError(RetrieverError, TypeError):
    """A value cannot be encoded (or decoded) by Retriever's msgpack codec."""


class UnregisteredTypeError(CodecError):
    """A value names a dataclass that is no value type registered in this process (``@io``);
    decoding imports and calls nothing to find one."""


class OutputError(RetrieverError, TypeError):
    """A step returned something its declared output type cannot be read from."""


class BackendError(RetrieverError):
    """An unknown backend was asked for, or a backend cannot run this graph."""


def _wrapped(head: str, cause: BaseException | str, context: str, hint: str) -> str:
    """``head``, the cause's first line and ``context`` on the first line, then the cause's other
    lines; ``hint`` last, unless the cause ends with a hint of its own (it knows the fix better)."""
    what = cause if isinstance(cause, str) else f"{type(cause).__name__}: {cause}"
    first, *rest = what.split("\n")
    own_hint = bool(rest) and rest[-1].lstrip().startswith("hint:")
    return "\n".join([f"{head}{first}{context}", *rest, *([] if own_hint else [f"    hint: {hint}"])])


#: what numpy says of a write into a read-only array (flow/read_only.py makes an event's arrays so)
_READ_ONLY_WRITE = "is read-only"


class StepError(RetrieverError):
    """A flow's ``step()`` raised. The original exception is chained as ``__cause__``."""

    def __init__(self, node: str, tag: tuple[int, int], cause: BaseException):
        self.node = node
        self.tag = tag
        from .time import format_tag

        if _READ_ONLY_WRITE in str(cause):
            hint = (f"if the array is an event's ('{node}''s input, or an array it emitted before): an emitted "
                    "value is immutable, since other consumers and the log share it; copy it first "
                    "(x = inp.frame.copy(); emit a new array each tick). docs/semantics.md says why")
        else:
            hint = (f"set on_error='skip_tick' or 'restart' on '{node}' "
                    "(flow.configure(on_error=...)) to keep the pipeline running")
        super().__init__(_wrapped(f"{node}.step() raised ", cause, f" (tick at {format_tag(tag)})", hint))


class SetupError(RetrieverError):
    """A flow's ``setup()`` raised, before its first tick: the run (or the replay, ``replay=True``)
    did not start. The original exception is chained as ``__cause__`` (on ``zenoh``, its text and
    the worker's traceback)."""

    def __init__(self, node: str, cause: BaseException | str, *, replay: bool = False):
        self.node = node
        if replay:
            context = ", before its first tick: the replay could not start"
            hint = (f"a replay sets '{node}' up again, in this process: it needs here what it needed in the run "
                    "(a file, a device, a model's weights)")
        else:
            context = ", before its first tick: the run did not start"
            hint = (f"setup() runs once, in the process that steps '{node}'; fix what it needs there (a file, a "
                    "device, a model's weights)")
        super().__init__(_wrapped(f"{node}.setup() raised ", cause, context, hint))


class RestartLimitError(StepError):
    """A flow with ``on_error="restart"`` needed more restarts than its budget allows."""

    def __init__(self, node: str, tag: tuple[int, int] | None, cause: BaseException | str, max_restarts: int,
                 window: float):
        """``tag``: the tick whose step raised; None when the flow's process died (zenoh)."""
        self.node, self.tag = node, tag
        from .time import format_tag

        where = (f" (tick at {format_tag(tag)})", "each failure is an error record of the trace and the log") \
            if tag is not None else ("", "retriever log info shows each process that died")
        RetrieverError.__init__(
            self, _wrapped(f"flow '{node}' failed again after {max_restarts} restart(s) within {window:g} s "
                           f"(max_restarts={max_restarts}, restart_window={window:g}): ", cause, where[0],
                           f"fix what makes '{node}' fail ({where[1]}), "
                           "or raise its budget: flow.configure(max_restarts=..., restart_window=...)"))


class RemoteError(RetrieverError):
    """An exception raised in a worker process, carried back as text."""


class CausalityError(RetrieverError):
    """An instant ran more than ``max_microsteps`` microsteps: an instantaneous (Zeno) loop."""

    def __init__(self, cycle: list[str], tag: tuple[int, int], max_microsteps: int):
        self.cycle = cycle
        self.tag = tag
        from .time import format_tag

        loop = " → ".join(cycle + cycle[:1]) if cycle else "(no declared cycle found)"
        super().__init__(
            f"Zeno loop: the instant at {format_tag(tag)} ran past max_microsteps={max_microsteps} "
            f"around the cycle {loop}\n"
            "    hint: break the cycle in time: give a flow on it latency= (flow.configure(latency=0.01)), "
            "put delay= on one of its edges, or clock one of its flows with Rate(hz=...)"
        )


class LogError(RetrieverError):
    """An MCAP event log is missing, not MCAP, corrupt, truncated, or cannot be replayed."""

    def __init__(self, message: str, hint: str | None = None):
        self.hint = hint
        super().__init__(message if hint is None else f"{message}\n    hint: {hint}")


class LogWriteError(LogError):
    """The OS refused a write to a run's log (its disk is full, it is a device that takes no data,
    an I/O error): the run was stopped, and the file is not a record of it."""


class FeatureError(RetrieverError, ValueError):
    """A value no feature holds, or keys that do not name features; one problem per line, each
    naming the source but not where it came from (the export and the policy flow add that)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class ChunkTooLargeError(LogError, ValueError):
    """A chunk that would decompress past the reader's MAX_CHUNK_BYTES."""


class UnmappableError(LogError):
    """A port's value that no dataset feature can hold."""


class AccessError(RetrieverError, ValueError):
    """A deployment secret that cannot be read, used or written."""


class WireError(RetrieverError):
    """A message on the key space is not a Retriever message of this version."""


class OtherProtocolReply(WireError):
    """Raised in place of the info reply of a daemon that speaks another protocol version: which
    one, and the version of Retriever it says it runs (what to install alike on both machines), as
    far as it says. (Its asker raises OtherProtocolError, which names the worker.)"""

    def __init__(self, message: str, protocol: int, retriever: str | None):
        super().__init__(message)
        self.protocol, self.retriever = protocol, retriever


class LinkError(RetrieverError):
    """A same-host link (backends/zenoh/link/) refused what a peer sent, naming it and the
    peer, or a producer's send waited past its bound for a consumer."""


class ReportError(RetrieverError):
    """A report could not be sent: the coordinator will not get this worker's records."""


class WorkerError(RetrieverError):
    """A worker that cannot start as asked, or a worker query that got no answer."""


class OtherProtocolError(WorkerError):
    """A worker that speaks another protocol version (``other.protocol``) than this process (``ours``):
    which one, and the version of Retriever it runs, as far as it said."""

    def __init__(self, name: str, other: OtherProtocolReply, ours: int):
        super().__init__(f"worker '{name}' speaks protocol {other.protocol}, this process {ours}")
        self.protocol, self.retriever = other.protocol, other.retriever


class RouterError(RetrieverError):
    """A router (``retriever router``) that cannot start as asked."""


class RunEnded(RetrieverError):
    """A step called ``sys.exit()`` (or ``sys.exit(0)``): the run ends at that tick, cleanly."""

    def __init__(self, node: str, tag: tuple[int, int]):
        from .time import format_tag

        super().__init__(f"{node} ended the run at {format_tag(tag)} (sys.exit(0) in its step)")
        self.node, self.tag = node, tag


class StopRun(RetrieverError):
    """The run must stop: a step failed with on_error="stop", or a miss in realtime="hard";
    ``zeno``: an instant ran past max_microsteps (the coordinator raises CausalityError);
    ``raised``: what the step raised, when it did (the coordinator raises StepError);
    ``out_of_restarts``: that step's restart was past the flow's budget (RestartLimitError)."""

    def __init__(self, message: str, tag: tuple[int, int] | None = None, zeno: bool = False,
                 raised: str | None = None, out_of_restarts: bool = False):
        super().__init__(message)
        self.tag = tag
        self.zeno = zeno
        self.raised = raised
        self.out_of_restarts = out_of_restarts


class ReplayedError(RetrieverError):
    """What a replayed step (``replace_step``) raises at a tick whose logged record is an error:
    the tick is recorded with the logged text (``"ValueError: bad tick"``), not this class's
    name, and handled by the node's ``on_error`` as in the run."""

    def __init__(self, error: str):
        super().__init__(error)
        self.error = error


class ValuesNotKeptError(RetrieverError):
    """A trace of a run that kept no values (``keep="records"``) was asked for them."""


class InternalError(RetrieverError):
    """A bug in Retriever itself, not in your program. Please report it with the traceback."""

    def __init__(self, message: str):
        super().__init__(f"{message} (this is a bug in Retriever, not in your program; please report it)")


class RetrieverWarning(UserWarning):
    """Something legal but probably unintended, e.g. an instantaneous cycle."""


class StarvedFlowWarning(RetrieverWarning):
    """After a run: a flow skipped every tick, or most of them, for an input that never had an
    event (a misspelled port wires nothing); names the port and the edge."""


class ViewDroppedWarning(RetrieverWarning):
    """After a run: a live view dropped values and step records its viewer did not take in time
    (log/rerun_live.py: a viewer stopped or too slow); how many, naming the viewer."""


class Interrupted(KeyboardInterrupt):
    """A stop signal (SIGTERM, or Ctrl-C's SIGINT) raised as Ctrl-C's exception in a command
    (``retriever.cli.stop_on_signals``), or a second one during a logged run: every ``except KeyboardInterrupt`` takes it. A subclass,
    not KeyboardInterrupt itself: CPython marks a bare KeyboardInterrupt that leaves an ``exec`` or
    ``eval`` of a string (a dataclass or a message class being made) as unhandled even when the
    command catches it later, and then ends the process by SIGINT instead of with the exit status
    the command chose."""
