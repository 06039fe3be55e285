"""Real-time chunking from event time: which rows of a policy's earlier chunks the controller
executes from the policy's tick on, known exactly from the tags (docs/learning.md, "Real-time
chunking, from event time").

A chunked policy ticking at ``t`` with latency ``L`` emits its new chunk at tag ``(t + L, 0)``
(``(t, 1)`` without latency); a controller on ``Rate(control_hz)`` behind an
``ActionChunking(chunk_hz)`` edge takes, at each of its ticks ``c``, the newest chunk whose tag is
``≤ (c, 0)``, row ``floor((c − t0) · chunk_hz)`` with ``t0`` the chunk's tag time, holding the last
row past its end. So the rows it executes while the new chunk is on its way, and those it would
execute after, follow from the tags alone, at any control rate::

    policy tick t                     new chunk's tag t + L
        │ c0    c1    c2    c3    c4  │ c5    c6 ...          controller ticks
        │ old   old   old   old   old │ new   new
        └──── delay = 5 ticks ────────┘

LeRobot's real-time chunking (RTC) takes exactly this: the leftover of the previous chunk from
the tick on (``prev_chunk_left_over``) and the number of steps that run before the new chunk
takes over (``inference_delay``).

Times here are nanoseconds since the run's start (``T0``): every Rate clock is phase-aligned to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..clocks import Rate
from ..time import NS_PER_S, rate_problem, seconds_problem, seconds_to_ns


@dataclass(frozen=True)
class Leftover:
    """What the controller executes of earlier chunks, from a policy tick on.

    ``rows[i]`` is ``(chunk, row)`` at the ``i``-th controller tick at or after the policy's tick:
    the chunk (its index among those the policy emitted, 0 first) and the row of it that tick
    plays. The first ``delay`` of them run before the new chunk takes over (a chunk already
    exhausted holds its last row there); the rest are what the earlier chunk would still play
    after (until its last row). ``rows`` is empty when no chunk is playing yet at the tick."""

    rows: tuple[tuple[int, int], ...]
    delay: int


@dataclass
class _Chunk:
    index: int
    visible: tuple[int, int]  # its event's tag: a controller tick at (c, 0) >= this sees it
    t0: int  # its start: the tag time
    length: int


@dataclass
class ChunkTimeline:
    """The chunks one policy emitted, placed on its controller's clock.

    ``control_hz``/``control_offset`` are the controller's ``Rate``; ``chunk_hz`` is the
    ``ActionChunking`` edge's ``control_hz`` (by default the controller's rate); ``latency`` the
    policy's declared latency (seconds)."""

    control_hz: float
    latency: float = 0.0
    chunk_hz: float | None = None
    control_offset: float = 0.0
    #: the chunks a controller tick from the last one added on may still play, oldest first
    chunks: list[_Chunk] = field(default_factory=list, init=False)
    emitted: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        problems = [problem for name in ("control_hz", "chunk_hz") if getattr(self, name) is not None
                    and (problem := rate_problem(name, getattr(self, name))) is not None]
        problems += [problem for name in ("latency", "control_offset")
                     if (problem := seconds_problem(name, getattr(self, name))) is not None]
        if problems:
            raise ValueError("ChunkTimeline: " + "; ".join(problems))
        self._clock = Rate(self.control_hz, offset=self.control_offset)
        self._latency_ns = seconds_to_ns(self.latency)  # as the flow's configure(latency=) counts it
        self._chunk_hz = self._clock.hz if self.chunk_hz is None else Rate(self.chunk_hz).hz

    def _tag_of_chunk(self, tick_ns: int) -> tuple[int, int]:
        return (tick_ns + self._latency_ns, 0) if self._latency_ns else (tick_ns, 1)

    def _playing(self, c: int) -> _Chunk | None:
        """The chunk a controller tick at ``c`` plays: the newest it sees (ActionChunking's rule)."""
        playing = None
        for chunk in self.chunks:
            if chunk.visible <= (c, 0):
                playing = chunk
        return playing

    def _row(self, chunk: _Chunk, c: int) -> int:
        """The row of ``chunk`` for a controller tick at ``c``; past its end, not yet held."""
        hz = self._chunk_hz
        return (c - chunk.t0) * hz.numerator // (NS_PER_S * hz.denominator)

    def leftover(self, tick_ns: int) -> Leftover:
        """The :class:`Leftover` for the policy's tick at ``tick_ns``, before its own chunk."""
        new_visible = self._tag_of_chunk(tick_ns)
        clock = self._clock
        first = clock.first_tick_at_or_after(tick_ns)
        delay = 0
        while (clock.tick_time(first + delay), 0) < new_visible:
            delay += 1
        if self._playing(clock.tick_time(first)) is None:
            return Leftover((), delay)
        rows: list[tuple[int, int]] = []
        while True:
            c = clock.tick_time(first + len(rows))
            chunk = self._playing(c)
            row = self._row(chunk, c)
            if len(rows) >= delay and row >= chunk.length:
                return Leftover(tuple(rows), delay)
            rows.append((chunk.index, min(row, chunk.length - 1)))

    def add(self, tick_ns: int, length: int) -> int:
        """Record the chunk of ``length`` rows emitted at the tick at ``tick_ns``; its index.
        Chunks that no controller tick from now on can play are forgotten."""
        if type(length) is not int or length < 1:
            raise ValueError(f"ChunkTimeline.add: a chunk has at least one row, got length={length!r}")
        tag = self._tag_of_chunk(tick_ns)
        self.chunks.append(_Chunk(self.emitted, tag, tag[0], length))
        self.emitted += 1
        first = self._clock.tick_time(self._clock.first_tick_at_or_after(tick_ns))
        while len(self.chunks) > 1 and self.chunks[1].visible <= (first, 0):
            self.chunks.pop(0)
        return self.emitted - 1
