"""What a worker daemon runs for a coordinator: one run's spec and its worker processes.

The coordinator side is remote.py; the ops here join the daemon's control queryable
(core.WorkerDaemon.ops), answered on Zenoh's threads under the daemon's lock. Each takes its
request record, as protocol.REQUEST decoded it (every field's type and range checked), and
returns its reply record (protocol/daemon.py):

    prepare {run, spec, nodes}   check the IR and each node's class (the allowlist, before anything
                                 is imported) and its module's file here against the IR's sha256,
                                 keep the spec in a private folder, made for this host: {nodes,
                                 warnings, key} (a code mismatch it runs anyway, with --code-mismatch
                                 warn; key: the run's events are signed with it, origin.sign)
    spawn {run, node, mode}      start that node's worker process (worker/), as the embedded run
                                 does, with a key made for it (origin.py) in a pipe it inherits:
                                 {pid, key}, in the reply, which reaches the querier alone; what
                                 it prints goes to the coordinator, and its exit
    spawn {run, node, group}     the same for the one process of a group of the spec's (flows that
                                 share a process: worker/group.py), every member prepared here
    signal {run, pid, signal}    SIGUSR1 (its stacks), SIGTERM or SIGKILL to one of the run's processes
    usage {run}                  the CPU seconds of each live process of the run: {cpu_s}
    end {run}                    stop what is left of the run, remove its folder

and it tells the coordinator what the run's processes print and how they exit (ProcessOutput,
ProcessExit on workers/<name>/events), signed with the run's key.

A daemon joined through routers with ``--local-router`` starts a router of each run's on this
machine when it prepares the run, a process the run's flows join (run_router.py), and stops it
with the run. One that ends before is told to the coordinator, the run's processes here are
stopped, and its spawns here refused from then on: its flows here would join no one.

A daemon serves one run at a time, and ends it by itself when its coordinator's liveliness token
goes (the coordinator died, or lost the network): its processes get SIGTERM, then, still there
after COORDINATOR_GRACE_S, SIGKILL. Its worker processes and run routers die with it
(PR_SET_PDEATHSIG).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import zenoh

from ....code import code_mismatch
from ....errors import IRError
from ....ir import IR
from ....plan import Plan
from ....rebuild import check_node
from ..access import RunAccess, TlsFiles, write_private
from ..folders import DAEMON_FOLDER
from ..command import GROUP_MODULE, WORKER_MODULE, worker_command
from ..hub import weak_callback
from ..origin import KEY_FD_ENV, key_pipe, new_key
from ..protocol import (ControlSigner, DaemonOp, EndReply, EndRequest, PrepareReply, PrepareRequest, ProcessExit,
                        ProcessOutput, Record, RunSpec, SignalReply, SignalRequest, SpawnReply, SpawnRequest, Stream,
                        UsageReply, UsageRequest)
from ..wire import RELIABLE, KeySpace, WireError
from .run_router import RunRouter, open_run_router
from .settings import ENDPOINT

#: after its coordinator is gone, how long a run's processes have to stop before SIGKILL (the
#: issue's bound is 3 s from the coordinator's death to the flows' stop)
COORDINATOR_GRACE_S = 2.0
#: lines of a process's output sent at most per event, and how long a line waits for company
OUTPUT_BATCH = 64
OUTPUT_FLUSH_S = 0.05
MAX_LINE_BYTES = 1 << 16
#: how many processes of one node may run at once: its own, and the one taking over while it restarts
MAX_PROCESSES_PER_NODE = 2
#: the name under which the coordinator prints what a daemon says of a run's router (run_router.py)
RUN_ROUTER_NAME = "run-router"
#: the signals a coordinator may send a run's process
SIGNALS = (signal.SIGUSR1, signal.SIGTERM, signal.SIGKILL)


#: what a flow process gets of its daemon's environment unasked: where things are, the locale,
#: and the runtime settings of the interpreter and of the libraries flows use (rendering, BLAS,
#: threads, GPUs); never a credential. A daemon passes more by name: --pass-env OPENAI_API_KEY
PASSED_ENV = ("PATH", "HOME", "USER", "LOGNAME", "SHELL", "TERM", "LANG", "LANGUAGE", "TZ", "TMPDIR",
              "PYTHONPATH", "PYTHONHOME", "PYTHONHASHSEED", "PYTHONUNBUFFERED", "PYTHONDONTWRITEBYTECODE",
              "PYTHONWARNINGS", "VIRTUAL_ENV", "LD_LIBRARY_PATH", "DISPLAY", "XDG_RUNTIME_DIR", "MUJOCO_GL",
              "PYOPENGL_PLATFORM", "LP_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
              "OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "CUDA_VISIBLE_DEVICES", "NVIDIA_VISIBLE_DEVICES",
              "RUST_LOG", "RUST_BACKTRACE")
PASSED_ENV_PREFIXES = ("LC_",)


def flow_environment(environ: dict[str, str], passed: tuple[str, ...] = ()) -> dict[str, str]:
    """The environment of a daemon's flow process: PASSED_ENV, the locale, and ``passed``."""
    return {k: v for k, v in environ.items()
            if k in PASSED_ENV or k in passed or k.startswith(PASSED_ENV_PREFIXES)}


