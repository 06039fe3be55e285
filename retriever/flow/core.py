"""``Flow``: a stateful Python object with a synchronous ``step``; and ``@io`` message types.

Only ``step`` is required. Two styles, both first-class:

- **typed**: ``class F(Flow[In, Out])`` with ``step(self, inp: In) -> Out``. ``In``/``Out`` are
  ``@io`` dataclasses whose fields are the ports; ``Flow[None, Out]`` is a source. A type that is
  not an ``@io`` dataclass is a single port named after it in snake_case (``ActionChunk`` →
  ``action_chunk``).
- **untyped** (the paper's Listing 1): ``class F(Flow)`` whose ``step`` takes one parameter per
  input port and returns a dict of output ports (a missing key, or ``None``, is no event).

A flow is callable directly, ``flow(inp)``, with no runtime involved: that is one method call.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import sys
import textwrap
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, TypeVar

from .. import declaring
from ..clocks import Clock
from ..codec import is_value_type, register_value_type
from ..errors import ClockError, OutputError
from ..time import is_finite_number, seconds_problem, seconds_to_ns

In = TypeVar("In")
Out = TypeVar("Out")

ON_ERROR = ("stop", "skip_tick", "restart")
ON_OVERRUN = ("skip", "error", "catch_up")
ON_DEADLINE_MISS = ("publish_late", "drop", "error")
#: what ``retriever replay`` does with a flow: run its step again and compare (``"rerun"``), or take
#: its outputs from the log (``"log"``: a step that consults the world outside the program)
REPLAY = ("rerun", "log")
#: on_error="restart": at most this many restarts of a flow within any RESTART_WINDOW_S seconds of
#: run time; one more stops the run (systemd's StartLimitBurst and StartLimitIntervalSec defaults)
MAX_RESTARTS = 5
#: ``configure(spin=...)``: at most this many seconds of busy-waiting before each tick
MAX_SPIN_S = 0.001
#: the longest node id or process name: each names files of a run (``<node>.<pid>.<n>.msg``,
#: ``<node>.handover``), and a file's name is at most 255 bytes
NAME_MAX = 128
#: what a node id or process name may be: one segment of the key space, at most NAME_MAX characters
NODE_ID = rf"[A-Za-z_][A-Za-z0-9_\-]{{0,{NAME_MAX - 1}}}"
RESTART_WINDOW_S = 10.0

class _NoDefault:
    def __repr__(self) -> str:
        return "NO_DEFAULT"


_NO_DEFAULT: Any = _NoDefault()


# ---------------------------------------------------------------------------------------------
# @io message types
# ---------------------------------------------------------------------------------------------
def io(cls: type | None = None, /, **dataclass_kwargs: Any):
    """Declare a typed message: its fields are ports. Use on (or above) ``@dataclass``.

    It also registers the class as a value type: the only kind of class the codec rebuilds from
    a message, a log or an IR (by its ``module:QualName``), in any process that defined it; and
    with it the dataclasses its fields are annotated with (``Optional[Pose]``, ``list[Pose]``),
    so that a plain dataclass nested in a message travels too."""

    def wrap(c: type) -> type:
        if not dataclasses.is_dataclass(c):
            c = dataclass(c, **dataclass_kwargs)
        c.__retriever_io__ = True
        _register_with_nested(c)
        return c

    return wrap if cls is None else wrap(cls)


def flow_io(cls: type | None = None, /, **dataclass_kwargs: Any):
    """The seed paper's name of :func:`io` (Appendix F, Listing 4): the same decorator."""
    return io(cls, **dataclass_kwargs)


def _register_with_nested(cls: type) -> None:
    register_value_type(cls)
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # a forward reference not resolvable yet: the fields' own types, as written
        hints = {f.name: f.type for f in dataclasses.fields(cls)}
    pending = list(hints.values())
    while pending:
        tp = pending.pop()
        if isinstance(tp, type) and dataclasses.is_dataclass(tp):
            if not is_value_type(tp):
                _register_with_nested(tp)
        else:
            pending.extend(typing.get_args(tp))


