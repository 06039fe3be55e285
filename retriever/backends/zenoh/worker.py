"""A worker process: one flow of a run, rebuilt from the IR, ticking in real time.

    python -m retriever.backends.zenoh.worker SPEC.json NODE [--join T0 END | --fresh T0 END]

(command.py builds and reads that line.) The coordinator (``retriever.backends.zenoh.coordinator``)
writes ``SPEC.json`` — the IR, the hub's endpoint, the namespace, the Python path the flows were
imported from and the coordinator's ``sys.argv``, which the worker takes as its own — and starts
one worker per node. A worker process goes through these phases, each a function below:

    main             the command line and the process's key → a :class:`Launch`; a thread
                     watches the parent from then on (watch_parent)
    serve            prepare_process (die with the parent, keep freed memory, signals for stacks)
      read_spec        the spec, its Python path and argv
      open_session     the Zenoh peer, the statuses it signs (Status)
      build            the flow rebuilt and wired (build_loop, or the loop a Launch hands in),
                       SIGTERM and PARENT_DIED handled, the flow's setup()
      start            first process: declare, link, say ``ready``, wait for ``start`` {T0, end}
      | join           --join: take over a restarted flow's state when told ``resume``
      | start_afresh   --fresh: a fresh flow on fresh inputs once told ``restarted``
      run              the loop until its end, ``stop``, or a failure
      finish           say ``failed`` / ``handed_over`` / ``done``, release (teardown), wait
                       until the coordinator took every report; the session closes
    exit_process     end the process with the node's exit code

A start by dora (backends/dora/node.py) is the same phases with a :class:`Launch` of its own:
its parent to watch, its key, its loop (events over dora) and its directory.

on_error="restart": the failed worker says ``restart`` and goes on listening (node/handover.py);
the coordinator starts a new worker with ``--join``, which subscribes, says ``ready``
and waits. The coordinator then puts ``handover`` {node}: the old worker writes its loop's state
to ``<run dir>/<node>.handover``, says ``handed_over`` and exits; then ``resume`` {node}: the new
one reads the state and goes on with a fresh flow. A worker process that died (kill -9, a
segfault) has no state to hand over: the coordinator starts one with ``--fresh``, which starts
the flow afresh on fresh inputs once told ``restarted`` (node/handover.py).

A worker exits when its node is done, on ``stop``, on SIGTERM, or when its parent dies; its
session always closes. Every status it sends carries its pid, and every status and report the MAC
of its process's key (origin.py). Exit codes: 0 done or stopped,
1 failed (the status message says why), 3 handed over to a restarted flow, 4 its parent died (it
said nothing: as if killed).
"""

from __future__ import annotations

import ctypes
import faulthandler
import gc
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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from . import protocol
from .command import FIRST, FRESH, JOIN, Mode, parse_mode

if TYPE_CHECKING:
    from .node import NodeLoop

EXIT_FAILED = 1
EXIT_HANDED_OVER = 3
EXIT_ABANDONED = 4  # its parent (a coordinator, a worker daemon) died: it ended without a word

#: Before it says ``ready``, a worker asks each consumer's progress with this much padding, so
#: that Zenoh sends the question through the session's shared-memory pool (messages over 3 KiB
#: between peers on one host go that way; the hub has no shared memory: hub.HUB_SHARED_MEMORY).
#: Zenoh creates the pool on its first such message and writes all of it (128 MiB of page
#: faults): so that happens before T0 (or before a restarted flow joins); left to the first big
#: frame, it held that put and made the source's next ticks late (benchmarks/reports/latency.md).
#: The answer comes once the pool exists: the question is in it. A node with no consumer on its
#: host never sends through a pool, and has none.
POOL_PADDING = 4096

#: the flows this process served, held until it ends: what a flow holds (a model, a device) is
#: finalized once, as the interpreter ends; the session its loop held is let go of
_kept_to_the_end: list = []

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

#: A new worker waits, before it says ready, for an answer from each producer (see start), and
#: from each consumer if it makes its pool (POOL_PADDING). With many flows starting at once, a
#: worker linked to its producer may never be told of that producer's queryable, and the run
#: would never start (benchmarks/reports/deploy.md, "Scale"). So after this long without an
#: answer it says ``unanswered``; the coordinator
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


