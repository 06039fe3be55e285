"""A run as training frames: one frame per tick of one flow (DESIGN.md §8, "A dataset frame is a tick").

A frame holds what the flow consumed on each input port at that tick, as its sync policy
selected it, and what it produced there. The events come from the flow's step record (its
``consumed`` and ``produced`` ids), never from arrival order; each input port's value is its
policy applied to exactly those events (a Window's list, an ActionChunking's row), checked to
select the ids the record names.

Values become features as :mod:`retriever.features` says (docs/learning.md, "From a log to a
dataset"): images, one state vector per port (its elements named by their paths, ``pose.q.0``),
text and ``None`` fields left out; an input's features are ``observation.*``, an output's
``action*``. A frame's features are its first frame's: a value whose shape or dtype changes from
frame to frame is refused.

Only ``ok`` and ``overrun`` ticks become frames (an overrun tick stepped on complete inputs and
produced its outputs; it only outlasted its period). A ``skipped``, ``incomplete``, ``late`` or
``error`` tick, a tick without a value on every port, a tick whose events the log lost, and a
Rate tick with no record at all are left out: before the first frame and after the last they are
dropped; between two frames they are a gap, which is refused (a dataset's frames are evenly spaced
in time, its readers index them so) or, with ``gaps="split"``, ends the episode there.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any, Callable, Iterator

import numpy as np

from ..errors import LogError, UnmappableError
from ..features import ACTION, OBSERVATION, FeatureError, excluded, feature_keys, port_features
from ..ir import IR
from ..plan import plan_ir
from ..sync import ActionChunking, PortBuffer
from ..time import NS_PER_S, exact_rational, format_tag, seconds_to_ns
from ..trace import StepRecord, StepStatus, Trace
from .reader import RunLog

#: the statuses of a tick that becomes a frame
FRAME_STATUSES = frozenset({StepStatus.OK, StepStatus.OVERRUN})
#: what a tick left out is counted as when it has no status of its own
NO_RECORD = "without a step record"
NO_VALUE = "without a value on {port}"
LOST = "whose events the log lost"
#: the key a text port is mapped to, to give each frame its task
TASK = "task"
GAPS = ("refuse", "split")

#: a state vector with more elements than this has no name per element (a dataset's names are then None)
NAMED_ELEMENTS_LIMIT = 1024

EventId = tuple[str, str, int]


@dataclass(frozen=True)
class Recording:
    """What an export reads of one run: its IR, its step records, and each event's tag and value."""

    name: str  # where it came from, for messages (a log's path)
    ir: IR
    steps: list[StepRecord]
    event: Callable[[EventId], tuple[tuple[int, int], Any] | None]  # None: not in the record

    @classmethod
    def of_log(cls, log: RunLog) -> "Recording":
        """A log's run; values decode without importing anything (a dataclass whose type this
        process did not register reads as its fields)."""
        events = {e.id: e for e in log.iter_events()}

        def event(event_id: EventId):
            logged = events.get(event_id)
            return None if logged is None else (logged.tag, log.value(logged, keep_unregistered=True))
        return cls(str(log.path), log.ir, list(log.iter_steps()), event)

    @classmethod
    def of_trace(cls, trace: Trace, ir: IR, name: str) -> "Recording":
        """A run held in memory: a pipeline's trace, or a replay's (``replay(log, keep_trace=True).trace``)."""
        events = {e.id: (e.tag, e.value) for e in trace.events}
        return cls(name, ir, list(trace.steps), events.get)


@dataclass(frozen=True)
class Feature:
    """One column of the dataset: an image, or a state vector with a name per element."""

    key: str
    source: str  # the path into the port's value it is taken from
    kind: str  # "image" or "state"
    dtype: np.dtype
    shape: tuple[int, ...]
    names: tuple[str, ...] = ()


@dataclass
class Frame:
    tick: tuple[int, int]
    timestamp: float  # seconds from the run's start: the tick's tag
    values: dict[str, np.ndarray]  # by feature key
    task: str | None  # from a port mapped to "task", else None


@dataclass
class Episode:
    """The frames of one stretch of consecutive ticks."""

    frames: list[Frame] = field(default_factory=list)


@dataclass(frozen=True)
class Mapping:
    """How ports become feature keys: ``maps`` renames a source (``port`` or ``port.field``) to
    a key (``task`` takes a text port as each frame's task); ``exclude`` leaves sources out."""

    maps: dict[str, str] = field(default_factory=dict)
    exclude: tuple[str, ...] = ()

    def excluded(self, source: str) -> bool:
        return excluded(source, self.exclude)