def is_io(tp: object) -> bool:
    return isinstance(tp, type) and tp.__dict__.get("__retriever_io__", False) is True


# ---------------------------------------------------------------------------------------------
# Ports
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PortSpec:
    """One input or output port: its name, declared type and (inputs) its MISSING fallback."""

    name: str
    type: Any = Any  # a class, a typing form, or a str naming an unresolved type
    default: Any = _NO_DEFAULT
    default_factory: Any = _NO_DEFAULT
    optional: bool = False

    @property
    def required(self) -> bool:
        """True when MISSING on this port skips the tick (no default, not Optional)."""
        return self.default is _NO_DEFAULT and self.default_factory is _NO_DEFAULT and not self.optional

    def fallback(self) -> Any:
        """The value a MISSING input becomes: the default, a fresh factory value, or None."""
        if self.default is not _NO_DEFAULT:
            return self.default
        if self.default_factory is not _NO_DEFAULT:
            return self.default_factory()
        return None

    @property
    def type_name(self) -> str:
        return type_name(self.type)


def snake_case(name: str) -> str:
    s = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name)
    return re.sub(r"\W+", "_", s).strip("_").lower()


def type_name(tp: Any) -> str:
    """Readable, stable name of a port type as the IR records it."""
    if tp is Any or tp is inspect.Parameter.empty:
        return "Any"
    if isinstance(tp, str):
        return tp
    if isinstance(tp, typing.ForwardRef):
        return tp.__forward_arg__
    if tp is type(None):
        return "None"
    if isinstance(tp, type) and not typing.get_args(tp):
        return tp.__qualname__ if tp.__module__ == "builtins" else f"{tp.__module__}.{tp.__qualname__}"
    return repr(tp).replace("typing.", "")


def _is_optional(tp: Any) -> bool:
    origin = typing.get_origin(tp)
    return origin in (typing.Union, types.UnionType) and type(None) in typing.get_args(tp)


def _resolve(tp: Any, module: str) -> Any:
    """Resolve a string/ForwardRef against the module it was written in; keep it opaque if unknown."""
    if isinstance(tp, typing.ForwardRef):
        tp = tp.__forward_arg__
    if isinstance(tp, str):
        namespace = vars(sys.modules[module]) if module in sys.modules else {}
        try:
            return eval(tp, dict(namespace))  # annotations are code the user wrote
        except Exception:
            return tp
    return tp


def _io_ports(cls: type) -> dict[str, PortSpec]:
    try:
        hints = typing.get_type_hints(cls)
    except Exception:
        hints = {}
    ports = {}
    for f in dataclasses.fields(cls):
        tp = hints.get(f.name, _resolve(f.type, cls.__module__))
        default = _NO_DEFAULT if f.default is dataclasses.MISSING else f.default
        factory = _NO_DEFAULT if f.default_factory is dataclasses.MISSING else f.default_factory
        ports[f.name] = PortSpec(f.name, tp, default, factory, _is_optional(tp))
    return ports


def _single_port(tp: Any) -> dict[str, PortSpec]:
    name = snake_case(type_name(tp).rpartition(".")[2].split("[")[0]) or "value"
    return {name: PortSpec(name, tp)}


# ---------------------------------------------------------------------------------------------
# What a Flow class declares
# ---------------------------------------------------------------------------------------------
@dataclass
class FlowSpec:
    """The ports and calling convention of a Flow class, derived once per class."""

    cls: type
    has_step: bool
    typed: bool
    in_mode: str  # "io" | "single" | "params" | "none"
    out_mode: str  # "io" | "single" | "dict"
    in_type: Any = None
    out_type: Any = None
    inputs: dict[str, PortSpec] = field(default_factory=dict)
    outputs: dict[str, PortSpec] | None = None  # None: untyped, ports named by outgoing edges
    source_takes_arg: bool = False
    problems: list[str] = field(default_factory=list)
    #: untyped: the output ports its step() can return, when every ``return`` in its source is a
    #: dict literal with string keys (or None); None when that cannot be told without running it
    returned_keys: frozenset | None = None
    #: untyped: the input ports in the order of step()'s parameters when it takes them all
    #: positionally (no ``*``, no keyword-only, its own signature: not a wrapper's); else None
    positional: tuple[str, ...] | None = None

    @property
    def is_source(self) -> bool:
        return self.in_mode == "none"


