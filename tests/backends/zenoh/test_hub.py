"""The hub over real Zenoh sessions in separate processes: endpoints, and garbage on the key space.

A client process joins the hub, handshakes, then puts valid data messages and garbage on the
run's data keys; the hub side decodes each with the wire decoder. Garbage must come out as
WireError, one per message, and the valid messages around it must arrive intact.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import weakref
from pathlib import Path

import zenoh

from retriever.backends.zenoh.hub import (
    SHM_POOL_MAX,
    SHM_POOL_MIN,
    SHM_POOL_RUN_MAX,
    SHM_POOL_SHARE,
    endpoint,
    free_port,
    needs_shared_memory,
    new_zid,
    open_hub,
    open_peer,
    peer_config,
    port_is_free,
    shm_pool_bytes,
    wait_for_links,
    weak_callback,
)
from retriever.backends.zenoh.wire import KeySpace, WireError, decode_data

CLIENT = r"""
import sys, time
import zenoh
from retriever.backends.zenoh.hub import open_peer
from retriever.backends.zenoh.wire import KeySpace, WireEncoder

keys, enc = KeySpace("hubtest"), WireEncoder()
acked = []
with open_peer(sys.argv[1]) as s:
    sub = s.declare_subscriber(keys.status("ack"), lambda sample: acked.append(1))
    deadline = time.monotonic() + 20  # bound only: the hub acks as soon as it hears us
    seq = 0
    while not acked:
        assert time.monotonic() < deadline, "no ack from the hub"
        s.put(keys.data("client", "hello"), enc.data((seq, 0), seq, (seq, 0), "client", "hello", seq))
        seq += 1
        time.sleep(0.05)
    for garbage in (b"", b"not msgpack at all", b"\x93\x01\x02\x03"):
        s.put(keys.data("client", "x"), garbage)
    s.put(keys.data("client", "x"), enc.data((7, 1), 0, (7, 1), "client", "x", {"ok": [1.5]}))
    sub.undeclare()
