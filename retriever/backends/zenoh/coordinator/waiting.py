"""The coordinator's waits: for every worker to be ready, then for the run to finish.

    wait(condition, give_up)
      ┌──▶ a stop asked from afar? ──▶ KeyboardInterrupt
      │    take what came (Inbox) ─ a failure? raise it ─ say who starves
      │    every CHECK_EVERY_S: look at the processes, count what was refused as forged
      │    hand the records to the log ─ tell the consumers what the coordinator has (`have`)
      └─── until condition(); past give_up: name each node waited for, with its stacks

In lockstep virtual time (node/waiting.py) the wait for the finish also grants the next window of
virtual time once every node reached the last one, none past a step's sys.exit(0); what the
nodes reported below that barrier is final (exits.ExitCut), the rest once the run is over.
"""

from __future__ import annotations

import dataclasses
import time

from ....errors import BackendError
from ..protocol import Grant, Start, State
from .book import RunBook
from .control import RunControl
from .diagnostics import Diagnostics
from .endchecks import say_starved
from .exits import ExitCut
from .inbox import Inbox
from .processes import Supervisor
from .reports import tell_have

#: how often, at most, the coordinator tells the consumers which events it has (control `have`)
HAVE_EVERY_S = 0.02
#: how long the coordinator waits for a message before it looks at the time again (a message
#: wakes it at once: a status, a report, a node reaching a grant)
POLL_S = 0.05
#: how often the coordinator looks at its processes and hosts (a dead one is found this late at
#: most): a pass polls each process and asks the hosting, too much for every wake of a busy run
CHECK_EVERY_S = 0.1
#: a real-time run may finish this long past its end and its longest deadline (at least a second)
#: before it is said stuck: workers send their last reports after the end
FINISH_SLACK_S = 10.0

#: how far each grant reaches past the last, in virtual ns: the nodes run that much of the
#: run between two barriers (a source never runs further ahead of its slowest consumer)
LOCKSTEP_WINDOW_NS = 50_000_000
#: how long (wall) without a grant reached before it is put again (a put may be missed), and
#: before the run fails naming the nodes that did not reach it
REGRANT_S = 0.5
LOCKSTEP_STALL_S = 120.0


