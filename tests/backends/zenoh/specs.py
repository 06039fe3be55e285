"""A run's spec for the tests that build a node's loop by hand (worker/build.py, build_loop)."""

from __future__ import annotations

from retriever.backends.zenoh.protocol import RunSpec
from retriever.ir import IR
from retriever.plan import plan_ir


def run_spec(ir_doc: dict, namespace: str, plan: dict | None = None, **fields) -> RunSpec:
    """The spec of a local run of ``ir_doc`` in ``namespace``, wired as ``plan`` says, by default
    the IR's own plan (the one a coordinator ships: tests/test_plan.py holds the two equal);
    ``fields``: the rest."""
    plan = plan_ir(IR(ir_doc)).to_data() if plan is None else plan
    fields = {"hub": None, "startup_timeout": 60.0, "zids": {}, "hub_zid": None, "virtual_time": False, **fields}
    return RunSpec(ir=ir_doc, plan=plan, namespace=namespace, **fields)