"""


def test_hub_leaves_zenohs_port_to_the_machines_router_and_takes_a_port_it_is_asked_for():
    """7447 is Zenoh's port: rmw_zenoh's router (which a ROS 2 flow joins there) and a worker
    daemon listen on it. A local run's hub took it whenever it was free (and then a ROS flow of
    that run linked to its own hub, and rmw_zenohd could not start)."""
    hub, at = open_hub()
    with hub:
        assert at != "tcp/127.0.0.1:7447" and at.startswith("tcp/127.0.0.1:")
        wanted = free_port()
        asked, asked_at = open_hub(wanted)
        with asked:
            assert asked_at == f"tcp/127.0.0.1:{wanted}"
            again, again_at = open_hub(wanted)  # taken now: another free one
            with again:
                assert again_at not in (asked_at, at) and again_at.startswith("tcp/127.0.0.1:")


def test_hub_port_0_means_any_free_port_and_says_which():
    """hub_port=0: the hub listened on a port the OS chose and announced port 0, which workers
    then could not reach (the run failed at its startup timeout)."""
    hub, at = open_hub(0)
    with hub:
        port = int(at.rsplit(":", 1)[1])
        assert port != 0 and not port_is_free(port)
        with open_peer(at) as peer:
            assert wait_for_links(peer, {str(hub.zid())}, timeout=30) == set()


def test_a_port_whose_last_connection_is_in_time_wait_is_free():
    """The hub of the run before closed its connections first: their side waits in TIME_WAIT on
    the hub's port for a minute. The next run's hub must still get that port."""
    with socket.socket() as listener:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", 0))
        port = listener.getsockname()[1]
        listener.listen()
        client = socket.create_connection(("127.0.0.1", port))
        conn, _ = listener.accept()
        conn.close()  # the listening side closes first: its end of the connection goes to TIME_WAIT
        client.close()
    assert port_is_free(port)
    hub, at = open_hub(port)
    with hub:
        assert at == f"tcp/127.0.0.1:{port}"

def test_garbage_from_another_process_is_refused_and_valid_messages_arrive(tmp_path):
    keys = KeySpace("hubtest")
    good, bad, done = [], [], threading.Event()
    hub, where = open_hub()
    with hub:
        def on_data(stream, sample):  # as a node takes its inputs: one subscriber per (producer, port)
            try:
                msg = decode_data(sample.payload.to_bytes(), stream)
            except WireError as e:
                bad.append(str(e))
                return
            good.append(msg)
            if msg.port == "hello" and len(good) == 1:
                hub.put(keys.status("ack"), b"")
            if msg.port == "x":
                done.set()

        subs = [hub.declare_subscriber(keys.data(*stream), lambda sample, k=stream: on_data(k, sample))
                for stream in (("client", "hello"), ("client", "x"))]
        client = subprocess.Popen([sys.executable, "-c", CLIENT, where], cwd=Path(__file__).resolve().parents[3],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert done.wait(60), "the final valid message never arrived"
            _, err = client.communicate(timeout=60)
        finally:
            if client.poll() is None:
                client.kill()
                client.wait()
        for sub in subs:
            sub.undeclare()
    assert client.returncode == 0, err
    assert len(bad) == 3, bad
    assert any("msgpack array of bins" in b for b in bad) and any("truncated" in b for b in bad)
    last = good[-1]
    assert (last.producer, last.port, last.tag, last.value) == ("client", "x", (7, 1), {"ok": [1.5]})


def test_the_shared_memory_pool_grows_with_what_dev_shm_has_free():
    """Big messages between local peers go through Zenoh's shared-memory pool only if they fit
    (hub.SHM_POOL_MAX); the pool never takes much of a small /dev/shm (Docker: 64 MB)."""
    assert shm_pool_bytes(0) == SHM_POOL_MIN, "no /dev/shm: Zenoh's default"
    assert shm_pool_bytes(64 * 10**6) == SHM_POOL_MIN
    assert shm_pool_bytes(SHM_POOL_SHARE * (48 << 20)) == 48 << 20
    assert shm_pool_bytes(12 << 30) == SHM_POOL_MAX
    optimization = json.loads(peer_config().get_json("transport/shared_memory/transport_optimization"))
    assert optimization["enabled"] and optimization["pool_size"] == shm_pool_bytes()


def test_the_processes_of_a_run_share_one_shared_memory_budget():
    """Every worker with a pool writes all of it: 50 flows at SHM_POOL_MAX each wrote 6.4 GB
    while they started, and some never received the run's start. A run's pools together stay
    within SHM_POOL_RUN_MAX (and the share of /dev/shm), each at least Zenoh's default."""
    free = 24 << 30  # this machine's /dev/shm
    assert shm_pool_bytes(free, sessions=3) == SHM_POOL_MAX, "a small run keeps the biggest pool"
    for sessions in (11, 26, 51):
        assert sessions * shm_pool_bytes(free, sessions=sessions) <= SHM_POOL_RUN_MAX
    assert shm_pool_bytes(free, sessions=101) == SHM_POOL_MIN
    assert shm_pool_bytes(SHM_POOL_SHARE * (480 << 20), sessions=10) == 48 << 20, "the /dev/shm share is split too"
    optimization = json.loads(peer_config(sessions=51).get_json("transport/shared_memory/transport_optimization"))
    assert optimization["pool_size"] == shm_pool_bytes(sessions=51)


RUNS = r"""
import json, sys
from retriever import Pipeline, Rate, Trigger
from retriever.backends.zenoh.hub import mapped_segments
from tests.backends.zenoh.payload_flows import Camera, SegmentsTaker

def rss_shmem_kb():
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("RssShmem:"))

with Pipeline("run_after_run") as pipe:
    camera = Camera(64 * 64 * 3).configure(name="camera") @ Rate(hz=50)
    camera.then(SegmentsTaker().configure(name="taker") @ Trigger("image"))
for _ in range(int(sys.argv[1])):
    # on Zenoh (same_host_links=False): the frames go through Zenoh's pools (over a same-host link
    # the camera's session has no shared memory at all)
    trace = pipe.run(duration=0.1, backend="zenoh", quiet=True, same_host_links=False)
    run_dir = str(pipe.session.run_dir)
    pipe.reset()
    taker = {path: size for segments in trace.values_of("taker", "segments") for path, size in segments}
    print(json.dumps({"rss_shmem_kb": rss_shmem_kb(), "mapped": sorted(mapped_segments()), "taker": taker,
                      "run_dir": run_dir}), flush=True)
"""