_specs: dict[type, FlowSpec] = {}


def _flow_type_args(cls: type) -> tuple[Any, Any] | None:
    for klass in cls.__mro__:
        for base in klass.__dict__.get("__orig_bases__", ()):
            if typing.get_origin(base) is Flow:
                args = typing.get_args(base)
                if len(args) == 2 and not any(isinstance(a, TypeVar) for a in args):
                    return args
    return None


def flow_spec(cls: type) -> FlowSpec:
    """The :class:`FlowSpec` of a Flow subclass (cached)."""
    spec = _specs.get(cls)
    if spec is None:
        spec = _specs[cls] = _derive_spec(cls)
    return spec


def _derive_spec(cls: type) -> FlowSpec:
    step = getattr(cls, "step", None)
    has_step = step is not None and step is not Flow.step
    params = []
    if has_step:
        try:
            params = list(inspect.signature(step).parameters.values())[1:]
        except (TypeError, ValueError):
            params = []
    args = _flow_type_args(cls)
    if args is not None:
        in_t, out_t = (_resolve(a, cls.__module__) for a in args)
        spec = FlowSpec(cls, has_step, True, "none", "single", in_t, out_t)
        if in_t is None or in_t is type(None):
            spec.in_mode = "none"
            spec.source_takes_arg = bool(params) and params[0].kind in (
                inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        elif is_io(in_t):
            spec.in_mode, spec.inputs = "io", _io_ports(in_t)
        else:
            spec.in_mode, spec.inputs = "single", _single_port(in_t)
        if is_io(out_t):
            spec.out_mode, spec.outputs = "io", _io_ports(out_t)
        elif out_t is None or out_t is type(None):
            spec.out_mode, spec.outputs = "io", {}
        else:
            spec.out_mode, spec.outputs = "single", _single_port(out_t)
        return spec
    spec = FlowSpec(cls, has_step, False, "params", "dict")
    spec.returned_keys = _returned_keys(step) if has_step else None
    try:
        hints = typing.get_type_hints(step) if has_step else {}
    except Exception:
        hints = {}
    for p in params:
        if p.kind in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD):
            spec.problems.append(
                f"step(…, {'*' if p.kind is p.VAR_POSITIONAL else '**'}{p.name}) cannot declare ports; "
                "name one parameter per input port")
            continue
        tp = hints.get(p.name, Any)
        default = _NO_DEFAULT if p.default is inspect.Parameter.empty else p.default
        spec.inputs[p.name] = PortSpec(p.name, tp, default, optional=_is_optional(tp))
    if not spec.inputs:
        spec.in_mode = "none"
    elif not spec.problems:
        spec.positional = _positional(step)
    return spec


def _positional(step: Callable) -> tuple[str, ...] | None:
    """The names of ``step``'s parameters after self, if a call may pass them all by position:
    read from the function's code, which is how a call binds (not from a signature a wrapper may
    claim): each parameter positional-or-keyword, no ``*args``, no ``**kwargs``."""
    code = getattr(step, "__code__", None)
    if type(step) is not types.FunctionType or code is None:
        return None
    gathers = code.co_flags & (inspect.CO_VARARGS | inspect.CO_VARKEYWORDS)
    if code.co_posonlyargcount or code.co_kwonlyargcount or gathers:
        return None
    return code.co_varnames[1:code.co_argcount] or None


