"""The tick functions of an in-process session (backends/inproc.py): generated for every node whose
tick ``inproc_ticks`` can write, the reference ``tick.run_tick`` for the others; and what the
generated ones keep to themselves (counts, seqs, how far they looked into their buffers) until
they hand it to the nodes.

The session asks for the functions when a run starts (:meth:`CompiledTicks.functions`), has the
generated ticks hand over what they keep where that is safe (:meth:`CompiledTicks.flush`), and
has them forgotten when a node changes under them (:meth:`CompiledTicks.drop`: a replaced step,
replay's routes, a tick run from outside), to be generated anew for the next run.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..sync import PortBuffer, before, bound
from ..tick import run_tick
from . import inproc_ticks


class CompiledTicks:
    """One session's tick functions, and the surface the generated ones read of it (``host``)."""

    def __init__(self, records: Any, nodes: list, groups: list, agenda: Any, recorder: Any, *,
                 max_microsteps: int, plain_types: frozenset[type], microsteps: Callable, fuse: bool,
                 generate: bool = True):
        """``records``: the session's trace (its tape); ``nodes``: the NodeRuntimes, by index;
        ``groups``: the rate groups; ``agenda``, ``recorder``: where ticks are scheduled and their
        outcomes go; ``microsteps``: the session's loop over the next microsteps; ``fuse``: whether
        a rate group's ticks may run in one function (nothing shuffles them); ``generate``: whether
        to generate tick code at all (False: every node ticks through ``tick.run_tick``)."""
        self.records, self.nodes, self.groups, self.recorder, self.fuse = records, nodes, groups, recorder, fuse
        #: what the generated ticks call and read of the session; its ``look`` is set when the
        #: loop is to look at a stop asked for, a recompile, the flushes other threads wait for
        self.host = inproc_ticks.Host(
            nodes={rt.id: rt for rt in nodes}, tape=records.tape, after=agenda.after, heap=agenda.heap,
            max_microsteps=max_microsteps, plain_types=plain_types, emit=recorder.emit, skipped=recorder.skipped,
            failed=recorder.failed, schedule=agenda.schedule, keep_next=agenda.keep_next, saw_ports=self.saw_ports,
            microsteps=microsteps, resume_group=agenda.resume_group, bound=self.bound)
        #: per node index, the function that runs one tick, and the one that runs it when it is
        #: the only tick due, which may go on along a chain; None until :meth:`functions`
        self.ticks: list | None = None
        self.chains: list = []
        self.flushes: list = []  # flush() of the generated ticks: hand their counts to stats and rt.seq
        self.peeks: list = []  # and their peek(): those counts, left where they are
        #: and their visibles: per input buffer's id, how far its tick looked into it now
        self.visibles: dict[int, Callable[[], int]] = {}
        self.generic_only = False  # set by the session's take_routes(): replay delivers events itself
        self.recompile = False  # set by saw_ports(): generate the ticks anew between two instants
        self.generate = generate
        #: the ids of the nodes whose ticks were generated code, in any run of the session so far
        self.generated: set[str] = set()

    def functions(self) -> list:
        """Per node index, ``f(tau, (tau[0], tau[1] + 1))`` running one tick, generated where
        :func:`.inproc_ticks.compile_tick` can, else the reference ``tick.run_tick``; and, set here
        and on the rate groups: the same per node, when it is the only tick due, going on along
        a chain of Trigger flows (``chains``), and per rate group its ticks in order (one fused
        function, with ``fuse``) and its loop while nothing else is due (``alone``).
        Each returns the next microstep of the last tick it ran."""
        if self.ticks is not None:
            return self.ticks
        parts = []
        recorder = self.recorder
        for rt in self.nodes:
            code = None if self.generic_only or not self.generate else inproc_ticks.compile_tick(self.host, rt)
            if code is not None:
                self.generated.add(rt.id)
            parts.append(code or (lambda tau, out_tag, rt=rt, r=recorder: run_tick(rt, tau, r.skipped, r.failed,
                                                                                   r.emit) or out_tag))
        groups = [(group.order, (group.offset_ns, group.step_num, group.step_den)) for group in self.groups]
        if any(isinstance(part, inproc_ticks.NodeCode) for part in parts):
            ticks, chains, fused, alone, flush, peek, visibles = inproc_ticks.make_ticks(self.host, parts, groups,
                                                                                           fuse=self.fuse)
            self.flushes.append(flush)
            self.peeks.append(peek)
            self.visibles.update(visibles)
        else:
            ticks, chains, fused, alone = parts, parts, [], []
        for g, group in enumerate(self.groups):
            group.ticks = (fused[g],) if fused else tuple(ticks[i] for i in group.order)
            group.alone = alone[g] if alone else None
        self.ticks, self.chains = ticks, chains
        return ticks

    def flush(self) -> None:
        """Hand what the generated ticks counted and their seqs to the nodes: in the run's thread
        (the ticks change them), after expanding the tape (its expanders count steps), under the
        trace's lock (another thread may be expanding it)."""
        self.records.expand(then=self._hand_over)

    def _hand_over(self) -> None:
        for flush in self.flushes:
            flush()

    def drop(self) -> None:
        """Hand the generated ticks' counts back and forget them; the next :meth:`functions`
        generates them anew (from rt.seq, which the reference tick may change in between)."""
        self.flush()
        self.ticks, self.flushes, self.peeks, self.visibles = None, [], [], {}

    def bound(self, buf: PortBuffer, tau: tuple[int, int]) -> None:
        """A tick at ``tau`` filled ``buf`` to its ``bound_at``: forget what its consumer can no
        longer select (sync.bound). Every tick to come is at or after ``tau`` (ticks run in tag
        order); a generated tick's count of what it saw in ``buf`` stays where it is."""
        visible = self.visibles.get(id(buf))
        bound(buf, before(tau), None if visible is None else visible())

    def saw_ports(self, rt: Any, outputs: dict) -> None:
        """An untyped step returned ports its generated tick did not expect: the first time, expect them."""
        if rt.ports_seen is None and all(type(port) is str for port in outputs):
            rt.ports_seen = tuple(outputs)
            self.recompile = self.host.look = True

    def not_handed_over(self) -> dict[int, tuple[int, int, int]]:
        """Per node index, ``(ticks, steps, step ns)`` the generated ticks counted and did not
        hand over yet, changing nothing (for counts read where flushing is not safe)."""
        return {k: counted for peek in self.peeks for k, *counted in peek()}
