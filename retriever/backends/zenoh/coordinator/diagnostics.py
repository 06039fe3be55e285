"""What the coordinator says when a run goes wrong: stacks, what a node left unfinished, its stderr.

A run that did not start or finish in time names each node it waited for, with the Python stacks
its process printed (SIGUSR1, written at once by a C handler), or why there are none, and, for a
node done but short of reports, the events those reports held. A failed run's error is built
here too (:func:`failure_error`), from what the failing node's process said.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

from ....errors import BackendError, CausalityError, RemoteError, SetupError, StepError
from ....tick import Decision, ending
from ..host import LocalHost
from ..protocol import ABSENT, State
from .book import RunBook

#: how long, at most, a worker's stack dump (SIGUSR1, written at once by a C handler) takes to read
STACKS_WAIT_S = 0.5
#: the lines of a node's stderr an error shows: when it failed, and when it did not finish
FAILED_TAIL_LINES = 15
UNFINISHED_TAIL_LINES = 60
#: the seqs of a stream searched for the ones that never came, back from the last, and how many runs named
UNSEEN_SEARCHED = 100_000
UNSEEN_NAMED = 8


class Diagnostics:
    """Reads the run's processes for an error message; ``hosting``: where their output is."""

    def __init__(self, book: RunBook, hosting):
        self.book, self.hosting = book, hosting
        #: nodes asked for their stacks that printed none, and how long waited (for :meth:`unfinished`)
        self.stackless: dict[str, float] = {}

    def dump_stacks(self, nodes: list[str], wait: float = STACKS_WAIT_S, show: bool = True) -> None:
        """Have these workers print every thread's Python stack to their stderr (SIGUSR1): on
        the coordinator's stderr (``show``), or only kept for an error message that shows them."""
        procs, before = self.book.processes, {}
        for nid in nodes:
            proc = procs.workers.get(nid)
            if proc is not None and proc.poll() is None:
                output = procs.hosts[nid].output(nid)
                before[nid] = output.stderr_lines
                output.forwarding = show
                proc.send_signal(signal.SIGUSR1)
        give_up = time.monotonic() + wait  # a bound: the dump is written at once by a C handler
        for nid, lines in before.items():
            output = procs.hosts[nid].output(nid)
            output.settle(lines, max(0.0, give_up - time.monotonic()))
            if output.stderr_lines == lines:  # asked, and nothing came: the error says so (unfinished)
                self.stackless[nid] = wait

    def unfinished(self, nid: str) -> str:
        """What the error of a run that did not finish says of node ``nid``: the stacks its process
        printed (on its stderr, last), or why there are none; and, done but short of reports, the
        events it sent that never reached the coordinator (lost with those reports)."""
        procs, intake, said = self.book.processes, self.book.intake, ""
        missing = intake.reports_sent[nid] - intake.reports[nid]
        if procs.state.get(nid) == State.DONE and missing > 0:
            sent = intake.done_info.get(nid, {}).get("sent", {})
            lost = [f"{nid}.{port} {seqs}" for port, last in sorted(sent.items())
                    if (seqs := self.unseen_seqs(nid, port, last))]
            said = (f"    {nid} said done after {intake.reports_sent[nid]} report(s), of which {missing} never reached "
                    f"the coordinator" + (f"; it never got the event(s) {', '.join(lost)}" if lost else "") + "\n")
        proc = procs.workers.get(nid)
        code = proc.poll() if proc is not None else None
        tail = self.hosting.stderr_tail(nid, UNFINISHED_TAIL_LINES)
        if code is None and nid not in self.stackless:
            return f"{said}    {nid} stderr (its stacks last):\n{tail}\n"
        if code is not None:
            why = f"its process had ended ({exit_text(code)})"
        else:
            stopped = isinstance(procs.hosts[nid], LocalHost) and is_stopped(proc.pid)
            why = (f"its process (pid {proc.pid}) printed none within {self.stackless[nid]:g} s of SIGUSR1: "
                   + ("it is stopped (SIGSTOP, or a debugger)" if stopped else
                      "stopped, or stuck in code that holds Python's lock"))
        return f"{said}    {nid}: no stacks: {why}" + (f"; its stderr last:\n{tail}\n" if tail.strip() else "\n")

    def unseen_seqs(self, nid: str, port: str, last: int, most: int = UNSEEN_NAMED) -> str:
        """The seqs up to ``last`` of stream ``nid.port`` that never reached the coordinator, as
        ``seqs 3, 5-7`` (the first ``most`` runs of them, of the last UNSEEN_SEARCHED seqs at most)."""
        runs: list[list[int]] = []
        intake = self.book.intake
        for seq in range(max(intake.have.get((nid, port), -1) + 1, last - UNSEEN_SEARCHED + 1), last + 1):
            if (nid, port, seq) in intake.event_ids:
                continue
            if runs and runs[-1][1] == seq - 1:
                runs[-1][1] = seq
            elif len(runs) < most:
                runs.append([seq, seq])
            else:
                break
        if not runs:
            return ""
        spelled = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)
        return f"seq{'s' if len(runs) > 1 or runs[0][0] != runs[0][1] else ''} {spelled}"


def failure_error(book: RunBook, backend_name: str) -> Exception:
    """The error a failed run raises, from what its failing node's process said (``book.ending.failure``)."""
    failure = book.ending.failure
    node, error, said = failure.node, failure.error, failure.failed
    graph = book.graph
    tb = said.traceback if said is not None else None
    where = "\n    worker traceback:\n" + "\n".join("        " + line for line in tb.strip().splitlines()) if tb else ""
    tag = said.tag if said is not None and said.tag is not ABSENT else None
    settings = graph.nodes[node].settings if node in graph.nodes else None
    if book.ending.limit is not None:
        return book.ending.limit
    cycle = next((c for c in graph.instantaneous_cycles if node in c), None)
    if said is not None and said.zeno is True and cycle is not None and tag is not None:
        return CausalityError(cycle, tag, graph.max_microsteps)
    if said is not None and said.setup is True and settings is not None:
        failure = SetupError(node, str(error))
        failure.args = (failure.args[0] + where,)
        return failure
    raised = said.raised if said is not None and said.raised is not ABSENT else None
    if (said is not None and said.out_of_restarts is True and tag is not None and raised is not None and settings
            and settings.on_error == "restart"):
        # a restart in place past the budget its process held: as a coordinator's own refusal says it
        # (believed of a flow that restarts: another never had a budget to spend)
        return ending(Decision.OUT_OF_RESTARTS, node, tag, raised, book.faults.restarts[node])
    if tag is not None and settings is not None and raised is not None:
        failure = StepError(node, tag, RemoteError(raised))
        failure.args = (failure.args[0] + where,)
        return failure
    return BackendError(f"{backend_name} run stopped: {error}{where}")


def exit_text(code: int) -> str:
    """How a process ended, from its exit status: ``killed by SIGKILL``, ``exited with code 7``."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


def is_stopped(pid: int) -> bool:
    """Whether process ``pid`` of this machine is stopped (Linux /proc: state T or t)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:][:1] in ("T", "t")