@dataclass(frozen=True)
class Parent:
    """The process whose end is this worker's end: the one that started it (a coordinator, a
    worker daemon), or, ``adopted``, a coordinator that is not its parent (dora's nodes are
    dora's children): no kernel tells an adopted worker that its coordinator died, so it tells
    itself, as the kernel would (PARENT_DIED)."""

    pid: int
    adopted: bool = False

    def gone(self, stat: int | None = None) -> bool:
        """Whether it is dead or dying. Its main thread's exit sends PR_SET_PDEATHSIG, and may
        leave its other threads, and our ppid, for a moment longer: the main thread's state (that
        of /proc/<pid>) is then already Z. ``stat``: a descriptor of that file, opened while the
        parent lived (it then names that process, whatever process gets its pid later: a read
        fails once it is gone)."""
        if not self.adopted and os.getppid() != self.pid:
            return True
        try:
            if stat is None:
                text = Path(f"/proc/{self.pid}/stat").read_bytes()
            else:
                text = os.pread(stat, 4096, 0)
        except OSError:
            return True
        return chr(text[text.rindex(b")") + 2]) in "ZX"


@dataclass
class Launch:
    """How this worker process was started, and what its starter hands it: the command line
    (:func:`main`), or dora's node module (backends/dora/node.py)."""

    spec_path: Path
    node: str
    parent: Parent
    #: the key it signs its statuses and reports with (origin.py); None: it signs nothing
    key: bytes | None
    mode: Mode = FIRST
    #: ``(spec, node, session) -> NodeLoop``: the node's loop, wired; None: :func:`build_loop`'s
    make_loop: Callable | None = None
    #: folders of the run besides its run directory, removed with it once the parent is gone
    folders: tuple[Path, ...] = ()

    @property
    def run_dir(self) -> Path:
        return self.spec_path.parent

    def remove_folders(self) -> None:
        """Remove the run's folders, which no one else will once its coordinator is gone."""
        if self.run_dir.name.startswith("retriever-run-"):
            for folder in self.folders:
                shutil.rmtree(folder, ignore_errors=True)
            shutil.rmtree(self.run_dir, ignore_errors=True)


def watch_parent(launch: Launch) -> None:
    """Watch the parent from a thread of its own, from now on (:func:`_watch_parent`)."""
    threading.Thread(target=_watch_parent, args=(launch,), name="retriever-watch-parent", daemon=True).start()


def _watch_parent(launch: Launch) -> None:
    """Once the parent is gone, exit within ORPHAN_GRACE_S, with every thread's stack on
    stderr, even when the step never returns (faulthandler's timer needs no GIL); and remove the
    run's folders, which no one else will."""
    parent = launch.parent
    try:  # read through one descriptor: a pread a look (an idle worker's thread wakes twice a second)
        stat = os.open(f"/proc/{parent.pid}/stat", os.O_RDONLY)
    except OSError:
        stat = None
    while not parent.gone(stat):
        time.sleep(0.5)
    faulthandler.dump_traceback_later(ORPHAN_GRACE_S, exit=True)
    launch.remove_folders()
    if parent.adopted:
        os.kill(os.getpid(), PARENT_DIED)


def _keep_freed_memory() -> None:
    """glibc: serve blocks up to 32 MiB from the heap and keep freed memory mapped. A worker
    allocates and frees a message-sized buffer per event; by default glibc returns big blocks to
    the kernel at once, so every event paid a page fault per 4 KiB again (a 16 MiB frame: 4096
    faults, which cost more than the copy itself)."""
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


def build_loop(spec: dict, node_id: str, session, transport=None):
    """Rebuild ``node_id`` from the IR in ``spec`` and wire its inputs as the run's plan says (the
    spec's ``plan``, if it carries one, else made here from the IR): a ready NodeLoop, its events
    through ``transport`` (a dora node's), or on ``session`` when None."""
    from ...flow._base import Flow
    from ...graph import compile_graph
    from ...ir import DEFAULT_DEADLINE, IR
    from ...plan import Plan, bind_inputs, plan_ir
    from ...rebuild import rebuild_node
    from ...sync import PortBuffer
    from .node import InEdge, NodeLoop
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
    plan = (Plan.from_data(spec["plan"], ir) if "plan" in spec else plan_ir(ir)).nodes[node_id]
    inputs, fallbacks = bind_inputs(plan, node.inputs, lambda: PortBuffer(trim_batch=1))
    buffers = {port: buf for port, buf, _, _ in inputs}
    edges = [InEdge(f.src, f.src_port, f.port, buffers[f.port], f.delay_ns, f.triggers, f.deadline_ns,
                    f.src_latency_ns) for f in plan.feeds]
    if type(node.flow).reset is not Flow.reset:
        node.flow.reset()  # the paper's flows initialise their state in reset()
    return NodeLoop(session, KeySpace(spec["namespace"]), node, edges, inputs, fallbacks,
                    realtime=meta.get("realtime", "soft"),
                    ports=sorted(ir.node(node_id)["outputs"]),
                    consumed=bool(plan.consumers),
                    spill_dir=spec.get("spill_dir") if os.path.isdir(spec.get("spill_dir") or "") else None,
                    # a flow with a setup() may hold what belongs to one thread (an OpenGL/EGL or
                    # CUDA context, a device handle): it steps on the thread that set it up
                    inline=not plan.on_a_cycle and type(node.flow).setup is Flow.setup,
                    cycle=plan.cycle, instant_ports=plan.instant_ports,
                    max_microsteps=meta.get("max_microsteps", 1000), virtual=bool(spec.get("virtual_time")),
                    transport=transport)


