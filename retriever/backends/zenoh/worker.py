"""A worker process: one flow of a run, rebuilt from the IR, ticking in real time.

    python -m retriever.backends.zenoh.worker SPEC.json NODE [--join T0 END | --fresh T0 END]

The coordinator (``retriever.backends.zenoh.coordinator``) writes ``SPEC.json`` — the IR, the hub's
endpoint, the namespace, the Python path the flows were imported from and the coordinator's
``sys.argv``, which the worker takes as its own — and starts one worker per node. A worker joins
the hub, declares its subscriptions, says ``ready`` on ``status/node/<node>``, and waits for
``start`` (T0 and the end) on ``ctl/run``.

on_error="restart": the failed worker says ``restart`` and goes on listening (see "Restarting" in
loop.py); the coordinator starts a new worker with ``--join``, which subscribes, says ``ready``
and waits. The coordinator then puts ``handover`` {node}: the old worker writes its loop's state
to ``<run dir>/<node>.handover``, says ``handed_over`` and exits; then ``resume`` {node}: the new
one reads the state and goes on with a fresh flow. A worker process that died (kill -9, a
segfault) has no state to hand over: the coordinator starts one with ``--fresh``, which starts
the flow afresh on fresh inputs once told ``restarted`` (see "Restarting after a lost process"
in loop.py).

A worker exits when its node is done, on ``stop``, on SIGTERM, or when its parent dies; its
session always closes. Every status it sends carries its pid, and every status and report the MAC
of its process's key (origin.py). Exit codes: 0 done or stopped,
1 failed (the status message says why), 3 handed over to a restarted flow, 4 its parent died (it
said nothing: as if killed).
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import importlib.util
import json
import os
import shutil
import signal
import sys
import threading
import time
import traceback
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .loop import NodeLoop

EXIT_FAILED = 1
EXIT_HANDED_OVER = 3
EXIT_ABANDONED = 4  # its parent (a coordinator, a worker daemon) died: it ended without a word

#: Before it says ``ready``, a worker asks each consumer's progress with this much padding, so
#: that Zenoh sends the question through the session's shared-memory pool (messages over 3 KiB
#: between peers on one host go that way; the hub has no shared memory: hub.HUB_SHARED_MEMORY).
#: Zenoh creates the pool on its first such message and writes all of it (128 MiB: ~37k page
#: faults, 130 ms here, more on memory the VM has not touched): so that happens before T0 (or
#: before a restarted flow joins); left to the first big frame, it held that put for 130 ms and
#: the source's next ticks started up to 120 ms late (benchmarks/reports/latency.md, at 16 MiB).
#: The answer comes once the pool exists: the question is in it. A node with no consumer on its
#: host never sends through a pool, and has none.
POOL_PADDING = 4096

#: the node this process serves, once it is a worker: a run started here (a flow's module that
#: runs a pipeline when imported) is refused, or every worker would start a run of its own
serving: str | None = None


#: The signal a worker gets when the thread that started it dies (PR_SET_PDEATHSIG): its own, not
#: SIGTERM, which a coordinator or daemon sends to stop a worker that goes on finishing. Told
#: apart, a worker whose parent was SIGKILLed ends without a word, whatever ``_orphaned`` sees:
#: a parent's threads die one by one, and the one that started it may be gone while
#: /proc still shows the process alive (a daemon's worker then said "done" with a final
#: frontier, and its consumer finished before the node's restart elsewhere could reach it).
PARENT_DIED = signal.SIGUSR2


def _die_with_parent() -> None:
    """Linux: PARENT_DIED to this process when its parent dies, so no worker outlives its run."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, PARENT_DIED)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


#: how long a restarted flow's process waits for its producers and consumers to answer before it
#: says ready anyway (one that never answers has finished, or is stuck)
NEIGHBOR_TIMEOUT_S = 10.0

#: A worker that said ``ready`` and has not seen ``start`` after this long says ``ready`` again
#: and asks the coordinator's ``ctl/start`` queryable for the start, and again every as long (a
#: restarted one waiting for ``resume`` or ``restarted`` says ready again). Either put can be
#: missed: one put as a link comes up may precede the subscriptions the other side declares on
#: it, and Zenoh drops what has no known subscriber (at 50 flows on 2 cores, 14 workers that said
#: ready never saw the start; a deployment waited for a ready that never came). A worker that
#: missed it would wait until the run gave up on it.
START_ASK_S = 0.5

