"""Deployments across hosts of the netns lab: deploy time, cross-host latency, scale (issue 18).

Everything runs in one lab of network namespaces (``deploy/netns-lab.sh`` through
``tests/deploy/lab.py``): host 1 runs the coordinator, hosts 2, 3, ... one worker daemon each
(``python -m retriever.cli worker --name wI --listen tcp/ADDR:7447 --secret KEY --path
benchmarks/``). Every session holds the deployment secret (a fresh one per run of this script);
processes on different hosts talk over real TCP between network stacks, and each host has a
/dev/shm of its own, so Zenoh's shared memory cannot shortcut a link between hosts.

The coordinator is this script on host 1, ``--coordinate JOB.json``: it runs the pipeline the way
``retriever deploy`` does, from Python (``pipe.run(backend="zenoh", connect=[...], secret=...,
placement=...)``: the same ``Deployment``), and stamps its steps with ``time.time_ns()`` from
outside (``Watch``): the deployment's own steps (join, discover, prepare) as its ``on_phase``
hook reports them, the rest by watching the session. Every namespace reads this machine's one
clock, so wall-clock stamps taken in different hosts compare directly.

1. ``deploy``: 3 workers x 10 flows (10 chains ``Counter @ Rate(10) -> Keep @ Trigger() -> Keep
   @ Trigger()``, 30 nodes, placed by load: consecutive nodes of a chain land on different
   workers, so every edge crosses hosts), ``--repeats`` deployments with the daemons staying up.
   Command start = this script's ``time.time_ns()`` right before it starts the coordinator's
   process; T0 = the coordinator's ``session.t0`` (the HLC time it put in ``start``); first tick =
   the earliest ``wall_start_ns`` of any step record of the run (a source's tick at T0), all
   ticked = the latest of each node's first ``wall_start_ns`` (a chain's end ticks on data that
   crossed two hosts). CPU: the coordinator's ``getrusage(RUSAGE_SELF)``, at the start and at its
   end; the daemons' own and their reaped children's (the flows') from ``/proc/PID/stat``.
2. ``latency``: one-way latency vs payload size of ``PayloadSource(size) @ Rate(20)`` on worker
   w1 (host 2) -> ``LatencySink() @ Trigger("frame")`` on worker w2 (host 3), each round a
   deployment, against raw zenoh-python between two plain processes on the same two hosts
   (``benchmarks/latency.py --raw-pub`` on host 2, ``--raw-sub`` listening on host 3: ``put(
   array.tobytes())``, a callback, ``np.frombuffer``). Timestamps as in latency.py: sent =
   ``time.time_ns()`` right before the send (the source's step returns), received =
   ``time.time_ns()`` with the array in hand (first thing in the sink's step). Rounds are
   interleaved, raw then Retriever, the order reversed every other round; each drops its first
   ``--warmup`` messages.
3. ``scale``: 8 workers x N flows each (``--scale-flows``, up to 25: 200 nodes), as in 1, with
   ``--scale-startup`` s for the flows to start; per size, whether every flow ticked.

    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py                   # all three parts, ~20 min
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --parts deploy --repeats 5
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --parts latency --sizes 64 1Mi --rounds 2
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --parts latency --sizes 16Mi --hz 5 --out /tmp/d
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --parts latency --coordinator-on-source --out /tmp/d
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --parts scale --scale-flows 5 25 --repeats 2
    PYTHONPATH=. .venv/bin/python benchmarks/deploy.py --replot          # the plot again, from the CSV

Needs root (network namespaces) and iproute2. Results: CSVs and the latency plot in ``--out``
(benchmarks/deploy_results/), and the output of each coordinator whose deployment failed in
``--out``/failures/. Whatever happens (an error, Ctrl-C, SIGTERM), every process it started is
stopped by its PID (daemons and coordinators run in sessions of their own: a signal meant for
this script's process group is not theirs) and the lab is taken down; every wait is bounded.
"""

from __future__ import annotations

import argparse
import csv
import faulthandler
import json
import math
import os
import resource
import secrets
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Self

#: the coordinator's first instant in Python (``--coordinate``), with only the standard library imported
SCRIPT_STARTED_NS = time.time_ns()

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # retriever and tests.deploy.lab from this checkout
sys.path.insert(0, str(HERE))  # zenoh_flows (the flows) and latency (its raw side and statistics)

PYTHON = sys.executable
LATENCY_SCRIPT = HERE / "latency.py"
DEFAULT_OUT = HERE / "deploy_results"
#: the lab's namespaces are PREFIX-h1 ... (two labs of different prefixes never touch)
DEFAULT_PREFIX = "bench"
#: a daemon's Zenoh port, on its host's lab address (hosts are separate stacks: all can use it)
WORKER_PORT = 7447
#: the raw subscriber's ports: a new one per round, so a listener never waits on the last one's TIME_WAIT
RAW_PORT_BASE = 7500
#: a bound on a daemon's start (its start line), and on any helper process beyond its own run time
BOUND_S = 60.0
#: how long a stopped process gets after SIGTERM before SIGKILL
STOP_S = 5.0
#: how many times a failed Retriever latency round is run again (each failure is reported)
RETRIES = 1
#: how long a stuck coordinator gets to print its stacks (SIGUSR1) before it is stopped
STACKS_S = 1.0
#: seconds of the coordinator's own bound for every flow to say ready (its default): part 1, part 2
STARTUP_S = 60.0
#: the deploy default (Deployment): from the last ``ready`` to T0
START_MARGIN_S = 0.5
#: a wait for the flow processes of the last run to be gone from every daemon, before the next run
IDLE_S = 30.0

# part 1 and 3: chains of flows
CHAIN = 3  # source -> relay -> sink: a chain's end ticks only on data that crossed two hosts
SOURCE_HZ = 10.0  # a camera-like rate; deploy time does not depend on it
DEPLOY_S = 2.0  # ticking time per deployment: every chain's end has ticked well before
SCALE_S = 3.0  # as benchmarks/scale.py
FAILOVER_HZ = 50.0  # src's rate: a step of mid every 20 ms, so "stepping again" is resolved to that
FAILOVER_S = 6.0  # ticking time per deployment: the kill 2 s past T0, then time enough to move
FAILOVER_KILL_S = 2.0