def run_sessions(nodes: int) -> int:
    """How many Zenoh sessions with a pool a run of ``nodes`` nodes has, which share the run's
    shared memory (hub.shm_pool_bytes): a worker's each (the hub has none, hub.HUB_SHARED_MEMORY)."""
    return nodes


PR_SET_TIMERSLACK = 29  # <linux/prctl.h>


def _no_timer_slack() -> None:
    """Let this thread's timed waits end on time: Linux may end each one up to its timer slack
    late (50 µs unless set) to wake threads together; the loop waits for ticks, so it asks for
    1 ns (benchmarks/control_jitter.py measures a tick's lateness). Per thread: call it
    on the thread that runs the loop. Elsewhere than Linux, or if refused, nothing changes."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None).prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    except (OSError, AttributeError):
        pass


# ---------------------------------------------------------------------------------------------
# The process: main, serve, exit_process
# ---------------------------------------------------------------------------------------------
def main(argv: list[str]) -> NoReturn:
    """``SPEC.json NODE [MODE]`` (command.py): serve the node, then end the process."""
    from .origin import take_key

    key = take_key()  # before any flow code runs (origin.py)
    try:
        spec_path, node, mode = Path(argv[0]), argv[1], parse_mode(argv[2:])
    except (IndexError, ValueError) as e:
        print(f"usage: python -m {__spec__.name if __spec__ else __name__} SPEC.json NODE "
              f"[{JOIN}|{FRESH} T0 END]: {e}", file=sys.stderr, flush=True)
        exit_process(EXIT_FAILED)
    launch = Launch(spec_path, node, Parent(os.getppid()), key, mode)
    watch_parent(launch)
    exit_process(serve(launch))


def serve(launch: Launch) -> int:
    """Serve one node, from this process's settings to its session's close: its exit code.
    A worker whose parent died meanwhile also removes the run's folders (the spec and unreported
    events, in /dev/shm), which no one else would."""
    code = EXIT_FAILED
    try:
        if prepare_process():
            pool: set[str] = set()
            code = _serve_node(launch, read_spec(launch), pool)
            _let_go_of(pool)
    except Exception:
        traceback.print_exc()
    finally:
        if launch.parent.gone():
            launch.remove_folders()
    return code


def prepare_process() -> bool:
    """This process's settings, before anything else; False when its parent is already gone."""
    _die_with_parent()
    _keep_freed_memory()
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # `kill -USR1 PID`: where is a stuck worker?
    sys.stdout.reconfigure(line_buffering=True)  # a pipe to the coordinator: a flow's print shows at once
    if os.getppid() == 1:
        return False
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the coordinator, which stops us
    return True


def read_spec(launch: Launch) -> dict:
    """The run's spec; its Python path joins this process's, and its argv becomes ours: the
    coordinator's ``sys.argv``, as multiprocessing gives its children the parent's (a script or
    a flow's module that parses sys.argv when imported must see its own arguments, not this
    worker's, or it parses the wrong ones and exits)."""
    from . import worker  # run with `python -m`, this module is __main__: the session reads the package's copy

    worker.serving = launch.node
    spec = json.loads(launch.spec_path.read_text())
    for path in reversed(spec.get("python_path", [])):
        if path not in sys.path:
            sys.path.insert(0, path)
    sys.argv = spec.get("argv", sys.argv)
    return spec


def exit_process(code: int) -> NoReturn:
    """End this process with ``code``, as Python ends: ``atexit`` functions, then the C library's
    exit handlers, in which Zenoh removes the shared-memory segments this process was the last to
    map. Collecting what a flow held (a torch model, object by object) may take seconds: a worker
    that said ``done`` has the coordinator's REAP_GRACE_S for it, not the stop grace of a stuck one."""
    sys.exit(code)


def _let_go_of(pool: set[str]) -> None:
    """Once the session closed, until Zenoh let go of the shared-memory pool it made (``pool``:
    its /dev/shm segments), at most hub.SEGMENT_RELEASE_S: Zenoh unlinks a segment when the last
    process that maps it lets go, and the exit handlers skip a segment this process still maps.
    The loop, which holds the session, goes first: the signal handlers held it (a stop has
    nothing left to stop: the process ends)."""
    from .hub import await_segments_released

    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(PARENT_DIED, signal.SIG_IGN)
    if pool:
        gc.collect()  # the loop's cycles (its threads, callbacks) hold the session too
        await_segments_released(pool)