#: A new worker waits, before it says ready, for an answer from each producer (see _serve), and
#: from each consumer if it makes its pool (POOL_PADDING). At 80 flows on 8 hosts of a 2-core
#: machine, a worker linked to its producer was, 2 runs in 3, never told of that producer's
#: queryable: the run never started (benchmarks/reports/deploy.md, "Scale"; the other nodes'
#: answers came). So after this long without an answer it says ``unanswered``; the coordinator
#: tells those neighbours to ``redeclare`` (on ctl/run, through the hub: the link
#: between the two may be what lost it), and the worker declares its own subscriptions again too.
REDECLARE_AFTER_S = 2.0

#: After its last status (done, handed over), a worker keeps its session open until the coordinator
#: has every report it sent. A report over 3 KiB goes through Zenoh's shared memory, and one whose
#: sender had closed its session by the time the receiver read it was dropped (the sender's buffers
#: no longer valid): the coordinator waited for it forever; so does one still in the sender's queue
#: (a report of big frames, across machines). A coordinator writing big frames to its log answers
#: late and takes reports long after they came (it waits for its disk): the worker waits as long as the
#: coordinator answers, and gives up only once it has not answered for REPORTS_TAKEN_S, its
#: link to it is gone, or after REPORTS_TAKEN_MAX_S in all (the coordinator ends a run that waits
#: for a report longer than its own patience anyway, and stops this process).
REPORTS_TAKEN_S = 5.0
REPORTS_TAKEN_MAX_S = 120.0

#: after its coordinator died, a worker's loop has this long to stop by itself (SIGTERM asks it
#: to), then the process exits anyway: a flow stuck in its step never looks at the request
ORPHAN_GRACE_S = 3.0


def _watch_parent(parent: int, run_dir: Path) -> None:
    """From a thread of its own: once the coordinator is gone, exit within ORPHAN_GRACE_S, with
    every thread's stack on stderr, even when the step never returns (faulthandler's timer needs
    no GIL); and remove the run directory, which no one else will. A worker dora started is told
    by no kernel that its coordinator died (dora is its parent): it tells itself, as the kernel
    would (PARENT_DIED), once the directories are gone."""
    try:  # read through one descriptor: a pread a look (an idle worker's thread wakes twice a second)
        stat = os.open(f"/proc/{parent}/stat", os.O_RDONLY)
    except OSError:
        stat = None
    while not _orphaned(parent, stat):
        time.sleep(0.5)
    faulthandler.dump_traceback_later(ORPHAN_GRACE_S, exit=True)
    _remove_run_dir(run_dir)
    if _adopted:
        os.kill(os.getpid(), PARENT_DIED)


def _remove_run_dir(run_dir: Path) -> None:
    if run_dir.name.startswith("retriever-run-"):
        if _adopted:  # and dora's directory (backends/dora)
            dora_dir = Path(_dora_spec(str(run_dir / "spec.json")).get("dir", ""))
            if dora_dir.name.startswith("retriever-dora-"):
                shutil.rmtree(dora_dir, ignore_errors=True)
        shutil.rmtree(run_dir, ignore_errors=True)


