"""Which edges of a run are same-host links (worker/links.py, link_plan), as both ends read
them from the same spec."""

from __future__ import annotations

from pathlib import Path

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.worker.links import link_plan
from retriever.plan import plan_ir

from .lifecycle_flows import Counter, Sink, Total
from .specs import run_spec


def _fanned_out() -> Pipeline:
    """counter feeds total in a process of its own and sink in a group's (``back``)."""
    with Pipeline("links") as pipe:
        counter = Counter().named("counter") @ Rate(hz=10)
        total = Total().named("total") @ Trigger("n")
        sink = Sink().named("sink").configure(process="back") @ Rate(hz=5)
        counter.then(total, sync=Latest())
        counter.then(sink, sync=Latest())
    return pipe


def test_a_producer_with_a_groups_consumer_links_the_others_and_puts_each_message_on_zenoh(tmp_path: Path):
    """An edge into a group's process stays on Zenoh: its producer links its other consumers and
    still puts every message on Zenoh (``on_zenoh``), not only while Zenoh's matching status says
    someone listens, which lags the routes (review16b: a restarted group member missed the put
    right after its subscription, a seq gap its stream held open)."""
    ir = _fanned_out().compile().to_ir()
    plan = plan_ir(ir)
    spec = run_spec(ir.doc, "links", links=True, groups={"back": ("sink",)})
    counter = link_plan(spec, plan.nodes["counter"], tmp_path)
    assert counter.consumers == {"total"} and counter.on_zenoh
    assert counter.path == tmp_path / "link-counter.sock"
    total = link_plan(spec, plan.nodes["total"], tmp_path)
    assert set(total.producers) == {"counter"} and total.path is None and not total.on_zenoh
    assert link_plan(spec, plan.nodes["sink"], tmp_path) is None  # a group's process: Zenoh only
    alone = link_plan(run_spec(ir.doc, "links", links=True), plan.nodes["counter"], tmp_path)
    assert alone.consumers == {"total", "sink"} and not alone.on_zenoh  # every consumer linked: watchers only
    assert link_plan(run_spec(ir.doc, "links", links=False), plan.nodes["counter"], tmp_path) is None
