"""Large arrays on the zenoh backend: they arrive intact, reach the coordinator's trace and log
through the run directory (files it maps and removes), and the log replays. See wire.py (arrays
out of band; test_wire.py checks they are read-only views) and node/reports.py (SPILL_BYTES)."""

from __future__ import annotations

import json
import os

import numpy as np

from retriever import Pipeline, Queue, Rate, Trigger, read_log
from retriever.backends.zenoh.hub import SHM_POOL_MIN
from retriever.backends.zenoh.node import SPILL_BYTES
from retriever.replay import replay

from .payload_flows import (BurstCamera, Camera, Holder, ImageShmWatcher, ShmOfImageTaker, ShmOfScalarTaker, ShmWatcher,
                            Sums, Viewer, frame)

SIZE = 1 << 20  # 1 MiB: well above SPILL_BYTES, so every frame takes the file path


def test_large_frames_arrive_intact_and_are_logged(tmp_path):
    assert SIZE >= 4 * SPILL_BYTES
    with Pipeline("frames", deadline=1.0) as pipe:
        camera = Camera(SIZE).configure(name="camera") @ Rate(hz=10)
        viewer = Viewer().configure(name="viewer") @ Trigger("image")
        camera.then(viewer)
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=1.5, backend="zenoh", quiet=True, log=path)

    session = pipe.session
    assert "garbage" not in pipe.counts(), pipe.counts()
    # its own run directory only: another run on the machine may have one of its own meanwhile
    assert str(session.run_dir).startswith("/dev/shm/") and not os.path.exists(session.run_dir), \
        "the run directory outlived the run"

    def port(events, node, name):  # one event per tick on each port (an @io field), in seq order
        return [e.value for e in sorted(events, key=lambda e: e.seq) if e.node == node and e.port == name]

    images = port(trace.events, "camera", "image")
    assert len(images) == 15
    for k, image in enumerate(images, 1):  # the coordinator's copy of each frame, from the mapped file
        assert image.shape == (SIZE // 1024, 1024) and np.array_equal(image.reshape(-1), frame(k, SIZE)), k
    assert port(trace.events, "viewer", "k") == list(range(1, 16))
    assert port(trace.events, "viewer", "checksum") == [int(frame(k, SIZE).sum(dtype=np.uint64)) for k in range(1, 16)]

    log = read_log(path)
    logged = [log.value(e) for e in sorted(log.iter_events(), key=lambda e: e.seq)
              if e.node == "camera" and e.port == "image"]
    assert len(logged) == 15 and all(np.array_equal(a, b) for a, b in zip(logged, images))
    report = replay(log)
    assert report.identical, report.divergences[:3]


def test_bursts_of_frames_arrive_in_order_are_logged_and_replay(tmp_path):
    """A burst is one message, however big (past SPILL_BYTES it reaches the coordinator as a
    file): every frame arrives, in seq order, the coordinator logs each as its own event, and
    the log replays."""
    size = SPILL_BYTES // 2  # two or more frames make a message that spills
    with Pipeline("bursts", deadline=1.0) as pipe:
        camera = BurstCamera(size).configure(name="camera") @ Rate(hz=10)
        sums = Sums().configure(name="sums") @ Trigger("image")
        camera.then(sums, sync=Queue(), map={"image": "image"})
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=0.65, backend="zenoh", quiet=True, log=path)
    assert "garbage" not in pipe.counts(), pipe.counts()
    n = sum(range(1, 8))  # ticks at 0, 100, …, 600 ms
    images = sorted(trace.events_of("camera", "image"), key=lambda e: e.seq)
    assert [e.seq for e in images] == list(range(n))
    assert all(np.array_equal(e.value, frame(e.seq, size)) for e in images)
    assert [e.value for e in sorted(trace.events_of("camera", "k"), key=lambda e: e.seq)] == list(range(n))
    sums_seen = [x for e in sorted(trace.events_of("sums", "sums"), key=lambda e: e.seq) for x in e.value]
    assert sums_seen == [int(frame(i, size).sum(dtype=np.uint64)) for i in range(n)]
    log = read_log(path)
    logged = sorted((e for e in log.iter_events() if e.node == "camera" and e.port == "image"), key=lambda e: e.seq)
    assert [e.seq for e in logged] == list(range(n)) and len({e.tag for e in logged[1:3]}) == 1  # one burst, one tag
    report = replay(log)
    assert report.identical, report.divergences[:3]