# ---------------------------------------------------------------------------------------------
# The node: open the session, build, wait for the start, run, finish
# ---------------------------------------------------------------------------------------------
class Status:
    """Puts this node's statuses on ``status/node/<node>``: each with this process's pid, and
    signed with its key. Called on the main thread, or a receiving one (on_restart)."""

    def __init__(self, session, keys, node: str, key: bytes | None):
        self.session, self.keys, self.node, self.key = session, keys, node, key

    def __call__(self, kind: type[protocol.Status], **fields) -> None:
        """Say a status of ``kind`` (a record of protocol.STATUS) with ``fields``, this node's and pid."""
        from .origin import sign
        from .wire import RELIABLE

        key, payload = self.keys.node_status(self.node), kind(node=self.node, pid=os.getpid(), **fields).encode()
        self.session.put(key, payload, congestion_control=RELIABLE,
                         attachment=sign(self.key, key, payload) if self.key is not None else None)


@dataclass
class Serving:
    """What the phases of serving one node share."""

    launch: Launch
    spec: dict
    session: object
    keys: object  # wire.KeySpace
    status: Status
    #: the questions that make this session's shared-memory pool before T0 (POOL_PADDING); None:
    #: the node has no pool to make
    padding: bytes | None
    #: the /dev/shm segments of that pool, once made (_let_go_of)
    pool: set[str]
    loop: NodeLoop | None = None

    @property
    def node(self) -> str:
        return self.launch.node

    def waiting(self) -> Callable[[], bool]:
        return lambda: self.loop.stopping


@dataclass(frozen=True)
class Start:
    """When the loop runs: from ``t0`` to ``end`` (ns); ``resume``: on a restarted flow's state;
    ``started_ns``: when the start came, ns since T0 (a restarted flow's process: None)."""

    t0: int
    end: int
    resume: bool = False
    started_ns: int | None = None


def _serve_node(launch: Launch, spec: dict, pool: set[str]) -> int:
    from .hub import needs_shared_memory
    from .wire import KeySpace

    keys = KeySpace(spec["namespace"])
    shared_memory = needs_shared_memory(spec["ir"], launch.node)
    with open_session(spec, launch.node, launch.mode, shared_memory) as session:
        w = Serving(launch, spec, session, keys, Status(session, keys, launch.node, launch.key),
                    padding=bytes(POOL_PADDING) if shared_memory else None, pool=pool)
        if not build(w):
            return EXIT_FAILED
        try:
            handle_signals(w)
            if not set_up_flow(w):
                return EXIT_FAILED
            return run(w)
        finally:
            release(w.loop, w.node)


def open_session(spec: dict, node: str, mode: Mode, shared_memory: bool):
    """This process's Zenoh peer, joined to the run's hub (close it: ``with``). A deployment
    started --insecure has no access entry: anyone on its network may join; a TLS one's links
    use its files. The first process of a node has the session id the others expect (a
    restarted one, whose old process may still be linked, has its own: it finds its neighbours
    by their answers)."""
    from .access import RunAccess, TlsFiles
    from .hub import open_peer

    config = RunAccess.from_spec(spec["access"]) if spec.get("access") else None
    access = {**(config[0].session_config(config[1]) if config else {}),
              **(TlsFiles(**spec["tls"]).session_config() if spec.get("tls") else {})}
    zid = spec.get("zids", {}).get(node) if mode.kind is None else None
    return open_peer(spec["hub"], sessions=run_sessions(len(spec["ir"]["nodes"])), access=access or None,
                     listen=spec.get("listen"), lease=spec.get("lease"), zid=zid,
                     blocked_put=spec.get("blocked_put"), shared_memory=shared_memory)


def build(w: Serving) -> bool:
    """The node's flow, rebuilt from the IR, in its loop (``w.loop``); False when it cannot be
    built (the status ``failed`` said why)."""
    try:
        if w.spec.get("main_file"):
            _import_main(w.spec["main_file"])
        w.loop = (w.launch.make_loop or build_loop)(w.spec, w.node, w.session)
        w.loop.reporter.key = w.launch.key
        w.loop.opener = protocol.ControlOpener(w.launch.key)
        _kept_to_the_end.append(w.loop.flow)
    except BaseException as exc:
        w.status(protocol.Failed, error=f"cannot build node '{w.node}': {type(exc).__name__}: {exc}",
                 traceback=traceback.format_exc())
        return False
    return True


def handle_signals(w: Serving) -> None:
    """SIGTERM asks the loop to stop; when the parent is dead (a SIGTERM sent by someone else
    then), or on PARENT_DIED, the process ends without a word, as if killed, promising its
    consumers nothing (not "done"): the run goes on without it."""
    from .node import CONTROL

    loop, parent = w.loop, w.launch.parent
    stop_item = (CONTROL, None, protocol.Stop())  # this process's own: no seal to open

    def on_sigterm(signum, frame) -> None:
        loop.abandoned = parent.gone()
        loop.stopping = True
        loop.inbox.put(stop_item)

    def on_parent_died(signum, frame) -> None:
        loop.abandoned = loop.stopping = True
        loop.inbox.put(stop_item)

    signal.signal(signal.SIGTERM, on_sigterm)
    signal.signal(PARENT_DIED, on_parent_died)


