"""Process supervision: a node's worker processes started, watched, restarted afresh and stopped.

    spawn ──▶ (ready ... done)                     one process per node, on its host (hosting.py)
      │  died after the start, on_error="restart" ──▶ lost ──▶ start afresh ──▶ ready ──▶ restarted
      │  died otherwise, or its host went          ──▶ the run fails (a deployment may move it)
      ▼  stop: `stop`, their last reports, then SIGTERM / SIGKILL what is left; reap

Workers are started and stopped by PID; none outlives the run (each also asks the kernel for
SIGTERM when its parent dies). Control is sealed for each process started (protocol/seal.py)
until its exit is confirmed (:func:`exit_confirmed`): a run that restarts a flow again and again
seals its control for the processes alive, not for every one it ever started.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable

from ....tick import Decision, ending, take_restart
from ..command import mode_args
from ..host import Host, WorkerProcess
from ..origin import new_key
from ..protocol import EXIT_FAILED, EXIT_HANDED_OVER, RESTART_SEQ_GAP, Lost, NodeState, Restarted, State, Stop
from .book import RunBook
from .control import RunControl
from .diagnostics import FAILED_TAIL_LINES, Diagnostics, exit_text, failure_error
from .faults import Fault, RunFailure
from .hosting import FailRun, Relocate
from .inbox import Inbox

#: after `stop`, how long workers have to send their last reports and exit; one still running is
#: stuck in a step (a loop looks at `stop` between steps only): its stacks are printed, it is killed
STOP_GRACE_S = 1.5
#: how long after a worker process ended by itself (exit code 0, 1 or 3) the coordinator waits for
#: the status that says why (Zenoh may deliver it after the exit is seen): none by then, it died
EXIT_GRACE_S = 2.0
#: when the run closes, how long its workers have to exit of themselves, then after SIGTERM; after
#: a stop, how long the ones killed have to be reaped
REAP_GRACE_S = 5.0
TERM_GRACE_S = 2.0
KILLED_GRACE_S = 0.5
#: how long the coordinator waits for one message at a time while its workers stop
STOP_POLL_S = 0.02


class Supervisor:
    """Starts, watches and stops the run's worker processes; ``hosting``: where they run, and what
    a host lost means (hosting.py); ``backend_name``: for the run's errors; ``on_fault``: a lost
    process's fault record, for the run's log; ``inbox``: what comes while the workers stop."""

    def __init__(self, book: RunBook, control: RunControl, hosting, diagnostics: Diagnostics, *, backend_name: str,
                 on_fault: Callable[[Fault], None], inbox: Inbox | None = None):
        self.book, self.control, self.hosting = book, control, hosting
        self.diagnostics, self.backend_name = diagnostics, backend_name
        self.on_fault, self.inbox = on_fault, inbox

    def spawn(self, nid: str, join: tuple[int, int] | None = None, fresh: bool = False) -> None:
        """Start the worker process of ``nid``; ``join``: (T0, end) of the run it joins, taking
        over the state of the process it replaces, or, ``fresh``, starting afresh (that one died)."""
        procs = self.book.processes
        mode = mode_args(join, fresh)
        procs.workers[nid], key = procs.hosts[nid].spawn(nid, mode, procs.first_keys.pop(nid, None) or new_key())
        procs.grouped.discard(nid)  # (a group's member moved elsewhere runs alone there: deploy's Relocate)
        procs.senders.add(nid, key, procs.workers[nid])
        self.control.signer.add(procs.workers[nid], key)
        if join is not None:
            procs.joining.add(nid)
        procs.state[nid] = NodeState.STARTING

    def spawn_group(self, name: str, nodes: list[str]) -> None:
        """Start the one process of the group ``name``: every member's process, with one key (a
        member restarts in it: node/in_place.py)."""
        procs = self.book.processes
        # the key the hosting made, if it did (a dora run's, in its spec: the first member's), else a new one
        made = [procs.first_keys.pop(nid, None) for nid in nodes]
        proc, key = procs.hosts[nodes[0]].spawn_group(name, nodes, made[0] or new_key())
        procs.grouped.update(nodes)
        for nid in nodes:
            procs.workers[nid] = proc
            procs.senders.add(nid, key, proc)
            procs.state[nid] = NodeState.STARTING
        self.control.signer.add(proc, key)

    def raise_failure(self) -> None:
        raise failure_error(self.book, self.backend_name)

    def forget_ended(self, polled: dict[int, int | None] | None = None) -> None:
        """Seal no more control for the processes whose exit is confirmed (a process that may
        still run keeps getting it: a ``stop``, its answers); each of them is reaped on the way.
        ``polled``: what ``poll()`` said of each process this check, by ``id``: each is asked once."""
        signer = self.control.signer
        for proc in signer.holders():
            if exit_confirmed(proc, polled):
                signer.drop(proc)

    # ---------------------------------------------------------------------------------------
    # Watching
    # ---------------------------------------------------------------------------------------
    def check(self) -> None:
        """Look at the hosts and the processes: a lost host or a dead process fails the run, or
        (on_error="restart", a deployment's on_worker_loss) starts its flows afresh."""
        book, procs = self.book, self.book.processes
        self.hosting.check()
        polled: dict[int, int | None] = {}  # each process polled once a check: a waitpid, every pass
        self.forget_ended(polled)
        for host in {id(h): h for h in procs.hosts.values()}.values():
            if not host.alive and book.ending.failure is None:  # its flows stopped with it, whatever they said
                self.host_lost(host)
                if book.ending.failure is not None:
                    self.raise_failure()
        for nid, proc in [*procs.workers.items(), *procs.retiring.items()]:
            code = polled[id(proc)] if id(proc) in polled else proc.poll()
            if code is None or procs.state[nid] == State.DONE or not procs.hosts[nid].alive:
                continue  # running, finished, or gone with its host (above)
            if code in (0, EXIT_HANDED_OVER, EXIT_FAILED):
                # a worker's own exit: its last status may still be on the way (it says why it ended)
                exited = procs.exited.setdefault(proc.pid, time.monotonic())
                if time.monotonic() - exited < EXIT_GRACE_S:
                    continue
            # it died, or ended without a word (os._exit in a step): its state is lost
            if book.ending.failure is not None:
                self.raise_failure()
            # (a group's process takes all its members with it: none starts afresh on its own)
            restarts = book.graph.nodes[nid].settings.on_error == "restart" and not procs.in_group(nid)
            if book.t0 is not None and restarts:
                self._lost(nid, proc, code)
                return  # the processes of the node changed: look again next time
            procs.hosts[nid].output(nid).drain()
            # (a group's process: every member it ran, which all went with it)
            members = sorted(n for n, p in procs.workers.items() if p is proc) or [nid]
            if book.t0 is not None:  # the log says what died (each member), and which of its outputs with it
                at = book.run_time()
                book.faults.unrecovered += [Fault(n, at, proc.pid, exit_text(code)) for n in members]
            served = ", ".join(f"'{n}'" for n in members)
            book.ending.failure = RunFailure(nid, f"worker process of {served} (pid {proc.pid}) {exit_text(code)} "
                                           f"before it finished\n{self.hosting.stderr_tail(nid, FAILED_TAIL_LINES)}")
            self.raise_failure()

    def host_lost(self, host: Host) -> None:
        """A host went with its nodes' processes: do what the hosting decides it means (hosting.py):
        fail the run (the log says which processes went with it, once their last reports are
        in), start the nodes afresh elsewhere, or go on without them until it is back."""
        book, procs = self.book, self.book.processes
        nodes = procs.nodes_of(host)
        decision = self.hosting.host_lost(host, nodes)
        if isinstance(decision, FailRun):
            if book.t0 is not None:
                book.faults.unrecovered += [Fault(nid, book.run_time(), procs.workers[nid].pid, decision.exit)
                                     for nid in nodes]
            book.ending.failure = RunFailure(nodes[0], decision.reason)
        elif isinstance(decision, Relocate):
            for nid, new_host in sorted(decision.hosts.items()):
                procs.hosts[nid] = new_host
                counts = book.intake.stats[nid].counts
                counts["moves"] = counts.get("moves", 0) + 1
                self.start_afresh(nid, Fault(nid, decision.at_ns, procs.workers[nid].pid, decision.exit,
                                             moved_to=decision.moved_to[nid]))
        else:  # AwaitHost: their processes, if a hung host still has them, stop; their consumers know
            for nid in decision.lost:
                self.control.put(Lost(node=nid))

    # ---------------------------------------------------------------------------------------
    # A lost process (on_error="restart"; node/handover.py)
    # ---------------------------------------------------------------------------------------
    def _lost(self, nid: str, proc, code: int) -> None:
        """A worker process of ``nid`` died after the start: within the restart budget, start the
        flow afresh in a new process (a hand-over in progress dies with it); else fail the run."""
        book = self.book
        at = book.run_time()
        why = f"its worker process (pid {proc.pid}) {exit_text(code)} at t={at / 1e9:.3f} s"
        if nid in book.faults.fresh:  # the last one died before it was ready: that fault stands on its own
            self.record_fault(book.faults.fresh.pop(nid), None)
        budget = book.faults.restarts[nid]
        decision = take_restart(budget, at)
        if decision is not Decision.RESTART:
            book.ending.limit = ending(decision, nid, None, why, budget)
            book.faults.unrecovered.append(Fault(nid, at, proc.pid, exit_text(code)))
            book.ending.failure = RunFailure(nid, str(book.ending.limit))
            return
        counts = book.intake.stats[nid].counts
        for name in ("restarts", "crash_restarts"):
            counts[name] = counts.get(name, 0) + 1
        print(f"retriever: flow '{nid}': {why}; starting it afresh (on_error='restart')",
              file=sys.stderr, flush=True)
        self.start_afresh(nid, Fault(nid, at, proc.pid, exit_text(code)))

    def start_afresh(self, nid: str, fault: Fault) -> None:
        """Start ``nid`` afresh in a new process on its host (node/handover.py);
        ``fault``: what became of the old one, logged once the new one is ready."""
        book, procs = self.book, self.book.processes
        for other in (procs.workers.get(nid), procs.retiring.pop(nid, None)):
            if other is not None:
                if other.poll() is None:
                    other.kill()
                procs.retired.append(other)
        self.control.put(Lost(node=nid))
        procs.restarted.pop(nid, None)
        book.faults.fresh[nid] = fault
        self.spawn(nid, join=(book.t0, book.end_ns), fresh=True)

    def restart_afresh(self, nid: str) -> None:
        """The new process of ``nid`` is ready: its streams go on past every seq the dead one may
        have used; the consumers and it are told (control ``restarted``), the log gets the fault."""
        book = self.book
        ports = {port for node, port in book.intake.max_seq if node == nid} | set(book.graph.nodes[nid].outputs)
        seqs = {port: book.intake.max_seq.get((nid, port), -1) + 1 + RESTART_SEQ_GAP for port in sorted(ports)}
        for port, first in seqs.items():  # the consumers give up the seqs below: nothing to wait for
            book.intake.have[(nid, port)] = max(book.intake.have.get((nid, port), -1), first - 1)
        self.record_fault(book.faults.fresh.pop(nid), seqs)
        book.processes.restarted[nid] = seqs
        self.control.put(Restarted(node=nid, seqs=seqs, values=book.values))
        book.processes.joining.discard(nid)

    def record_fault(self, fault: Fault, seqs: dict[str, int] | None) -> None:
        """Keep a lost process's fault, and log it: the outputs its step records claimed and no
        report carried (LET outputs it still held) are lost, which a replay must know."""
        book = self.book
        lost = sorted(event_id for event_id in book.intake.unseen if event_id[0] == fault.node)
        book.intake.unseen.difference_update(lost)
        fault = fault.settled(seqs, [list(event_id) for event_id in lost])
        book.faults.logged.append(fault)
        self.on_fault(fault)

    def record_faults_left(self) -> None:
        """Log the faults of processes that died and were not started afresh (not allowed, out
        of budget, the run ended first, or their host never came back), once their last reports are in."""
        faults = self.book.faults
        faults.unrecovered += self.hosting.faults_left()
        for fault in [*faults.fresh.values(), *faults.unrecovered]:
            self.record_fault(fault, None)
        faults.fresh.clear()
        faults.unrecovered.clear()

    # ---------------------------------------------------------------------------------------
    # Stopping
    # ---------------------------------------------------------------------------------------
    def stop(self, grace: float = STOP_GRACE_S) -> None:
        """Ask every live worker to stop, collect what they send, then make sure they are gone:
        one still running after ``grace`` is stuck in a step, so its stacks are printed and it is
        killed. Before the run's start they have nothing to send, and may not listen yet: SIGTERM them."""
        book, procs = self.book, self.book.processes
        self.hosting.before_stop()
        if book.t0 is None:
            for p in procs.started():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            self.reap()
            return
        book.ending.stop_sent = True
        try:
            self.control.put(Stop())
        except Exception:
            pass
        # a process not in the run yet (a restarted flow's, before it took over or was told its
        # seqs) has nothing to send, and may be waiting for its neighbours, not reading control
        for nid in procs.joining:
            p = procs.workers.get(nid)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        give_up = time.monotonic() + grace
        while time.monotonic() < give_up and any(p.poll() is None for p in procs.started()):
            self.inbox.take_one(STOP_POLL_S)
        self.inbox.drain()
        # one that said done is past its flow's teardown and only ending (Python collecting a big
        # model object by object takes seconds): reap gives it REAP_GRACE_S; the others are stuck
        running = [(nid, p) for nid, p in [*procs.workers.items(), *procs.retiring.items()] if p.poll() is None]
        stuck = sorted(nid for nid, p in running if procs.state.get(nid) != State.DONE or p in procs.retiring.values())
        if stuck:  # they had their grace: where are they? (once, on our stderr, prefixed with the node)
            print(f"retriever: worker(s) {', '.join(stuck)} did not stop within {grace:g} s; their stacks, "
                  "then SIGKILL:", file=sys.stderr, flush=True)
            self.diagnostics.dump_stacks(stuck)
            for nid, p in running:
                if nid in stuck:
                    p.kill()
        self.reap(grace=REAP_GRACE_S if len(stuck) < len(running) else KILLED_GRACE_S)

    def reap(self, grace: float = REAP_GRACE_S) -> None:
        """Wait for every worker to exit; SIGTERM, then SIGKILL, the ones that do not."""
        started = self.book.processes.started()
        deadline = time.monotonic() + grace
        for p in started:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.send_signal(signal.SIGTERM)
        for p in started:
            try:
                p.wait(timeout=TERM_GRACE_S)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.forget_ended()


def exit_confirmed(proc: WorkerProcess, polled: dict[int, int | None] | None = None) -> bool:
    """Whether ``proc`` is known to have ended: a child of this process, or dora's, once
    ``poll()`` says how (kept in ``polled``, by ``id``, when given: asked once); a worker
    daemon's once its daemon said it exited (remote.RemoteProcess: one whose daemon was lost
    counts as killed, yet may still run and read control)."""
    confirmed = getattr(proc, "exit_confirmed", None)
    if confirmed is not None:
        return confirmed
    if polled is None:
        return proc.poll() is not None
    if id(proc) not in polled:
        polled[id(proc)] = proc.poll()
    return polled[id(proc)] is not None