def _returned_keys(step: Callable) -> frozenset | None:
    """The keys of the dict literals ``step`` returns, read from its source (never run): None
    unless every ``return`` is one with constant string keys, or returns None, and ``step`` is
    the function its source says (a decorator's wrapper may return what it likes; getsource
    would read the wrapped function's source)."""
    if hasattr(step, "__wrapped__"):
        return None
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(step)))
    except (OSError, TypeError, SyntaxError, ValueError):
        return None
    func = tree.body[0] if tree.body and isinstance(tree.body[0], (ast.FunctionDef, ast.AsyncFunctionDef)) else None
    if func is None or func.decorator_list:
        return None
    keys: set[str] = set()
    returns = [node for node in ast.walk(func) if isinstance(node, ast.Return)]
    unclear = [node for node in ast.walk(func) if isinstance(node, (ast.Yield, ast.YieldFrom, ast.Lambda))
               or (node is not func and isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)))]
    if unclear or not returns:
        return None
    for node in returns:
        value = node.value
        if value is None or (isinstance(value, ast.Constant) and value.value is None):
            continue
        if not isinstance(value, ast.Dict) or not all(isinstance(k, ast.Constant) and isinstance(k.value, str)
                                                      for k in value.keys):
            return None
        keys.update(k.value for k in value.keys)
    return frozenset(keys)


# ---------------------------------------------------------------------------------------------
# Per-instance runtime settings (kept off the user's attribute namespace)
# ---------------------------------------------------------------------------------------------
@dataclass
class FlowSettings:
    args: tuple
    kwargs: dict
    clock: Clock | None = None
    name: str | None = None
    latency: float = 0.0
    latency_ns: int = 0
    on_error: str = "stop"
    on_overrun: str = "skip"
    on_deadline_miss: str = "publish_late"
    replay: str = "rerun"
    #: real time: seconds before each Rate tick to stop sleeping and busy-wait to it (configure(spin=))
    spin: float = 0.0
    spin_ns: int = 0
    #: real time: the worker process it shares with the other flows of that name (configure(process=))
    process: str | None = None
    #: the pipeline the flow belongs to (a weak reference: a flow does not keep a pipeline alive)
    pipeline: Callable[[], Any] | None = field(default=None, repr=False, compare=False)
    max_restarts: int = MAX_RESTARTS
    restart_window: float = RESTART_WINDOW_S
    #: set_up(): whether setup() ran and teardown() has not; the attributes setup() bound
    #: (the default reset() keeps them)
    is_set_up: bool = field(default=False, compare=False)
    setup_attrs: tuple = field(default=(), compare=False)
    #: what the flow said of its current tick with add_step_detail(): its step record's detail["flow"]
    step_detail: dict = field(default_factory=dict, repr=False, compare=False)


def _shown(name: object, most: int = 40) -> str:
    """``name``'s repr for an error, a long one cut with its length said (the length may be its fault)."""
    text = repr(name)
    if len(text) <= most:
        return text
    return f"{text[:most]}… ({len(name)} characters)" if isinstance(name, str) else f"{text[:most]}…"


