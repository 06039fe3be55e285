"""The run's spec as the coordinator builds it (protocol.RunSpec, coordinator/core.py): the file
its processes read and the prepare request a worker daemon gets are what the coordinator wrote
and sent when it built the spec as a dict: the same record read back, the same bytes sent."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from retriever import Latest, Pipeline, Rate, Trigger
from retriever.backends.zenoh.coordinator import Coordinator
from retriever.backends.zenoh.coordinator.hosting import LocalHosting
from retriever.backends.zenoh.coordinator.spec import main_file, process_groups, python_path, shipped_plan
from retriever.backends.zenoh.protocol import PrepareRequest, RunSpec

from .lifecycle_flows import Counter, Sink, Total


class _Placed(Exception):
    """The hosting wrote the spec: the coordinator stops there, before any process starts."""


class _WrittenHosting(LocalHosting):
    """This machine's hosting, which keeps what it wrote and what the old coordinator's dict
    was made of, then stops the run."""

    def place(self):
        super().place()
        run = self.run
        self.written = (run.run_dir / "spec.json").read_bytes()
        self.spec, self.endpoint, self.hub_zid = run.spec, run.endpoint, str(run.hub.zid())
        self.run_dir, self.access = run.run_dir, run.access
        raise _Placed


def _grouped() -> Pipeline:
    """A chain whose last two flows share a process (the spec's groups)."""
    with Pipeline("spec") as pipe:
        counter = Counter().named("counter") @ Rate(hz=10)
        total = Total().named("total").configure(process="back") @ Trigger("n")
        sink = Sink().named("sink").configure(process="back") @ Rate(hz=5)
        counter.then(total, sync=Latest())
        total.then(sink, sync=Latest())
    return pipe


def _as_the_dict_was(hosting: _WrittenHosting, graph, startup_timeout, virtual_time) -> dict:
    """The spec as coordinator/core.py built it before RunSpec (each value made as it made it)."""
    spec = hosting.spec
    access = hosting.access.to_spec(Path(spec.access["dictionary_file"]))
    assert spec.access == access  # (the one value taken from the new spec: where the dictionary was written)
    return {"ir": graph.to_ir().doc, "namespace": "spec-bytes", "hub": hosting.endpoint, "plan": shipped_plan(graph),
            "python_path": python_path(), "main_file": main_file(graph), "argv": list(sys.argv),
            "spill_dir": str(hosting.run_dir), "access": access, "startup_timeout": startup_timeout,
            "zids": dict(spec.zids), "hub_zid": hosting.hub_zid, "virtual_time": virtual_time,
            "groups": process_groups(graph), "links": True}  # (LocalHosting: same-host links)


@pytest.mark.parametrize("startup_timeout, virtual_time", [(60.0, False), (5, True)])
def test_the_spec_written_and_sent_is_what_the_dict_was(startup_timeout, virtual_time):
    pipe = _grouped()
    graph = pipe.compile()
    hosting = _WrittenHosting()
    with pytest.raises(_Placed):
        Coordinator(graph, hosting=hosting, namespace="spec-bytes", startup_timeout=startup_timeout,
                    virtual_time=virtual_time, quiet=True)
    spec, old = hosting.spec, _as_the_dict_was(hosting, graph, startup_timeout, virtual_time)
    assert old["groups"] == {"back": ["total", "sink"]} and spec.zids["total"] == spec.zids["sink"]
    # the record holds each field as its decoder reads it (tuples, floats), so it is its file's
    assert RunSpec.from_fields(json.loads(hosting.written), "the file") == spec
    # the file: the dict's JSON, but the fields at their default (None, empty), which its reader reads alike
    assert json.loads(hosting.written) == {k: v for k, v in json.loads(json.dumps(old)).items()
                                           if v not in (None, [], {})}
    assert old["main_file"] is None and "main_file" not in json.loads(hosting.written)
    assert RunSpec.from_fields(json.loads(json.dumps(old)), "the dict") == spec
    # the prepare request: byte for byte what the deployment (deploy/) sent, the dict filtered by its keys
    remote = {k: v for k, v in old.items() if k not in ("access", "python_path", "spill_dir", "main_file")}
    before = PrepareRequest(run="r", spec=RunSpec.from_fields(remote, "the run's spec"), nodes=("counter",))
    assert PrepareRequest(run="r", spec=spec.for_remote(), nodes=("counter",)).encode() == before.encode()


def test_a_spec_for_a_remote_worker_leaves_out_what_holds_on_this_machine_only(tmp_path):
    spec = RunSpec(ir={"nodes": [{"id": "cam"}]}, namespace="ns", hub="tcp/10.0.0.2:7447", plan={"nodes": []},
                   python_path=("/src",), main_file="/src/main.py", argv=("main.py",), spill_dir="/dev/shm/run",
                   access={"run_password": "p"}, startup_timeout=60.0, zids={}, hub_zid=None, virtual_time=False)
    remote = spec.for_remote()
    assert remote.to_fields() == {k: v for k, v in spec.to_fields().items()
                                  if k not in ("python_path", "main_file", "spill_dir", "access")}
    path = spec.write_file(tmp_path / "spec.json")
    assert RunSpec.read_file(path) == spec and path.stat().st_mode & 0o777 == 0o600