def set_up_flow(w: Serving) -> bool:
    """The flow's heavy work (weights, devices), once, here, before this process says ready;
    then the loop's statuses hooked up. False when setup() raised (said)."""
    from ...flow._base import set_up

    loop, status = w.loop, w.status
    try:
        set_up(loop.flow)
    except Exception as exc:
        status(protocol.Failed, error=f"{type(exc).__name__}: {exc}", setup=True, traceback=traceback.format_exc())
        return False
    loop.on_restart = lambda tag, error: status(protocol.Restart, tag=tuple(tag), error=error)
    loop.on_exit = lambda tag: status(protocol.Exit, tag=tuple(tag))
    if loop.virtual:  # lockstep (a restarted flow's process learns the grant from the next one put)
        loop.on_reached = lambda until: status(protocol.Reached, until=until)
    return True


def run(w: Serving) -> int:
    """Wait for the start as the mode says, run the loop, and finish: the exit code."""
    from ...errors import StopRun

    loop = w.loop
    wait = {None: start, JOIN: join, FRESH: start_afresh}[w.launch.mode.kind]
    try:
        begin = wait(w)
        if begin is None:  # stopped first
            return 0
        if not loop.virtual:
            _no_timer_slack()
        hub_link = _watch_hub_link(w.session, w.spec.get("hub_zid"), w.node)
        try:
            loop.run(begin.t0, begin.end, resume=begin.resume)
        finally:
            if hub_link is not None:
                hub_link.undeclare()
        if loop.abandoned:
            loop.undeclare()
            return EXIT_ABANDONED
    except StopRun as exc:
        loop.outputs.release_held()
        loop.reports.finish()
        cause = exc.__cause__  # the exception a step raised: where in the flow's code
        w.status(protocol.Failed, error=str(exc), tag=tuple(exc.tag) if exc.tag else None, counts=dict(loop.counts),
                 traceback="".join(traceback.format_exception(cause)) if cause is not None else None,
                 zeno=exc.zeno)
        loop.undeclare()
        return EXIT_FAILED
    except BaseException as exc:
        loop.reports.finish()
        w.status(protocol.Failed, error=f"worker '{w.node}' crashed: {type(exc).__name__}: {exc}",
                 traceback=traceback.format_exc(), counts=dict(loop.counts))
        loop.undeclare()
        return EXIT_FAILED
    return finish(w, begin)


def finish(w: Serving, begin: Start) -> int:
    """After the loop's run: hand the state over to the flow's new process (a restart), or say
    ``done``; release the flow; keep the session until the coordinator has every report."""
    from ...codec import packb

    loop, status = w.loop, w.status
    if loop.handing_over:
        loop.undeclare()  # first: no message may arrive after the state is taken
        state = packb(loop.handover_state())
        loop.reports.finish()
        handover_file = w.launch.run_dir / f"{w.node}.handover"
        tmp = handover_file.with_suffix(".tmp")
        tmp.write_bytes(state)
        tmp.replace(handover_file)
        status(protocol.HandedOver, counts=dict(loop.counts), reports=loop.reporter.sent)
        release(loop, w.node)  # the new process has set up its own: free this one's now
        _await_reports_taken(w.session, w.keys, w.loop.opener, w.node, w.spec.get("hub_zid"))
        return EXIT_HANDED_OVER
    status(protocol.Done, counts=dict(loop.counts), reports=loop.reporter.sent, started_ns=begin.started_ns,
           ticks=loop.reports.recorded, stopped=loop.told_to_stop, sent=dict(loop.sent))
    loop.undeclare()
    release(loop, w.node)
    _await_reports_taken(w.session, w.keys, w.loop.opener, w.node, w.spec.get("hub_zid"))
    return 0


def _stopped_before_start(w: Serving) -> None:
    w.status(protocol.Done, counts=dict(w.loop.counts))
    w.loop.undeclare()


