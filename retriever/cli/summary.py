"""What a run prints at its end: its table, what it counted, where its log is; and the errors
that fail a run that went on (``run_errors``)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from rich.table import Table
from rich.text import Text

from ..errors import RetrieverError
from . import console
from .console import cell


def print_summary(pipe, trace, title: str, log: Path | None) -> None:
    """The run's table, what it counted, and where its log is."""
    session = pipe.session
    placed = getattr(getattr(session, "hosting", None), "placed", None)  # a deployment: where each node ran
    starved = _starved_cells(session.starved if session is not None else [])
    table = Table(title=f"{pipe.name}: {title}", title_justify="left")
    for col in ("node", *(("worker",) if placed else ()), "ticks", "steps", "skips", "errors", "mean step",
                *(("starved",) if starved else ())):
        table.add_column(col, justify="left" if col in ("node", "worker", "starved") else "right")
    for node, s in sorted(pipe.stats().items()):
        mean = f"{s.mean_step_s * 1e6:.1f} µs" if s.mean_step_s < 0.01 else f"{s.mean_step_s * 1e3:.1f} ms"
        table.add_row(node, *((cell(placed[node]),) if placed else ()), str(s.ticks), str(s.steps), str(s.skips),
                      str(s.errors), mean, *((starved.get(node, ""),) if starved else ()))
    console.out.print(table)
    for node, s in sorted(pipe.stats().items()):  # what a real-time run counted, node by node
        if any(s.counts.values()):
            console.out.print(f"{node} counted: {counters_in_words(s.counts)}", highlight=False)
    unowned = Counter(pipe.counts())
    unowned.subtract(sum((Counter(s.counts) for s in pipe.stats().values()), Counter()))
    if +unowned:
        console.out.print(f"the coordinator counted: {counters_in_words(+unowned)}", highlight=False)
    if session is not None and session.keep == "counters":  # reading the log back could take GBs
        steps = sum(s.steps for s in pipe.stats().values())
        kept = "kept only in the log" if log is not None else "not kept"
        console.out.print(f"{steps} steps · records {kept} (--keep counters)", highlight=False)
    else:
        digest = f"trace digest {trace.digest()[:16]}" if trace.values_kept else "values not kept (--keep records)"
        console.out.print(f"{len(trace.events)} events · {len(trace.steps)} steps · {digest}", highlight=False)
    if log is not None:
        console.out.print(f"log: {log} ({log.stat().st_size / 1e6:.2f} MB); check it with: retriever replay {log}",
                          highlight=False, soft_wrap=True)  # a command to copy: never broken across lines


def _starved_cells(episodes: list[dict]) -> dict[str, Text]:
    """Per node, the table's mark of the spans its inputs starved (StarvationWatch):
    ``pixels from 3.9 s`` (to the end), ``pixels 3.9–5.1 s`` (it had events again)."""
    cells: dict[str, list[str]] = {}
    for e in episodes:
        since = f"{e['since_ns'] / 1e9:.3g}"
        span = f"from {since} s" if e["until_ns"] is None else f"{since}–{e['until_ns'] / 1e9:.3g} s"
        cells.setdefault(e["node"], []).append(f"{e['port']} {span}")
    return {node: cell(", ".join(marks)) for node, marks in cells.items()}


def run_errors(stats: dict) -> RetrieverError | None:
    """What a run that went on had that fails it (None: nothing): its step errors and restarts
    (``NodeStats`` by node). A node that moved because its worker was lost restarted too, by the
    same rule; the error says it moved, and the hint names the option that moved it."""
    errors = {node: s.errors for node, s in sorted(stats.items()) if s.errors}
    moves = {node: s.counts["moves"] for node, s in sorted(stats.items()) if s.counts.get("moves")}
    restarts = {node: s.counts.get("restarts", 0) + moves.get(node, 0) for node, s in sorted(stats.items())
                if s.counts.get("restarts") or node in moves}
    if not errors and not restarts:
        return None
    parts = [f"{node}: {n} step error(s)" + (f", {_restarts_text(node, restarts, moves)}" if node in restarts else "")
             for node, n in errors.items()]
    parts += [f"{node}: {_restarts_text(node, restarts, moves)}" for node in restarts if node not in errors]
    return RetrieverError(f"the run went on, but had errors ({'; '.join(parts)})\n"
                          f"    hint: {_errors_hint(stats, errors, restarts, moves)}")


def _restarts_text(node: str, restarts: dict[str, int], moves: dict[str, int]) -> str:
    """``2 restart(s)``, ``1 restart(s) (moved because its worker was lost, not a step error)``."""
    if node not in moves:
        return f"{restarts[node]} restart(s)"
    which = "moved" if moves[node] == restarts[node] else f"{moves[node]} of them moved"
    return f"{restarts[node]} restart(s) ({which} because its worker was lost, not a step error)"


def _errors_hint(stats: dict, errors: dict, restarts: dict, moves: dict) -> str:
    """Where to read what went wrong, and which policy, with --allow-errors, absorbs it."""
    crashes = sum(s.counts.get("crash_restarts", 0) for s in stats.values())
    where = ["the error records say what raised (retriever log cat LOG --steps)"] if errors else []
    if crashes:
        where.append(f"{crashes} restart(s) followed a process that died: retriever log info LOG shows each fault")
    if moves:
        where.append(f"{sum(moves.values())} move(s) followed a lost worker: retriever log info LOG shows which "
                     "worker ran each node")
    restarted = errors or any(n > moves.get(node, 0) for node, n in restarts.items())  # by on_error
    policies = [*(["on_error='skip_tick' or 'restart'"] if restarted else []),
                *(["on_worker_loss='replace' or 'wait'"] if moves else [])]
    return "; ".join([*where, f"pass --allow-errors when {' or '.join(policies)} is meant to absorb them"])


_COUNTER_LABELS = {"late": "late events", "incomplete": "ticks with an incomplete edge", "overrun": "ticks skipped after overruns",
                   "restart_skipped": "ticks skipped during restarts",
                   "deadline_miss": "LET deadline misses", "unrun_ticks": "ticks never run",
                   "unfinished_inputs": "input streams cut off at the end",
                   "garbage": "garbage messages dropped", "forged": "forged messages or records refused",
                   "report_waits": "waits for the log"}


def counters_in_words(counts: dict[str, int]) -> str:
    """``3 late events, 2 waits for the log (171 ms)``: a run's counters (base.COUNTERS) in words."""
    parts = []
    for name, n in sorted(counts.items()):
        if not n or name == "report_wait_ns":
            continue
        if name == "spin_ns":  # (CPU spent by choice: configure(spin=))
            parts.append(f"{n / 1e9:.3g} s busy-waiting for ticks (spin)")
            continue
        part = f"{n} {_COUNTER_LABELS.get(name, name)}"
        if name == "report_waits" and counts.get("report_wait_ns"):
            part += f" ({counts['report_wait_ns'] / 1e6:.0f} ms)"
        parts.append(part)
    return ", ".join(parts)