def test_each_worker_has_its_shared_memory_pool_before_t0():
    """Zenoh creates a session's shared-memory pool on its first big message, writing all of it
    (130 ms for 128 MiB here): a worker makes that happen before it says ``ready``, with a padded
    question to each consumer (worker/starts.py, POOL_PADDING), so no tick pays for it. The first step of a
    flow that has sent nothing yet finds the pool mapped."""
    with Pipeline("pool") as pipe:
        watcher = ImageShmWatcher().configure(name="watcher") @ Rate(hz=10)
        watcher.then(ShmOfImageTaker().configure(name="taker") @ Trigger("image"))
    trace = pipe.run(duration=0.25, backend="zenoh", quiet=True, same_host_links=False)  # (Zenoh's pools)
    first = min(trace.events_of("watcher", "zenoh_shm"), key=lambda e: e.seq)
    assert first.value >= SHM_POOL_MIN, f"no Zenoh pool mapped at the first step: biggest segment {first.value} B"


def test_only_a_node_whose_edges_may_carry_big_values_has_shared_memory():
    """Zenoh's shared memory costs a process 20 wake-ups a second once one of its links uses it
    (hub.needs_shared_memory), and serves messages over 3 KiB only: a node with no edge, or
    whose connected ports are all of scalar types, opens its session without it. A node with an
    array or untyped port on an edge keeps it, and has a pool if it has a consumer (a pool of its
    own serves what it sends)."""
    with Pipeline("pool_where_needed") as pipe:
        ShmWatcher().configure(name="alone") @ Rate(hz=10)
        images = ImageShmWatcher().configure(name="images") @ Rate(hz=10)
        images.then(ShmOfImageTaker().configure(name="image_taker") @ Trigger("image"))
        images.then(ShmOfScalarTaker().configure(name="scalar_taker") @ Trigger("zenoh_shm"))
    ir = {n["id"]: n for n in json.loads(pipe.build_ir().to_json())["nodes"]}
    assert ir["scalar_taker"]["inputs"] == {"zenoh_shm": "int"}, ir["scalar_taker"]  # what the test stands on
    trace = pipe.run(duration=0.25, backend="zenoh", quiet=True, same_host_links=False)  # (Zenoh's pools)
    biggest = {node: max(trace.values_of(node, "zenoh_shm"))
               for node in ("alone", "images", "image_taker", "scalar_taker")}
    assert biggest["images"] >= SHM_POOL_MIN, biggest
    # its session's own segment, and no pool: it sends to no one (and got only small images)
    assert 0 < biggest["image_taker"] < SHM_POOL_MIN, biggest
    assert biggest["alone"] == 0 and biggest["scalar_taker"] == 0, biggest

    # over same-host links (the default), every edge of these nodes is a link: no session has
    # shared memory, none makes a pool (worker/links.py, all_linked)
    pipe.reset()
    trace = pipe.run(duration=0.25, backend="zenoh", quiet=True)
    assert pipe.session.hosted.spec.links
    biggest = {node: max(trace.values_of(node, "zenoh_shm"))
               for node in ("alone", "images", "image_taker", "scalar_taker")}
    assert biggest == dict.fromkeys(biggest, 0), biggest


def test_a_worker_rebuilds_its_flow_with_the_arguments_as_given():
    """Tuples, arrays and numpy scalars pass through the IR tagged (ir.param_to_ir), so the flow
    in its worker gets what the flow in-process gets: not a list for a tuple."""
    value = ((640, 480), np.eye(2, dtype=np.float32), np.int16(3), [1, (2,)])
    with Pipeline("arguments") as pipe:
        Holder(value).configure(name="holder") @ Rate(hz=10)
    (first, *_) = pipe.run(duration=0.3, backend="zenoh", quiet=True).values_of("holder", "dict")  # one output port, named by its type
    assert first["types"] == ["tuple", "ndarray", "int16", "list"], first
    assert first["value"][0] == (640, 480) and first["value"][3] == [1, (2,)]
    assert np.array_equal(first["value"][1], np.eye(2)) and first["value"][1].dtype == np.float32