# ---------------------------------------------------------------------------------------------
# The three ways to the start
# ---------------------------------------------------------------------------------------------
def start(w: Serving) -> Start | None:
    """The node's first process: declare everything; a direct link to the hub and each
    neighbour before anything is published (peers do not route for each other); each producer
    knowing this node's subscriptions (its answer to a query comes on the link after them: an
    event put before that went to no one, a gap in its stream's seqs that no frontier crosses,
    and this node waited for it forever); its pool; the events' own routes where they are not
    Zenoh's (dora). Then ``ready``, and wait for ``start``. None: stopped first."""
    from .hub import wait_for_answers, wait_for_links

    loop, session, spec, keys, status = w.loop, w.session, w.spec, w.keys, w.status
    timeout = spec.get("startup_timeout", 60.0)
    loop.declare()
    unlinked = wait_for_links(session, _links_needed(spec, w.node), timeout=timeout, stop=w.waiting())

    def nudge(unanswered: set[str]) -> None:  # see REDECLARE_AFTER_S
        status(protocol.Unanswered, nodes=tuple(sorted(key.rsplit("/", 1)[1] for key in unanswered)))
        loop.redeclare()

    wait_for_answers(session, {keys.progress(p) for p in _producers(spec, w.node)}, timeout=timeout,
                     stop=w.waiting(), nudge=nudge, nudge_every=REDECLARE_AFTER_S)
    if w.padding is not None:  # its pool, before T0
        _make_pool(w, lambda: wait_for_answers(session, {keys.progress(c) for c in _consumers(spec, w.node)},
                                               timeout=timeout, stop=w.waiting(), nudge=nudge,
                                               nudge_every=REDECLARE_AFTER_S, payload=w.padding))
    loop.await_routes(timeout=timeout)
    if loop.stopping:
        loop.undeclare()
        return None

    def ready() -> None:
        status(protocol.Ready, linked=not unlinked, unlinked=tuple(_names_of(spec, unlinked)),
               peers=len(session.info.peers_zid()))

    ready()
    # said again with each ask: a put made as a link came up may reach the hub before
    # its subscriptions did, and be dropped (the coordinator then waited for it forever)
    said = _await_control(loop, protocol.Start, w.node, ask=lambda: (ready(), _ask_start(session, keys, loop)))
    if said is None:
        _stopped_before_start(w)
        return None
    t0, end = said.t0, said.end
    loop.reports.values = said.values  # whether the coordinator wants the events' values
    if loop.virtual:  # lockstep: the ticks below the first grant may run
        loop.granted = min(0 if said.grant is protocol.ABSENT else said.grant, end)
    # after T0 when the start came late (a loaded machine): after the end, no tick ran
    return Start(t0, end, started_ns=session.new_timestamp().get_time_as_ntp64().as_nanos() - t0)


def join(w: Serving) -> Start | None:
    """A restarted flow's new process: listen now, with links to its producers and consumers,
    each knowing the other's subscribers (once the old process stops, a message that reached
    neither would be a gap); its pool; say ``ready``; take the old process's place, and state,
    when told ``resume``. None: stopped first."""
    from ...codec import unpackb
    from .hub import wait_for_answers
    from .node import handover

    loop, session, spec, keys = w.loop, w.session, w.spec, w.keys
    loop.declare_inputs()
    neighbors = {e[end]["node"] for e in spec["ir"]["edges"] for end in ("source", "destination")
                 if w.node in (e["source"]["node"], e["destination"]["node"])}

    def gone() -> set[str]:
        return {keys.progress(n) for n in _coordinator_says(session, keys, loop.opener)[0]}

    wait_for_answers(session, {keys.progress(n) for n in neighbors}, timeout=NEIGHBOR_TIMEOUT_S,
                     stop=w.waiting(), gone=gone)
    if w.padding is not None:  # its pool, before it joins
        _make_pool(w, lambda: wait_for_answers(session, {keys.progress(n) for n in _consumers(spec, w.node)},
                                               timeout=NEIGHBOR_TIMEOUT_S, stop=w.waiting(), payload=w.padding,
                                               gone=gone))
    _link_to_hub(session, spec, loop)

    def say_ready() -> None:
        w.status(protocol.Ready)

    say_ready()
    if _await_control(loop, protocol.Resume, w.node, ask=say_ready) is None:
        _stopped_before_start(w)
        return None
    handover_file = w.launch.run_dir / f"{w.node}.handover"
    handover.take_over(loop, unpackb(handover_file.read_bytes()))
    handover_file.unlink()
    loop.declare_outputs()
    return Start(w.launch.mode.t0, w.launch.mode.end, resume=True)


def start_afresh(w: Serving) -> Start | None:
    """A flow whose process died, in its new process: a fresh flow on fresh inputs, its output
    seqs from the coordinator's ``restarted`` (:func:`_join_afresh`). None: stopped first."""
    from .node import handover
    seqs = _join_afresh(w)
    if seqs is None:
        _stopped_before_start(w)
        return None
    handover.start_fresh(w.loop, seqs, w.launch.mode.t0)
    w.loop.declare_outputs()
    return Start(w.launch.mode.t0, w.launch.mode.end)


def _make_pool(w: Serving, ask: Callable[[], object]) -> None:
    """``ask()`` the consumers, with POOL_PADDING if the node has a pool to make, which Zenoh
    then makes: its /dev/shm segments are kept (_let_go_of)."""
    from .hub import mapped_segments

    before = mapped_segments() if w.padding is not None else set()
    ask()
    if w.padding is not None:
        w.pool |= mapped_segments() - before


