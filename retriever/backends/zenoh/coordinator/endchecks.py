"""What the coordinator checks and says once a run is over (and, for starvation, while it runs).

A run that looks fine with something missing is worse than none: messages refused as forged
are counted and warned of; a step's sys.exit(0) whose record never came fails the run; a flow
whose clock had ticks due and ran none fails it; a flow that never stepped because its inputs
came late is warned of, with the fix; starved inputs are said at once and logged at the end.
"""

from __future__ import annotations

import sys
import warnings

from ....errors import BackendError, RetrieverWarning
from ....trace import Trace
from .book import RunBook

#: how many frames up from a check its warning names: the user's pipe.run (through Coordinator.advance)
WARN_STACKLEVEL = 4


def ticks_due(clock, end_ns: int) -> int:
    """How many ticks of a rate clock fall in [0, end_ns): the first at or after the end counts
    them; 0 for a clock without a rate (a Trigger ticks only on what arrives)."""
    first_at_or_after = getattr(clock, "first_tick_at_or_after", None)
    return first_at_or_after(end_ns) if first_at_or_after is not None else 0


def warn_forged(book: RunBook) -> None:
    """Messages and records refused as forged (origin.py): the run stands, and says so."""
    book.tell_forged()
    if book.counts["forged"]:
        warnings.warn(f"{book.counts['forged']} message(s) or record(s) on the run's key space were refused: "
                      f"no process of the run's node made them ({'; '.join(book.processes.senders.reasons)})\n"
                      "    hint: a process holding the run's secret or password put them; none reached the "
                      "trace or the log (pipe.counts()['forged'])", RetrieverWarning, stacklevel=WARN_STACKLEVEL)


def exit_unrecorded(book: RunBook) -> str | None:
    """A node whose process said its step called sys.exit(0), and never sent the record of that step."""
    return next((node for node, said in sorted(book.ending.exit_said.items(), key=lambda item: item[0])
                 if book.ending.exit_recorded.get(node) != said), None)


def check_exit_recorded(book: RunBook, backend_name: str) -> None:
    """A node whose process said its step called sys.exit(0) and never sent that step's
    record did not end the run: the run went on, and fails saying so."""
    node = exit_unrecorded(book)
    if node is not None:
        raise BackendError(f"{backend_name} run: the process of '{node}' said its step called sys.exit(0) "
                           f"at {book.ending.exit_said[node][0]}, and never sent the record of that step: the run "
                           "went on without it")


def check_every_flow_ticked(book: RunBook, backend_name: str, start_margin_ns: int) -> None:
    """A flow with a rate that had ticks due in the run's window, and ran none, fails the
    run: a run that exits 0 with flows that never ran looks fine and is not, which is worse
    than one that fails. Its worker's ``done`` says what it saw."""
    if book.ending.ended_by is not None:  # a step's sys.exit(0) ended the run before its end
        return
    idle = []
    for nid, node in book.graph.nodes.items():
        due = ticks_due(node.clock, book.end_ns)
        if due == 0 or book.intake.stats[nid].ticks > 0:
            continue
        said = book.intake.done_info.get(nid, {})
        if said.get("ticks"):
            why = f"its worker ran {said['ticks']} ticks, whose step records never reached the coordinator"
        elif "started_ns" in said:
            why = f"its worker ran none; the run's start reached it {said['started_ns'] / 1e9:.2f} s after T0"
        else:
            why = "its worker stopped before the run's start reached it"
        idle.append(f"    {nid} ({node.clock!r}): 0 of {due} ticks; {why}")
    if idle:
        raise BackendError(f"{backend_name} run: {len(idle)} flow(s) never ticked in the run's "
                           f"{book.end_ns / 1e9:g} s, though their clocks had ticks due:\n" + "\n".join(idle)
                           + "\n    hint: a machine too loaded to start the run's processes in time needs a "
                           f"later start: pipe.run(..., start_margin=seconds) (now {start_margin_ns / 1e9:g})")


def say_starved(book: RunBook) -> None:
    """Say at once which input starves (its node skips tick after tick while its producer makes
    events), and when one that did has an event again."""
    news, book.intake.starvation.news = book.intake.starvation.news, []
    for what, episode in news:
        node, port = episode["node"], episode["port"]
        if what == "starved":
            print(f"retriever: warning: node '{node}' is starved: its input '{port}' has had no event since "
                  f"t={episode['since_ns'] / 1e9:.3f} s ({episode['ticks']} ticks), while "
                  f"{' and '.join(episode['producers'])} made {episode['produced']} events there"
                  "\n    hint: its step records say why each tick went without (retriever log cat LOG "
                  f"--steps); `retriever status` shows whether it recovers", file=sys.stderr, flush=True)
        else:
            print(f"retriever: node '{node}' has events on its input '{port}' again at "
                  f"t={episode['until_ns'] / 1e9:.3f} s, after {episode['ticks']} ticks without",
                  file=sys.stderr, flush=True)


def record_starved(book: RunBook, log) -> None:
    """Log each starved span (the run ends: one still starved lasted to its end)."""
    if book.intake.starvation.news:
        say_starved(book)
    if log is not None:
        for episode in book.intake.starvation.episodes:
            log.add_starved(episode)


def warn_starved_by_late_events(book: RunBook, trace: Trace) -> None:
    """A flow that never stepped though events came on its inputs, late (after the ticks they
    were for): say which edge, and the fix. The run stands (it did what its policies say)."""
    for nid, stats in sorted(book.intake.stats.items()):
        if stats.steps or not stats.counts.get("late"):
            continue
        ports = sorted({port for node, _, _, _, _, detail, *_ in trace.raw_steps
                        if node == nid and detail for port in (detail.get("late") or {})})
        # the edges into the ports the step records name (none are kept under keep="counters"),
        # whose producer made any event: another into the same port may have been silent
        into = [e for e in book.graph.edges if e.dst == nid and (e.src, e.src_port) in book.intake.max_seq]
        edges = [e for e in into if e.dst_port in ports] or into
        names = ", ".join(f"{e.src}.{e.src_port} → {nid}.{e.dst_port}" for e in edges)
        e = edges[0] if edges else None
        stale = [x for x in edges if getattr(x.sync, "staleness", None) is not None]
        hint = ("give the producer a latency= that covers its step (a LET flow: its outputs are due at tick + "
                "latency)" + (f", or the edge a longer deadline: {e.src}.then({nid}, deadline=seconds)"
                              if e is not None else ""))
        if stale:  # the late events came, and were too old for the policy by then
            hint = (f"{stale[0].sync!r} on {stale[0].src} → {nid} takes no event older than its staleness, and "
                    "late ones are: allow more staleness, or " + hint)
        warnings.warn(
            f"flow '{nid}' never stepped in this run: its inputs were late, {stats.counts['late']} event(s) "
            f"on {names} arrived after the ticks they were for, and its policies took none later\n"
            f"    hint: {hint}", RetrieverWarning, stacklevel=WARN_STACKLEVEL)