class Waits:
    """The waits of one run; ``session``: the coordinator, whose log is written as the run goes."""

    def __init__(self, session, book: RunBook, inbox: Inbox, control: RunControl, supervisor: Supervisor,
                 diagnostics: Diagnostics, exits: ExitCut | None = None):
        self.session, self.book, self.inbox, self.control = session, book, inbox, control
        self.supervisor, self.diagnostics, self.exits = supervisor, diagnostics, exits

    def until_ready(self, timeout: float) -> None:
        procs = self.book.processes
        self.wait(lambda: all(s == State.READY for s in procs.state.values()), time.monotonic() + timeout, "start")

    def until_finished(self, start: Start, virtual_time: bool) -> None:
        """Put the run's ``start`` and wait for every node to be done with every report in."""
        book, end_ns = self.book, start.end
        if virtual_time:
            grants = book.grants
            grants.granted = min(LOCKSTEP_WINDOW_NS, end_ns)
            grants.last_grant = (time.monotonic(), time.monotonic())
            self.control.put(dataclasses.replace(start, grant=grants.granted))
            try:
                self.wait(lambda: self.lockstep() and book.finished(), float("inf"), "finish")
            finally:  # what is held goes to the trace and the log (a failed run's too: what it ran)
                self.settle()
            return
        self.control.put(start)
        slack = max(self._deadlines(), 1.0) + FINISH_SLACK_S
        # a coordinator behind on its reports (a logged run of many events) finishes late,
        # not in error: the wait goes on while they come
        self.wait(book.finished, time.monotonic() + (book.t0 + end_ns - time.time_ns()) / 1e9 + slack, "finish",
                  patience=slack)

    def _deadlines(self) -> float:
        graph = self.book.graph
        deadlines = [e.deadline for e in graph.edges if e.deadline is not None]
        return max([graph.deadline, *deadlines])

    def lockstep(self) -> bool:
        """Grant the next window once every node not done has reached this one; whether the
        last grant is out: the run's end, or the one in which a step called sys.exit(0), past
        which no node is to run. Fails the run when nothing moved for LOCKSTEP_STALL_S."""
        book, grants, state, now = self.book, self.book.grants, self.book.processes.state, time.monotonic()
        behind = sorted(n for n, s in state.items() if s != State.DONE and grants.reached.get(n, -1) < grants.granted)
        first_exit = self.exits.earliest(book.ending.exit_said)
        last = book.end_ns if first_exit is None else min(book.end_ns, first_exit[0][0] + 1)
        if not behind:  # every exit below the grant is said (exits.py)
            self.exits.final_below(grants.granted if first_exit is None else min(grants.granted, first_exit[0][0]))
        if not behind and grants.granted < last:
            grants.granted = min(grants.granted + LOCKSTEP_WINDOW_NS, book.end_ns)
            grants.last_grant = (now, now)
            self.control.put(Grant(until=grants.granted))
            return False
        if behind and now - grants.last_grant[1] > REGRANT_S:  # a put may be missed: again
            grants.last_grant = (grants.last_grant[0], now)
            self.control.put(Grant(until=grants.granted))
        if now - grants.last_grant[0] > LOCKSTEP_STALL_S:
            waiting = behind or sorted(n for n, s in state.items()
                                       if s != State.DONE or book.intake.reports[n] < book.intake.reports_sent[n])
            self.diagnostics.dump_stacks(waiting, show=False)
            raise BackendError(
                f"zenoh run (virtual time): worker(s) {', '.join(waiting)} did not "
                + (f"reach t={grants.granted / 1e9:g} s" if behind else "finish")
                + f" within {LOCKSTEP_STALL_S:g} s of wall time\n"
                + "".join(self.diagnostics.unfinished(n) for n in waiting)
                + "    hint: the stacks show where a step that did not return is")
        return grants.granted >= last

    def settle(self) -> None:
        """Virtual time, the run over: what is held is final but what its earliest exit cuts off
        (exits.ExitCut), and the run ended there."""
        book = self.book
        cut = self.exits.earliest(book.ending.exit_said)
        self.exits.settle(cut)
        if cut is not None:
            book.ending.ended_by = cut[1]

    def wait(self, condition, give_up: float, what: str, patience: float | None = None) -> None:
        """Collect messages until ``condition()``; fail on a failed or dead worker or at ``give_up``
        (with ``patience``, at the latest that long after the last report came)."""
        session, book = self.session, self.book
        next_write = next_have = next_check = time.monotonic()
        reports = sum(book.intake.reports.values())
        while not condition():
            if session.stop_requested:  # asked from afar (retriever stop): as Ctrl-C here would
                raise KeyboardInterrupt
            self.inbox.take(POLL_S)
            if book.ending.failure is not None:
                self.supervisor.raise_failure()
            if book.intake.starvation.news:
                say_starved(book)
            now = time.monotonic()
            if now >= next_check:
                book.tell_forged()
                self.supervisor.check()
                next_check = now + CHECK_EVERY_S
            if now >= next_write:
                if session.log is not None:
                    session.write_log()
                    # while this thread waited for the log's disk no report was taken: that time
                    # is the coordinator's, not a late worker's
                    give_up += time.monotonic() - now
                else:
                    session.drop_records()
                next_write = now + session.LOG_HANDOVER_S
            if now >= next_have:
                tell_have(book.intake, self.control)
                next_have = now + HAVE_EVERY_S
            if patience is not None and sum(book.intake.reports.values()) != reports:
                reports = sum(book.intake.reports.values())
                give_up = max(give_up, now + patience)
            if now > give_up and not condition():  # (what was just taken may have met it)
                self._timed_out(what)
        if session.log is not None:
            session.write_log()

    def _timed_out(self, what: str) -> None:
        """The run did not ``start`` or ``finish`` in time: name each node waited for."""
        book, session = self.book, self.session
        intake, awaited = book.intake, State.READY if what == "start" else State.DONE
        waiting = sorted(n for n, s in book.processes.state.items()
                         if s != awaited or intake.reports[n] < intake.reports_sent[n])
        self.diagnostics.dump_stacks(waiting, show=False)  # the error below shows them
        said = "".join(self.diagnostics.unfinished(n) for n in waiting)  # (before the kill: how each was found)
        if what == "finish":  # stuck in a step (SIGTERM only asks the loop to stop): no use waiting
            for nid in waiting:
                book.processes.workers[nid].kill()
        raise BackendError(f"{session.backend_name} run: worker(s) {', '.join(waiting)} did not {what} in time\n"
                           + said
                           + ("    hint: a flow that takes longer to load needs pipe.run(..., startup_timeout="
                              f"seconds) (now {session.startup_timeout:g})" if what == "start" else
                              "    hint: the stacks show where a step that did not return is"))