def _join_afresh(w: Serving) -> dict[str, int] | None:
    """A flow whose process died, in its new process: subscribe to the inputs, take each stream
    on from where its producer stands (its progress answer: the reply comes on the link after
    our subscriptions, so every later event reaches us), link to the consumers (asking them
    with POOL_PADDING), say ``ready`` and wait for the coordinator's ``restarted``: the first
    seq of each output port. None on ``stop``. A neighbour that is itself starting afresh is not
    waited for as a consumer (each would wait for the other), only as a producer (it answers
    once restarted, not waiting for us)."""
    from .hub import wait_for_answers
    from .node import RESTART_SEQ_GAP, handover

    loop, session, spec, keys = w.loop, w.session, w.spec, w.keys
    loop.declare_inputs()
    # its own outputs fed back to it start with the seqs it gets below (start_fresh)
    answers = _producers_progress(w)
    if loop.stopping:
        return None
    handover.sync_inputs(loop.streams, answers)  # a producer that never answered: its events are taken from seq 0
    _make_pool(w, lambda: wait_for_answers(
        session, {keys.progress(n) for n in _consumers(spec, w.node)}, timeout=NEIGHBOR_TIMEOUT_S,
        stop=w.waiting(), payload=w.padding,
        gone=lambda: {keys.progress(n) for n in set().union(*_coordinator_says(session, keys, loop.opener))}))
    # the coordinator's comes after `ready`: one before is not its
    _drop_queued(loop, protocol.Restarted, w.node)
    _link_to_hub(session, spec, loop)

    def ready() -> None:
        w.status(protocol.Ready)

    ready()
    restarted = _await_control(loop, protocol.Restarted, w.node, ask=ready)  # said again: see START_ASK_S
    if restarted is None:
        return None
    loop.reports.values = restarted.values
    seqs = restarted.seqs
    if not all(seqs.get(p, -1) >= RESTART_SEQ_GAP for p in loop.ports):
        raise RuntimeError(f"the 'restarted' for {w.node} carries no seq past {RESTART_SEQ_GAP} for each output "
                           f"port: {seqs!r:.200}")
    return dict(seqs)


def _producers_progress(w: Serving) -> dict:
    """Each producer's progress, as it answers (None for one the coordinator says is done), for
    NEIGHBOR_TIMEOUT_S at most; a producer that never answered is left out."""
    from .wire import WireError, decode_progress

    producers = _producers(w.spec, w.node)
    answers: dict = {}
    give_up = time.monotonic() + NEIGHBOR_TIMEOUT_S
    while not w.loop.stopping and time.monotonic() < give_up:
        for src in sorted(producers - set(answers)):
            for reply in w.session.get(w.keys.progress(src), timeout=0.25):
                try:
                    answers[src] = decode_progress(reply.ok.payload.to_bytes(), expected=src)
                except (AttributeError, WireError):  # no answer (reply.err), or not a progress message
                    continue
        done, _ = _coordinator_says(w.session, w.keys, w.loop.opener)
        answers.update((n, None) for n in (producers - set(answers)) & done)
        if producers <= set(answers):
            break
        time.sleep(0.02)
    return answers


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


def _drop_queued(loop: NodeLoop, kind: type[protocol.Record], node_id: str) -> None:
    """Forget the control messages of ``kind`` to ``node_id`` queued in the loop's inbox; keep the rest."""
    import queue

    from .node import CONTROL

    kept = []
    while True:
        try:
            item = loop.inbox.get_nowait()
        except queue.Empty:
            break
        if item[0] == CONTROL and type(item[2]) is kind and item[2].node == node_id:
            loop.counts["garbage"] += 1
            continue
        kept.append(item)
    for item in kept:
        loop.inbox.put(item)


def _coordinator_says(session, keys, opener) -> tuple[set[str], set[str]]:
    """The nodes the coordinator knows are done (they will not answer, nor send, again), and
    those starting afresh after their process died (``opener``: this process's, for the answer)."""
    said = _finished(session, keys, opener) or {}
    return said.get("nodes", set()), said.get("restarting", set())


def _finished(session, keys, opener) -> dict[str, set[str]] | None:
    """The coordinator's ``finished`` answer: ``nodes`` (done), ``complete`` (done, every report
    in), ``restarting``; None when it did not answer. An answer the coordinator did not seal for
    this process (``opener``: its ControlOpener) is none."""
    from .wire import WireError

    said: dict[str, set[str]] | None = None
    nonce = protocol.new_nonce()
    for reply in session.get(keys.finished(), attachment=nonce, timeout=0.25):
        if reply.ok is None:
            continue
        try:
            finished = opener.reply(protocol.Finished, str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                    reply.ok.attachment, nonce)
        except WireError:
            continue
        said = said or {"nodes": set(), "complete": set(), "restarting": set()}
        for field, found in said.items():
            found.update(getattr(finished, field))
    return said