# part 2: latency
LATENCY_HZ = 20.0  # as latency.py
DEFAULT_SIZES = ["64", "16Ki", "1Mi", "16Mi"]
TARGET_RATIO = 1.2  # the issue's: Retriever's median <= 1.2x raw zenoh's at every size


# ---------------------------------------------------------------------------------------------
# The coordinator (--coordinate JOB.json), on lab host 1
# ---------------------------------------------------------------------------------------------
def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class Watch:
    """Stamps the coordinator's steps from outside it, in its process: the deployment's own steps
    (join, discover, prepare) as its ``on_phase`` reports each one's end; from a thread of its own,
    polling every ``POLL_S``: the session built (``pipe.session`` set, once each flow's process is
    spawned), each node's first ``ready`` (the session's ``book.processes.state``), and, once T0 is chosen
    (``book.t0`` set: every flow ready; ``start`` is put right after), when that was (T0 less the
    start margin) and the CPU this process used by then, the watcher's own left out; and it
    prints the failure that makes the session close early as soon as the book holds it (a hang
    in the close would hide it)."""

    #: how often the watcher looks until T0 (the stamps' resolution), and after
    POLL_S, POLL_AFTER_S = 0.005, 0.05

    def __init__(self, pipe, stamps: dict):
        self.pipe, self.stamps = pipe, stamps
        self.phases: dict[str, float] = stamps.setdefault("phases", {})  # name -> s
        self.ready_at: dict[str, int] = stamps.setdefault("ready_at", {})
        self.done = threading.Event()
        self.own_cpu_ns = 0
        self.thread = threading.Thread(target=self._watch, name="bench-watch", daemon=True)

    def on_phase(self, name: str, seconds: float) -> None:
        """The deployment's hook: ``name`` ended now, ``seconds`` after it began."""
        self.phases[name] = seconds
        if name == "prepare":  # the coordinator spawns each flow's process next
            self.stamps["spawn"] = [time.time_ns(), 0]

    def __enter__(self) -> Self:
        self.stamps["session"] = [time.time_ns(), 0]
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.done.set()
        self.thread.join()

    def cpu_seconds(self) -> float:
        """This process's CPU s so far, without the watcher's."""
        return cpu_seconds() - self.own_cpu_ns / 1e9

    def _watch(self) -> None:
        from retriever.backends.zenoh.protocol import State

        stamps, session, told = self.stamps, None, False
        while not self.done.wait(self.POLL_S if "ready" not in stamps else self.POLL_AFTER_S):
            begin = time.thread_time_ns()
            now = time.time_ns()
            if session is None and (session := self.pipe.session) is not None:
                stamps["session"][1] = now
                if "spawn" in stamps:
                    stamps["spawn"][1] = now
            book = getattr(session, "book", None)
            if book is not None:
                for node, state in list(book.processes.state.items()):
                    if state == State.READY and node not in self.ready_at:
                        self.ready_at[node] = now
                if book.t0 is not None and "ready" not in stamps:
                    stamps["ready"] = book.t0 - session.start_margin_ns  # T0 is chosen that far ahead
                    stamps["cpu_at_start"] = self.cpu_seconds() - (time.thread_time_ns() - begin) / 1e9
                if book.ending.failure is not None and not told:
                    told = True
                    self._tell(now, book.ending.failure)
            self.own_cpu_ns += time.thread_time_ns() - begin

    def _tell(self, now: int, failure) -> None:
        node, error = failure.node, failure.error
        spans = {k: [round((t - SCRIPT_STARTED_NS) / 1e9, 3) for t in v] for k, v in self.stamps.items()
                 if isinstance(v, list)}
        print(f"coordinator: the session closes on a failure of '{node}', {(now - SCRIPT_STARTED_NS) / 1e9:.3f} s "
              f"after the script started: {error}\n{len(self.ready_at)} nodes had said ready; spans (s "
              f"since the script started): {spans}; the deployment's phases (s): {self.phases}", file=sys.stderr,
              flush=True)


def chains_pipeline(nodes: int, chain: int, hz: float):
    """``nodes`` flows in chains of ``chain``: Counter @ Rate(hz) -> Keep @ Trigger() -> ...; the
    last chain is shorter when ``chain`` does not divide ``nodes``."""
    from zenoh_flows import Counter, Keep

    from retriever import Latest, Pipeline, Rate, Trigger

    with Pipeline(f"chains{nodes}") as pipe:
        for c in range(math.ceil(nodes / chain)):
            length = min(chain, nodes - c * chain)
            prev = Counter().configure(name=f"c{c:03d}n0") @ Rate(hz=hz)
            for k in range(1, length):
                node = Keep().configure(name=f"c{c:03d}n{k}") @ Trigger()
                prev.then(node, sync=Latest())
                prev = node
    return pipe


def latency_pipeline(size: int, hz: float, record: str | None = None):
    from zenoh_flows import LatencySink, PayloadSource

    from retriever import Pipeline, Rate, Trigger

    with Pipeline(f"latency{size}") as pipe:
        src = PayloadSource(size).named("src") @ Rate(hz=hz)
        sink = LatencySink(record).named("sink") @ Trigger("frame")
        pipe.connect(src, sink)
    return pipe


def failover_pipeline(hz: float):
    """``src`` @ Rate(hz) -> ``mid`` @ Trigger() -> ``sink`` @ Trigger(): src and sink pinned to the
    first worker, mid placed by load on another (the one the benchmark kills)."""
    from zenoh_flows import Counter, Keep

    from retriever import Latest, Pipeline, Rate, Trigger

    with Pipeline("failover") as pipe:
        src = Counter().configure(name="src") @ Rate(hz=hz)
        mid = Keep().configure(name="mid") @ Trigger()
        sink = Keep().configure(name="sink") @ Trigger()
        src.then(mid, sync=Latest()).then(sink, sync=Latest())
    return pipe


