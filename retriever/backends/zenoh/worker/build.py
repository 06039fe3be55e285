"""A worker's node rebuilt from the run's spec: the flow, its loop wired as the run's plan says,
the process's session, and the statuses it signs.

    open_session    the Zenoh peer (or a client of the deployment's routers)
    build           the flow rebuilt from the IR (build_loop), its events on the transport a Launch names
    set_up_flow     the flow's setup(), once, before the process says ready
    restart_in_place  a group's member with on_error="restart": its fresh flows (node/in_place.py)
"""

from __future__ import annotations

import importlib.util
import os
import sys
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from ....errors import StopRun
from ....flow.core import Flow, set_up
from ....graph import compile_graph
from ....ir import DEFAULT_DEADLINE, IR
from ....plan import NodePlan, Plan, bind_inputs
from ....rebuild import rebuild_node
from ....sync import PortBuffer
from ....tick import RestartBudget
from .. import protocol
from ..access import RunAccess, TlsFiles
from ..command import StartMode
from ..hub import client_config, open_peer
from ..node import InEdge, NodeLoop
from ..node.in_place import InPlaceRestart
from ..node.linked import LinkedTransport
from ..origin import sign
from ..protocol import RunSpec
from ..wire import RELIABLE, KeySpace
from .process import Launch
from .links import link_plan

#: the flows this process served, held until it ends: what a flow holds (a model, a device) is
#: finalized once, as the interpreter ends; the session its loop held is let go of
_kept_to_the_end: list = []


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


def node_plan(spec: RunSpec, node_id: str, ir: IR | None = None) -> NodePlan:
    """``node_id``'s wiring as the run's plan says (:func:`run_plan`)."""
    return run_plan(spec, ir)[node_id]


def run_plan(spec: RunSpec, ir: IR | None = None) -> dict[str, NodePlan]:
    """Every node's wiring as the run's plan says (``ir``: the spec's IR, if the caller has read
    it already)."""
    if ir is None:
        ir = IR(spec.ir, source="the run's IR")
    return Plan.from_data(spec.plan, ir).nodes


