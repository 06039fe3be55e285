"""A deployment's log says which worker ran each node, and where a node went when its worker was
lost (issue 38): ``RunLog.deployment`` and ``retriever log info``, on logs the writer makes with
the metadata and fault records a deployment's coordinator gives it."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import pytest

from retriever import read_log
from retriever.backends.zenoh.daemon import DaemonInfo
from retriever.backends.zenoh.deploy import Deployment
from retriever.backends.zenoh.protocol import PROTOCOL_VERSION, InfoReply
from retriever.log.deployment import Move, Span
from retriever.log.writer import LogFile, LogWriter
from tests.log.helpers import assert_cli_error, cli
from tests.log.log_flows import build_small

S = 1_000_000_000
PLACED = {"counter": "arm-pc", "accumulate": "gpu-box", "tally": "arm-pc"}
WORKERS = {"arm-pc": {"host": "arm", "pid": 41, "labels": ["arm", "camera"]},
           "gpu-box": {"host": "gpu", "pid": 42, "labels": ["gpu"]},
           "spare": {"host": "coord", "pid": 43, "labels": []}}


def moved(node: str, lost: str, to: str, at_ns: int) -> dict:
    """The fault record of a node that started afresh on ``to`` after its worker ``lost`` was
    (deploy.py's start_afresh, as the coordinator's record_fault completes it)."""
    return {"kind": "process_lost", "node": node, "at_ns": at_ns, "pid": 7,
            "exit": f"was lost with its worker '{lost}'", "moved_to": to, "restarted": True,
            "seqs": {"summary": 1_000_000}, "lost_events": []}


def deployment_log(path: Path, faults: list[dict], placed: dict = PLACED) -> Path:
    """A log of build_small's graph, written as a deployment's run writes it: the run record with
    the coordinator's own ``deployment`` metadata, then each fault."""
    pipe = build_small()
    daemons = {name: DaemonInfo(name, InfoReply(protocol=PROTOCOL_VERSION, name=name, labels=tuple(info["labels"]),
                                                host=info["host"], pid=info["pid"], python="3.12", packages={},
                                                clock_ns=0, nodes=(), counts={}), None, None)
               for name, info in WORKERS.items()}
    hosting = SimpleNamespace(run=SimpleNamespace(namespace="lab"), placed=placed, daemons=daemons, ran_other_code={})
    writer = LogWriter(LogFile(path), pipe.compile(), backend="zenoh", extra=Deployment.log_metadata(hosting))
    for fault in faults:
        writer.add_fault(fault)
    writer.close(pipe.trace, 4 * S)
    return path


def info_lines(result) -> dict[str, list[str]]:
    """``log info``'s ``key  value`` lines, the values of each key in order."""
    assert result.returncode == 0, result.stderr
    found: dict[str, list[str]] = {}
    for line in result.stdout.splitlines():
        if m := re.match(r"^ *(\w[\w ]*?)  (\S.*)$", line):
            found.setdefault(m[1], []).append(m[2])
    return found


def test_a_deployments_log_reads_back_where_each_node_ran_and_its_moves(tmp_path):
    log = read_log(deployment_log(tmp_path / "run.mcap", [moved("accumulate", "gpu-box", "spare", 2 * S)]))
    deployment = log.deployment
    assert deployment.namespace == "lab" and deployment.placed == PLACED
    assert deployment.moves == (Move("accumulate", "gpu-box", "spare", 2 * S),)
    assert deployment.spans_on("gpu-box") == [Span("accumulate", "gpu-box", None, 2 * S)]
    assert deployment.spans_on("spare") == [Span("accumulate", "spare", 2 * S, None)]
    assert deployment.spans_on("arm-pc") == [Span("counter", "arm-pc", None, None), Span("tally", "arm-pc", None, None)]


def test_log_info_of_a_deployment_shows_its_workers_the_nodes_each_ran_and_each_move(tmp_path):
    """The deployment's namespace, a line per worker (what it said of itself, the nodes it ran,
    with when for one that moved), and a ``moved`` line per move beside its ``fault`` line."""
    path = deployment_log(tmp_path / "run.mcap", [moved("accumulate", "gpu-box", "spare", 2 * S)])
    lines = info_lines(cli("log", "info", path))
    assert lines["deployment"] == ["namespace 'lab', 3 worker(s)"]
    assert lines["worker"] == ["arm-pc (host arm, pid 41, labels arm, camera): ran counter, tally",
                               "gpu-box (host gpu, pid 42, labels gpu): ran accumulate (until t=2 s)",
                               "spare (host coord, pid 43): ran accumulate (from t=2 s)"]
    assert lines["moved"] == ["accumulate: worker 'gpu-box' was lost at t=2 s; the node started afresh on worker "
                              "'spare'"]
    # the fault line stays as it was, and what every log's info shows is still there
    assert lines["fault"] == ["accumulate: its process (pid 7) was lost with its worker 'gpu-box' at t=2 s; "
                              "restarted afresh"]
    assert lines["backend"] == ["zenoh"] and lines["pipeline"] == ["small_log"]


def test_log_info_follows_a_node_moved_twice_and_one_back_on_the_worker_it_waited_for(tmp_path):
    """A second move starts from where the first one went; on_worker_loss='wait' starts the node
    afresh on the same worker once it is back: the same worker ran it throughout."""
    path = deployment_log(tmp_path / "run.mcap", [moved("accumulate", "gpu-box", "spare", 1 * S),
                                                  moved("accumulate", "spare", "arm-pc", 3 * S),
                                                  moved("counter", "arm-pc", "arm-pc", 3 * S)])
    lines = info_lines(cli("log", "info", path))
    assert lines["moved"] == [
        "accumulate: worker 'gpu-box' was lost at t=1 s; the node started afresh on worker 'spare'",
        "accumulate: worker 'spare' was lost at t=3 s; the node started afresh on worker 'arm-pc'",
        "counter: worker 'arm-pc' was lost at t=3 s; the node started afresh on it once it was back"]
    assert lines["worker"] == ["arm-pc (host arm, pid 41, labels arm, camera): ran accumulate (from t=3 s), counter, "
                               "tally",
                               "gpu-box (host gpu, pid 42, labels gpu): ran accumulate (until t=1 s)",
                               "spare (host coord, pid 43): ran accumulate (from t=1 s until t=3 s)"]


def test_log_info_of_a_run_that_was_no_deployment_has_no_deployment_lines(tmp_path):
    path = tmp_path / "run.mcap"
    build_small().run(duration=0.3, log=path)
    assert read_log(path).deployment is None
    lines = info_lines(cli("log", "info", path))
    assert not {"deployment", "worker", "moved"} & set(lines), lines


@pytest.mark.parametrize("deployment", [
    "not json",
    json.dumps([1]),
    json.dumps({"namespace": "lab", "placed": {"counter": 3}, "workers": {}}),
    json.dumps({"namespace": "lab", "placed": {}, "workers": {"arm-pc": "up"}}),
    json.dumps({"placed": {}, "workers": {}}),
])
def test_log_info_of_a_forged_deployment_record_is_an_error_not_a_traceback(tmp_path, deployment):
    pipe = build_small()
    path = tmp_path / "forged.mcap"
    writer = LogWriter(LogFile(path), pipe.compile(), backend="zenoh", extra={"deployment": deployment})
    writer.close(pipe.trace, S)
    assert_cli_error(cli("log", "info", path), r"^error: .*forged\.mcap: its metadata 'deployment' is not a JSON "
                                               r"object of a deployment's namespace, placement and workers",
                     hint="the file was changed after it was written")
