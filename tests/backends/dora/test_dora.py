"""The dora backend with dora's real runtime (`dora run`), real worker processes and real logs.

The conformance suite's real-time part (test_let_conformance.py) and the lifecycle tests
(test_setup_teardown.py) run on it too; here: the dataflow it compiles, the log and its replay,
what it refuses, a step that raises, a killed worker, and no process left behind.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
import yaml

from retriever import BackendError, Latest, Pipeline, Rate, StepError, Trigger, read_log
from retriever.backends.dora import host as dora_host
from retriever.backends.dora.dataflow import PROGRESS, QUEUE_SIZE, WARM, DoraNames, dataflow_yaml
from retriever.backends.dora.host import pid_alive
from retriever.backends.zenoh.folders import DORA_FOLDER
from retriever.backends.zenoh.origin import KEY_BYTES
from retriever.backends.zenoh.protocol import RunSpec
from retriever.replay import replay

from ...helpers import poll
from ..test_conformance import Echo, EchoOpt, Source
from ..zenoh.lifecycle_flows import Counter, two_node_pipeline
from ..zenoh.test_lifecycle import RETRIEVER, _cmdline, _env
from .dora_flows import Extra, Frames, Raises

BOUND_S = 60.0  # a bound on any wait: a loaded 2-core machine
ROOT = Path(__file__).resolve().parents[3]


def _let_chain(name: str = "chain") -> Pipeline:
    """src @ 20 Hz ──value──▶ echo @ Trigger ──saw──▶ slow @ 10 Hz: LET everywhere, so its trace is inproc's."""
    with Pipeline(name, deadline=5.0) as pipe:
        src = Source().named("src").configure(latency=0.01) @ Rate(20)
        echo = Echo().named("echo").configure(latency=0.005) @ Trigger("x")
        slow = EchoOpt().named("slow").configure(latency=0.02) @ Rate(10, offset=0.015)
        src.then(echo, sync=Latest(), map={"value": "x"})
        echo.then(slow, sync=Latest(), map={"saw": "x"})
    return pipe


def _nothing_left(session) -> None:
    """The run's `dora run` and every worker it started are gone."""
    assert session.hosting.dora.proc.poll() is not None, "dora run outlived its run"
    alive = {nid: pid for nid, pid in session.worker_pids().items() if pid > 0 and pid_alive(pid)}
    assert not alive, f"worker(s) {alive} outlived the run"


# ---------------------------------------------------------------------------------------------
# The dataflow
# ---------------------------------------------------------------------------------------------
def test_the_dataflow_has_a_node_per_flow_an_output_per_port_and_progress_for_consumed_flows():
    names = DoraNames.of(_let_chain().compile().to_ir().doc)
    doc = yaml.safe_load(dataflow_yaml("chain", names, "/venv/bin/python", "/run/spec.json", "/src"))
    nodes = {n["id"]: n for n in doc["nodes"]}
    assert sorted(nodes) == ["echo", "slow", "src"]
    assert nodes["src"]["args"] == "-m retriever.backends.dora.node /run/spec.json src"
    assert nodes["src"]["path"] == "/venv/bin/python" and nodes["src"]["env"] == {"PYTHONPATH": "/src"}
    assert nodes["src"]["outputs"] == ["value", PROGRESS, WARM]  # warm: its consumers' warm-up input takes it
    assert nodes["slow"]["outputs"] == ["saw"] and "inputs" not in nodes["src"]  # slow: nobody consumes it
    queue = {"queue_size": QUEUE_SIZE, "queue_policy": "backpressure"}  # dora's direct route lost events
    assert nodes["echo"]["inputs"] == {"src__value": {"source": "src/value", **queue},
                                       "src__progress": {"source": "src/progress", **queue},
                                       "src__warm": {"source": "src/warm", **queue}}  # on the events' route
    assert names.warm_inputs("echo") == {"src__warm": ["src"]} and names.warm_inputs("src") == {}