def _await_reports_taken(session, keys, opener, node_id: str, hub_zid: str | None) -> None:
    """After its last status, until the coordinator (whose session is ``hub_zid``) has every
    report of this node (its ``finished`` answer, opened by ``opener``, says so); see
    REPORTS_TAKEN_S for how long."""
    start = answered = time.monotonic()
    while (now := time.monotonic()) - answered < REPORTS_TAKEN_S and now - start < REPORTS_TAKEN_MAX_S:
        said = _finished(session, keys, opener)
        if said is not None and node_id in said["complete"]:
            return
        if said is not None:
            answered = time.monotonic()
        elif hub_zid is None or hub_zid not in {str(z) for z in session.info.peers_zid()}:
            if hub_zid is not None:  # the coordinator waits for reports that cannot come: say why
                print(f"retriever: worker '{node_id}' has no link to the coordinator at its end: the coordinator may "
                      "lack its last reports and status", file=sys.stderr, flush=True)
            return  # the coordinator is gone (or, without its id, may be): nothing more reaches it
        time.sleep(0.02)


def _watch_hub_link(session, hub_zid: str | None, node_id: str):
    """Say on stderr when this process's link to the coordinator's session (``hub_zid``) closes
    while the node runs; the listener (undeclare it), or None without a hub id.

    Nothing else would tell: a put with no route is dropped without an error, and Zenoh re-opens
    only the links to a session's configured endpoints. A flow on a worker daemon found the hub by
    gossip, so from then on its reports and its last status go nowhere and the run ends with
    "exited with code 0 before it finished". Zenoh closes a healthy link when its peer's lease
    passes with nothing read from it, and reading stops while Zenoh closes another link whose
    queue a put holds (a consumer's host cut off, congestion control BLOCK): it takes that queue's
    lock, on a thread that also reads links, and waits for each put that holds it, up to its
    wait_before_close, before the link leaves the routes (benchmarks/reports/partition_move.md)."""
    import zenoh

    if not hub_zid:
        return None

    def closed(event) -> None:  # on a thread of zenoh-python's
        if event.kind == zenoh.SampleKind.DELETE and str(event.transport.zid) == hub_zid:
            print(f"retriever: worker '{node_id}' lost its link to the coordinator at {time.strftime('%H:%M:%S')} "
                  "(Zenoh closed it, and does not open it again): what it reports from now on does not reach the "
                  "coordinator", file=sys.stderr, flush=True)

    return session.info.declare_transport_events_listener(closed)


def _ask_start(session, keys, loop: NodeLoop) -> None:
    """Ask the coordinator for the run's start; its answer joins the loop's inbox as control (one
    the coordinator did not seal for this process, as the WireError saying so: garbage)."""
    from .node import CONTROL
    from .wire import WireError

    nonce = protocol.new_nonce()
    for reply in session.get(keys.start(), attachment=nonce, timeout=START_ASK_S):
        if reply.ok is not None:
            try:
                start = loop.opener.reply(protocol.Start, str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                                          reply.ok.attachment, nonce)
            except WireError as e:
                loop.inbox.put((CONTROL, None, e))
                continue
            loop.inbox.put((CONTROL, None, start))


def _await_control(loop: NodeLoop, wanted: type[protocol.Record], node_id: str, ask=None) -> protocol.Record | None:
    """Wait for the run's control to say ``wanted`` (a record of protocol.RUN_CONTROL: to this
    node, if it names one): that record; None on ``stop``. ``ask()``, if given, is called after
    every START_ASK_S without it. What else arrives meanwhile is put back in the loop's inbox."""
    import queue

    from .node import CONTROL
    from .wire import WireError

    early = []
    try:
        while True:
            try:
                item = loop.inbox.get(timeout=START_ASK_S if ask is not None else None)
            except queue.Empty:
                ask()
                continue
            if item[0] != CONTROL:
                early.append(item)
                continue
            record = item[2]
            kind = type(record)
            if isinstance(record, WireError):
                loop.counts["garbage"] += 1
            elif kind is protocol.Stop:
                return None
            elif kind is wanted and getattr(record, "node", node_id) == node_id:
                return record
            elif kind in (protocol.Lost, protocol.Restarted):  # of a producer: the loop must know, once it runs
                early.append(item)
            elif kind is protocol.Redeclare and node_id in record.nodes:
                loop.redeclare()  # a consumer never got this node's answer (REDECLARE_AFTER_S)
    finally:
        for item in early:
            loop.inbox.put(item)


if __name__ == "__main__":
    main(sys.argv[1:])