def _keep_freed_memory() -> None:
    """glibc: serve blocks up to 32 MiB from the heap and keep freed memory mapped. A worker
    allocates and frees a message-sized buffer per event; by default glibc returns big blocks to
    the kernel at once, so every event paid a page fault per 4 KiB again (a 16 MiB frame: 4096
    faults, about 6 ms on the benchmark machine, against 1 ms for the copy itself)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD (the most glibc allows)
        libc.mallopt(-1, 512 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def _import_main(path: str) -> None:
    """Flows defined in the coordinator's ``__main__`` script: import it the way multiprocessing
    does (as ``__mp_main__``, so its ``if __name__ == "__main__":`` block does not run)."""
    spec = importlib.util.spec_from_file_location("__mp_main__", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import the main script {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules["__mp_main__"] = module
    spec.loader.exec_module(module)
    sys.modules["__main__"] = module


def build_loop(spec: dict, node_id: str, session):
    """Rebuild ``node_id`` from the IR in ``spec`` and wire its inputs as the run's plan says (the
    spec's ``plan``, if it carries one, else made here from the IR): a ready NodeLoop."""
    from ...flow._base import Flow
    from ...graph import compile_graph
    from ...ir import DEFAULT_DEADLINE, IR
    from ...plan import Plan, bind_inputs, plan_ir
    from ...rebuild import rebuild_node
    from ...sync import PortBuffer
    from .loop import InEdge, NodeLoop
    from .wire import KeySpace

    ir = IR(spec["ir"], source="the run's IR")
    meta = ir.doc["metadata"]
    flows: dict = {}
    problems: list[str] = []
    node_doc = dict(ir.node(node_id))
    if spec.get("main_file") and node_doc.get("rebuild_needs_main"):
        node_doc["rebuildable"] = True  # _import_main made __main__ importable here
    rebuild_node(node_doc, flows, problems)
    if problems:
        raise RuntimeError("; ".join(problems))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        graph = compile_graph(ir.name, [flows[node_id]], [], meta.get("max_microsteps", 1000),
                              meta.get("realtime", "soft"), meta.get("deadline", DEFAULT_DEADLINE))
    node = graph.nodes[node_id]
    plan = (Plan.from_data(spec["plan"]) if "plan" in spec else plan_ir(ir)).nodes[node_id]
    inputs, fallbacks = bind_inputs(plan, node.inputs, lambda: PortBuffer(trim_batch=1))
    buffers = {port: buf for port, buf, _, _ in inputs}
    edges = [InEdge(f.src, f.src_port, f.port, buffers[f.port], f.delay_ns, f.triggers, f.deadline_ns,
                    f.src_latency_ns) for f in plan.feeds]
    if type(node.flow).reset is not Flow.reset:
        node.flow.reset()  # the paper's flows initialise their state in reset()
    loop_class, transport = NodeLoop, {}
    if spec.get("dora"):  # the dora backend: events and progress over dora (backends/dora/link.py)
        from ..dora.dataflow import DoraNames
        from ..dora.link import DoraNodeLoop

        loop_class, transport = DoraNodeLoop, {"names": DoraNames.from_spec(spec["dora"])}
    return loop_class(session, KeySpace(spec["namespace"]), node, edges, inputs, fallbacks,
                    realtime=meta.get("realtime", "soft"),
                    ports=sorted(ir.node(node_id)["outputs"]),
                    consumed=bool(plan.consumers),
                    spill_dir=spec.get("spill_dir") if os.path.isdir(spec.get("spill_dir") or "") else None,
                    # a flow with a setup() may hold what belongs to one thread (an OpenGL/EGL or
                    # CUDA context, a device handle): it steps on the thread that set it up
                    inline=not plan.on_a_cycle and type(node.flow).setup is Flow.setup,
                    cycle=plan.cycle, instant_ports=plan.instant_ports,
                    max_microsteps=meta.get("max_microsteps", 1000), virtual=bool(spec.get("virtual_time")),
                    **transport)


def run_sessions(nodes: int) -> int:
    """How many Zenoh sessions with a pool a run of ``nodes`` nodes has, which share the run's
    shared memory (hub.shm_pool_bytes): a worker's each (the hub has none, hub.HUB_SHARED_MEMORY)."""
    return nodes


PR_SET_TIMERSLACK = 29  # <linux/prctl.h>


def _no_timer_slack() -> None:
    """Let this thread's timed waits end on time: Linux may end each one up to its timer slack
    late (50 µs unless set) to wake threads together; the loop waits for ticks, so it asks for
    1 ns (a tick's lateness p50 120 → 65 µs, benchmarks/control_jitter.py). Per thread: call it
    on the thread that runs the loop. Elsewhere than Linux, or if refused, nothing changes."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None).prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def main(argv: list[str]) -> int:
    """Serve one node; a worker whose coordinator died meanwhile also removes the run directory
    (the spec and unreported events, in /dev/shm), which no one else would."""
    global _adopted
    parent = os.getppid()
    run_dir = Path(argv[0]).parent
    coordinator = _dora_coordinator(argv[0])
    if coordinator is not None:  # dora's child: the coordinator is its grandparent or further
        parent, _adopted = coordinator, True
    threading.Thread(target=_watch_parent, args=(parent, run_dir), name="retriever-watch-parent", daemon=True).start()
    code = EXIT_FAILED
    try:
        code = _serve(argv, parent)
        return code
    finally:
        if _exit_file is not None:  # started by dora: how it ended, for the coordinator (not its parent)
            with contextlib.suppress(OSError):
                _exit_file.write_text(str(code))
        if _orphaned(parent):
            _remove_run_dir(run_dir)


#: started by dora: the file that tells the coordinator this process's exit code
_exit_file: Path | None = None


def _started_by_dora(spec: dict, dora_id: str, run_dir: Path) -> str:
    """A worker that dora started (backends/dora): its node id, from its dora id. The coordinator,
    which is not its parent, learns its pid from ``<node>.pid`` and its exit code from
    ``<node>.exit`` (host.py there); it works in the coordinator's directory, as a child would."""
    global _exit_file
    from ..dora.dataflow import DoraNames

    node_id = DoraNames.from_spec(spec["dora"]).node_of(dora_id)
    (run_dir / f"{node_id}.pid").write_text(str(os.getpid()))
    _exit_file = run_dir / f"{node_id}.exit"
    for fd, name in ((1, "stdout"), (2, "stderr")):  # to the coordinator, which reads them (dora/host.py)
        with contextlib.suppress(OSError):
            pipe = os.open(run_dir / f"{dora_id}.{name}", os.O_WRONLY)
            os.dup2(pipe, fd)
            os.close(pipe)
    os.chdir(spec["dora"]["cwd"])
    return node_id


