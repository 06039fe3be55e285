"""The status state machine: what each status a node's process says (status/node/<node>) does.

    status ──▶ decode ──▶ its node's? ──▶ signed by the process that may say it? ──▶ may_say? ──▶ HANDLERS[state]

Each process says where it is in its life (PROCESS_STAGES); the other statuses (``reached``,
``exit``, ``unanswered``) are news of its run. One handler per status, picked from a table: the
machine only dispatches, as dora's daemon loop does.
"""

from __future__ import annotations


from ....tick import Decision, ending, take_restart
from ..protocol import (ABSENT, STATUS, Done, End, Exit, Failed, HandedOver, Handover, Reached, Ready, Redeclare,
                        Restart, Restarted, Resume, State, Status, Unanswered)
from ..wire import WireError
from .book import RunBook
from .control import RunControl
from .exits import ExitCut
from .faults import RunFailure

#: where in its life each state a worker process says of itself puts it: a process says a state
#: only after those below it (`ready` again and again while it waits for the start), and says a
#: last one (done, failed, handed_over) once. Anything else is an insider's replay of a status of
#: the process (its signature holds): a second `done` added its counts and reports again, a `ready`
#: after its `done` moved the node back; refused (may_say)
PROCESS_STAGES = {State.READY: 0, State.RESTART: 1, State.DONE: 2, State.FAILED: 2, State.HANDED_OVER: 2}


def may_say(last: State | None, state: State) -> bool:
    """Whether a process whose last state was ``last`` (None: none yet) may now say ``state``."""
    return last is None or PROCESS_STAGES[state] > PROCESS_STAGES[last] or state == last == State.READY