def kill_mid_worker(pipe, after_s: float, out: dict) -> None:
    """In the coordinator's process, on a thread: ``after_s`` past T0, SIGKILL the daemon running
    ``mid`` (the lab's namespaces share one PID space) and note when, and which worker it was."""
    give_up = time.monotonic() + 300
    while time.monotonic() < give_up:
        session = pipe.session
        t0 = getattr(session, "t0", None)
        if t0 is not None and time.time_ns() >= t0 + after_s * 1e9:
            name = session.hosting.placed["mid"]
            out["killed_worker"] = name
            out["kill_ns"] = time.time_ns()
            os.kill(session.hosting.daemons[name].info.pid, signal.SIGKILL)
            return
        time.sleep(0.005)


def failover_result(trace, session, killed: dict) -> dict:
    """From the kill to ``mid``'s first step on its new worker, and to the first step of ``sink``
    on an event of that new process (the pipeline end to end again)."""
    from retriever import StepStatus
    kill = killed.get("kill_ns")
    if kill is None:
        return {"error": "the worker of mid was never killed"}
    mid_after = [s for s in trace.steps if s.node == "mid" and s.status == StepStatus.OK and s.wall_start_ns > kill]
    first_mid = min(mid_after, key=lambda s: s.wall_start_ns) if mid_after else None
    new_ids = {i for s in mid_after for i in s.produced}
    sink_after = [s for s in trace.steps if s.node == "sink" and s.wall_start_ns > kill
                  and any(i in new_ids for ids in s.consumed.values() for i in ids)]
    first_sink = min((s.wall_start_ns for s in sink_after), default=None)
    return {**killed, "moved_to": session.hosting.placed.get("mid"),
            "mid_again_ms": (first_mid.wall_start_ns - kill) / 1e6 if first_mid else None,
            "sink_again_ms": (first_sink - kill) / 1e6 if first_sink else None,
            "moves": session.counts.get("moves", 0)}


def chains_result(trace, session) -> dict:
    """Each node's first tick (Unix ns) and steps; where each node ran; edges across workers."""
    from retriever import StepStatus
    first: dict[str, int] = {}
    steps: dict[str, int] = {}
    for st in trace.steps:
        first[st.node] = min(first.get(st.node, st.wall_start_ns), st.wall_start_ns)
        steps[st.node] = steps.get(st.node, 0) + (st.status == StepStatus.OK)
    placed = session.hosting.placed
    crossing = sum(placed[e.src] != placed[e.dst] for e in session.graph.edges)
    return {"first_tick": first, "ok_steps": steps, "nodes": sorted(session.graph.nodes),
            "edges": len(session.graph.edges), "edges_across": crossing, "placed": placed,
            "reported_bytes": session.reported_bytes, "redeclared": session.counts.get("redeclared", 0)}


def latency_result(trace, warmup: int, pipe, record: str | None = None) -> dict:
    """The sink's [sent, received, size] events, in order, the first ``warmup`` dropped; what each
    node counted (late, incomplete, overrun, report waits: why a frame was not stepped on).
    ``record``: the file the sink wrote them to (a run that kept no values)."""
    if record is None:
        values = [ev.value for ev in sorted((ev for ev in trace.events if ev.node == "sink"), key=lambda ev: ev.seq)]
    else:
        values = [[int(x) for x in line.split()] for line in Path(record).read_text().splitlines()]
        Path(record).unlink()
    sent = sum(1 for ev in trace.events if ev.node == "src")
    return {"lat": [v[1] - v[0] for v in values[warmup:]], "received": len(values), "sent": sent,
            "sizes": sorted({v[2] for v in values}),
            "counts": {node: dict(s.counts) for node, s in pipe.stats().items() if s.counts}}