#: started by dora: the coordinator it watches is not its parent (dora's daemon is)
_adopted = False


def _dora_spec(spec_path: str) -> dict:
    """The spec's dora part (backends/dora), or {}."""
    try:
        dora = json.loads(Path(spec_path).read_text()).get("dora")
    except (OSError, ValueError, AttributeError):
        return {}
    return dora if type(dora) is dict else {}


def _dora_coordinator(spec_path: str) -> int | None:
    """The coordinator's pid, for a worker that dora started."""
    coordinator = _dora_spec(spec_path).get("coordinator")
    return coordinator if type(coordinator) is int else None


def _orphaned(parent: int, stat: int | None = None) -> bool:
    """Whether the coordinator that started this worker is dead or dying. Its main thread's exit
    sends PR_SET_PDEATHSIG, and may leave its other threads, and our ppid, for a moment longer:
    the main thread's state (that of /proc/<pid>) is then already Z. ``stat``: a descriptor of
    that file, opened while the coordinator lived (it then names that process, whatever process
    gets its pid later: a read fails once it is gone)."""
    if not _adopted and os.getppid() != parent:
        return True
    try:
        if stat is None:
            text = Path(f"/proc/{parent}/stat").read_bytes()
        else:
            text = os.pread(stat, 4096, 0)
    except OSError:
        return True
    return chr(text[text.rindex(b")") + 2]) in "ZX"


