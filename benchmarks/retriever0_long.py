"""Retriever-0 kept running after its task is done, for a long real-time log (issue 42).

The paper's episode (``agents/retriever0.py:pipe``, the spice in TR) ends the whole run one
second after the plan says ``Done()``: the monitor's ``end_after=1.0``. ``build()`` does not
expose it, so this file builds that same graph, gives the monitor ``end_after=None`` (its own
constructor's "never end the run") in the graph's IR, and rebuilds the pipeline from that IR (as
every worker process of a run does): the one difference in the IR. Nothing else changes: after the task the world
keeps stepping physics at 200 Hz, the cameras render at 10 Hz, the monitor, the skill policy and
the controller keep ticking, so the log grows at the agent's own rate for as long as it runs.

    retriever run benchmarks/retriever0_long.py:pipe --backend zenoh --duration 3600 \
        --keep counters --log /tmp/longlog/r0-3600.mcap
"""

from retriever import Pipeline

from agents.retriever0 import build

_ir = build(drawer="TR").build_ir()
_monitor = [node for node in _ir.nodes if node["type"] == "agents.flows:Monitor"]
assert len(_monitor) == 1, _monitor
_monitor[0]["params"]["end_after"] = None
pipe = Pipeline.from_ir(_ir)