def test_a_process_that_starts_run_after_run_keeps_none_of_their_shared_memory():
    """Zenoh keeps every shared-memory segment a process attached until the process exits
    (hub.HUB_SHARED_MEMORY). With a hub that had shared memory, each run of this pipeline (64×64×3
    frames) left the workers' pools mapped in the process that started it, 258 MiB of RAM a run:
    a notebook, a gymnasium loop or a service that starts runs would run out of memory. In a
    process of its own, 20 runs one after another: its shared memory stays flat, and /dev/shm
    keeps none of the runs' segments or folders once it has exited."""
    runs = 20
    proc = subprocess.run([sys.executable, "-c", RUNS, str(runs)], cwd=Path(__file__).resolve().parents[3],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    reports = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(reports) == runs, proc.stdout
    shmem = [r["rss_shmem_kb"] for r in reports]
    assert max(shmem[1:]) - shmem[1] <= 2048, shmem  # never 2 MiB more than after the second run
    mapped = [len(r["mapped"]) for r in reports]
    assert max(mapped[1:]) <= mapped[1], mapped
    # what that stands on: the frames went through the camera's pool (a camera late by more than
    # the run, on a loaded machine, may have sent none)
    stepped = [r["taker"] for r in reports if r["taker"]]
    assert len(stepped) >= runs - 3 and all(max(t.values()) >= SHM_POOL_MIN for t in stepped), stepped
    left = [path for r in reports for path in [*r["taker"], r["run_dir"]] if os.path.exists(path)]
    assert not left, left


def _ir(ports: dict[str, str], *, edge: str | None = "x", other: str = "numpy.ndarray") -> dict:
    """An IR of a node ``n`` whose input ``x`` has the type ``ports["x"]``, fed by ``src`` (whose
    output has the type ``other``) when ``edge`` names it; and an edge between two other nodes."""
    nodes = [{"id": "n", "inputs": ports, "outputs": {}}, {"id": "src", "inputs": {}, "outputs": {"x": other}},
             {"id": "a", "inputs": {}, "outputs": {"y": "Any"}}, {"id": "b", "inputs": {"y": "Any"}, "outputs": {}}]
    edges = [{"source": {"node": "a", "port": "y"}, "destination": {"node": "b", "port": "y"}}]
    if edge is not None:
        edges.append({"source": {"node": "src", "port": "x"}, "destination": {"node": "n", "port": edge}})
    return {"nodes": nodes, "edges": edges}


def test_a_node_has_shared_memory_unless_its_connected_ports_are_all_scalars():
    """(hub.needs_shared_memory says what shared memory costs a process that does not need it)"""
    for small in ("float", "int", "bool", "None", "int | None", "Optional[float]", "Union[int, float]"):
        assert not needs_shared_memory(_ir({"x": small}), "n"), small
    for big in ("numpy.ndarray", "Any", "str", "bytes", "list[float]", "numpy.ndarray | None", "dict", "",
                "float | numpy.ndarray", "tuple[int, int]", "Optional", "Union", "Optional[]", "Union[,]",
                "Optional[Any]", "list[Optional[int]]"):
        assert needs_shared_memory(_ir({"x": big}), "n"), big
    assert not needs_shared_memory(_ir({"x": "numpy.ndarray"}, edge=None), "n"), "no edge: an unconnected port"
    assert needs_shared_memory(_ir({"x": "float"}), "src"), "the producer's own port type decides for it"
    assert not needs_shared_memory(_ir({"x": "float"}, other="float"), "src")
    assert needs_shared_memory(_ir({"x": "float"}), "a"), "an untyped port"


def test_an_ir_it_cannot_read_keeps_shared_memory_on():
    """Zenoh's default, whatever is wrong: the worker refuses a bad IR elsewhere, with its own
    message; choosing a transport option must not be where it fails."""
    bad = [None, {}, {"nodes": [], "edges": []}, {"nodes": [{"id": "n"}], "edges": [1]},
           _ir({"x": 3}), _ir({}), {"nodes": "n", "edges": 1},
           {**_ir({"x": "float"}), "edges": [{"source": None, "destination": {"node": "n", "port": "x"}}]}]
    for ir in bad:
        assert needs_shared_memory(ir, "n"), ir
    assert json.loads(peer_config(shared_memory=False).get_json("transport/shared_memory/enabled")) is False
    assert json.loads(peer_config().get_json("transport/shared_memory/enabled")) is True


def test_a_worker_that_missed_the_start_asks_the_coordinator_for_it():
    """A ``start`` put can be missed (seen at 50 flows): a worker that said ready asks the
    coordinator's ``ctl/start`` queryable every START_ASK_S until it has the start, which joins
    its inbox like the put would have; other messages that came meanwhile stay for the loop. An
    answer the coordinator did not seal for the worker's process (an insider's) is garbage."""
    import queue
    from collections import Counter

    from retriever.backends.zenoh.node import DATA
    from retriever.backends.zenoh.origin import new_key
    from retriever.backends.zenoh.protocol import ControlOpener, ControlSigner, Start
    from retriever.backends.zenoh.worker.waits import ask_start, await_control

    keys = KeySpace("missed-start")
    hub, at = open_hub(free_port())
    asked = []
    key, signer = new_key(), ControlSigner()
    signer.add(key, key)

    def answer(query) -> None:
        asked.append(1)
        start = Start(t0=123, end=456, values=True).encode()
        if len(asked) == 2:  # an insider's answer, unsealed
            query.reply(keys.start(), Start(t0=1, end=2, values=True).encode())
        elif len(asked) >= 3:  # the coordinator has no start before the run's: no reply the first time
            nonce = None if query.attachment is None else query.attachment.to_bytes()
            query.reply(keys.start(), start, attachment=signer.seal_reply(keys.start(), start, nonce))

    class Inbox:  # the part of a NodeLoop that await_control uses
        inbox: queue.SimpleQueue = queue.SimpleQueue()
        counts: Counter = Counter()
        opener = ControlOpener(key)

    loop = Inbox()
    data = (DATA, ("a", "b"), b"early")
    loop.inbox.put(data)
    with hub:
        queryable = hub.declare_queryable(keys.start(), answer)
        with open_peer(at) as worker:
            start = await_control(loop, Start, "n", ask=lambda: ask_start(worker, keys, loop))
        queryable.undeclare()
    assert start == Start(t0=123, end=456, values=True)
    assert len(asked) >= 3
    assert loop.counts["garbage"] == 1, "the unsealed answer was refused"
    left = []
    while not loop.inbox.empty():
        left.append(loop.inbox.get_nowait())
    assert left == [data]


def test_a_session_given_a_new_zid_has_it_and_a_peer_waits_for_a_link_to_it_by_that_id():
    zids = {new_zid() for _ in range(200)}
    assert len(zids) == 200 and all(len(z) == 32 and z[0] != "0" and int(z, 16) for z in zids)
    port = free_port()
    mine, theirs, never = new_zid(), new_zid(), new_zid()
    with zenoh.open(peer_config(listen=[endpoint(port)], zid=mine)) as listener:
        assert str(listener.zid()) == mine  # as str(zid) spells it: the others compare by that
        with open_peer(endpoint(port), zid=theirs) as joiner:
            assert wait_for_links(listener, {theirs}, timeout=30.0) == set()
            assert wait_for_links(joiner, {mine}, timeout=30.0) == set()
            # one that never comes: named, once the bound is out
            assert wait_for_links(joiner, {mine, never}, timeout=0.2) == {never}


class Listener:
    def __init__(self):
        self.heard = []

    def hear(self, *args):
        self.heard.append(args)


def test_a_weak_callback_calls_its_method_while_its_object_lives_and_does_not_keep_it():
    listener = Listener()
    callback = weak_callback(listener.hear, "run-1")
    callback("sample")
    assert listener.heard == [("run-1", "sample")]
    alive = weakref.ref(listener)
    del listener
    assert alive() is None, "the callback (which Zenoh may keep) holds its object"
    callback("late")  # what comes after is dropped