def _serve(argv: list[str], parent: int) -> int:
    _die_with_parent()
    _keep_freed_memory()
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # `kill -USR1 PID`: where is a stuck worker?
    sys.stdout.reconfigure(line_buffering=True)  # a pipe to the coordinator: a flow's print shows at once
    if os.getppid() == 1:
        return EXIT_FAILED  # the coordinator is already gone
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the coordinator, which stops us
    spec_path, node_id = argv[0], argv[1]
    from . import worker  # run with `python -m`, this module is __main__: the session reads the package's copy
    from .origin import key_of_text, sign, take_key

    worker.serving = node_id
    process_key = take_key()  # before any flow code runs (origin.py)
    join = argv[2:5] if len(argv) >= 5 and argv[2] == "--join" else None
    fresh = argv[2:5] if len(argv) >= 5 and argv[2] == "--fresh" else None
    spec = json.loads(Path(spec_path).read_text())
    if spec.get("dora"):  # started by dora (backends/dora): its argument is the node's dora id
        node_id = worker.serving = _started_by_dora(spec, node_id, Path(spec_path).parent)
        process_key = key_of_text(spec["dora"].get("keys", {}).get(node_id))
    for path in reversed(spec.get("python_path", [])):
        if path not in sys.path:
            sys.path.insert(0, path)
    # the coordinator's sys.argv, as multiprocessing gives its children the parent's: a script or
    # a flow's module that parses sys.argv when imported (argparse at module level) must see its
    # own arguments, not this worker's (SPEC.json NODE), or it parses the wrong ones and exits
    sys.argv = spec.get("argv", sys.argv)

    from ...codec import packb, unpackb
    from ...flow._base import set_up
    from .access import RunAccess, TlsFiles
    from .hub import needs_shared_memory, open_peer, wait_for_answers, wait_for_links
    from .loop import _CONTROL, StopRun
    from .wire import RELIABLE, KeySpace, WireEncoder

    keys = KeySpace(spec["namespace"])
    handover_file = Path(spec_path).parent / f"{node_id}.handover"
    # a deployment started --insecure has no access entry: anyone on its network may join
    config = RunAccess.from_spec(spec["access"]) if spec.get("access") else None
    access = {**(config[0].session_config(config[1]) if config else {}),
              **(TlsFiles(**spec["tls"]).session_config() if spec.get("tls") else {})}  # a TLS deployment's links
    # the first process of a node has the session id the others expect (a restarted one, whose
    # old process may still be linked, has its own: it finds its neighbours by their answers)
    zid = spec.get("zids", {}).get(node_id) if fresh is None and join is None else None
    shared_memory = needs_shared_memory(spec["ir"], node_id)
    padding = bytes(POOL_PADDING) if shared_memory else None  # no pool to make before T0 without it
    with open_peer(spec["hub"], sessions=run_sessions(len(spec["ir"]["nodes"])), access=access or None,
                   listen=spec.get("listen"), lease=spec.get("lease"), zid=zid,
                   blocked_put=spec.get("blocked_put"),
                   shared_memory=shared_memory) as session:
        def status(state: str, **info) -> None:  # on the main thread, or a receiving one (on_restart)
            info["pid"] = os.getpid()
            key, payload = keys.node_status(node_id), WireEncoder().status(node_id, state, info)
            session.put(key, payload, congestion_control=RELIABLE,
                        attachment=sign(process_key, key, payload) if process_key is not None else None)

        try:
            if spec.get("main_file"):
                _import_main(spec["main_file"])
            loop = build_loop(spec, node_id, session)
            loop.reporter.key = process_key
        except BaseException as exc:
            status("failed", error=f"cannot build node '{node_id}': {type(exc).__name__}: {exc}",
                   traceback=traceback.format_exc())
            return EXIT_FAILED
        try:
            stop_item = (_CONTROL, None, WireEncoder().control("stop", {}))

            def on_sigterm(signum, frame) -> None:
                # asked to stop; when its parent is dead (a SIGTERM sent by someone else then), it
                # ends as on PARENT_DIED
                loop.abandoned = _orphaned(parent)
                loop.stopping = True
                loop.inbox.put(stop_item)

            def on_parent_died(signum, frame) -> None:
                # the run goes on without this process, which ends without a word, as if killed,
                # promising its consumers nothing (not "done")
                loop.abandoned = loop.stopping = True
                loop.inbox.put(stop_item)

            signal.signal(signal.SIGTERM, on_sigterm)
            signal.signal(PARENT_DIED, on_parent_died)
            try:  # heavy work (weights, devices) once, here, before this process says ready
                set_up(loop.flow)
            except Exception as exc:
                status("failed", error=f"{type(exc).__name__}: {exc}", setup=True, traceback=traceback.format_exc())
                return EXIT_FAILED
            started_ns = None  # when the start came, ns since T0 (a restarted flow's process: None)
            loop.on_restart = lambda tag, error: status("restart", tag=list(tag), error=error)
            loop.on_exit = lambda tag: status("exit", tag=list(tag))
            if loop.virtual:  # lockstep (a restarted flow's process learns the grant from the next one put)
                loop.on_reached = lambda until: status("reached", until=until)
            try:
                if fresh is not None:  # its old process died: a fresh flow, on fresh inputs
                    t0, end = int(fresh[1]), int(fresh[2])
                    seqs = _join_afresh(session, keys, spec, node_id, loop,
                                        ready=lambda: status("ready"), padding=padding)
                    if seqs is None:
                        status("done", counts=dict(loop.counts))
                        loop.undeclare()
                        return 0
                    loop.start_fresh(seqs, t0)
                    loop.declare_outputs()
                elif join is not None:  # a restarted flow: listen now, take the old process's place when told
                    loop.declare_inputs()
                    # links to its producers and consumers, each knowing the other's subscribers:
                    # once the old process stops, a message that reached neither would be a gap
                    neighbors = {e[end]["node"] for e in spec["ir"]["edges"] for end in ("source", "destination")
                                 if node_id in (e["source"]["node"], e["destination"]["node"])}
                    wait_for_answers(session, {keys.progress(n) for n in neighbors},
                                     timeout=NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping,
                                     gone=lambda: {keys.progress(n) for n in _coordinator_says(session, keys)[0]})
                    if padding:  # its pool, before it joins (POOL_PADDING)
                        wait_for_answers(session, {keys.progress(n) for n in _consumers(spec, node_id)},
                                         timeout=NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping, payload=padding,
                                         gone=lambda: {keys.progress(n) for n in _coordinator_says(session, keys)[0]})
                    t0, end = int(join[1]), int(join[2])
                    _link_to_hub(session, spec, loop)

                    def say_ready() -> None:
                        status("ready")

                    say_ready()
                    if _await_control(loop, "resume", node_id, ask=say_ready) is None:
                        status("done", counts=dict(loop.counts))
                        loop.undeclare()
                        return 0
                    loop.take_over(unpackb(handover_file.read_bytes()))
                    handover_file.unlink()
                    loop.declare_outputs()
                else:
                    loop.declare()
                    # a direct link to the hub and each neighbour, before anything is published
                    # (peers do not route for each other)
                    unlinked = wait_for_links(session, _links_needed(spec, node_id),
                                              timeout=spec.get("startup_timeout", 60.0), stop=lambda: loop.stopping)
                    # and each producer knows this node's subscriptions: its answer to a query comes
                    # on the link after them (an event put before that went to no one: a gap in its
                    # stream's seqs that no frontier crosses, and this node waited for it forever)
                    def nudge(unanswered: set[str]) -> None:  # see REDECLARE_AFTER_S
                        status("unanswered", nodes=sorted(key.rsplit("/", 1)[1] for key in unanswered))
                        loop.redeclare()

                    wait_for_answers(session, {keys.progress(p) for p in _producers(spec, node_id)},
                                     timeout=spec.get("startup_timeout", 60.0), stop=lambda: loop.stopping,
                                     nudge=nudge, nudge_every=REDECLARE_AFTER_S)
                    if padding:  # its pool, before T0 (POOL_PADDING)
                        wait_for_answers(session, {keys.progress(c) for c in _consumers(spec, node_id)},
                                         timeout=spec.get("startup_timeout", 60.0), stop=lambda: loop.stopping,
                                         nudge=nudge, nudge_every=REDECLARE_AFTER_S, payload=padding)
                    # the events' own routes, where they are not Zenoh's (dora): one message through each
                    loop.await_routes(timeout=spec.get("startup_timeout", 60.0))
                    if loop.stopping:
                        loop.undeclare()
                        return 0

                    def ready() -> None:
                        status("ready", linked=not unlinked, unlinked=_names_of(spec, unlinked),
                               peers=len(session.info.peers_zid()))

                    ready()
                    # said again with each ask: a put made as a link came up may reach the hub before
                    # its subscriptions did, and be dropped (the coordinator then waited for it forever)
                    start = _await_control(loop, "start", node_id,
                                           ask=lambda: (ready(), _ask_start(session, keys, loop)))
                    if start is None:
                        status("done", counts=dict(loop.counts))
                        loop.undeclare()
                        return 0
                    t0, end = int(start["t0"]), int(start["end"])
                    loop.values = start.get("values") is not False
                    if loop.virtual:  # lockstep: the ticks below the first grant may run
                        loop.granted = max(0, min(int(start.get("grant", 0)), end))
                    # after T0 when the start came late (a loaded machine): after the end, no tick ran
                    started_ns = session.new_timestamp().get_time_as_ntp64().as_nanos() - t0
                if not loop.virtual:
                    _no_timer_slack()
                loop.run(t0, end, resume=join is not None)
                if loop.abandoned:
                    loop.undeclare()
                    return EXIT_ABANDONED
            except StopRun as exc:
                loop.release_held()
                loop.finish_reports()
                cause = exc.__cause__  # the exception a step raised: where in the flow's code
                status("failed", error=str(exc), tag=list(exc.tag) if exc.tag else None, counts=dict(loop.counts),
                       traceback="".join(traceback.format_exception(cause)) if cause is not None else None,
                       zeno=exc.zeno)
                loop.undeclare()
                return EXIT_FAILED
            except BaseException as exc:
                loop.finish_reports()
                status("failed", error=f"worker '{node_id}' crashed: {type(exc).__name__}: {exc}",
                       traceback=traceback.format_exc(), counts=dict(loop.counts))
                loop.undeclare()
                return EXIT_FAILED
            if loop.handing_over:
                loop.undeclare()  # first: no message may arrive after the state is taken
                state = packb(loop.handover_state())
                loop.finish_reports()
                tmp = handover_file.with_suffix(".tmp")
                tmp.write_bytes(state)
                tmp.replace(handover_file)
                status("handed_over", counts=dict(loop.counts), reports=loop.reporter.sent)
                release(loop, node_id)  # the new process has set up its own: free this one's now
                _await_reports_taken(session, keys, node_id, spec.get("hub_zid"))
                return EXIT_HANDED_OVER
            status("done", counts=dict(loop.counts), reports=loop.reporter.sent, started_ns=started_ns,
                   ticks=loop.recorded, stopped=loop.told_to_stop, sent=dict(loop.sent))
            loop.undeclare()
            release(loop, node_id)
            _await_reports_taken(session, keys, node_id, spec.get("hub_zid"))
        finally:
            release(loop, node_id)
    return 0