def parse_maps(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """``["port=key", ...]`` → ``{port: key}``, or LogError naming the bad item."""
    maps: dict[str, str] = {}
    for item in items:
        port, sep, key = item.partition("=")
        if not sep or not port.strip() or not key.strip():
            raise LogError(f"--map {item!r}: expected PORT=KEY",
                           "e.g. --map joints=observation.state --map cam=observation.images.front")
        maps[port.strip()] = key.strip()
    return maps


def flow_rate(ir: IR, flow: str, where: str) -> tuple[Fraction, int]:
    """The flow's Rate as an exact rational and its offset in ns, or LogError saying why not."""
    names = [n["id"] for n in ir.nodes]
    if flow not in names:
        raise LogError(f"{where} has no flow '{flow}' (its flows: {', '.join(sorted(names))})",
                       "pass the node id of the flow whose ticks are the frames: --flow NODE")
    clock = ir.node(flow)["config"].get("clock")
    kind = next(iter(clock)) if isinstance(clock, dict) and len(clock) == 1 else None
    if kind != "Rate":
        raise LogError(f"flow '{flow}' in {where} runs on a {kind or 'missing'} clock, not a Rate: a dataset's frames "
                       "are evenly spaced in time (its fps), and only a Rate flow's ticks are (a Trigger flow ticks "
                       "when its inputs arrive)", "export a flow on a Rate clock: --flow NODE")
    params = clock["Rate"]
    try:
        hz, offset = exact_rational(params["hz"]), seconds_to_ns(params.get("offset", 0.0))
        if hz <= 0:
            raise ValueError(hz)
    except (KeyError, TypeError, ValueError):
        raise LogError(f"the clock of flow '{flow}' in {where} is malformed: {clock!r:.80}",
                       "the file was changed after it was written") from None
    return hz, offset


def _tick_index(t: int, hz: Fraction, offset: int) -> int | None:
    """k such that ``t`` is the Rate's tick ``offset + floor(k·1e9/hz)``, or None if it is no tick."""
    k = -(-(t - offset) * hz.numerator // (NS_PER_S * hz.denominator))  # ceil
    return k if k >= 0 and offset + (k * NS_PER_S * hz.denominator) // hz.numerator == t else None


class _Inputs:
    """Each input port's sync policy and the delay of each edge into it: the flow's plan (plan.py)."""

    def __init__(self, ir: IR, flow: str, hz: Fraction):
        node = plan_ir(ir).nodes[flow]
        self.policies: dict[str, Any] = {
            port: policy.bound_to_rate(float(hz)) if isinstance(policy, ActionChunking) else policy
            for port, policy in node.policies.items()}
        #: (port, producer, its port) -> ns
        self.delays: dict[tuple[str, str, str], int] = {(f.port, f.src, f.src_port): f.delay_ns for f in node.feeds}

    def value(self, port: str, tau: tuple[int, int], events: list[tuple[EventId, tuple[int, int], Any]]) -> Any:
        """What the port's policy selects from exactly these events at ``tau``."""
        buf = PortBuffer()
        for (node, out, seq), tag, value in events:
            delay = self.delays.get((port, node, out), 0)
            buf.insert(((tag[0] + delay, 0) if delay else tag, node, out, seq, value))
        value, ids, _, _ = self.policies[port].select(buf, tau)
        if tuple(ids or ()) != tuple(e[0] for e in events):
            raise LogError(f"the step record at {format_tag(tau)} names events on port '{port}' that its sync policy "
                           "would not select from them", "the file was changed after it was written")
        return value


# -- values to features -----------------------------------------------------------------------
class _Features:
    """The features of a flow's frames, fixed by its first frame; every later frame is checked
    against them. How a value becomes named features is :mod:`retriever.features`'s."""

    def __init__(self, mapping: Mapping, inputs: list[str], outputs: list[str]):
        self.mapping = mapping
        self.sides = {**{p: OBSERVATION for p in inputs}, **{p: ACTION for p in outputs}}
        self.features: list[Feature] | None = None
        self.task_port: str | None = next((p for p, k in mapping.maps.items() if k == TASK), None)
        self.fields_left_out: list[str] = []
        #: the sources with NaN or infinite values: {source: (frames with one, the first's tick)}
        self.non_finite: dict[str, tuple[int, tuple[int, int]]] = {}

    def frame(self, tick: tuple[int, int], values: dict[str, Any],
              where: str) -> tuple[dict[str, np.ndarray], str | None]:
        """A tick's port values as feature values (and the task, if a port gives it)."""
        found: dict[str, tuple[str, np.ndarray]] = {}  # source -> (kind, array)
        names: dict[str, tuple[str, ...]] = {}
        task = None
        for port, value in values.items():
            try:
                taken = port_features(port, value, self.mapping.exclude)
            except FeatureError as e:
                raise UnmappableError(f"{where}: port '{port}' of the flow carries {e} (at {format_tag(tick)})",
                                      f"leave it out with --exclude {port}") from None
            if port == self.task_port:
                if taken.text is None:
                    raise UnmappableError(f"{where}: port '{port}' is mapped to the task, but carries a "
                                          f"{type(value).__name__}, not text",
                                          f"map a port whose value is text to {TASK}")
                task = taken.text
                continue
            if taken.text is not None:
                raise UnmappableError(f"{where}: port '{port}' of the flow carries text ({taken.text[:40]!r}), which "
                                      f"no feature holds but the task (at {format_tag(tick)})",
                                      f"leave it out with --exclude {port}, or make it the task: --map {port}={TASK}")
            found.update(taken.sources())
            if self.features is None:
                if taken.state is not None and taken.state.size <= NAMED_ELEMENTS_LIMIT:
                    names[port] = taken.state_names
                self.fields_left_out += taken.left_out
        if self.features is None:
            self.features = self._fix(found, names, where)
        return self._check(tick, found, where), task

    def _fix(self, found: dict[str, tuple[str, np.ndarray]], names: dict[str, tuple[str, ...]],
             where: str) -> list[Feature]:
        maps = {source: key for source, key in self.mapping.maps.items() if source != self.task_port}
        try:
            keys = feature_keys({source: kind for source, (kind, _) in found.items()}, self.sides, maps)
        except FeatureError as e:
            raise LogError(f"{where}: " + "\n    ".join(e.problems),
                           "--map SOURCE=KEY gives a port, or an image field as port.field, its own key") from None
        if not found:
            raise LogError(f"{where}: the flow's frames hold no feature", "export a flow with inputs or outputs")
        return [Feature(keys[source], source, kind, array.dtype, array.shape, names.get(source, ()))
                for source, (kind, array) in found.items()]

    def _check(self, tick, found: dict[str, tuple[str, np.ndarray]], where: str) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        for feature in self.features:
            kind, array = found.get(feature.source, (None, None))
            if array is None or kind != feature.kind or array.shape != feature.shape:
                had = "nothing" if array is None else f"{kind} {array.dtype}{list(array.shape)}"
                raise UnmappableError(f"{where}: '{feature.source}' gives {had} at {format_tag(tick)}, but "
                                      f"{feature.kind} {feature.dtype}{list(feature.shape)} at the first frame: "
                                      "a feature has one shape and dtype",
                                      f"leave it out with --exclude {feature.source}")
            if array.dtype != feature.dtype:
                if not np.can_cast(array.dtype, feature.dtype, "safe"):
                    raise UnmappableError(f"{where}: '{feature.source}' is {array.dtype} at {format_tag(tick)}, but "
                                          f"{feature.dtype} at the first frame", "give the port one dtype in the flow")
                array = array.astype(feature.dtype)
            if array.dtype.kind == "f" and not np.isfinite(array).all():
                count, first = self.non_finite.get(feature.source, (0, tick))
                self.non_finite[feature.source] = (count + 1, first)
            out[feature.key] = array
        extra = sorted(set(found) - {f.source for f in self.features})
        if extra:
            raise UnmappableError(f"{where}: '{extra[0]}' gives a value at {format_tag(tick)} that the first frame did "
                                  "not have", f"leave it out with --exclude {extra[0]}")
        return out


# -- ticks to frames ---------------------------------------------------------------------------
class FlowFrames:
    """The frames of ``flow``'s ticks in ``recording``: :meth:`episodes` yields them, episode by
    episode; then ``features`` (fixed by the first frame), ``left_out`` (ticks left out, by
    status, or NO_RECORD, NO_VALUE, LOST), ``non_finite`` (sources with NaN or inf), ``sparse`` (ports left out: :func:`_sparse_ports`) and
    ``fields_left_out`` (dataclass fields no feature holds) say what was taken. LogError for a
    flow that is not there or not on a Rate clock, a value no feature holds, or a gap between
    frames (unless ``gaps="split"``)."""

    def __init__(self, recording: Recording, flow: str, mapping: Mapping = Mapping(), gaps: str = "refuse"):
        if gaps not in GAPS:
            raise LogError(f"gaps={gaps!r}: expected one of {', '.join(GAPS)}")
        self.recording, self.flow, self.gaps = recording, flow, gaps
        self.fps, self._offset = flow_rate(recording.ir, flow, recording.name)
        self._inputs = _Inputs(recording.ir, flow, self.fps)
        self._steps = sorted((s for s in recording.steps if s.node == flow), key=lambda s: s.tag)
        ports = [*self._inputs.policies, *_outputs(recording.ir, flow, self._steps)]
        self.sparse = _sparse_ports(self._steps, ports, mapping)
        kept = [p for p in ports if not mapping.excluded(p) and p not in self.sparse]
        self._in_ports = sorted(p for p in kept if p in self._inputs.policies)
        self._out_ports = sorted(p for p in kept if p not in self._inputs.policies)
        self._features = _Features(mapping, self._in_ports, self._out_ports)
        self.left_out: Counter = Counter()

    @property
    def features(self) -> list[Feature]:
        return self._features.features or []

    @property
    def fields_left_out(self) -> list[str]:
        return self._features.fields_left_out

    @property
    def non_finite(self) -> dict[str, tuple[int, tuple[int, int]]]:
        return self._features.non_finite

    def episodes(self, progress: Callable[[int, int], None] | None = None) -> Iterator[Episode]:
        where, flow, hz, offset = self.recording.name, self.flow, self.fps, self._offset
        steps = self._steps
        pending: Counter = Counter()  # left out since the last frame: a gap, if a frame follows
        episode = Episode()
        last_k: int | None = None
        for i, step in enumerate(steps):
            if progress is not None:
                progress(i, len(steps))
            k = _tick_index(step.tag[0], hz, offset) if step.tag[1] == 0 else None
            if k is None:
                raise LogError(f"{where}: a step record of '{flow}' at {format_tag(step.tag)} is at no tick of its "
                               f"Rate ({float(hz):g} Hz)", "the file was changed after it was written")
            if last_k is not None and k <= last_k:
                raise LogError(f"{where}: '{flow}' has two step records at {format_tag(step.tag)}",
                               "the file was changed after it was written")
            if last_k is not None and k > last_k + 1:
                pending[NO_RECORD] += k - last_k - 1
            last_k = k
            values, why = _tick_values(self.recording, self._inputs, self._in_ports, self._out_ports, step)
            if why is not None:
                pending[why] += 1
                continue
            if pending:
                if episode.frames and self.gaps == "refuse":
                    what = ", ".join(f"{n} {status}" for status, n in sorted(pending.items()))
                    raise LogError(f"{where}: a gap between two frames of '{flow}': the {sum(pending.values())} "
                                   f"tick(s) before {format_tag(step.tag)} are no frame ({what}); a dataset's "
                                   "frames are evenly spaced in time, and its readers index them so",
                                   "pass --gaps split (gaps='split') to end the episode at each gap")
                self.left_out.update(pending)
                pending.clear()
                if episode.frames:
                    yield episode
                    episode = Episode()
            array_values, task = self._features.frame(step.tag, values, where)
            episode.frames.append(Frame(step.tag, step.tag[0] / NS_PER_S, array_values, task))
        self.left_out.update(pending)
        if progress is not None:
            progress(len(steps), len(steps))
        if episode.frames:
            yield episode


def _outputs(ir: IR, flow: str, steps: list[StepRecord]) -> list[str]:
    """The flow's output ports: its typed outputs in the IR, and every port its step records say it
    produced on (an untyped flow's output that no edge reads is in no IR)."""
    ports = dict.fromkeys(ir.node(flow).get("outputs", {}))
    for step in steps:
        ports.update(dict.fromkeys(event_id[1] for event_id in step.produced))
    return list(ports)


def _sparse_ports(steps: list[StepRecord], ports: list[str], mapping: Mapping) -> dict[str, tuple[int, int]]:
    """The ports with a value at fewer than half of the flow's frame ticks (an event now and then:
    a flag, a report, a Queue mostly empty), which a frame leaves out unless ``--map`` names them:
    ``{port: (ticks with a value, frame ticks)}``."""
    ticks = [s for s in steps if s.status in FRAME_STATUSES]
    had = Counter(p for s in ticks for p in {*(p for p, ids in s.consumed.items() if ids), *(i[1] for i in s.produced)})
    return {p: (had[p], len(ticks)) for p in ports if 2 * had[p] < len(ticks) and p not in mapping.maps}


def _tick_values(recording: Recording, inputs: _Inputs, in_ports: list[str], out_ports: list[str],
                 step: StepRecord) -> tuple[dict[str, Any], str | None]:
    """The port values of a tick, or why it is no frame."""
    if step.status not in FRAME_STATUSES:
        return {}, step.status
    values: dict[str, Any] = {}
    for port in in_ports:
        ids = step.consumed.get(port)
        if not ids:
            return {}, NO_VALUE.format(port=port)
        events = []
        for event_id in ids:
            got = recording.event(event_id)
            if got is None:
                return {}, LOST
            events.append((event_id, *got))
        values[port] = inputs.value(port, step.tag, events)
    produced = {event_id[1]: event_id for event_id in step.produced}
    for port in out_ports:
        if port not in produced:
            return {}, NO_VALUE.format(port=port)
        got = recording.event(produced[port])
        if got is None:
            return {}, LOST
        values[port] = got[1]
    return values, None