class StatusMachine:
    """Takes the statuses of the run's processes. ``supervisor``: starts a node's processes
    (processes.Supervisor); ``exits``: in a run in lockstep virtual time, where its steps'
    sys.exit(0) cut it (exits.ExitCut; None in real time); ``startup_timeout``: for the error of
    a worker that never linked to its neighbours."""

    def __init__(self, book: RunBook, control: RunControl, supervisor, *, exits: ExitCut | None = None,
                 startup_timeout: float = 60.0):
        self.book, self.control, self.supervisor = book, control, supervisor
        self.exits, self.virtual_time, self.startup_timeout = exits, exits is not None, startup_timeout
        self.handlers = {State.REACHED: self._reached, State.EXIT: self._exit, State.UNANSWERED: self._unanswered,
                         State.READY: self._ready, State.RESTART: self._restart, State.FAILED: self._failed,
                         State.HANDED_OVER: self._handed_over, State.DONE: self._done}

    def take(self, key: str, data: bytes, sender: object) -> None:
        """A status on ``key``, signed by ``sender`` (a process of its node: origin.py)."""
        book = self.book
        try:
            status = STATUS.decode(data, node=key.rsplit("/", 1)[1])
        except WireError as e:
            book.garbage(key, e)
            return
        node, state, procs = status.node, status.NAME, book.processes
        if node not in procs.state:
            book.garbage(key, WireError(f"status of an unknown node '{node}'"))
            return
        # Only the node's own process speaks for it: its running one (a restart spawns a process,
        # so only it may ask for one), or, while it restarts, the old one (which alone says it
        # handed over). A status signed by another of its processes (one that already handed
        # over or was replaced) is garbage; an insider's (a `failed` stopped the run, a `done`
        # added its counts, an `exit` ended it) is signed by none and never got here.
        current, retiring = procs.workers.get(node), procs.retiring.get(node)
        sayers = {State.HANDED_OVER: (retiring,), State.DONE: (current, retiring), State.FAILED: (current, retiring)}
        if sender is None or not any(sender is p for p in sayers.get(state, (current,))):
            book.garbage(key, WireError(f"a '{state}' status of {node} from pid {status.pid}, "
                                        f"which is not the process of {node} that could say it"))
            return
        if state in PROCESS_STAGES:
            if not may_say(procs.said.get((sender, node)), state):
                book.garbage(key, WireError(f"a '{state}' status of {node} after its process said "
                                            f"'{procs.said[sender, node]}' (a replay)"))
                return
            procs.said[sender, node] = state
            self._count(status)
        self.handlers[state](key, status, sender)

    def _count(self, status: Status) -> None:
        """What every stage of a process says besides: its counters, and the reports it sent."""
        book, node = self.book, status.node
        counts = getattr(status, "counts", ABSENT)
        if counts is not ABSENT:
            node_counts = book.intake.stats[node].counts
            for name, n in counts.items():
                node_counts[name] = node_counts.get(name, 0) + n
        reports = getattr(status, "reports", ABSENT)
        if reports is not ABSENT:
            book.intake.reports_sent[node] += reports
        if status.NAME != State.READY:
            book.processes.restarted.pop(node, None)

    # ---------------------------------------------------------------------------------------
    # News of a process's run
    # ---------------------------------------------------------------------------------------
    def _reached(self, key: str, status: Reached, sender: object) -> None:
        """Virtual time: the node ran every tick below ``until``."""
        book = self.book
        if not self.virtual_time:
            book.garbage(key, WireError(f"a 'reached' status of {status.node} with until {status.until} in a run "
                                        "not in virtual time"))
            return
        book.grants.reach(status.node, status.until)

    def _exit(self, key: str, status: Exit, sender: object) -> None:
        """Its step called sys.exit(0): the run ends there, once its record is in."""
        self.book.ending.exit_said[status.node] = (status.tag, sender)
        self.end_by_exit(status.node)

    def end_by_exit(self, node: str) -> None:
        """End the run as a step of ``node`` asked (sys.exit(0)), once its process both said so
        (status ``exit``) and recorded that step (status ok, detail ``{"exit": 0}``) at that tag."""
        book = self.book
        said = book.ending.exit_said.get(node)
        if said is None or book.ending.exit_recorded.get(node) != said or book.t0 is None:
            return
        if self.exits is not None:
            self._end_in_virtual_time(node)
            return
        if book.ending.stop_sent:
            return
        book.ending.stop_sent = True
        book.ending.ended_by = node
        # as if the run ended now: no tick at or past the exit, but every event sent before
        # it (each stamped before now, the exit's tag may be earlier on a late node) still
        # reaches the ticks it triggers, within their deadline, as at any run's end
        self.control.put(End(at=max(said[0][0], book.run_time())))

    def _end_in_virtual_time(self, node: str) -> None:
        """In virtual time the run ends at the earliest exit (exits.ExitCut): at this one, unless
        another node's, said, is earlier. Every tick at its time still runs (the nodes before it
        in the tie order are recorded, the others dropped with what runs past it: exits.py)."""
        book = self.book
        tag, first = self.exits.earliest(book.ending.exit_said)
        if first == node and book.ending.ended_by != node:
            book.ending.stop_sent, book.ending.ended_by = True, node
            self.control.put(End(at=tag[0] + 1))

    def _unanswered(self, key: str, status: Unanswered, sender: object) -> None:
        """Before the start: its neighbours declare themselves again."""
        book = self.book
        if not all(n in book.processes.state for n in status.nodes):
            book.garbage(key, WireError(f"an 'unanswered' status of {status.node} that names no nodes of the run"))
        elif book.t0 is not None:  # no worker asks once the run started
            book.garbage(key, WireError(f"an 'unanswered' status of {status.node} after the run's start"))
        else:
            self.control.put(Redeclare(nodes=tuple(sorted(set(status.nodes)))))

    # ---------------------------------------------------------------------------------------
    # The stages of a process's life (PROCESS_STAGES)
    # ---------------------------------------------------------------------------------------
    def _ready(self, key: str, status: Ready, sender: object) -> None:
        book, node = self.book, status.node
        if status.linked is False and book.ending.failure is None:
            # peers do not route for each other: a worker without a link to another would never
            # get that one's events, nor it this one's
            unlinked = (", ".join(f"'{n:.60}'" for n in status.unlinked[:8])
                        if status.unlinked is not ABSENT else "some of its neighbours")
            book.ending.failure = RunFailure(node, (
                f"the worker of '{node}' has no direct link to {unlinked} after {self.startup_timeout:g} s\n"
                f"    hint: on a loaded machine, give it longer: pipe.run(..., startup_timeout=seconds); across "
                f"machines, each must reach the others at the address it listens on (retriever-worker --listen)"))
            return
        procs = book.processes
        if node in book.faults.fresh:
            self.supervisor.restart_afresh(node)
        elif node in procs.restarted:
            # said again: it has not seen `restarted` yet (worker/waits.py, START_ASK_S), nor, maybe, its consumers
            self.control.put(Restarted(node=node, seqs=procs.restarted[node], values=book.values))
        elif node in procs.retiring:
            if procs.state[node] == State.DONE:  # the run ended while it restarted: stopped at close
                return
            self.control.put(Handover(node=node))
        procs.state[node] = State.READY

    def _restart(self, key: str, status: Restart, sender: object) -> None:
        """Its flow asks for a restart in a new process: the old one keeps listening until the
        new one takes over."""
        book, node, tag = self.book, status.node, status.tag
        budget = book.faults.restarts[node]
        decision = take_restart(budget, tag[0])  # the node decided on a restart; the budget here
        if decision is not Decision.RESTART:
            book.ending.limit = ending(decision, node, tag, status.error, budget)
            book.ending.failure = RunFailure(node, str(book.ending.limit))
            return
        node_counts = book.intake.stats[node].counts
        node_counts["restarts"] = node_counts.get("restarts", 0) + 1
        procs = book.processes
        procs.retiring[node] = procs.workers[node]
        procs.handed_over.discard(node)  # (the old process it replaces has not handed over yet)
        self.supervisor.spawn(node, join=(book.t0, book.end_ns))

    def _failed(self, key: str, status: Failed, sender: object) -> None:
        self.book.ending.failure = RunFailure.said(status)
        self.book.processes.state[status.node] = State.FAILED

    def _handed_over(self, key: str, status: HandedOver, sender: object) -> None:
        """The old process of a restarting node gave its state to the new one, which resumes."""
        procs = self.book.processes
        procs.retired.append(procs.retiring.pop(status.node))
        procs.handed_over.add(status.node)
        self.control.put(Resume(node=status.node))
        procs.joining.discard(status.node)

    def _done(self, key: str, status: Done, sender: object) -> None:
        book, node = self.book, status.node
        if (status.stopped is True and not book.ending.stop_sent and book.t0 is not None
                and book.ending.failure is None
                and node not in book.ending.exit_said):  # (an exit's record may come after its `done`)
            # it ended before the run's end on a stop this coordinator never sent: a run cut
            # short must not look finished (a SIGTERM to it: a `stop` on ctl/run it takes only sealed)
            book.ending.failure = RunFailure(node, (
                f"{node} stopped before the run's end: told to stop, and not by this coordinator (someone sent "
                "its worker SIGTERM)"))
        book.intake.done_info[node] = {k: v for k in ("started_ns", "ticks") if type(v := getattr(status, k)) is int}
        # {port: last seq put}: which events its reports held (diagnostics.unfinished)
        if status.sent is not ABSENT and all(p in book.graph.nodes[node].outputs for p in status.sent):
            book.intake.done_info[node]["sent"] = status.sent
        procs = book.processes
        old = procs.retiring.pop(node, None)
        if old is not None:
            procs.retired.append(old)
        procs.state[node] = State.DONE