def release(loop: NodeLoop, node_id: str) -> None:
    """The flow's ``teardown()``, once (see Flow.setup): as soon as its process has nothing more
    to step, not after it waited for its reports to be taken. A failure is told, not fatal."""
    from ...flow._base import tear_down

    try:
        tear_down(loop.flow)
    except Exception as exc:
        print(f"{node_id}.teardown() raised {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)


def _links_needed(spec: dict, node_id: str) -> set[str]:
    """The Zenoh ids of the sessions a node's first process must be linked to before it says
    ready: the hub's, and its producers' and consumers' (an old spec without ids: none)."""
    zids = spec.get("zids")
    if not zids or not spec.get("hub_zid"):
        return set()
    neighbors = _producers(spec, node_id) | _consumers(spec, node_id)
    return {spec["hub_zid"], *(zids[n] for n in neighbors if n in zids)}


def _producers(spec: dict, node_id: str) -> set[str]:
    """The other nodes with an edge into ``node_id``."""
    return {e["source"]["node"] for e in spec["ir"]["edges"] if e["destination"]["node"] == node_id} - {node_id}


def _consumers(spec: dict, node_id: str) -> set[str]:
    """The other nodes with an edge from ``node_id``."""
    return {e["destination"]["node"] for e in spec["ir"]["edges"] if e["source"]["node"] == node_id} - {node_id}


def _link_to_hub(session, spec: dict, loop: NodeLoop) -> None:
    """Wait (NEIGHBOR_TIMEOUT_S at most) for a direct link to the coordinator's session: a
    process on another machine joins through its worker daemon and finds the hub by gossip,
    and a status it put before that link was up went nowhere (peers do not route)."""
    from .hub import wait_for_links

    if spec.get("hub_zid"):
        wait_for_links(session, {spec["hub_zid"]}, NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping)


def _names_of(spec: dict, zids: set[str]) -> list[str]:
    """What the sessions ``zids`` are, by node name ("the coordinator" for the hub)."""
    names = {z: n for n, z in spec.get("zids", {}).items()}
    names[spec.get("hub_zid")] = "the coordinator"
    return sorted(names.get(z, z) for z in zids)


def _join_afresh(session, keys, spec: dict, node_id: str, loop: NodeLoop, ready,
                 padding: bytes | None) -> dict[str, int] | None:
    """A flow whose process died, in its new process: subscribe to the inputs, take each stream
    on from where its producer stands (its progress answer: the reply comes on the link after
    our subscriptions, so every later event reaches us), link to the consumers (asking them
    with ``padding``: POOL_PADDING), say ``ready``
    and wait for the coordinator's ``restarted``: the first seq of each output port. None on
    ``stop``. A neighbour that is itself starting afresh is not waited for as a consumer (each
    would wait for the other), only as a producer (it answers once restarted, not waiting for us)."""
    from .hub import wait_for_answers
    from .loop import RESTART_SEQ_GAP
    from .wire import WireError, decode_progress

    loop.declare_inputs()
    # its own outputs fed back to it start with the seqs it gets below (start_fresh)
    producers, consumers = _producers(spec, node_id), _consumers(spec, node_id)
    answers: dict = {}
    give_up = time.monotonic() + NEIGHBOR_TIMEOUT_S
    while not loop.stopping and time.monotonic() < give_up:
        for src in sorted(producers - set(answers)):
            for reply in session.get(keys.progress(src), timeout=0.25):
                try:
                    answers[src] = decode_progress(reply.ok.payload.to_bytes(), expected=src)
                except (AttributeError, WireError):  # no answer (reply.err), or not a progress message
                    continue
        done, _ = _coordinator_says(session, keys)
        answers.update((n, None) for n in (producers - set(answers)) & done)
        if producers <= set(answers):
            break
        time.sleep(0.02)
    if loop.stopping:
        return None
    loop.sync_inputs(answers)  # a producer that never answered: its events are taken from seq 0
    wait_for_answers(session, {keys.progress(n) for n in consumers},
                     timeout=NEIGHBOR_TIMEOUT_S, stop=lambda: loop.stopping, payload=padding,
                     gone=lambda: {keys.progress(n) for n in set().union(*_coordinator_says(session, keys))})
    _drop_queued(loop, "restarted", node_id)  # the coordinator's comes after `ready`: one before is not its
    _link_to_hub(session, spec, loop)
    ready()
    args = _await_control(loop, "restarted", node_id, ask=ready)  # said again: see START_ASK_S
    if args is None:
        return None
    loop.values = args.get("values") is not False
    seqs = args.get("seqs")
    if type(seqs) is not dict or not all(type(seqs.get(p)) is int and seqs[p] >= RESTART_SEQ_GAP for p in loop.ports):
        raise RuntimeError(f"the 'restarted' for {node_id} carries no seq past {RESTART_SEQ_GAP} for each output "
                           f"port: {seqs!r:.200}")
    return {p: s for p, s in seqs.items() if type(p) is str and type(s) is int and s >= 0}


def _drop_queued(loop: NodeLoop, op: str, node_id: str) -> None:
    """Forget the control messages ``op`` to ``node_id`` queued in the loop's inbox; keep the rest."""
    import queue

    from .loop import _CONTROL
    from .wire import WireError, decode_control

    kept = []
    while True:
        try:
            item = loop.inbox.get_nowait()
        except queue.Empty:
            break
        if item[0] == _CONTROL:
            try:
                got, args = decode_control(item[2])
                if got == op and args.get("node") == node_id:
                    loop.counts["garbage"] += 1
                    continue
            except WireError:
                pass
        kept.append(item)
    for item in kept:
        loop.inbox.put(item)


def _coordinator_says(session, keys) -> tuple[set[str], set[str]]:
    """The nodes the coordinator knows are done (they will not answer, nor send, again), and
    those starting afresh after their process died."""
    said = _finished(session, keys) or {}
    return said.get("nodes", set()), said.get("restarting", set())


def _finished(session, keys) -> dict[str, set[str]] | None:
    """The coordinator's ``finished`` answer: ``nodes`` (done), ``complete`` (done, every report
    in), ``restarting``; None when it did not answer."""
    from .wire import WireError, decode_control

    said: dict[str, set[str]] | None = None
    for reply in session.get(keys.finished(), timeout=0.25):
        if reply.ok is None:
            continue
        try:
            _, args = decode_control(reply.ok.payload.to_bytes())
        except WireError:
            continue
        said = said or {"nodes": set(), "complete": set(), "restarting": set()}
        for key, found in said.items():
            names = args.get(key)
            if type(names) is list:
                found.update(n for n in names if type(n) is str)
    return said


def _await_reports_taken(session, keys, node_id: str, hub_zid: str | None) -> None:
    """After its last status, until the coordinator (whose session is ``hub_zid``) has every
    report of this node (its ``finished`` answer says so); see REPORTS_TAKEN_S for how long."""
    start = answered = time.monotonic()
    while (now := time.monotonic()) - answered < REPORTS_TAKEN_S and now - start < REPORTS_TAKEN_MAX_S:
        said = _finished(session, keys)
        if said is not None and node_id in said["complete"]:
            return
        if said is not None:
            answered = time.monotonic()
        elif hub_zid is None or hub_zid not in {str(z) for z in session.info.peers_zid()}:
            return  # the coordinator is gone (or, without its id, may be): nothing more reaches it
        time.sleep(0.02)


def _ask_start(session, keys, loop: NodeLoop) -> None:
    """Ask the coordinator for the run's start; its answer joins the loop's inbox as control."""
    from .loop import _CONTROL

    for reply in session.get(keys.start(), timeout=START_ASK_S):
        if reply.ok is not None:
            loop.inbox.put((_CONTROL, None, reply.ok.payload.to_bytes()))


def _await_control(loop: NodeLoop, wanted: str, node_id: str, ask=None) -> dict | None:
    """Wait for the run's control to say ``wanted`` (to this node, if it names one): its
    arguments; None on ``stop``. ``ask()``, if given, is called after every START_ASK_S without
    it. What else arrives meanwhile is put back in the loop's inbox."""
    import queue

    from .loop import _CONTROL
    from .wire import WireError, decode_control

    early = []
    try:
        while True:
            try:
                item = loop.inbox.get(timeout=START_ASK_S if ask is not None else None)
            except queue.Empty:
                ask()
                continue
            if item[0] != _CONTROL:
                early.append(item)
                continue
            try:
                op, args = decode_control(item[2])
            except WireError:
                loop.counts["garbage"] += 1
                continue
            if op == "stop":
                return None
            if op == wanted and args.get("node", node_id) == node_id:
                return args
            if op in ("lost", "restarted"):  # of a producer: the loop must know, once it runs
                early.append(item)
            elif op == "redeclare" and type(args.get("nodes")) is list and node_id in args["nodes"]:
                loop.redeclare()  # a consumer never got this node's answer (REDECLARE_AFTER_S)
    finally:
        for item in early:
            loop.inbox.put(item)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