def _choice(owner: str, name: str, value: str, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise ValueError(f"{owner}: {name}={value!r} is not one of {', '.join(map(repr, allowed))}")
    return value


class Flow(Generic[In, Out]):
    """A stateful module with a synchronous ``step``; the runtime decides when and with what.

    Subclasses implement ``step`` and, optionally, ``setup``, ``teardown`` and ``reset``. They
    need not call ``super().__init__()``. Bind a clock with ``flow @ Rate(hz=30)``; wire with
    ``a.then(b)``.

    Lifecycle: ``__init__`` runs wherever the pipeline is built (on ``zenoh``, also in every
    worker process that imports the script), so keep it cheap: store the arguments. Heavy work
    (model weights, devices, sockets) goes in ``setup()``, which every backend calls once per
    run, in the process that steps the flow, before its first tick; ``teardown()`` releases it
    when the flow's run is over (after its last tick, also after an error). ``reset()`` keeps
    what ``setup()`` made.
    """

    _retriever: FlowSettings

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # the seed paper's spelling: a flow whose method is ``run`` (Listing 4) steps with it
        if "run" in cls.__dict__ and callable(cls.__dict__["run"]) and getattr(cls, "step", None) is Flow.step:
            cls.step = cls.__dict__["run"]

    def __new__(cls, *args: Any, **kwargs: Any):
        self = super().__new__(cls)
        self.__dict__["_retriever"] = FlowSettings(args, dict(kwargs))
        pipe = declaring.current_pipeline()
        if pipe is not None:
            pipe.add(self)
        return self

    def step(self, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError(
            f"{type(self).__qualname__} has no step() method\n"
            "    hint: define step(self, inp) (typed) or step(self, port_a, ...) (untyped)")

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """Call ``step`` directly, with no runtime: ``flow(In(...))``."""
        return self.step(*args, **kwargs)

    def add_step_detail(self, **detail: Any) -> None:
        """Say something of the tick running now in its step record: ``detail`` (names to values
        Retriever encodes: numbers, strings, lists, dicts) lands under ``detail["flow"]`` of the
        record, in the trace and the log, on every backend (``retriever log show`` prints it).
        For what a flow counts that no event shows (messages it dropped, bytes it could not read).
        Called in ``step()``; said in ``setup()`` or ``teardown()``, it goes with the next record."""
        self._retriever.step_detail.update(detail)

    def setup(self) -> None:
        """Acquire what is heavy or belongs to one process (weights, a GPU, a camera, a socket):
        called once per run in the process that steps this flow, before its first tick, on the
        thread that then runs every ``step()`` (so a thread-bound handle, such as an OpenGL/EGL
        context, may be made here). The attributes it sets survive the default ``reset()``."""

    def teardown(self) -> None:
        """Release what ``setup()`` acquired: called once, in the same process, when the flow's
        run is over (its last tick ran, the run stopped or failed); not after a crash."""

    def reset(self) -> None:
        """Restore the initial state. By default, re-run ``__init__`` with the original arguments,
        keeping the attributes ``setup()`` set (a loaded model stays loaded).

        Override it when state lives elsewhere. Backends call it on ``pipe.reset()``, on
        ``on_error="restart"``, and at the start of a run for classes that define their own
        ``reset`` (the paper's pattern of initialising state there).
        """
        settings = self._retriever
        kept = {k: self.__dict__[k] for k in settings.setup_attrs if k in self.__dict__}
        self.__dict__.clear()
        self.__dict__["_retriever"] = settings
        init = type(self).__init__
        if init is not object.__init__:
            init(self, *settings.args, **settings.kwargs)
        self.__dict__.update(kept)

    # -- graph building -------------------------------------------------------------------
    def __matmul__(self, clock: Clock):
        """Bind the flow's clock, in the pipeline of the enclosing ``with`` block if there is one."""
        if not isinstance(clock, Clock):
            return NotImplemented
        settings = self._retriever
        if settings.clock is not None and settings.clock != clock:
            raise ClockError(f"{self!r} @ {clock!r}: the flow already has the clock {settings.clock!r}, and a flow "
                             "has one clock\n    hint: to tick on a rate and on events, bind one Hybrid(hz=..., "
                             "trigger=[...])")
        pipe = declaring.current_pipeline()
        if pipe is not None:
            pipe.add(self)  # raises if the flow belongs to another pipeline
        settings.clock = clock
        return self

    def configure(self, *, name: str | None = None, latency: float | None = None,
                  on_error: str | None = None, on_overrun: str | None = None,
                  on_deadline_miss: str | None = None, max_restarts: int | None = None,
                  restart_window: float | None = None, replay: str | None = None,
                  spin: float | None = None, process: str | None = None):
        """Set this flow's node id, logical execution time (seconds) and failure policies;
        with ``on_error="restart"``, at most ``max_restarts`` restarts within any
        ``restart_window`` seconds of run time (more stop the run).

        ``replay="log"`` is for a flow whose step consults the world outside the program (a
        model behind a network endpoint, a human's input, a device): ``retriever replay`` then
        takes its outputs from the log instead of calling it (nor its ``setup()``), as it does
        for sources; its consumers are still re-executed and compared. The default, ``"rerun"``,
        re-executes the step and compares its outputs byte for byte.

        ``spin`` (seconds, at most 0.001; default 0) is for a control loop whose tick must start on
        time: in real time, its worker stops sleeping ``spin`` before each Rate tick and busy-waits
        to it, so the tick starts when due rather than when the OS wakes the process
        (benchmarks/control_jitter.py measures the lateness with and without it). The cost is CPU:
        up to ``spin`` per tick (``spin=100e-6`` at 200 Hz: at most 2% of a core).
        In virtual time it changes nothing.

        ``process`` (a name like a node id) puts the flow in one worker process with every other
        flow of that name, on the real-time backends: one interpreter, one Zenoh session, one
        thread stepping them in turn, and events between them handed over by reference (no
        encode, copy or network). What each tick reads and emits is the same as apart; when it
        runs may differ, since a long step of one holds up the others. Keep a flow that must be
        on time, that may crash, or that holds the GIL for long in a process of its own (the
        default). A flow that restarts (``on_error="restart"``) or whose process died starts
        again in a process of its own. In-process (``inproc``) it changes nothing.

        Returns the flow, so it chains: ``Policy().configure(latency=0.3) @ Rate(hz=2)``.
        """
        s = self._retriever
        owner = type(self).__qualname__
        if name is not None:
            if not isinstance(name, str) or not re.fullmatch(NODE_ID, name):
                raise ValueError(f"{owner}: node name {_shown(name)} must be an identifier-like str (letters, digits, "
                                 f"_ and -, at most {NAME_MAX}; it becomes a key-space segment and names files)")
            s.name = name
        if latency is not None:
            problem = seconds_problem("latency", latency)
            if problem is not None:
                raise ValueError(f"{owner}.configure(latency={latency!r}): {problem}\n    hint: latency is the "
                                 "flow's logical execution time, the seconds from a tick to its outputs")
            s.latency, s.latency_ns = latency, seconds_to_ns(latency)
        if on_error is not None:
            s.on_error = _choice(owner, "on_error", on_error, ON_ERROR)
        if on_overrun is not None:
            s.on_overrun = _choice(owner, "on_overrun", on_overrun, ON_OVERRUN)
        if on_deadline_miss is not None:
            s.on_deadline_miss = _choice(owner, "on_deadline_miss", on_deadline_miss, ON_DEADLINE_MISS)
        if replay is not None:
            s.replay = _choice(owner, "replay", replay, REPLAY)
        if max_restarts is not None:
            if type(max_restarts) is not int or max_restarts < 0:
                raise ValueError(f"{owner}: max_restarts={max_restarts!r} must be an integer >= 0")
            s.max_restarts = max_restarts
        if restart_window is not None:
            problem = seconds_problem("restart_window", restart_window)
            if problem is not None or restart_window == 0:
                raise ValueError(f"{owner}: {problem or 'restart_window must be more than 0 s, got 0'}")
            s.restart_window = restart_window
        if spin is not None:
            problem = (f"spin must be at most {MAX_SPIN_S:g} s (a busy-wait before each tick), got {spin!r:.40}"
                       if is_finite_number(spin) and spin > MAX_SPIN_S else seconds_problem("spin", spin))
            if problem is not None:
                raise ValueError(f"{owner}.configure(spin={spin!r:.40}): {problem}\n    hint: spin is how long before "
                                 "each tick its worker busy-waits instead of sleeping, e.g. spin=100e-6")
            s.spin, s.spin_ns = spin, seconds_to_ns(spin)
        if process is not None:
            if not isinstance(process, str) or not re.fullmatch(NODE_ID, process):
                raise ValueError(f"{owner}.configure(process={_shown(process)}): a process name must be an "
                                 f"identifier-like str (letters, digits, _ and -, at most {NAME_MAX}), "
                                 "e.g. process='perception'")
            s.process = process
        return self

    def named(self, name: str):
        """Set this flow's node id; shorthand for ``configure(name=...)``."""
        return self.configure(name=name)

    def then(self, other: "Flow", sync=None, map: dict[str, str] | None = None,
             delay: float = 0.0, qsize: int = 10, deadline: float | None = None) -> "Flow":
        """Connect this flow to ``other`` in the current pipeline; returns ``other`` to chain."""
        pipe = declaring.current_pipeline()
        if pipe is None:
            raise RuntimeError(
                f"{type(self).__qualname__}.then(...) was called outside a `with Pipeline(...)` block\n"
                "    hint: wrap the wiring in `with Pipeline(\"name\") as pipe:` or use pipe.connect(a, b)")
        pipe.connect(self, other, sync=sync, map=map, delay=delay, qsize=qsize, deadline=deadline, _stacklevel=3)
        return other

    def __repr__(self) -> str:
        s = self._retriever
        name = f" {s.name!r}" if s.name else ""
        clock = f" @ {s.clock!r}" if s.clock is not None else ""
        return f"<{type(self).__qualname__}{name}{clock}>"


def settings_of(flow: Flow) -> FlowSettings:
    """The settings ``configure()`` and ``@`` gave ``flow`` (its name, clock, latency, policies):
    how the graph, the pipeline and a flow's own code read them. They live under a name of their
    own so that they never collide with the attributes a user gives a flow."""
    return flow.__dict__["_retriever"]


# ---------------------------------------------------------------------------------------------
# Calling a flow from a runtime
# ---------------------------------------------------------------------------------------------
def set_up(flow: Flow) -> None:
    """Call ``flow.setup()`` unless it ran already (and ``teardown()`` did not); remember the
    attributes it bound, which the default ``reset()`` keeps."""
    settings = flow._retriever
    if settings.is_set_up:
        return
    before = dict(flow.__dict__)
    flow.setup()
    settings.is_set_up = True
    settings.setup_attrs = tuple(k for k, v in flow.__dict__.items()
                                 if k != "_retriever" and (k not in before or before[k] is not v))


def tear_down(flow: Flow) -> None:
    """Call ``flow.teardown()`` if ``setup()`` ran and it did not yet."""
    settings = flow._retriever
    if settings.is_set_up:
        settings.is_set_up = False
        flow.teardown()


def with_step_detail(flow: Flow, detail: dict | None) -> dict | None:
    """``detail`` of a step record of ``flow``, with what the flow said of the tick
    (:meth:`Flow.add_step_detail`) under ``"flow"``; that is then said."""
    said = flow._retriever.step_detail
    if not said:
        return detail
    taken = dict(said)
    said.clear()  # in place: the in-process backend's compiled ticks look at this one dict
    return {**(detail or {}), "flow": taken}


def make_invoker(flow: Flow, spec: FlowSpec) -> Callable[[dict], Any]:
    """A function ``values -> raw step output`` for one flow instance."""
    step = flow.step
    if spec.in_mode == "io":
        in_type = spec.in_type
        return lambda values: step(in_type(**values))
    if spec.in_mode == "single":
        (port,) = spec.inputs
        return lambda values: step(values[port])
    if spec.in_mode == "params":
        return lambda values: step(**values)
    if spec.source_takes_arg:
        return lambda values: step(None)
    return lambda values: step()


def make_output_reader(spec: FlowSpec) -> Callable[[Any], Any]:
    """A function ``raw step output -> iterable of (port, value)``; a ``None`` value is no event
    and the caller skips it (so a dict output is handed over as its ``items()``, uncopied)."""
    if spec.out_mode == "io":
        out_type, names = spec.out_type, tuple(spec.outputs or ())
        known = frozenset(names)

        def read_io(raw):
            if raw is None:
                return []
            if type(raw) is out_type or isinstance(raw, out_type):
                events = []  # (a loop, not a comprehension: one call less per step)
                for n in names:
                    if (v := getattr(raw, n)) is not None:
                        events.append((n, v))
                return events
            if isinstance(raw, dict):
                if not known.issuperset(raw):
                    unknown = ", ".join(repr(k) for k in raw if k not in known)
                    raise OutputError(f"step() returned a dict with port(s) {unknown}, which {type_name(out_type)} "
                                      f"does not declare (its ports: {', '.join(names)})")
                return raw.items()
            raise OutputError(f"step() returned {type(raw).__qualname__}, expected {type_name(out_type)}")

        return read_io
    if spec.out_mode == "single":
        (port,) = spec.outputs
        return lambda raw: [] if raw is None else [(port, raw)]

    def read_dict(raw):
        if type(raw) is dict:
            return raw.items()
        if raw is None:
            return ()
        if isinstance(raw, dict):
            return raw.items()
        raise OutputError(f"an untyped flow's step() must return a dict of output ports or None, "
                          f"got {type(raw).__qualname__}")

    return read_dict