def test_ids_dora_would_refuse_are_renamed_and_mapped_back():
    doc = {"nodes": [{"id": "cam.left", "outputs": {"progress": {}, "img": {}}}, {"id": "dora", "outputs": {}}],
           "edges": [{"source": {"node": "cam.left", "port": "progress"},
                      "destination": {"node": "dora", "port": "x"}}]}
    names = DoraNames.of(doc)
    assert names.nodes == {"cam.left": "n0", "dora": "n1"}
    assert names.outputs["cam.left"] == {"img": "img", "progress": "o1"}  # the port named like the progress output
    assert names.inputs["dora"] == {"n0__o1": ["cam.left", "progress"], "n0__progress": ["cam.left", None]}
    assert names.members("n0") == ["cam.left"] and names.progress == {"cam.left": PROGRESS}
    flow = yaml.safe_load(dataflow_yaml("odd", names, "/py", "/spec.json", "/src"))
    assert [n["id"] for n in flow["nodes"]] == ["n0", "n1"] and flow["nodes"][0]["outputs"] == ["img", "o1", PROGRESS, WARM]


def test_the_warm_up_output_is_named_past_the_ports_and_only_where_events_are_heard():
    doc = {"nodes": [{"id": "a", "outputs": {"warm": {}, "warm_1": {}}}, {"id": "b", "outputs": {"out": {}}}],
           "edges": [{"source": {"node": "a", "port": "warm"}, "destination": {"node": "b", "port": "x"}}]}
    names = DoraNames.of(doc)
    assert names.warm("a") == "warm_2" and names.warm("b") is None  # b: nobody hears it
    flow = {n["id"]: n for n in yaml.safe_load(dataflow_yaml("w", names, "/py", "/spec.json", "/src"))["nodes"]}
    assert flow["a"]["outputs"] == ["warm", "warm_1", PROGRESS, "warm_2"] and flow["b"]["outputs"] == ["out"]
    assert flow["b"]["inputs"]["a__warm_2"]["source"] == "a/warm_2"  # b hears a: a's warm-ups, b's warm-up input
    assert names.warm_inputs("b") == {"a__warm_2": ["a"]}


def test_the_specs_dora_part_is_the_dict_it_was_and_a_node_reads_its_names_back(tmp_path):
    doc = _let_chain().compile().to_ir().doc
    names, keys = DoraNames.of(doc), {"src": b"\x01" * KEY_BYTES, "echo": b"\x02" * KEY_BYTES}
    part = names.part(cwd="/home/me", coordinator=4242, dir="/tmp/retriever-dora-x", keys=keys)
    # as DoraHosting.place wrote it when the spec was a dict: the same keys, in the same order
    assert part.to_fields() == {"nodes": names.nodes, "outputs": names.outputs, "inputs": names.inputs,
                                "progress": names.progress,
                                "cwd": "/home/me", "coordinator": 4242, "dir": "/tmp/retriever-dora-x",
                                "keys": {"src": "01" * KEY_BYTES, "echo": "02" * KEY_BYTES}}
    spec = RunSpec(ir=doc, namespace="dora-part", hub="tcp/127.0.0.1:7447", plan={"nodes": []}, startup_timeout=60.0,
                   zids={}, hub_zid=None, virtual_time=False,
                   dora_part=part)
    read = RunSpec.read_file(spec.write_file(tmp_path / "spec.json")).dora_part
    assert read == part and DoraNames.of_part(read) == names and read.keys["echo"] == keys["echo"]


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------
def test_a_logged_run_is_inprocs_trace_and_replays_identically(tmp_path):
    path = tmp_path / "run.mcap"
    pipe = _let_chain()
    trace = pipe.run(duration=1.0, backend="dora", quiet=True, log=path)
    reference = _let_chain().run(duration=1.0, backend="inproc")
    assert trace.first_difference(reference) is None and trace.digest() == reference.digest()
    log = read_log(path)
    assert log.end["status"] == "finished" and log.run["backend"] == "dora"
    assert replay(log).identical
    _nothing_left(pipe.session)


def test_dora_folders_of_a_process_that_is_gone_are_removed_by_the_next_run():
    """dora's folder (its dataflow, its logs) is named with the coordinator's pid, so that one left
    by a killed coordinator whose workers never ran to remove it is reaped by the next dora run."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    stale = Path(tempfile.gettempdir()) / f"{DORA_FOLDER}-{gone.pid}-left"
    stale.mkdir()
    (stale / "dora.out").write_text("a killed run's")
    try:
        _let_chain().run(duration=0.2, backend="dora", quiet=True)
        assert not stale.exists()
    finally:
        shutil.rmtree(stale, ignore_errors=True)


def test_an_output_no_edge_takes_is_logged(tmp_path):
    """An untyped flow's extra key has no dora output (nobody consumes it): still in the trace."""
    with Pipeline("extra") as pipe:
        extra = Extra().named("extra").configure(latency=0.01) @ Rate(10)
        sink = EchoOpt().named("sink").configure(latency=0.01) @ Trigger("x")
        extra.then(sink, sync=Latest(), map={"x": "x"})
    trace = pipe.run(duration=0.5, backend="dora", quiet=True, keep="trace")
    assert trace.values_of("extra", "note") == [f"tick {i}" for i in range(5)]
    assert len(trace.steps_of("sink")) == 5