def coordinate(job_path: str) -> int:
    """Run one deployment as JOB.json says; write what it measured to the job's ``out`` file."""
    job = json.loads(Path(job_path).read_text())
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # the benchmark's bound ran out: where is it stuck?
    stamps: dict = {}
    from retriever.placement import Constraint, Placement

    record = None  # keep="records": the sink's measurements come in a file, not in the trace
    killed: dict = {}
    if job["kind"] == "chains":
        pipe = chains_pipeline(job["nodes"], job["chain"], job["hz"])
    elif job["kind"] == "failover":
        pipe = failover_pipeline(job["hz"])
        threading.Thread(target=kill_mid_worker, args=(pipe, job["kill_after"], killed), daemon=True).start()
    else:
        if job.get("keep") == "records":
            record = f"{tempfile.gettempdir()}/retriever-bench-sink-{os.getpid()}.txt"
        pipe = latency_pipeline(job["size"], job["hz"], record)
    pins = job.get("pin") or {}
    placement = Placement({node: Constraint(worker=w) for node, w in pins.items()}) if pins else None
    result: dict = {"script_started": SCRIPT_STARTED_NS, "stamps": stamps}
    watch = Watch(pipe, stamps)
    try:
        with watch:
            trace = pipe.run(duration=job["duration"], backend="zenoh", quiet=True, connect=job["connect"],
                             namespace=job["namespace"], secret=job["secret"], placement=placement,
                             startup_timeout=job["startup_timeout"], start_margin=START_MARGIN_S,
                             keep=job.get("keep", "trace"), on_phase=watch.on_phase)
        session = pipe.session
        if job["kind"] == "chains":
            result.update(chains_result(trace, session))
        elif job["kind"] == "failover":
            result.update(failover_result(trace, session, killed))
        else:
            result.update(latency_result(trace, job["warmup"], pipe, record))
    except Exception as exc:  # noqa: BLE001 - reported to the benchmark, which goes on
        traceback.print_exc()
        result["error"] = f"{type(exc).__name__}: {exc}"
    session = pipe.session
    result["t0"] = getattr(session, "t0", None)
    result["cpu_s"] = watch.cpu_seconds()
    result["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    Path(job["out"]).write_text(json.dumps(result))
    return 0 if "error" not in result else 1


# ---------------------------------------------------------------------------------------------
# The lab: daemons, coordinator runs, raw zenoh processes
# ---------------------------------------------------------------------------------------------
def proc_cpu(pid: int) -> tuple[float, float]:
    """A process's own CPU s and that of its reaped children, from /proc (0 when it is gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0.0, 0.0
    fields = stat[stat.rindex(")") + 2:].split()
    tick = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / tick, (int(fields[13]) + int(fields[14])) / tick


def children_of(pids: set[int]) -> list[int]:
    """The live processes whose parent is one of ``pids`` (a daemon's flow processes)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[1]) in pids and fields[0] not in "ZX":
                found.append(int(entry.name))
    return found


class Daemons:
    """``count`` worker daemons w1 ... on lab hosts 2 ... (namespace ``namespace``), until the
    ``with`` block ends: then each is stopped by its PID (SIGTERM, SIGKILL after STOP_S)."""

    def __init__(self, bench: Bench, count: int, namespace: str):
        self.bench, self.namespace = bench, namespace
        self.hosts = bench.lab.hosts[1:count + 1]
        self.names = [f"w{i}" for i in range(1, count + 1)]
        self.procs: list[subprocess.Popen] = []
        self.said: dict[str, list[str]] = {}  # what each printed on stderr
        self.shown: dict[str, int] = {}  # how many of those lines print_news showed
        self.deaths: list[str] = []  # daemons found gone before a run, and started again

    def __enter__(self) -> Self:
        try:
            for host, name in zip(self.hosts, self.names):
                self.procs.append(self._start(host, name))
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _start(self, host, name: str) -> subprocess.Popen:
        proc = host.popen([PYTHON, "-m", "retriever.cli", "worker", "--name", name, "--listen",
                           f"tcp/{host.address}:{WORKER_PORT}", "--namespace", self.namespace, "--secret",
                           str(self.bench.secret), "--path", str(HERE)],
                          env=self.bench.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                          start_new_session=True)  # a signal to this benchmark's process group is not theirs
        said = self.said[name] = []
        self.shown[name] = 1
        give_up = time.monotonic() + BOUND_S
        while time.monotonic() < give_up:
            if select.select([proc.stderr], [], [], 0.1)[0]:
                said.append(proc.stderr.readline())
                if said[-1].startswith(f"retriever-worker '{name}' in namespace"):
                    threading.Thread(target=lambda: said.extend(proc.stderr), daemon=True).start()  # keep reading
                    return proc
            if proc.poll() is not None:
                raise RuntimeError(f"daemon {name} exited {proc.returncode}: {''.join(said)}")
        raise RuntimeError(f"daemon {name} did not start within {BOUND_S:g} s: {''.join(said)}")

    def stop(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def ensure_up(self) -> None:
        """Start again each daemon that is gone (it should not be: say so, with what it printed)."""
        for i, (host, name, proc) in enumerate(zip(self.hosts, self.names, self.procs)):
            if proc.poll() is not None:
                self.print_news()
                self.deaths.append(f"{time.strftime('%H:%M:%S')} daemon {name} (pid {proc.pid}) had exited "
                                   f"{proc.returncode}; started again")
                print(f"    {self.deaths[-1]}", flush=True)
                self.procs[i] = self._start(host, name)

    def print_news(self) -> None:
        """What the daemons printed since their start line (each line once)."""
        for name, said in self.said.items():
            for line in said[self.shown.get(name, 1):]:
                print(f"    [daemon {name}] {line.rstrip()}")
            self.shown[name] = len(said)

    @property
    def endpoints(self) -> list[str]:
        return [f"tcp/{host.address}:{WORKER_PORT}" for host in self.hosts]

    def cpu(self) -> tuple[float, float]:
        """CPU s of the daemons themselves, and of the flow processes they reaped."""
        own, reaped = zip(*(proc_cpu(p.pid) for p in self.procs))
        return sum(own), sum(reaped)

    def wait_idle(self) -> int:
        """Wait until no daemon has a flow process left (the last run's), at most IDLE_S; how many are left."""
        pids = {p.pid for p in self.procs}
        give_up = time.monotonic() + IDLE_S
        while (left := children_of(pids)) and time.monotonic() < give_up:
            time.sleep(0.05)
        return len(left)


class Bench:
    """The lab and what every part shares: the secret, the coordinator's host, a scratch folder."""

    def __init__(self, lab, scratch: Path, failures: Path):
        self.lab, self.scratch, self.failure_logs = lab, scratch, failures
        self.secret = scratch / "lab.key"
        self.secret.write_text(secrets.token_hex(32) + "\n")
        self.secret.chmod(0o600)
        self.coordinator = lab.hosts[0]
        # every process here imports this checkout's retriever (the venv may hold another's)
        self.env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
        self.jobs = 0
        self.failures: list[str] = []  # deployments that failed and were run again (latency)

    def daemons(self, count: int, namespace: str) -> Daemons:
        return Daemons(self, count, namespace)

    def coordinate(self, job: dict, bound: float, host=None) -> dict:
        """Run the coordinator with ``job`` on ``host`` (default host 1), at most ``bound`` s; what
        it measured, with ``started`` (this process's clock right before it started it)."""
        self.jobs += 1
        path, out, log = (self.scratch / f"job{self.jobs}.{ext}" for ext in ("json", "out.json", "log"))
        path.write_text(json.dumps({**job, "secret": str(self.secret), "out": str(out)}))
        with log.open("w") as stream:
            started = time.time_ns()
            argv = [PYTHON, str(Path(__file__).resolve()), "--coordinate", str(path)]
            proc = (host or self.coordinator).popen(argv, env=self.env, stdout=stream, stderr=subprocess.STDOUT,
                                                    start_new_session=True)  # stopped by its PID, as the daemons
            try:
                proc.wait(bound)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGUSR1)  # its stacks, into its output
                time.sleep(STACKS_S)
                proc.terminate()
                try:
                    proc.wait(STOP_S)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        result = json.loads(out.read_text()) if out.exists() else {"error": f"the coordinator exited {proc.returncode}"
                                                                           f" without a result (bound {bound:g} s)"}
        result["started"] = started
        if "error" in result:
            self.failure_logs.mkdir(parents=True, exist_ok=True)
            kept = self.failure_logs / f"{self.scratch.name}-job{self.jobs}.log"
            kept.write_text(f"job: {json.dumps(job)}\nresult: {result['error']}\n\n{log.read_text()}")
            result["output"] = f"(the coordinator's output is in {kept})\n" + log.read_text()[-1500:]
        return result


# ---------------------------------------------------------------------------------------------
# Parts 1 and 3: deploy time
# ---------------------------------------------------------------------------------------------
DEPLOY_FIELDS = ("workers", "flows_per_worker", "nodes", "repeat", "ok", "launch_s", "imports_s", "join_s",
                 "discover_s", "prepare_s", "spawn_s", "ready_wait_s", "margin_s", "to_t0_s", "first_tick_s",
                 "all_ticked_s", "first_tick_after_t0_ms", "all_ticked_after_t0_ms", "first_ready_s", "last_ready_s",
                 "ticked", "edges_across", "coord_cpu_to_t0_s", "coord_cpu_s",
                 "coord_rss_mb", "daemons_cpu_s", "flows_cpu_s", "load1", "daemons_restarted", "reported_mb",
                 "redeclared", "error")


def span_s(stamps: dict, key: str) -> float:
    begin, end = stamps.get(key, (0, 0))
    return (end - begin) / 1e9 if begin and end else float("nan")


def phase_s(stamps: dict, name: str) -> float:
    """How long the deployment's step ``name`` took (its ``on_phase``), in s."""
    return stamps.get("phases", {}).get(name, float("nan"))


def deploy_row(res: dict, workers: int, per_worker: int, repeat: int, cpu: tuple) -> dict:
    """One deployment's figures, in s from the command's start unless a span."""
    st, t0, started = res.get("stamps", {}), res.get("t0"), res["started"]
    first = res.get("first_tick", {})
    def since(ns: int | None) -> float:
        return (ns - started) / 1e9 if ns else float("nan")

    nodes = workers * per_worker
    ticked = sum(1 for n in res.get("nodes", []) if res.get("ok_steps", {}).get(n))
    return {
        "workers": workers, "flows_per_worker": per_worker, "nodes": nodes, "repeat": repeat,
        "ok": "error" not in res and ticked == nodes,
        "launch_s": since(res.get("script_started")),
        "imports_s": (st["session"][0] - res["script_started"]) / 1e9 if "session" in st else float("nan"),
        "join_s": phase_s(st, "join"), "discover_s": phase_s(st, "discover"), "prepare_s": phase_s(st, "prepare"),
        "spawn_s": span_s(st, "spawn"),
        "ready_wait_s": (st["ready"] - st["session"][1]) / 1e9 if "ready" in st and "session" in st else float("nan"),
        "margin_s": (t0 - st["ready"]) / 1e9 if t0 and "ready" in st else float("nan"),
        "to_t0_s": since(t0), "first_tick_s": since(min(first.values(), default=0)),
        "all_ticked_s": since(max(first.values(), default=0)),
        "first_tick_after_t0_ms": (min(first.values()) - t0) / 1e6 if first and t0 else float("nan"),
        "all_ticked_after_t0_ms": (max(first.values()) - t0) / 1e6 if first and t0 else float("nan"),
        "first_ready_s": since(min(st.get("ready_at", {}).values(), default=0)),
        "last_ready_s": since(max(st.get("ready_at", {}).values(), default=0)),
        "ticked": ticked,
        "edges_across": f"{res.get('edges_across', '?')}/{res.get('edges', '?')}",
        "coord_cpu_to_t0_s": st.get("cpu_at_start", float("nan")), "coord_cpu_s": res.get("cpu_s", float("nan")),
        "coord_rss_mb": res.get("maxrss_mb", float("nan")), "daemons_cpu_s": cpu[0], "flows_cpu_s": cpu[1],
        "reported_mb": res.get("reported_bytes", float("nan")) / 1e6, "redeclared": res.get("redeclared"),
        "error": res.get("error", "")[:300],
    }


def measure_deploys(bench: Bench, workers: int, per_worker: int, repeats: int, duration: float,
                    startup: float, namespace: str) -> list[dict]:
    """``repeats`` deployments of ``workers`` x ``per_worker`` flows on daemons that stay up."""
    rows = []
    with bench.daemons(workers, namespace) as daemons:
        for r in range(1, repeats + 1):
            left, deaths = daemons.wait_idle(), len(daemons.deaths)
            daemons.ensure_up()
            before, load1 = daemons.cpu(), os.getloadavg()[0]
            job = {"kind": "chains", "nodes": workers * per_worker, "chain": CHAIN, "hz": SOURCE_HZ,
                   "duration": duration, "connect": daemons.endpoints, "namespace": namespace,
                   "startup_timeout": startup}
            res = bench.coordinate(job, bound=startup + duration + BOUND_S)
            daemons.wait_idle()  # the flows reaped: their CPU is in the daemons' children's
            after = daemons.cpu()
            row = deploy_row(res, workers, per_worker, r, (after[0] - before[0], after[1] - before[1]))
            row["load1"] = load1  # the machine's load average when the deployment started
            row["daemons_restarted"] = len(daemons.deaths) - deaths  # found gone right before this run
            if not row["ok"]:
                daemons.print_news()
            rows.append(row)
            print(f"  {workers} workers x {per_worker} flows, run {r}: to T0 {row['to_t0_s']:.2f} s, first tick "
                  f"{row['first_tick_s']:.2f} s, all ticked {row['all_ticked_s']:.2f} s, {row['ticked']}/"
                  f"{row['nodes']} ticked" + (f" ({left} processes of the last run were still up)" if left else "")
                  + (f"\n    ERROR: {res['error']}\n" + res.get("output", "")[-1500:] if "error" in res else ""),
                  flush=True)
    return rows


def measure_failover(bench: Bench, repeats: int) -> list[dict]:
    """``repeats`` deployments on 3 workers, each killing the worker of ``mid`` 2 s past T0."""
    rows = []
    with bench.daemons(3, "bench-failover") as daemons:
        for r in range(1, repeats + 1):
            daemons.wait_idle()
            daemons.ensure_up()  # the last round's killed daemon, started again
            load1 = os.getloadavg()[0]
            job = {"kind": "failover", "hz": FAILOVER_HZ, "duration": FAILOVER_S, "kill_after": FAILOVER_KILL_S,
                   "pin": {"src": daemons.names[0], "sink": daemons.names[0]}, "connect": daemons.endpoints,
                   "namespace": daemons.namespace, "startup_timeout": STARTUP_S}
            res = bench.coordinate(job, bound=STARTUP_S + FAILOVER_S + BOUND_S)
            row = {"repeat": r, "load1": load1, "killed_worker": res.get("killed_worker"),
                   "moved_to": res.get("moved_to"), "mid_again_ms": res.get("mid_again_ms"),
                   "sink_again_ms": res.get("sink_again_ms"), "moves": res.get("moves"),
                   "error": res.get("error", "")[:300]}
            rows.append(row)
            print(f"  failover {r}: killed {row['killed_worker']}, mid on {row['moved_to']} stepping again after "
                  f"{row['mid_again_ms']} ms, sink on its events after {row['sink_again_ms']} ms"
                  + (f"\n    ERROR: {res['error']}\n" + res.get("output", "")[-1500:] if "error" in res else ""),
                  flush=True)
    return rows


def med_spread(values: list[float], fmt: str = "{:.2f}") -> str:
    """median [min–max] of the finite values."""
    values = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    if not values:
        return "-"
    return f"{fmt.format(statistics.median(values))} [{fmt.format(min(values))}–{fmt.format(max(values))}]"


DEPLOY_COLUMNS = [("to_t0_s", "to T0 s", "{:.2f}"), ("first_tick_after_t0_ms", "1st tick-T0 ms", "{:.1f}"),
                  ("all_ticked_after_t0_ms", "all ticked-T0 ms", "{:.0f}"), ("coord_cpu_to_t0_s", "coord CPU@T0 s", "{:.2f}"),
                  ("coord_cpu_s", "coord CPU s", "{:.2f}"), ("flows_cpu_s", "flows CPU s", "{:.1f}")]
PHASES = ("launch_s", "imports_s", "join_s", "discover_s", "prepare_s", "spawn_s", "ready_wait_s", "margin_s")


def print_deploys(rows: list[dict], title: str) -> None:
    """Per size: median [min–max] of each column over the runs that worked; then the phases to T0."""
    sizes = sorted({(r["workers"], r["flows_per_worker"]) for r in rows})
    of = {key: [r for r in rows if (r["workers"], r["flows_per_worker"]) == key] for key in sizes}
    print(f"\n{title}: median [min–max] over the runs that worked (ok = every node ticked)")
    print(f"{'workers x flows':>15} │ {'ok':>5} │ " + " │ ".join(f"{name:>21}" for _, name, _ in DEPLOY_COLUMNS))
    for key in sizes:
        good = [r for r in of[key] if r["ok"]]
        cells = [med_spread([r[c] for r in good], fmt).rjust(21) for c, _, fmt in DEPLOY_COLUMNS]
        print(f"{f'{key[0]} x {key[1]}':>15} │ {len(good)}/{len(of[key]):<3} │ " + " │ ".join(cells))
    print("phases to T0, s (median [min–max]): " + ", ".join(p.removesuffix("_s") for p in PHASES))
    for key in sizes:
        good = [r for r in of[key] if r["ok"]]
        print(f"{f'{key[0]} x {key[1]}':>15} │ " + " │ ".join(med_spread([r[p] for r in good]) for p in PHASES))
    for r in rows:
        if not r["ok"]:
            why = r["error"] or f"{r['ticked']}/{r['nodes']} nodes ticked"
            print(f"  {r['workers']} x {r['flows_per_worker']} run {r['repeat']} failed: {why}")


# ---------------------------------------------------------------------------------------------
# Part 2: latency, Retriever across hosts vs raw zenoh-python across the same hosts
# ---------------------------------------------------------------------------------------------
def raw_round(bench: Bench, pub_host, sub_host, size: int, total: int, warmup: int, hz: float, port: int) -> dict:
    """latency.py's raw publisher on ``pub_host`` -> its raw subscriber on ``sub_host``."""
    key = f"bench/deploy/{os.getpid()}/{size}"
    listen = f"tcp/{sub_host.address}:{port}"
    timeout = total / hz + 30  # the subscriber's own bound for the last message
    sub = sub_host.popen([PYTHON, str(LATENCY_SCRIPT), "--raw-sub", key, listen, str(total), str(timeout)],
                         env=bench.env, stdout=subprocess.PIPE, text=True)
    if not select.select([sub.stdout], [], [], BOUND_S)[0] or sub.stdout.readline().strip() != "READY":
        raise RuntimeError(f"the raw subscriber on {sub_host.name} did not start within {BOUND_S:g} s")
    pub = pub_host.popen([PYTHON, str(LATENCY_SCRIPT), "--raw-pub", key, listen, str(size), str(total),
                          str(hz), "1", "batched"], env=bench.env, stdout=subprocess.PIPE, text=True)
    try:
        got = json.loads(sub.communicate(timeout=timeout + BOUND_S)[0].strip().splitlines()[-1])
        pub.communicate(timeout=BOUND_S)
    except subprocess.TimeoutExpired:
        raise RuntimeError("a raw zenoh process did not finish in time") from None
    if any(n != size for _, _, _, n, _ in got):
        raise RuntimeError("the raw subscriber got a payload of the wrong size")
    got.sort()
    return {"lat": [received - sent for seq, sent, received, _, _ in got if seq >= warmup], "received": len(got)}


def retriever_round(bench: Bench, daemons: Daemons, size: int, total: int, warmup: int, hz: float,
                    host, keep: str = "trace") -> dict:
    """A deployment: src pinned on w1 (host 2), sink on w2 (host 3), the coordinator on ``host``.
    One that fails is run again, RETRIES times at most; each failure is kept in ``bench.failures``."""
    job = {"kind": "latency", "size": size, "hz": hz, "duration": total / hz, "warmup": warmup,
           "pin": {"src": daemons.names[0], "sink": daemons.names[1]}, "connect": daemons.endpoints,
           "namespace": daemons.namespace, "startup_timeout": STARTUP_S, "keep": keep}
    for _ in range(1 + RETRIES):
        res = bench.coordinate(job, bound=STARTUP_S + total / hz + 2 * BOUND_S, host=host)
        if "error" not in res:
            break
        st = res.get("stamps", {})
        bench.failures.append(f"latency {size} B: {res['error']} (join {phase_s(st, 'join'):.3f} s, discover "
                              f"{phase_s(st, 'discover'):.3f} s)")
        print(f"    FAILED: {bench.failures[-1]}\n{res.get('output', '')[-1500:]}", flush=True)
    else:
        raise RuntimeError(f"the Retriever round of {size} B failed {1 + RETRIES} times (above)")
    if res["sizes"] != [size]:
        raise RuntimeError(f"the sink got payloads of sizes {res['sizes']}, not {size}")
    return res


def measure_latency(bench: Bench, sizes: list[int], rounds: int, per_round: int, warmup: int, hz: float,
                    coordinator_on_source: bool = False, keep: str = "trace") -> tuple[list[dict], list[dict]]:
    """Per size, ``rounds`` rounds of each side, interleaved: one row per kept sample, one per round."""
    samples, per_round_rows, total = [], [], warmup + per_round
    port = RAW_PORT_BASE
    with bench.daemons(2, "bench-latency") as daemons:
        pub_host, sub_host = daemons.hosts
        host = pub_host if coordinator_on_source else bench.coordinator
        for size in sizes:
            for r in range(1, rounds + 1):
                for side in ("raw", "retriever") if r % 2 else ("retriever", "raw"):
                    daemons.wait_idle()
                    daemons.ensure_up()
                    port += 1
                    out = (raw_round(bench, pub_host, sub_host, size, total, warmup, hz, port) if side == "raw"
                           else retriever_round(bench, daemons, size, total, warmup, hz, host, keep))
                    samples += [{"size": size, "side": side, "round": r, "latency_us": lat / 1e3} for lat in out["lat"]]
                    row = {"size": size, "side": side, "round": r, "sent": out.get("sent", total),
                           "received": out["received"], "median_us": statistics.median(out["lat"] or [math.nan]) / 1e3,
                           "counted": json.dumps(out.get("counts") or {})}
                    per_round_rows.append(row)
                    print(f"  {size:>9} B round {r} {side:>9}: {row['received']}/{row['sent']} received, median "
                          f"{row['median_us']:.0f} µs" + (f"; counted {row['counted']}" if out.get("counts") else ""),
                          flush=True)
    return samples, per_round_rows


def latency_summary(samples: list[dict], sizes: list[int]) -> list[dict]:
    from latency import quantile, ratio_interval

    rows = []
    for size in sizes:
        row = {"size": size}
        for side in ("raw", "retriever"):
            lat = sorted(s["latency_us"] for s in samples if s["size"] == size and s["side"] == side)
            row |= {f"{side}_n": len(lat), f"{side}_p10_us": quantile(lat, 0.1),
                    f"{side}_median_us": quantile(lat, 0.5), f"{side}_p90_us": quantile(lat, 0.9)}
        ret = [s["latency_us"] for s in samples if s["size"] == size and s["side"] == "retriever"]
        raw = [s["latency_us"] for s in samples if s["size"] == size and s["side"] == "raw"]
        row["ratio"] = row["retriever_median_us"] / row["raw_median_us"]
        row["ratio_ci_lo"], row["ratio_ci_hi"] = ratio_interval(ret, raw)
        row["target_met"] = row["ratio"] <= TARGET_RATIO
        rows.append(row)
    return rows


def print_latency(rows: list[dict]) -> None:
    from latency import fmt_size

    print("\none-way latency across hosts, µs: median (p10–p90); ratio = Retriever median / raw median (95% CI)")
    print(f"{'payload':>8} │ {'raw zenoh':>24} │ {'Retriever':>24} │ {'ratio':>17} │ ≤{TARGET_RATIO:g}×")
    for r in rows:
        cells = [f"{r[f'{s}_median_us']:.0f} ({r[f'{s}_p10_us']:.0f}–{r[f'{s}_p90_us']:.0f}) n={r[f'{s}_n']}"
                 for s in ("raw", "retriever")]
        print(f"{fmt_size(r['size']):>8} │ {cells[0]:>24} │ {cells[1]:>24} │ "
              f"{r['ratio']:.2f} ({r['ratio_ci_lo']:.2f}–{r['ratio_ci_hi']:.2f}) │ {'yes' if r['target_met'] else 'NO'}")


def plot_latency(rows: list[dict], path: Path, title: str) -> None:
    """Top: each side's median with its p10–p90; bottom: the ratio of medians with its 95% interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from latency import fmt_size
    from matplotlib.ticker import FuncFormatter, NullLocator

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6.5), sharex=True, height_ratios=[2.2, 1])
    sizes = [r["size"] for r in rows]
    for side, label, shift in (("raw", "raw zenoh-python", 0.93), ("retriever", "Retriever, deployed", 1.07)):
        med = [r[f"{side}_median_us"] for r in rows]
        err = [[m - r[f"{side}_p10_us"] for m, r in zip(med, rows)], [r[f"{side}_p90_us"] - m for m, r in zip(med, rows)]]
        top.errorbar([s * shift for s in sizes], med, yerr=err, marker="o", capsize=4, label=f"{label}: median, p10–p90")
    top.set(yscale="log", ylabel="one-way latency (µs)", title=title)
    top.legend()
    ratio = [r["ratio"] for r in rows]
    ci = [[q - r["ratio_ci_lo"] for q, r in zip(ratio, rows)], [r["ratio_ci_hi"] - q for q, r in zip(ratio, rows)]]
    bottom.errorbar(sizes, ratio, yerr=ci, marker="o", capsize=4, color="black", label="median ratio, 95% CI")
    bottom.axhline(TARGET_RATIO, linestyle="--", color="red", label=f"target {TARGET_RATIO:g}×")
    bottom.set(xscale="log", yscale="log", xlabel="payload", ylabel="Retriever / raw")
    bottom.legend(fontsize=8)
    for ax in (top, bottom):
        ax.grid(True, which="both", alpha=0.3)
    bottom.set_xticks(sizes, [fmt_size(s) for s in sizes])
    bottom.xaxis.set_minor_locator(NullLocator())
    plain = FuncFormatter(lambda y, _: f"{y:g}")  # 2, not 2×10⁰
    bottom.yaxis.set_major_formatter(plain)
    bottom.yaxis.set_minor_formatter(plain)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def replot(out: Path, hz: float) -> None:
    """The plot again, from the summary CSV a run wrote (``--replot``)."""
    with (out / "deploy_latency.csv").open() as f:
        rows = [{k: (v == "True" if v in ("True", "False") else float(v)) for k, v in row.items()}
                for row in csv.DictReader(f)]
    for row in rows:
        row["size"] = int(row["size"])
    plot_latency(rows, out / "deploy_latency.png", latency_title(hz))
    print(f"wrote {out / 'deploy_latency.png'}")


def latency_title(hz: float, keep: str = "trace") -> str:
    return f"one-way latency, host A → host B of the netns lab (TCP), {hz:g} Hz, keep={keep}"


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def write_csv(path: Path, rows: list[dict], fields=None) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(fields or rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def run_parts(bench: Bench, args, out: Path) -> None:
    from latency import parse_size

    if "deploy" in args.parts:
        print(f"part 1: 3 workers x 10 flows, {args.repeats} deployments; load {load()}", flush=True)
        rows = measure_deploys(bench, 3, 10, args.repeats, DEPLOY_S, STARTUP_S, "bench-deploy")
        write_csv(out / "deploy_time.csv", rows, DEPLOY_FIELDS)
        print_deploys(rows, "deploy time")
    if "latency" in args.parts:
        sizes = [parse_size(s) for s in args.sizes]
        print(f"\npart 2: latency, {args.rounds} rounds x ({args.warmup} + {args.samples}) messages per side and size "
              f"at {args.hz:g} Hz; load {load()}", flush=True)
        samples, rounds = measure_latency(bench, sizes, args.rounds, args.samples, args.warmup, args.hz,
                                          args.coordinator_on_source, args.keep)
        write_csv(out / "deploy_latency_samples.csv", samples)
        write_csv(out / "deploy_latency_rounds.csv", rounds)
        rows = latency_summary(samples, sizes)
        write_csv(out / "deploy_latency.csv", rows)
        print_latency(rows)
        plot_latency(rows, out / "deploy_latency.png", latency_title(args.hz, args.keep))
        print(f"wrote {out / 'deploy_latency.png'}")
        for failure in bench.failures:  # each was run again; the samples above are of the runs that worked
            print(f"a Retriever round failed and was run again: {failure}")
    if "failover" in args.parts:
        print(f"\npart 4: failover, 3 workers, {args.repeats} deployments; load {load()}", flush=True)
        rows = measure_failover(bench, args.repeats)
        write_csv(out / "deploy_failover.csv", rows)
        for name in ("mid_again_ms", "sink_again_ms"):
            print(f"  {name}: median [min–max] {med_spread([r[name] for r in rows if not r['error']], '{:.0f}')}")
    if "scale" in args.parts:
        rows, repeats = [], args.repeats
        for per_worker in sorted(args.scale_flows):
            print(f"\npart 3: {args.scale_workers} workers x {per_worker} flows; load {load()}", flush=True)
            mine = measure_deploys(bench, args.scale_workers, per_worker, repeats, SCALE_S, args.scale_startup,
                                   f"bench-scale{per_worker}")
            rows += mine
            write_csv(out / "deploy_scale.csv", rows, DEPLOY_FIELDS)  # after each size: a failure later keeps it
            if not any(r["ok"] for r in mine):
                repeats = 1  # past a size where no run worked, one run each shows whether larger ones do
        print_deploys(rows, "scale")


def parse_args(argv: list[str] | None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--parts", nargs="+", default=["deploy", "latency", "failover", "scale"],
                   choices=["deploy", "latency", "failover", "scale"])
    p.add_argument("--repeats", type=int, default=3, help="deployments per size in parts 1 and 3 (default 3)")
    p.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, help="payloads, suffixes Ki, Mi (default 64 16Ki 1Mi 16Mi)")
    p.add_argument("--hz", type=float, default=LATENCY_HZ, help="latency: messages per second (default 20)")
    p.add_argument("--rounds", type=int, default=4, help="latency rounds per side and size, interleaved (default 4)")
    p.add_argument("--samples", type=int, default=40, help="messages kept per round (default 40)")
    p.add_argument("--warmup", type=int, default=10, help="messages dropped at the start of each round (default 10)")
    p.add_argument("--keep", choices=["trace", "records"], default="trace",
                   help="latency: what the coordinator keeps (pipe.run keep=): 'trace' gets every frame to it, "
                        "'records' only ids and step records (the sink's samples then come in a file)")
    p.add_argument("--coordinator-on-source", action="store_true",
                   help="diagnostic (latency): the coordinator on the source's host (its reports then go through "
                        "that host's shared memory, not TCP); write to another --out")
    p.add_argument("--scale-workers", type=int, default=8)
    p.add_argument("--scale-flows", type=int, nargs="+", default=[5, 8, 10, 25],
                   help="flows per worker (default 5 8 10 25)")
    p.add_argument("--scale-startup", type=float, default=120.0,
                   help="the coordinator's bound for every flow to be ready, s (default 120: 4x what 100 flows took "
                        "on one host, benchmarks/reports/scale.md)")
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="the lab's RETRIEVER_LAB_PREFIX (default bench)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="where the CSVs and the plot go")
    p.add_argument("--replot", action="store_true", help="only draw the latency plot again, from --out's CSV")
    p.add_argument("--coordinate", metavar="JOB.json", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.coordinate:
        return coordinate(args.coordinate)
    if args.replot:
        replot(args.out, args.hz)
        return 0
    from tests.deploy.lab import Lab, unavailable

    if reason := unavailable():
        raise SystemExit(f"error: {reason}")
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM cleans up as Ctrl-C does
    args.out.mkdir(parents=True, exist_ok=True)
    hosts = 1 + max(3, args.scale_workers if "scale" in args.parts else 0)
    print(f"retriever deployments on the netns lab '{args.prefix}' ({hosts} hosts); {os.cpu_count()} cpus; "
          f"load at start {load()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="retriever-bench-") as scratch, Lab(hosts, prefix=args.prefix) as lab:
        run_parts(Bench(lab, Path(scratch), args.out / "failures"), args, args.out)
    print(f"\nload at end {load()}; the lab is down")
    return 0


if __name__ == "__main__":
    sys.exit(main())
