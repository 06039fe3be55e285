"""A graph of the conformance suite's flows for ``retriever deploy --virtual-time`` across the
netns lab (test_deploy.py): every clock (Rate, Trigger, Hybrid), the policies (Latest with
staleness, Window, Queue, LatestDistinct, ActionChunking), MISSING and skipped ticks, LET, a
cycle closed by a delay, fan-in. Workers import the flows from the repository (``--path`` its
root); the coordinator loads this file (``retriever deploy tests/deploy/lockstep_flows.py:pipe``)."""

from __future__ import annotations

from retriever import ActionChunking, Hybrid, Latest, LatestDistinct, Pipeline, Queue, Rate, Trigger, Window
from tests.backends.test_conformance import (
    ChunkSource, CycleMonitor, CyclePolicy, EchoOpt, SkipRecorder, Source, WindowQueueRecorder,
)

with Pipeline("lockstep") as pipe:
    cam = Source().named("cam") @ Rate(10, offset=0.25)
    ticker = Source().named("ticker") @ Rate(10)
    once = Source(only=[0]).named("once") @ Rate(10)
    skipper = SkipRecorder().named("skipper") @ Rate(5)
    cam.then(skipper, sync=Latest(), map={"value": "img"})
    ticker.then(skipper, sync=Queue(), map={"value": "q"})
    once.then(skipper, sync=LatestDistinct(), map={"value": "ld"})

    windows = WindowQueueRecorder().named("windows").configure(latency=0.02) @ Rate(3)
    ticker.then(windows, sync=Window(buffer_size=2), map={"value": "win"})
    ticker.then(windows, sync=Queue(maxsize=2), map={"value": "q"})
    ticker.then(windows, sync=Queue(), map={"value": "q_all"})

    chunks = ChunkSource().named("chunks") @ Rate(10)
    ctrl = EchoOpt().named("ctrl") @ Rate(200)
    hybrid = EchoOpt().named("hybrid") @ Hybrid(200, trigger=["x"])
    chunks.then(ctrl, sync=ActionChunking(control_hz=200, chunk_steps=8), map={"chunk": "x"})
    chunks.then(hybrid, sync=ActionChunking(control_hz=200, chunk_steps=8, on_exhausted="missing"), map={"chunk": "x"})

    monitor = CycleMonitor(limit=40).named("monitor") @ Trigger("fb")
    policy = CyclePolicy().named("policy") @ Trigger("skill")
    kick = Source(only=[0]).named("kick") @ Rate(1)
    kick.then(policy, sync=Latest(), map={"value": "skill"})
    monitor.then(policy, sync=Latest())
    policy.then(monitor, sync=Latest(), delay=0.01)
    stale = EchoOpt().named("stale") @ Trigger("x")
    policy.then(stale, sync=Latest(staleness=0.05), map={"fb": "x"})