def test_big_outputs_bring_none_of_doras_diagnostic_warnings(capfd):
    """dora 1.1's node API logs two warnings for each of a run's first messages over 4 KiB
    (dora-rs/dora#2742 diagnostic); a worker's other output still comes through."""
    with Pipeline("frames") as pipe:
        frames = Frames().named("frames") @ Rate(20)
        sink = EchoOpt().named("sink") @ Trigger("x")
        frames.then(sink, sync=Latest(), map={"x": "x"})
    trace = pipe.run(duration=0.5, backend="dora", quiet=True, keep="records")
    assert len(trace.steps_of("sink")) == 10
    out, err = capfd.readouterr()
    assert "2742" not in out + err
    assert "[frames] frames: first frame\n" in out and "[frames] frames: first frame, on stderr\n" in err
    assert dora_host.dora_diagnostic('{"timestamp":"2026-11-27T13:11:41Z","level":"WARN","fields":{"message":'
                                     '"output `x`: 74184 B -> daemon path (dora-rs/dora#2742 diagnostic)"},'
                                     '"target":"dora_node_api::node"}')
    assert not dora_host.dora_diagnostic("a flow's print about dora-rs/dora#2742 diagnostic")


def test_a_step_that_raises_stops_the_run_with_the_workers_traceback():
    with Pipeline("raises") as pipe:
        src = Counter() @ Rate(hz=20)
        bad = Raises(at=3).named("bad") @ Trigger()
        src.then(bad, sync=Latest())
    with pytest.raises(StepError, match=r"bad\.step\(\) raised RemoteError: ValueError: third time(.|\n)*"
                                        r"worker traceback:(.|\n)*dora_flows\.py"):
        pipe.run(duration=5.0, backend="dora", quiet=True)
    _nothing_left(pipe.session)


@pytest.mark.parametrize("on_error", ["stop", "restart"])
def test_a_sigkilled_worker_stops_the_run_naming_its_node(on_error):
    """With on_error="restart" too: dora starts its processes once, so a flow restarts in place
    (test_restart.py), and a process that died is not started afresh."""
    pipe = two_node_pipeline("killdora")
    pipe.compile().nodes["total"].flow.configure(on_error=on_error)
    pids: dict[str, int] = {}
    done = threading.Event()

    def kill_once_going() -> None:
        give_up = time.monotonic() + BOUND_S
        while not done.is_set() and time.monotonic() < give_up:
            session = pipe.session
            if session is not None and session.t0 is not None and session.trace.raw_steps:
                pids.update(session.worker_pids())
                os.kill(pids["total"], signal.SIGKILL)
                return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_once_going, daemon=True)
    killer.start()
    try:
        with pytest.raises(BackendError) as caught:
            pipe.run(duration=60.0, backend="dora", quiet=True, keep="trace")
    finally:
        done.set()
        killer.join(BOUND_S)
    assert pids, "the killer never saw the run going"
    message = str(caught.value)
    assert f"worker process of 'total' (pid {pids['total']}) was killed by SIGKILL" in message, message
    _nothing_left(pipe.session)


# ---------------------------------------------------------------------------------------------
# What it refuses, before anything starts
# ---------------------------------------------------------------------------------------------
def test_virtual_time_is_refused_with_where_it_is():
    with pytest.raises(BackendError, match=r"takes no options \['virtual_time'\](.|\n)*backend='zenoh', "
                                           r"virtual_time=True"):
        _let_chain().run(duration=1.0, backend="dora", virtual_time=True)


def test_without_dora_installed_the_error_says_what_to_install(monkeypatch, tmp_path):
    monkeypatch.setattr(dora_host.sys, "executable", str(tmp_path / "python"))  # no dora beside it
    monkeypatch.setattr(dora_host.shutil, "which", lambda name: None)
    with pytest.raises(BackendError, match=r"needs dora's runtime, which is not installed\n"
                                           r"    hint: pip install 'retriever-robotics\[dora\]'"):
        _let_chain().run(duration=1.0, backend="dora")


