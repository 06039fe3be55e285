"""The coordinator of a run on dora: the zenoh backend's, handed a hosting whose workers dora starts.

    pipe.run(duration=10, backend="dora")
        │ open the run's private Zenoh hub (the control plane), write spec.json and dataflow.yml
        │ `dora run dataflow.yml` ──▶ one worker per flow (or group of flows), each a dora node, says `ready`
        │ put `start` {T0, end}; the workers' events and progress go to each other over dora
        │ collect their reports (step records, events) into the trace and the log
        ▼ every worker says `done` → dora run ends; the hub closes

A flow with on_error="restart" restarts in place, in its process, as a group's member does on
zenoh (zenoh/node/in_place.py): dora starts the dataflow's processes once, so none starts afresh.
A group's member is so already; a flow alone runs as a group of one (:meth:`DoraHosting.groups_of_one`).
A process that dies (a segfault) ends the run, whatever its flows' on_error. Lockstep virtual
time is refused before anything starts (use inproc or zenoh's ``virtual_time=True``).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import shutil
import time
from pathlib import Path

from ...graph import Graph
from ..zenoh.coordinator import Coordinator, Hosting
from ..zenoh.coordinator.diagnostics import exit_text
from ..zenoh.coordinator.hosting import FailRun
from ..zenoh.folders import DORA_FOLDER, private_folder
from ..zenoh.host import Host
from ..zenoh.origin import new_key
from .dataflow import DoraNames, dataflow_yaml
from .host import DoraHost, dora_command

#: before the start, how long a stopped worker has to tear down what its setup made
TEARDOWN_S = 5.0
#: how often the coordinator looks whether those workers are gone
TEARDOWN_POLL_S = 0.02

#: T0 this long after the start is put, by default (zenoh's: 0.3 s). Every worker said ready, and a
#: greeting came through each of its inputs, but for a second or two more dora is slow to deliver:
#: with less margin, a source's first events reach their consumers late, then drain as a backlog.
START_MARGIN_S = 2.0

#: the lines of dora's own output an error shows
DORA_TAIL_LINES = 10


def open_coordinator(graph: Graph, **options) -> Coordinator:
    """A run of ``graph`` on dora: the zenoh coordinator, hosted by ``dora run``."""
    options.setdefault("start_margin", START_MARGIN_S)
    return Coordinator(graph, hosting=DoraHosting(), **options)


class DoraHosting(Hosting):
    """Every process a dora node of one dataflow, which ``dora run`` starts (host.DoraHost): a
    node's, or a group's (``configure(process=)``: its members' one process)."""

    backend_name = "dora"
    shares_processes = True

    def __init__(self) -> None:
        #: ``dora run`` and what it prints, once the nodes are placed
        self.dora: DoraHost | None = None

    def check_deployable(self, graph: Graph) -> None:
        dora_command()  # installed? (before any process starts)
        super().check_deployable(graph)

    def groups_of_one(self, graph: Graph, groups: dict[str, list[str]]) -> list[str]:
        """A flow with on_error="restart" outside any group: dora starts its process once, so the
        group worker serves it alone and restarts it in place, as a group's member (its dora node,
        outputs, pid and output files are a lone flow's: named as the node)."""
        grouped = {nid for members in groups.values() for nid in members}
        return [nid for nid, node in graph.nodes.items() if node.settings.on_error == "restart" and nid not in grouped]

    def where(self) -> str:
        return f"a dora dataflow, control on the Zenoh hub at {self.run.endpoint}"

    def how_to_watch(self) -> str:
        return ("its events go between the flows over dora, not Zenoh: watch it live with foxglove=PORT or "
                "rerun=TARGET, or read its log")

    def place(self) -> dict[str, Host]:
        run = self.run
        graph = run.graph
        groups = {name: list(members) for name, members in run.spec.groups.items()}
        names = DoraNames.of(run.spec.ir, groups)
        # dora's own directory (it writes its logs there, as long as the run goes): on disk, not in
        # the run's directory, which may be in shared memory
        dora_dir = private_folder(DORA_FOLDER)  # named with this pid: reaped once this process is gone
        try:
            self.dora = self.dora_host(dora_dir, names, groups)
        except BaseException:
            shutil.rmtree(dora_dir, ignore_errors=True)
            raise
        return {nid: self.dora for nid in graph.nodes}

    def dora_host(self, dora_dir: Path, names: DoraNames, groups: dict[str, list[str]]) -> DoraHost:
        """The run's spec and dataflow written, and the host that runs it with ``dora run``."""
        run = self.run
        graph = run.graph
        # the workers are dora's children: they watch this process to know when they are orphans
        # (and then remove the run's directories, which no one else will)
        # and each node's process finds the key it signs with (origin.py) in the private spec
        keys = {nid: new_key() for nid in graph.nodes}
        for members in groups.values():  # a group's process signs for all its members with one
            keys.update(dict.fromkeys(members, keys[members[0]]))
        run.expect_keys(keys)
        run.spec = dataclasses.replace(run.spec, dora_part=names.part(cwd=os.getcwd(), coordinator=os.getpid(),
                                                                      dir=str(dora_dir), keys=keys))
        spec_path = run.spec.write_file(run.run_dir / "spec.json")
        package_root = str(Path(__file__).resolve().parents[3])  # the workers run this copy of retriever
        dataflow = dora_dir / "dataflow.yml"
        dataflow.write_text(dataflow_yaml(graph.name, names, sys.executable, str(spec_path), package_root))
        return DoraHost(run.run_dir, dataflow, names.processes(groups))

    def check(self) -> None:
        dora = self.dora
        if dora is not None and dora.alive and (dora.proc.returncode or dora.proc.poll() or 0) < 0:
            dora.alive = False  # killed: every worker goes with it (a node's own failure ends it with a code)

    def host_lost(self, host: Host, nodes: list[str]) -> FailRun:
        dora = self.dora
        last = "\n".join("        " + line for line in list(dora.tail)[-DORA_TAIL_LINES:])
        return FailRun(
            f"dora's runtime (`dora run`, pid {dora.proc.pid}) {exit_text(dora.proc.returncode)} during the run: "
            f"the dataflow's nodes ({', '.join(nodes)}) stopped with it\n    hint: was it killed (out of "
            f"memory?), or stopped by someone else? Its last errors:\n{last}", super().host_lost(host, nodes).exit)

    def before_stop(self) -> None:
        """Before the start (Ctrl-C, a flow's setup failed), the workers dora started are told to
        stop, and given TEARDOWN_S to tear down what their setup made; then dora run is ended, and
        with it whatever it has not started yet, or is stuck in its setup."""
        dora, book = self.dora, self.run.book
        if book.t0 is None and dora is not None and dora.proc.poll() is None:
            dora.interrupted = True  # what dora says of the ends we cause is not for the terminal
            started = [p for p in book.processes() if p.pid > 0 and p.poll() is None]
            for p in started:
                p.send_signal(signal.SIGTERM)
            give_up = time.monotonic() + TEARDOWN_S
            while any(p.poll() is None for p in started) and time.monotonic() < give_up:
                time.sleep(TEARDOWN_POLL_S)
            dora.interrupt()

    def release(self) -> None:
        if self.dora is not None:
            self.dora.stop()

    def stderr_tail(self, nid: str, lines: int) -> str:
        tail = super().stderr_tail(nid, lines)
        if not tail.strip() and self.dora is not None and self.dora.tail:  # it never started: dora says why
            tail = "\n".join("        " + line for line in list(self.dora.tail)[-lines:])
        return tail