class Run:
    """One prepared run: its folder (0700), its spec for this host, its processes by pid, and
    the key its events (``exit``, ``output``) are signed with: answered in the prepare reply, which
    reaches the coordinator alone, so an insider cannot tell it a process exited."""

    def __init__(self, run_id: str, folder: Path, nodes: list[str]):
        self.id, self.folder, self.nodes = run_id, folder, set(nodes)
        self.key = new_key()
        self.events = ControlSigner()  # seals its events with the key, each with a counter (seal.py)
        self.events.add(self, self.key)
        self.processes: dict[int, tuple[str, subprocess.Popen]] = {}  # by pid: (node or group, process)
        self.groups: dict[str, tuple[str, ...]] = {}  # the spec's groups (flows that share a process)
        self.members: dict[int, tuple[str, ...]] = {}  # by pid: the nodes a group's process serves
        self.watch = None  # the liveliness subscriber on the coordinator's token
        self.ir: dict = {}
        self.router: RunRouter | None = None  # the run's own router (--local-router)


class DaemonRuns:
    """The runs ops of one daemon (see the module docstring)."""

    def __init__(self, session: zenoh.Session, name: str, namespace: str, *, listen: tuple[str, ...],
                 secret: bytes | None, allowed: Callable[[str], bool], refusal: Callable[[str], str],
                 paths: tuple[str, ...], tls: TlsFiles | None = None, lease: float | None = None,
                 code_mismatch: str = "refuse", pass_env: tuple[str, ...] = (), router: tuple[str, ...] = (),
                 local_router: bool = False):
        self.session, self.name, self.keys = session, name, KeySpace(namespace)
        self.router = router  # the routers the daemon joined through: its flows join through them too
        self.local_router = local_router  # or through a router of each run's here, linked to those (run_router.py)
        # the deployment secret (None: --insecure): each run's passwords are derived from it for
        # that run alone (access.RunAccess.create), never sent
        self.listen, self.secret, self.allowed, self.refusal, self.tls = listen, secret, allowed, refusal, tls
        self.lease = lease  # how long its links live silent, and its flows' puts wait on one (local_spec)
        self.code_mismatch = code_mismatch  # settings.CODE_MISMATCH
        self.pass_env = pass_env
        self._spawner = ThreadPoolExecutor(1, thread_name_prefix="retriever-spawner")
        self.paths = [str(Path(p).resolve()) for p in paths]
        for folder in reversed(self.paths):  # where check_node finds the flows' modules (it imports nothing)
            if folder not in sys.path:
                sys.path.insert(0, folder)
        self.run: Run | None = None
        self._events = session.declare_publisher(self.keys.worker_events(name), congestion_control=RELIABLE)
        # how many coordinators' liveliness tokens are up (a callback counts them: asking Zenoh
        # from inside a query's callback blocked it past the coordinator's patience)
        self._coordinators = 0
        self._coordinator_watch = session.liveliness().declare_subscriber(
            self.keys.deployment(), weak_callback(self._coordinator_seen), history=True)

    @property
    def ops(self) -> dict[DaemonOp, Callable[[Record], Record]]:
        return {DaemonOp.PREPARE: self.prepare, DaemonOp.SPAWN: self.spawn, DaemonOp.SIGNAL: self.signal,
                DaemonOp.END: self.end, DaemonOp.USAGE: self.usage}

    def nodes(self) -> list[str]:
        """The nodes whose processes run now (a group's process: each of its members)."""
        run = self.run
        if run is None:
            return []
        return sorted({node for pid, (name, proc) in run.processes.items() if proc.poll() is None
                       for node in run.members.get(pid, (name,))})

    # -- ops -----------------------------------------------------------------------------------
    def prepare(self, request: PrepareRequest) -> PrepareReply:
        run_id, spec, nodes = request.run, request.spec, list(request.nodes)
        if self.run is not None and self.run.id == run_id:  # more nodes of its run (a lost worker's)
            if spec.ir != self.run.ir:
                raise WireError(f"run {run_id} was prepared on worker '{self.name}' with another IR")
            warnings = self._checked(IR(self.run.ir, source="the run's IR"), nodes)
            self.run.nodes.update(nodes)
            return PrepareReply(nodes=tuple(sorted(self.run.nodes)), warnings=tuple(warnings), key=self.run.key)
        if self.run is not None and self.run.id != run_id:
            if any(proc.poll() is None for _, proc in self.run.processes.values()):
                raise WireError(f"worker '{self.name}' runs another deployment's nodes ({', '.join(self.nodes())})"
                                "\n    hint: `retriever stop` it first, or deploy to other workers")
            self._end(self.run)
        try:
            ir = IR(spec.ir, source=f"the IR a coordinator sent worker '{self.name}'")
            Plan.from_data(spec.plan, ir)  # checked here too, so that a bad one is refused before a folder is made
        except (IRError, TypeError, ValueError) as e:
            raise WireError(str(e)) from None
        warnings = self._checked(ir, nodes)
        if not self._coordinator_up():
            raise WireError(f"worker '{self.name}' prepares runs only for a coordinator whose liveliness token "
                            f"({self.keys.deployment()}) is up: none is (its processes would never be stopped)")
        if not self.router and (spec.hub is None or not ENDPOINT.fullmatch(spec.hub)):
            raise WireError(f"worker '{self.name}' was given no hub endpoint its flows can join "
                            f"(hub {spec.hub!r:.80})")
        # mode 0700; named by this daemon's pid: the next daemon removes it if this one was SIGKILLed
        # (it holds the run's passwords), as it does the daemon's own folder (reap_stale_folders)
        folder = Path(tempfile.mkdtemp(prefix=f"{DAEMON_FOLDER}-{os.getpid()}-run-"))
        self.run = run = Run(run_id, folder, nodes)
        run.ir, run.groups = ir.doc, dict(spec.groups)
        if self.local_router:
            try:
                run.router = self._open_run_router(run)
            except Exception:  # no run is left half made: its folder holds its passwords
                self._end(run)
                raise
            run.router.watch(functools.partial(self._router_ended, run))
        write_private(folder / "spec.json", self.local_spec(spec, folder, run_id, run.router).to_json())
        run.watch = self.session.liveliness().declare_subscriber(
            self.keys.deployment(), weak_callback(self._coordinator_token, run), history=True)
        return PrepareReply(nodes=tuple(sorted(nodes)), warnings=tuple(warnings), key=run.key)

    def spawn(self, request: SpawnRequest) -> SpawnReply:
        """(A key in the request is refused by its decoder: a query reaches every queryable on
        ctl/<name>, an insider's too.)"""
        run, name = self._run_of(request.run), request.node
        nodes = self._served(run, name, request.group)
        ended = run.router.ended() if run.router is not None else None
        if ended is not None:
            raise WireError(f"worker '{self.name}' cannot start '{name}': {ended}")
        mode = [str(part) for part in request.mode]
        if request.group and mode:
            raise WireError(f"group '{name}': a group's process starts with its run only (mode {mode!r:.60})")
        if self.code_mismatch == "refuse":  # its file may have changed since prepare (a restart comes much later)
            for node in nodes:
                mismatch = self._code_mismatch(run.ir, node)
                if mismatch is not None:
                    raise WireError(f"worker '{self.name}' will not run {mismatch}")
        self._check_room(run, name, nodes, request.group)
        module = GROUP_MODULE if request.group else WORKER_MODULE
        proc, key = self._start(worker_command(str(run.folder / "spec.json"), name, mode, module=module))
        run.processes[proc.pid] = (name, proc)
        if request.group:
            run.members[proc.pid] = tuple(nodes)
        tell = functools.partial(self._tell, run)
        for stream, pipe in ((Stream.STDOUT, proc.stdout), (Stream.STDERR, proc.stderr)):
            threading.Thread(target=forward_output, args=(pipe, tell, run.id, name, stream), daemon=True,
                             name=f"retriever-{stream}-{name}").start()
        threading.Thread(target=self._await_exit, args=(run, name, proc), daemon=True,
                         name=f"retriever-exit-{name}").start()
        return SpawnReply(pid=proc.pid, key=key)

    def _served(self, run: Run, name: str, group: bool) -> list[str]:
        """The nodes a spawn of ``name`` serves: that node, or a group's members, each prepared here."""
        if not group:
            if name not in run.nodes:
                raise WireError(f"node {name!r:.60} was not prepared on worker '{self.name}'")
            return [name]
        members = run.groups.get(name)
        if members is None:
            raise WireError(f"{name!r:.60} is no group of run {run.id}'s spec (its groups: "
                            f"{', '.join(sorted(run.groups)) or 'none'})"[:300])
        missing = sorted(set(members) - run.nodes)
        if missing:
            raise WireError(f"group '{name}': its node(s) {', '.join(missing)} were not prepared on worker "
                            f"'{self.name}' (a group's nodes run in one process, on one worker)"[:300])
        return list(members)

    def _check_room(self, run: Run, name: str, nodes: list[str], group: bool) -> None:
        """Refuse a spawn that would run a node in more than MAX_PROCESSES_PER_NODE processes (one, two
        while it restarts): a group's process counts for each of its members."""
        for node in nodes:
            live = [pid for pid, (n, proc) in run.processes.items()
                    if node in run.members.get(pid, (n,)) and proc.poll() is None]
            if len(live) >= MAX_PROCESSES_PER_NODE:
                raise WireError(f"{f'group {name!r}: its ' if group else ''}node '{node}' already runs in {len(live)} "
                                f"processes on worker '{self.name}' (pids {', '.join(map(str, live))})")

    def _start(self, command: list[str]) -> tuple[subprocess.Popen, bytes]:
        """Start ``command`` with a key made for it (answered in the reply, which Zenoh routes to
        the querier alone: origin.py), from a thread that lives as long as the daemon: a worker
        gets PR_SET_PDEATHSIG when the thread that started it ends, which a thread of Zenoh's
        (this op's) may do at any time."""
        key = new_key()
        pipe = key_pipe(key)
        try:
            proc = self._spawner.submit(
                subprocess.Popen, command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                start_new_session=True, pass_fds=(pipe,),
                env={**flow_environment(os.environ, self.pass_env), KEY_FD_ENV: str(pipe)}).result()
        finally:
            os.close(pipe)
        return proc, key

    def signal(self, request: SignalRequest) -> SignalReply:
        run, pid, sig = self._run_of(request.run), request.pid, request.signal
        if pid not in run.processes or sig not in SIGNALS:
            raise WireError(f"signal {sig!r:.20} to pid {pid!r:.20}: not a process of run {run.id} or not a "
                            "signal a coordinator may send")
        proc = run.processes[pid][1]
        if proc.poll() is None:
            proc.send_signal(sig)
        return SignalReply()

    def usage(self, request: UsageRequest) -> UsageReply:
        """The CPU time of each live process of the run, by node (a group's process: for each member)."""
        run = self._run_of(request.run)
        cpu = {}
        for pid, (name, proc) in list(run.processes.items()):
            seconds = cpu_seconds(pid) if proc.poll() is None else None
            if seconds is not None:
                cpu.update(dict.fromkeys(run.members.get(pid, (name,)), seconds))
        return UsageReply(cpu_s=cpu)

    def end(self, request: EndRequest) -> EndReply:
        self._end(self._run_of(request.run))
        return EndReply()

    # -- inside ----------------------------------------------------------------------------------
    def _run_of(self, run_id: str) -> Run:
        run = self.run
        if run is None or run_id != run.id:
            raise WireError(f"worker '{self.name}' has no run {run_id!r:.40}")
        return run

    def _coordinator_up(self) -> bool:
        """Whether a coordinator's liveliness token is up (one declared just before it prepares
        may still be on its way: the coordinator asks again, remote.PREPARE_TRIES)."""
        return self._coordinators > 0

    def _coordinator_seen(self, sample: zenoh.Sample) -> None:
        self._coordinators = max(0, self._coordinators + (1 if sample.kind == zenoh.SampleKind.PUT else -1))

    def _checked(self, ir: IR, nodes: list[str]) -> list[str]:
        """The warnings of running ``nodes`` of ``ir`` here (each also on the daemon's stderr), or
        a WireError with every problem, one a line."""
        importlib.invalidate_caches()  # a module copied here since the last look is seen
        problems, warnings = self._check(ir, nodes)
        if problems:
            raise WireError(f"worker '{self.name}' will not run {len(problems)} of its node(s):\n"
                            + "\n".join(f"  - {p}" for p in problems))
        for warning in warnings:
            print(f"retriever-worker {self.name}: warning: {warning}", file=sys.stderr, flush=True)
        return warnings

    def _check(self, ir: IR, nodes: list[str]) -> tuple[list[str], list[str]]:
        """Every problem with running ``nodes`` of ``ir`` here, before anything is imported, and
        the warnings of the code mismatches it runs anyway (--code-mismatch warn)."""
        known = {n["id"]: n for n in ir.nodes}
        problems, warnings = [], []
        for nid in nodes:
            node = known.get(nid)
            if node is None:
                problems.append(f"node '{nid}' is not in the IR")
                continue
            module = node["type"].partition(":")[0]
            if node.get("rebuild_needs_main"):
                problems.append(f"node '{nid}': its class {node['type']} is defined in the coordinator's main "
                                "script, which a worker cannot import\n    hint: move the flow classes to a module "
                                "on the worker's --path")
            elif not self.allowed(module):
                problems.append(f"node '{nid}' ({node['type']}): {self.refusal(module)}")
            elif check_node(node, problems, ir.doc["metadata"].get("module_folders", {})) is not None:
                mismatch = self._code_mismatch(ir.doc, nid)
                if mismatch is not None:
                    (problems if self.code_mismatch == "refuse" else warnings).append(mismatch)
        return problems, warnings

    def _code_mismatch(self, ir_doc: dict, nid: str) -> str | None:
        """How this worker's file of node ``nid``'s module differs from the one the IR (a
        validated one, holding ``nid``) was built from, with what to do; None when it is the same,
        or the IR has no hash of it."""
        node_type = next(node["type"] for node in ir_doc["nodes"] if node["id"] == nid)
        module = node_type.partition(":")[0]
        recorded = ir_doc["metadata"].get("code_sha256", {}).get(module)
        problem = None if recorded is None else code_mismatch(module, recorded)
        if problem is None:
            return None
        fix = (f"sync {module} on worker '{self.name}' with the coordinator's copy"
               + (", or start the worker with --code-mismatch warn to run its own copy anyway"
                  if self.code_mismatch == "refuse" else " (it runs its own copy: --code-mismatch warn)"))
        return f"node '{nid}': {problem}\n    hint: {fix}"

    def _open_run_router(self, run: Run) -> RunRouter:
        """``run``'s own router (run_router.py), started from the spawner's thread: its process
        dies with that thread (PARENT_DIED), which lives as long as the daemon, and the Zenoh
        thread that answers this query must not wait that long itself."""
        upstream_ids = [str(z) for z in self.session.info.routers_zid()]
        return self._spawner.submit(open_run_router, self.keys.namespace, self.secret, run.id, self.router,
                                    upstream_ids, self.tls, flow_environment(os.environ)).result()

    def _router_ended(self, run: Run, why: str) -> None:
        """``run``'s router ended before its run: said on the daemon's stderr and to the
        coordinator, and the run's processes here are stopped (SIGTERM), for they have no link to
        anyone, each other included: the coordinator learns of their exits, and decides."""
        print(f"retriever-worker {self.name}: error: {why}", file=sys.stderr, flush=True)
        self._tell(run, ProcessOutput(run=run.id, node=RUN_ROUTER_NAME, stream=Stream.STDERR,
                                      lines=tuple(line[:MAX_LINE_BYTES] for line in f"error: {why}".splitlines())))
        for _, proc in list(run.processes.values()):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)

    def local_spec(self, spec: RunSpec, folder: Path, run_id: str, run_router: RunRouter | None = None) -> RunSpec:
        """The coordinator's ``spec`` as this host runs it, which prepare writes to the run's
        ``folder`` for its processes: its Python path, the credentials of run ``run_id``
        (derived here from the secret: access.RunAccess.create; their files in ``folder``), the
        hub's address as this host reaches it, which the coordinator put in ``spec`` (or, for a
        daemon joined through routers, those routers, whose clients its flows are too:
        ``router``, with the namespace's credentials, which a router's fixed dictionary holds;
        or ``run_router``, the run's own here, with the run's credentials: run_router.py);
        no shared folder with the coordinator, no main script, no argv (a worker's flows see the
        worker's own: sys.argv is no channel for a stranger's arguments to a module that parses
        them when imported).

        The flows link to the hub and to each other, never to this daemon's session: it holds
        the namespace's credentials, theirs are the run's (nothing of one run opens a link to
        the daemons, nor to another run)."""
        if run_router is not None:  # its one link is on loopback: no TLS
            hub, router, listen = None, (run_router.endpoint,), ()
            access = RunAccess.create(self.keys.namespace, self.secret, run=run_id)
        elif self.router:
            hub, router, listen = None, tuple(self.router), ()
            access = RunAccess.create(self.keys.namespace, self.secret) if self.secret is not None else None
        else:
            proto, host, _ = _split(self.listen[0]) if self.listen else ("tcp", "127.0.0.1", None)
            hub, router, listen = spec.hub, (), (f"{proto}/{host}:0",)
            access = (RunAccess.create(self.keys.namespace, self.secret, run=run_id)
                      if self.secret is not None else None)
        # The flows keep Zenoh's lease: the daemon's short one, taken by every link of a flow,
        # closes links that are merely slow and stalls the producers behind them. But a put held
        # by a link that took nothing for the daemon's lease (its far end cut off: the link's
        # queue is full, BLOCK) gives up that link then, not after Zenoh's wait_before_close: the
        # producer's other consumers, the node moved off the cut-off host among them, wait no
        # longer than that for its events (benchmarks/reports/partition_move.md measures it)
        return dataclasses.replace(
            spec, namespace=self.keys.namespace, hub=hub, router=router, listen=listen,
            python_path=(*self.paths, *(p for p in sys.path if p and os.path.isdir(p))),
            main_file=None, spill_dir=None, argv=None, dora_part=None,
            access=access.to_spec(access.write_dictionary(folder)) if access is not None else None,
            tls=vars(self.tls) if self.tls is not None and run_router is None else None, lease=None,
            blocked_put=self.lease)

    def _await_exit(self, run: Run, node: str, proc: subprocess.Popen) -> None:
        code = proc.wait()
        self._tell(run, ProcessExit(run=run.id, node=node, pid=proc.pid, code=code))

    def _tell(self, run: Run, event: ProcessOutput | ProcessExit) -> None:
        """An event of ``run`` to its coordinator, signed with the run's key."""
        payload = event.encode()
        try:
            self._events.put(payload, attachment=run.events.seal(self.keys.worker_events(self.name), payload))
        except zenoh.ZError:  # the daemon is closing
            pass

    def _coordinator_token(self, run: Run, sample: zenoh.Sample) -> None:
        """The coordinator's liveliness: gone, the run ends here too (its flows must not run on)."""
        if sample.kind == zenoh.SampleKind.DELETE and self.run is run:
            print(f"retriever-worker {self.name}: the coordinator of run {run.id} is gone; stopping its "
                  f"nodes ({', '.join(self.nodes()) or 'none running'})", file=sys.stderr, flush=True)
            threading.Thread(target=self._end, args=(run,), daemon=True).start()

    def _end(self, run: Run) -> None:
        """SIGTERM every live process of the run, SIGKILL what is left after the grace, forget it."""
        procs = [proc for _, proc in run.processes.values() if proc.poll() is None]
        for proc in procs:
            proc.send_signal(signal.SIGTERM)
        give_up = time.monotonic() + COORDINATOR_GRACE_S
        for proc in procs:
            try:
                proc.wait(timeout=max(0.0, give_up - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if run.watch is not None:
            run.watch.undeclare()
            run.watch = None
        if run.router is not None:  # after its flows, whose last words have left
            run.router.close()
            run.router = None
        shutil.rmtree(run.folder, ignore_errors=True)
        if self.run is run:
            self.run = None

    def close(self) -> None:
        """The daemon stops: so does its run."""
        if self.run is not None:
            self._end(self.run)
        self._coordinator_watch.undeclare()
        self._events.undeclare()
        self._spawner.shutdown(wait=False)


def forward_output(pipe, tell: Callable[[ProcessOutput], None], run_id: str, node: str, stream: Stream) -> None:
    """Read what a process of run ``run_id`` prints on ``pipe`` (its ``stream``) until it closes,
    and ``tell`` it (to the coordinator: DaemonRuns signs and puts each) in batches of lines: a
    batch goes when it is full or its first line has waited OUTPUT_FLUSH_S, whether or not more
    output comes (a stack dump's last lines are its most telling, and nothing may follow them)."""
    fd = pipe.fileno()
    lines: list[str] = []
    partial = b""
    first = 0.0  # when the oldest held line came

    def send() -> None:
        nonlocal lines
        tell(ProcessOutput(run=run_id, node=node, stream=stream, lines=tuple(lines)))
        lines = []

    with pipe:
        while True:
            wait = max(0.0, first + OUTPUT_FLUSH_S - time.monotonic()) if lines else None
            if not select.select([fd], [], [], wait)[0]:
                send()  # the batch waited long enough
                continue
            chunk = os.read(fd, 1 << 16)
            if not chunk:
                break
            *complete, partial = (partial + chunk).split(b"\n")
            if len(partial) > MAX_LINE_BYTES:  # a line without end: sent in pieces, not held forever
                complete.append(partial)
                partial = b""
            for raw in complete:
                if not lines:
                    first = time.monotonic()
                lines.append(raw.decode(errors="replace").rstrip("\r"))
                if len(lines) >= OUTPUT_BATCH:
                    send()
    if partial:
        lines.append(partial.decode(errors="replace").rstrip("\r"))
    if lines:
        send()


def cpu_seconds(pid: int) -> float | None:
    """User plus system CPU time of process ``pid`` so far (Linux /proc), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _split(endpoint: str) -> tuple[str, str, str | None]:
    """``tcp/10.0.0.2:7447`` → ``("tcp", "10.0.0.2", "7447")``; without a port: (proto, address, None)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.split("#")[0].rpartition(":")
    return (proto, host, port) if host else (proto, address, None)