def test_retriever_run_takes_backend_dora(tmp_path):
    log = tmp_path / "run.mcap"
    done = subprocess.run([sys.executable, "-m", "retriever", "run", "tests/backends/zenoh/lifecycle_flows.py:pipe",
                           "--backend", "dora", "--duration", "0.5", "--log", str(log)],
                          cwd=ROOT, capture_output=True, text=True, timeout=BOUND_S * 2)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on dora" in done.stdout + done.stderr
    assert read_log(log).run["backend"] == "dora"
    replayed = subprocess.run([sys.executable, "-m", "retriever", "replay", str(log)], cwd=ROOT,
                              capture_output=True, text=True, timeout=BOUND_S)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr


COORDINATOR = """
import sys
from tests.backends.zenoh.lifecycle_flows import two_node_pipeline
two_node_pipeline("orphans").run(duration=600, backend="dora", quiet=True)
"""


@pytest.mark.parametrize("when", ["as dora run starts", "once its workers run"])
def test_a_sigkilled_coordinators_workers_dora_and_directories_go_by_themselves(when):
    """The workers are dora's children, not the coordinator's: they watch the coordinator's pid,
    and once it is gone they remove the run's directory and dora's (which hold the run's
    credentials, and dora's logs), and stop; dora run ends with its last node. Killed as dora run
    starts, dora run still starts the nodes (its output goes to a file, not to a dead pipe)."""
    proc = subprocess.Popen([sys.executable, "-c", COORDINATOR], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        dora = poll(lambda: proc.poll() is None and _children_of(proc.pid, "dora run"), "dora run")
        run_dir, dora_dir = _directories_of(dora[0])
        if when == "once its workers run":
            poll(lambda: _children_of(proc.pid, "retriever.backends.dora.node"), "workers")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(BOUND_S)

        poll(lambda: not _left(dora[0], run_dir, dora_dir), "end of dora run, its workers and directories",
              bound=30.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_ctrl_c_before_the_start_ends_dora_and_its_nodes_at_once_without_their_noise(tmp_path):
    """Interrupted while a flow's setup() still runs, nothing has anything to send: dora run is
    ended, its nodes go with it, and what dora says of their ends (caused by us) is not printed."""
    stderr = tmp_path / "stderr.txt"
    with open(stderr, "wb") as err:
        proc = subprocess.Popen([str(RETRIEVER), "run", "tests/backends/dora/dora_flows.py:never_ready", "--backend",
                                 "dora", "--duration", "5"], stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT,
                                env=_env())
    try:
        dora = poll(lambda: proc.poll() is None and _children_of(proc.pid, "dora run"), "dora run")
        run_dir, dora_dir = _directories_of(dora[0])
        poll(lambda: all((run_dir / f"{node}.pid").exists() for node in ("ok", "stuck")), "both workers")
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=BOUND_S) == 130, stderr.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    said = stderr.read_text()
    assert "interrupted" in said and "Traceback" not in said, said
    assert "[dora]" not in said, said
    assert not _left(dora[0], run_dir, dora_dir)


def _directories_of(dora: int) -> tuple[Path, Path]:
    """The run's directory and dora's, of the run whose `dora run` is ``dora``."""
    words = _cmdline(dora).split()
    dataflow = Path(words[words.index("run") + 1])
    spec = yaml.safe_load(poll(lambda: dataflow.read_text(), "dataflow.yml"))["nodes"][0]["args"].split()[2]
    return Path(spec).parent, dataflow.parent


def _left(dora: int, run_dir: Path, dora_dir: Path) -> list:
    """What is left of a run: `dora run`, its workers (by their spec's path), its directories."""
    processes = [pid for pid in _pids() if pid_alive(pid) and (pid == dora or str(run_dir) in _cmdline(pid))]
    return processes + [d for d in (run_dir, dora_dir) if d.exists()]


def _pids() -> list[int]:
    return [int(path.name) for path in Path("/proc").iterdir() if path.name.isdigit()]


def _children_of(root: int, needle: str) -> list[int]:
    """Processes under ``root`` (any depth) whose command line holds ``needle``."""
    parents = {}
    for pid in _pids():
        try:
            text = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        parents[pid] = int(text[text.rindex(")") + 2:].split()[1])

    def under(pid: int) -> bool:
        seen = 0
        while pid in parents and seen < 64:
            if parents[pid] == root:
                return True
            pid, seen = parents[pid], seen + 1
        return False

    return sorted(pid for pid in parents if under(pid) and needle in _cmdline(pid))