def build_loop(spec: RunSpec, node_id: str, session, transport=None, plan: NodePlan | None = None,
               ir: IR | None = None):
    """Rebuild ``node_id`` from the IR in ``spec`` and wire its inputs as ``plan`` says (default:
    :func:`node_plan`'s): a ready NodeLoop, its events through ``transport`` (a dora node's), or
    on ``session`` when None. ``ir``: the spec's IR, if the caller has read it already (a group
    reads it once for all its members: checking it is linear in the run's size)."""
    if ir is None:
        ir = IR(spec.ir, source="the run's IR")
    meta = ir.doc["metadata"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        graph = compile_graph(ir.name, [rebuild_flow(spec, node_id, ir)], [], meta.get("max_microsteps", 1000),
                              meta.get("realtime", "soft"), meta.get("deadline", DEFAULT_DEADLINE))
    node = graph.nodes[node_id]
    if plan is None:
        plan = node_plan(spec, node_id, ir)
    inputs, fallbacks = bind_inputs(plan, node.inputs, lambda: PortBuffer(trim_batch=1))
    buffers = {port: buf for port, buf, _, _ in inputs}
    edges = [InEdge(f.src, f.src_port, f.port, buffers[f.port], f.delay_ns, f.triggers, f.deadline_ns,
                    f.src_latency_ns) for f in plan.feeds]
    return NodeLoop(session, KeySpace(spec.namespace), node, edges, inputs, fallbacks,
                    realtime=meta.get("realtime", "soft"),
                    ports=sorted(ir.node(node_id)["outputs"]),
                    consumed=bool(plan.consumers),
                    spill_dir=spec.spill_dir if os.path.isdir(spec.spill_dir or "") else None,
                    # a flow with a setup() may hold what belongs to one thread (an OpenGL/EGL or
                    # CUDA context, a device handle): it steps on the thread that set it up
                    inline=not plan.on_a_cycle and type(node.flow).setup is Flow.setup,
                    cycle=plan.cycle, instant_ports=plan.instant_ports,
                    max_microsteps=meta.get("max_microsteps", 1000), virtual=spec.virtual_time,
                    transport=transport)


def rebuild_flow(spec: RunSpec, node_id: str, ir: IR) -> Flow:
    """``node_id``'s flow rebuilt from ``ir`` (the spec's), in its initial state: what a new
    process of the node steps first (and a restart in place: worker/group.py)."""
    flows: dict = {}
    problems: list[str] = []
    node_doc = dict(ir.node(node_id))
    if spec.main_file and node_doc.get("rebuild_needs_main"):
        node_doc["rebuildable"] = True  # _import_main made __main__ importable here
    rebuild_node(node_doc, flows, problems)
    if problems:
        raise RuntimeError("; ".join(problems))
    flow = flows[node_id]
    if type(flow).reset is not Flow.reset:
        flow.reset()  # the paper's flows initialise their state in reset()
    return flow


class StatusSender:
    """Puts this node's statuses on ``status/node/<node>``: each with this process's pid, and
    signed with its key. Called on the main thread, or a receiving one (on_restart)."""

    def __init__(self, session, keys, node: str, key: bytes | None):
        self.session, self.keys, self.node, self.key = session, keys, node, key

    def __call__(self, kind: type[protocol.Status], **fields) -> None:
        """Say a status of ``kind`` (a record of protocol.STATUS) with ``fields``, this node's and pid."""
        key, payload = self.keys.node_status(self.node), kind(node=self.node, pid=os.getpid(), **fields).encode()
        self.session.put(key, payload, congestion_control=RELIABLE,
                         attachment=sign(self.key, key, payload) if self.key is not None else None)


@dataclass
class Serving:
    """What the phases of serving one node share."""

    launch: Launch
    spec: RunSpec
    session: object
    keys: object  # wire.KeySpace
    status: StatusSender
    #: the questions that make this session's shared-memory pool before T0 (POOL_PADDING); None:
    #: the node has no pool to make
    padding: bytes | None
    #: the /dev/shm segments of that pool, once made (let_go_of)
    pool: set[str]
    #: the node's wiring (node_plan): its loop's, and whose answers and links it waits for
    plan: NodePlan | None = None
    #: the run's IR, read once (a group's, for all its members: build_loop); None: read here
    ir: IR | None = None
    #: ``(session, node) -> Transport``, winning over the launch's (a group's member: worker/group.py)
    transport: Callable | None = None
    loop: NodeLoop | None = None

    @property
    def node(self) -> str:
        return self.launch.node

    def waiting(self) -> Callable[[], bool]:
        return lambda: self.loop.stopping


def open_session(spec: RunSpec, node: str, mode: StartMode, shared_memory: bool):
    """This process's Zenoh session (close it: ``with``): a peer joined to the run's hub, or,
    where the spec names routers (a deployment joined through them: ``router``), a client of
    those. A deployment started --insecure has no access entry: anyone on its network may
    join; a TLS one's links use its files. The first process of a node has the session id the
    others expect (a restarted one, whose old process may still be linked, has its own: it
    finds its neighbours by their answers)."""
    config = RunAccess.from_spec(spec.access) if spec.access else None
    tls = TlsFiles(**spec.tls).session_config() if spec.tls else {}
    zid = spec.zids.get(node) if mode.kind is None else None
    # the run's sessions with a pool, which share its shared memory (hub.shm_pool_bytes): one per
    # worker (the hub has none, hub.HUB_SHARED_MEMORY)
    sessions = len(spec.ir["nodes"])
    if spec.router:
        access = {**(config[0].client_config(spec.namespace) if config else {}), **tls}
        return zenoh.open(client_config(connect=list(spec.router), sessions=sessions, access=access or None,
                                        lease=spec.lease, zid=zid, blocked_put=spec.blocked_put,
                                        shared_memory=shared_memory))
    access = {**(config[0].session_config(config[1]) if config else {}), **tls}
    return open_peer(spec.hub, sessions=sessions, access=access or None,
                     listen=list(spec.listen) or None, lease=spec.lease, zid=zid,
                     blocked_put=spec.blocked_put, shared_memory=shared_memory)


def build(w: Serving) -> bool:
    """The node's flow, rebuilt from the IR, in its loop (``w.loop``); False when it cannot be
    built (the status ``failed`` said why)."""
    try:
        if w.spec.main_file:
            _import_main(w.spec.main_file)
        if w.plan is None:  # (a group's members come with theirs: the run's plan decoded once)
            w.plan = node_plan(w.spec, w.node)
        make_transport = w.transport or w.launch.transport
        transport = make_transport(w.session, w.node) if make_transport is not None else None
        if transport is None:
            links = link_plan(w.spec, w.plan, w.launch.run_dir)
            if links is not None:  # (its edges to processes of this host over links: node/linked.py)
                transport = LinkedTransport(w.session, w.keys, w.node, links)
        w.loop = build_loop(w.spec, w.node, w.session, transport=transport, plan=w.plan, ir=w.ir)
        w.loop.reporter.key = w.launch.key
        w.loop.opener = protocol.ControlOpener(w.launch.key)
        _kept_to_the_end.append(w.loop.flow)
    except BaseException as exc:
        w.status(protocol.Failed, error=f"cannot build node '{w.node}': {type(exc).__name__}: {exc}",
                 traceback=traceback.format_exc())
        return False
    return True


def set_up_flow(w: Serving) -> bool:
    """The flow's heavy work (weights, devices), once, here, before this process says ready;
    then the loop's statuses hooked up. False when setup() raised (said)."""
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


def restart_in_place(w: Serving, ir: IR) -> None:
    """Restart the flow of ``w`` where it runs if it has ``on_error="restart"`` (a group's member,
    whose process must not end with it: node/in_place.py), within its budget, held by its loop:
    each fresh flow is rebuilt from ``ir`` and set up here, as a new process would."""
    settings = w.loop.node.settings
    if settings.on_error != "restart":
        return

    def fresh() -> Flow:
        try:  # its constructor or reset() raising is the flow's failure, not a crash of the group's process
            flow = rebuild_flow(w.spec, w.node, ir)
        except Exception as exc:
            raise StopRun(f"{w.node}: its fresh flow could not be made: {type(exc).__name__}: {exc}, as the flow "
                          "restarted after its step failed") from exc
        try:
            set_up(flow)
        except Exception as exc:
            raise StopRun(f"{w.node}.setup() raised {type(exc).__name__}: {exc}, as the flow restarted after its "
                          "step failed") from exc
        # kept in the old one's place (still the loop's, torn down), which goes: not one more
        # model held per restart until the process ends (the first stays its loop's Node's)
        old = w.loop.flow
        _kept_to_the_end[:] = [f for f in _kept_to_the_end if f is not old] + [flow]
        return flow

    w.loop.in_place = InPlaceRestart(RestartBudget(settings.max_restarts, settings.restart_window), fresh)
