"""``rerun=TARGET``: a running pipeline streamed live to Rerun from the coordinating process
(issue 39 §3), here to an ``.rrd`` file, read back with Rerun's own loader: every event and step
record of the run is there, at its tag on the event timeline, with the run's values; a target
that cannot be reached is said before the run starts."""

from __future__ import annotations

import json
import re
import socket
import warnings
from collections import defaultdict

import numpy as np
import pyarrow as pa
import pytest
import rerun as rr

from retriever import LogError, Pipeline, Rate, RetrieverWarning, Trigger
from retriever.backends.zenoh.hub import free_port
from retriever.log.rerun_live import RerunLiveView

from ...helpers import poll
from ...log.test_foxglove import Cam, Stats

#: each port's entity and the archetype it is shown as (log/rerun.py's mapping)
ENTITIES = {
    "/cam/rgb": "Image", "/cam/depth": "Image", "/cam/exposure": "Scalars", "/stats/mean": "Scalars",
    "/stats/hist": "Scalars", "/stats/big": "Tensor", "/stats/label": "TextLog",
    "/retriever/steps/cam": "TextLog", "/retriever/steps/stats": "TextLog",
}


def live_pipeline() -> Pipeline:
    with Pipeline("live") as pipe:
        cam = Cam().configure(name="cam") @ Rate(hz=10)
        stats = Stats().configure(name="stats") @ Trigger("rgb")
        cam.then(stats, map={"rgb": "rgb"})
    return pipe


def rows_by_tag(recording, entity: str) -> list[dict]:
    """An entity's rows, each as its columns (short names), in event-time order."""
    table = recording.view(index="log_tick", contents=entity).select().read_all()
    columns = {name.rpartition(":")[2]: table.column(name) for name in table.column_names}
    for timeline in {"event_time", "wall_time"} & set(columns):
        columns[timeline] = columns[timeline].cast(pa.int64())
    rows = [dict(zip(columns, values)) for values in zip(*(c.to_pylist() for c in columns.values()))]
    return sorted(rows, key=lambda row: row["event_time"])


@pytest.mark.parametrize("backend", ["zenoh", "dora"])  # (dora: the view is the coordinator's, as on zenoh)
def test_a_run_streamed_to_an_rrd_holds_its_steps_and_values_on_the_event_timeline(tmp_path, backend):
    pipe = live_pipeline()
    out = tmp_path / "live.rrd"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrieverWarning)  # neither view stops
        pipe.run(duration=1.0, backend=backend, quiet=True, rerun=out, foxglove=free_port())  # side by side
    trace = pipe.trace

    recording = rr.dataframe.load_recording(out)
    archetypes = {c.entity_path: c.archetype.rpartition(".")[2] for c in recording.schema().component_columns()}
    archetypes.pop("/__properties")
    assert archetypes == ENTITIES
    events = defaultdict(list)
    for event in trace.events:
        events[f"/{event.node}/{event.port}"].append(event)
    for entity, logged in events.items():
        logged.sort(key=lambda e: e.tag)
        rows = rows_by_tag(recording, entity)
        assert [row["event_time"] for row in rows] == [e.tag[0] for e in logged], entity
        assert [row["wall_time"] for row in rows] == [e.publish_ns for e in logged], entity
        assert [row["seq"] for row in rows] == [e.seq for e in logged], entity  # the seq timeline
        for row, event in zip(rows, logged):
            if ENTITIES[entity] == "Scalars":
                assert row["scalars"] == np.asarray(event.value, dtype=np.float64).reshape(-1).tolist(), entity
            elif ENTITIES[entity] == "Image":
                assert bytes(row["buffer"][0]) == event.value.tobytes(), entity
            elif ENTITIES[entity] == "TextLog":
                assert row["text"] == [event.value], entity
    assert len(events["/cam/rgb"]) == 10
    for node in ("cam", "stats"):
        steps = sorted((s for s in trace.steps if s.node == node), key=lambda s: s.tag)
        rows = rows_by_tag(recording, f"/retriever/steps/{node}")
        assert len(rows) == len(steps) == pipe.stats()[node].ticks
        assert [row["seq"] for row in rows] == list(range(len(steps)))
        for row, step in zip(rows, steps):
            record = json.loads(row["text"][0])
            assert (row["event_time"], record["node"], record["status"], record["tag_ns"], record["microstep"]) == (
                step.tag[0], node, step.status, *step.tag)
            assert record["produced"] == [list(i) for i in step.produced]


def test_a_file_that_cannot_be_written_is_said_before_the_run_starts_and_closes_the_other_view(tmp_path):
    """A folder that takes no file (/proc: not even root may make one there), which no check
    before the run can tell: the SDK's own error, said as the view starts (before T0)."""
    pipe = live_pipeline()
    port = free_port()
    with pytest.raises(LogError, match=r"cannot stream the run to Rerun at /proc/retriever-live\.rrd: .*"
                                       r"(.|\n)*hint: give a new path"):
        pipe.run(duration=1.0, backend="zenoh", quiet=True, rerun="/proc/retriever-live.rrd", foxglove=port)
    with socket.socket() as s:  # the Foxglove view, started first, is closed: its port is free again
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


def test_a_file_that_exists_is_never_replaced_not_even_the_runs_log(tmp_path):
    """--log run.rrd --rerun run.rrd (or any file there): the view refuses it, and the file is kept."""
    there = tmp_path / "run.RRD"  # an .rrd path in any case
    there.write_bytes(b"what was there")
    with pytest.raises(LogError, match=r"cannot stream the run to Rerun at .*run\.RRD: the file exists(.|\n)*"
                                       r"hint: give a new path"):
        RerunLiveView(there, "live")
    assert there.read_bytes() == b"what was there"
    log = tmp_path / "run.rrd"
    with pytest.raises(LogError, match="the file exists"):
        live_pipeline().run(duration=1.0, backend="zenoh", quiet=True, log=log, rerun=log)
    assert not log.exists() or log.read_bytes().startswith(b"\x89MCAP"), "the log is not a Rerun recording"


def test_a_viewer_url_nothing_listens_on_is_said_with_how_to_start_one():
    with pytest.raises(LogError, match=r"cannot stream the run to Rerun at rerun\+http://127\.0\.0\.1:\d+/proxy: "
                                       r"no viewer listens at 127\.0\.0\.1:\d+ \(Connection refused\)"
                                       r"(.|\n)*hint: start a viewer first: `rerun`.*`rerun --serve-web`"):
        RerunLiveView(f"rerun+http://127.0.0.1:{free_port()}/proxy", "live")


@pytest.mark.parametrize("backend", ["zenoh", "dora"])
def test_pipe_run_refuses_a_viewer_url_nothing_listens_on_before_any_worker_starts_and_leaves_no_log(
        tmp_path, capfd, backend):
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    with pytest.raises(LogError, match=rf"cannot stream the run to Rerun at {re.escape(url)}: no viewer listens"):
        live_pipeline().run(duration=0.5, backend=backend, rerun=url, log=tmp_path / "x.mcap")
    assert "namespace" not in capfd.readouterr().err  # no hub was opened, no worker started
    assert list(tmp_path.iterdir()) == []


def test_a_viewer_that_listens_takes_the_stream():
    server = rr.RecordingStream("viewer", send_properties=False)  # the SDK's own gRPC server, as a viewer's
    url = server.serve_grpc(grpc_port=free_port())
    try:
        view = RerunLiveView(url, "live")
        view.event("cam", "exposure", (10, 0), 0, 0.25, 0)
        view.close()
    finally:
        server.disconnect()
    assert view.written == {"/cam/exposure": 1}


def test_a_target_that_is_neither_a_url_nor_an_rrd_path_says_what_to_give():
    with pytest.raises(LogError, match=r"cannot stream the run to Rerun at view\.mcap(.|\n)*\.rrd"):
        RerunLiveView("view.mcap", "live")



def test_a_view_that_fails_mid_run_stops_with_a_warning_and_is_told_nothing_more(tmp_path):
    from retriever.log.live import LiveViews

    view = RerunLiveView(tmp_path / "live.rrd", "live")
    views = LiveViews([view])
    views.event("cam", "exposure", (10, 0), 0, 0.25, 0)
    with pytest.warns(RetrieverWarning, match=r"the Rerun live view stopped: LogError: a time in the log"):
        views.event("cam", "exposure", (2**63, 0), 1, 0.5, 0)  # past what Rerun's times hold
    views.event("cam", "exposure", (30, 0), 2, 0.75, 0)
    views.close()
    assert views.views == [] and list(views.errors) == ["the Rerun live view"]
    assert view.written == {"/cam/exposure": 1}
    rows = rows_by_tag(rr.dataframe.load_recording(tmp_path / "live.rrd"), "/cam/exposure")
    assert [(row["event_time"], row["scalars"]) for row in rows] == [(10, [0.25])]


def test_the_cli_streams_a_run_to_the_rrd_given_to_rerun(tmp_path):
    from tests.test_cli import QUICKSTART, cli, quickstart_ir

    out = tmp_path / "live.rrd"
    result = cli("run", str(QUICKSTART), "--duration", "0.5", "--backend", "zenoh", "--rerun", str(out))
    assert result.returncode == 0, result.stderr
    assert f"Rerun live view streaming to {out}" in result.stderr
    entities = {c.entity_path for c in rr.dataframe.load_recording(out).schema().component_columns()}
    nodes = json.loads(quickstart_ir("json"))["nodes"]
    assert {f"/retriever/steps/{node['id']}" for node in nodes} <= entities, entities


def test_the_cli_takes_rerun_without_a_target_and_refuses_it_in_process():
    from tests.test_cli import QUICKSTART, assert_cli_error, cli

    result = cli("run", str(QUICKSTART), "--rerun", "--duration", "0.5", "--backend", "inproc")
    assert_cli_error(result, "--rerun streams a real-time run: it needs --backend zenoh or dora",
                     "for an in-process run, write a log and open its export: "
                     "retriever log export run.mcap --format rerun -o run.rrd")


#: a pipeline whose file and whose flow's setup() each leave a mark: what ran before a refusal
MARKED = '''
from pathlib import Path
from retriever import Flow, Pipeline, Rate

Path(__file__).with_name("loaded").touch()

class Marked(Flow):
    def setup(self):
        Path(__file__).with_name("set_up").touch()

    def step(self):
        return {"x": 1.0}

with Pipeline("marked") as pipe:
    Marked() @ Rate(hz=10)
'''


@pytest.mark.parametrize("option, said, hint", [
    (["--rerun="], r"'': it is empty", r"give a path ending in \.rrd"),  # not "a folder" (Path("") is ".")
    (["--rerun", "adir"], r"adir: it is a folder", r"give a path ending in \.rrd"),  # a folder, as a bare word
    (["--rerun", "adir/"], r"adir/: it is a folder", r"give a path ending in \.rrd"),
    (["--rerun", "adir.rrd"], r"adir\.rrd: it is a folder", r"give a path ending in \.rrd"),  # named as a file
    (["--rerun", "missing/live.rrd"], r"missing/live\.rrd: its folder missing does not exist",
     r"give a path ending in \.rrd in a folder that exists"),
    (["--rerun=view.mcap"], r"view\.mcap: it is neither a Rerun viewer's URL \(rerun://…, rerun\+http://…, "
                            r"rerun\+https://…\) nor a path ending in \.rrd", r"give a Rerun gRPC URL"),
    (["--rerun", "rerun://"], r"rerun://: it names no host", r"give a Rerun gRPC URL"),
    (["--rerun", "rerun+http://[::1"], r"rerun\+http://\[::1: it is not a valid URL \(Invalid IPv6 URL\)",
     r"give a Rerun gRPC URL"),
    (["--rerun", "rerun+http://127.0.0.1:9876"], r"rerun\+http://127\.0\.0\.1:9876: a Rerun viewer's URL ends in "
                                                  r"/proxy after its host and port", r"give a Rerun gRPC URL"),
    (["--rerun", "rerun+http://127.0.0.1:1/proxy"], r"rerun\+http://127\.0\.0\.1:1/proxy: no viewer listens at "
                                                     r"127\.0\.0\.1:1 \(Connection refused\)",
     r"start a viewer first: `rerun`"),  # port 1: nothing listens there (tcpmux is long gone)
])
def test_the_cli_refuses_a_target_that_is_no_file_or_url_before_the_pipeline_is_even_loaded(tmp_path, option, said,
                                                                                            hint):
    """--rerun takes a viewer's URL or a PATH.rrd (docs: TARGET_HINT), nothing else: a folder
    (which used to be taken for a stray argument, or streamed to after the workers had started),
    or a file in a folder that does not exist, is refused with the forms it accepts, before the
    pipeline's file is imported or any worker starts."""
    from tests.test_cli import assert_cli_error, cli

    (tmp_path / "adir").mkdir()
    (tmp_path / "adir.rrd").mkdir()
    (tmp_path / "marked.py").write_text(MARKED)
    result = cli("run", "marked.py", "--duration", "0.5", "--backend", "zenoh", *option, "--log", "x.mcap",
                 cwd=tmp_path)
    assert_cli_error(result, rf"^error: cannot stream the run to Rerun at {said}$",
                     rf"{hint}.*rerun\+http://127\.0\.0\.1:9876/proxy")
    assert not (tmp_path / "loaded").exists() and not (tmp_path / "set_up").exists(), "the pipeline was started"
    assert "namespace" not in result.stderr, result.stderr  # no run was opened
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "adir.rrd", "marked.py"]


@pytest.mark.parametrize("backend", ["zenoh", "dora"])
@pytest.mark.parametrize("target, said", [("adir", r"adir: it is a folder"),
                                          ("missing/live.rrd", r"live\.rrd: its folder .*missing does not exist")])
def test_pipe_run_refuses_a_folder_or_a_missing_folder_before_any_worker_starts(tmp_path, capfd, backend, target,
                                                                              said):
    (tmp_path / "adir").mkdir()
    with pytest.raises(LogError, match=rf"cannot stream the run to Rerun at .*{said}(.|\n)*hint: "):
        live_pipeline().run(duration=0.5, backend=backend, rerun=tmp_path / target)
    assert "namespace" not in capfd.readouterr().err  # no hub was opened, no worker started


@pytest.mark.parametrize("target, meant", [
    (True, r"for the local viewer, rerun='rerun\+http://127\.0\.0\.1:9876/proxy'; or rerun='live\.rrd'"),
    (9876, r"for a viewer listening on port 9876, rerun='rerun\+http://127\.0\.0\.1:9876/proxy'"),
    (b"live.rrd", r"for the local viewer, rerun='rerun\+http://127\.0\.0\.1:9876/proxy'; or rerun='live\.rrd'"),
])
def test_pipe_run_refuses_a_target_that_is_no_str_or_path_naming_the_forms_it_takes(tmp_path, capfd, target, meant):
    with pytest.raises(LogError, match=rf"rerun={re.escape(repr(target))} is no Rerun target: it takes a viewer's "
                                       rf"gRPC URL \(a str: rerun://…, rerun\+http://…, rerun\+https://…\) or a "
                                       rf"path ending in \.rrd \(a str or a pathlib\.Path\)(.|\n)*hint: {meant}"):
        live_pipeline().run(duration=0.5, backend="zenoh", rerun=target, log=tmp_path / "x.mcap")
    assert "namespace" not in capfd.readouterr().err  # no hub was opened, no worker started
    assert list(tmp_path.iterdir()) == []


def test_pipe_run_on_the_inproc_backend_says_how_to_see_the_run_in_rerun(tmp_path):
    from retriever.errors import BackendError

    with pytest.raises(BackendError, match=r"the inproc backend takes no options \['rerun'\](.|\n)*hint: a live view "
                                           r"needs backend='zenoh' or 'dora'(.|\n)*retriever log export run\.mcap "
                                           r"--format rerun"):
        live_pipeline().run(duration=0.5, rerun=tmp_path / "live.rrd")
    assert list(tmp_path.iterdir()) == []


def test_deploy_refuses_a_folder_as_its_rerun_target_before_it_looks_for_workers(tmp_path):
    from tests.test_cli import assert_cli_error, cli

    (tmp_path / "adir").mkdir()
    (tmp_path / "marked.py").write_text(MARKED)
    result = cli("deploy", "marked.py", "--connect", "tcp/127.0.0.1:9", "--insecure", "--rerun", "adir", cwd=tmp_path)
    assert_cli_error(result, r"^error: cannot stream the run to Rerun at adir: it is a folder$")
    assert not (tmp_path / "loaded").exists()


def chunk_rows(rrd, entity: str) -> list[int]:
    """The rows of each chunk of ``entity`` in ``rrd``, in the order they were written, as Rerun's
    own CLI (``rerun rrd print``) lists them: a chunk is what the SDK flushed at once."""
    import subprocess
    import sys

    listing = subprocess.run([sys.executable, "-m", "rerun_cli", "rrd", "print", str(rrd)], capture_output=True,
                             text=True, check=True, timeout=120).stdout
    return [int(m[1]) for m in re.finditer(rf"^Chunk\(\S+\) with (\d+) rows \(.*\) - {re.escape(entity)} - ",
                                          listing, re.MULTILINE)]


def test_numbers_beside_a_camera_of_big_frames_are_flushed_with_its_frames_not_in_1_mib_lumps(tmp_path):
    """Rerun's SDK holds a row until its entity has 1 MiB of rows or its tick, and skips the tick
    whenever an entity flushed for its bytes since the last: beside a camera of 230 kB frames (a
    flush by bytes every 5 frames) a 100 Hz number's rows were held in 1 MiB lumps (here: all 300
    of them, to the end). The view's stream flushes by bytes only past LIVE_FLUSH_BYTES, so its
    tick is never skipped and takes every entity's rows at once: the number is cut into chunks
    wherever the frames are (a tick, LIVE_FLUSH_S apart; or the end), and nothing is lost."""
    out = tmp_path / "live.rrd"
    view = RerunLiveView(out, "live")
    frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)  # 230 kB
    t0, period = 1_700_000_000_000_000_000, 10_000_000  # the number at 100 Hz, a frame every third (33 Hz)
    for i in range(300):
        view.event("sensor", "x", (i * period, 0), i, float(i), t0 + i * period)
        if i % 3 == 0:
            view.event("cam", "rgb", (i * period, 0), i // 3, frame, t0 + i * period)
    view.close()
    assert view.written == {"/sensor/x": 300, "/cam/rgb": 100}
    numbers, frames = chunk_rows(out, "/sensor/x"), chunk_rows(out, "/cam/rgb")
    assert sum(numbers) == 300 and sum(frames) == 100
    # each cut of the frames cut the number too (the code before: [300] beside 20 chunks of 5 frames);
    # one less for a tick that found a frame but no number since the last (a stall of the loop)
    assert len(numbers) >= len(frames) - 1, (numbers, frames)
    rows = rows_by_tag(rr.dataframe.load_recording(out), "/sensor/x")
    assert [row["scalars"] for row in rows] == [[float(i)] for i in range(300)]


#: a viewer in a process of its own (Rerun's SDK's gRPC server, as the viewer's): it says its URL
#: once its port takes connections, and ends when its standard input closes
VIEWER = r"""
import socket, sys
import rerun as rr
s = rr.RecordingStream("viewer", send_properties=False)
url = s.serve_grpc(grpc_port=int(sys.argv[1]))
while True:
    try:
        socket.create_connection(("127.0.0.1", int(sys.argv[1])), 1.0).close()
        break
    except OSError:
        pass
print(url, flush=True)
sys.stdin.read()
"""
#: how long a test waits for what a viewer process does
VIEWER_BOUND_S = 30.0


@pytest.fixture
def viewer():
    """A viewer process (VIEWER) and its URL; killed at the end whatever it was left as (stopped)."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", VIEWER, str(free_port())], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("rerun+http://"), url
        yield proc, url
    finally:
        proc.kill()
        proc.wait()


def test_a_stopped_viewer_holds_the_view_to_its_budget_it_drops_frames_first_says_so_and_resumes(viewer):
    """Rerun's SDK queues without bound what a viewer does not take: a viewer suspended (SIGSTOP)
    grew the run's process by 1.7 MB a MB of frames (benchmarks/reports/export_memory.md). Now
    what the view hands the SDK and its sink did not take stays under its budget (here 4 MiB,
    and 1 MiB more for small rows): frames are dropped first (the numbers beside them still go),
    counted, said once as it starts and, at close, how many; once the viewer is resumed and has
    taken what it was sent, frames go again."""
    import os
    import signal

    from retriever.log.rerun import RECORD_BYTES

    proc, url = viewer
    budget, small = 4 << 20, 1 << 20
    view = RerunLiveView(url, "live", behind_bytes=budget, small_bytes=small)
    frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)  # 230 kB
    os.kill(proc.pid, signal.SIGSTOP)
    with pytest.warns(RetrieverWarning) as said:
        for i in range(2000):  # at most 460 MB of frames: what a viewer's socket takes is a few MB
            view.event("cam", "rgb", (i, 0), i, frame, 0)
            view.event("sensor", "x", (i, 0), i, float(i), 0)
            assert view.behind <= budget + RECORD_BYTES + frame.nbytes, i  # never past it by more than a row
            if view.dropped["values"] >= 20:
                break
    starts = [w for w in said if "is not taking the stream" in str(w.message)]
    assert len(starts) == 1 and len(said) == 1, [str(w.message) for w in said]
    assert re.search(rf"the Rerun live view: the viewer at {re.escape(url)} is not taking the stream \(\d+ MiB sent "
                     r"it has not taken\): frames and other large values are dropped", str(starts[0].message))
    assert view.dropped["values"] >= 20 and view.dropped["spells"] >= 1  # (2 if its socket took a flush's worth)
    sent_frames = view.written["/cam/rgb"]
    assert view.written["/sensor/x"] == i + 1  # the numbers went on: small, under the 1 MiB more
    assert view.dropped["bytes"] == (i + 1 - sent_frames) * frame.nbytes  # every value dropped was a frame

    os.kill(proc.pid, signal.SIGCONT)
    poll(lambda: view.behind <= budget, "catching up of the resumed viewer", VIEWER_BOUND_S)
    view.event("cam", "rgb", (i + 1, 0), i + 1, frame, 0)
    assert view.written["/cam/rgb"] == sent_frames + 1  # frames go again
    from retriever.errors import ViewDroppedWarning

    with pytest.warns(ViewDroppedWarning, match=rf"the Rerun live view dropped {view.dropped['values']} values "
                                              rf"\(\d+\.\d MB\) and 0 step records that the viewer at "
                                              rf"{re.escape(url)} did not take in time \(behind by more than 4 "
                                              rf"MiB {view.dropped['spells']} times?\); a log of the run keeps them "
                                              rf"all"):
        view.close()


def test_a_viewer_that_stays_stopped_past_the_small_budget_gets_no_step_records_and_close_is_bounded(viewer):
    """Past the small rows' budget too, step records are dropped (counted), and closing a view
    whose viewer takes nothing waits a bounded time (the SDK's own flush would wait forever) and
    says the viewer did not take the end."""
    import os
    import signal
    import time

    proc, url = viewer
    view = RerunLiveView(url, "live", behind_bytes=1 << 20, small_bytes=64 << 10)
    frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    os.kill(proc.pid, signal.SIGSTOP)
    with pytest.warns(RetrieverWarning, match="is not taking the stream"):
        for i in range(2000):
            view.event("cam", "rgb", (i, 0), i, frame, 0)
            view.step("cam", (i, 0), {}, [("rgb", 0)], "ok", None, 0, 0)
            if view.dropped["records"] >= 5:
                break
    assert view.dropped["records"] >= 5
    start = time.monotonic()
    with pytest.warns(RetrieverWarning, match=r"dropped \d+ values .* and \d+ step records"), \
            pytest.raises(LogError, match=rf"the viewer at {re.escape(url)} did not take the end of the stream"):
        view.close()
    assert time.monotonic() - start < VIEWER_BOUND_S


def test_a_viewer_killed_mid_run_stops_the_view_with_a_warning_naming_it(viewer):
    from retriever.log.live import LiveViews

    proc, url = viewer
    view = RerunLiveView(url, "live")
    views = LiveViews([view])
    views.event("cam", "exposure", (10, 0), 0, 0.25, 0)
    proc.kill()
    proc.wait()
    with pytest.warns(RetrieverWarning, match=rf"the Rerun live view stopped: LogError: the viewer at "
                                              rf"{re.escape(url)} went away"):
        poll(lambda: views.event("cam", "exposure", (20, 0), 1, 0.5, 0) or not views.views, "stop of the view",
             VIEWER_BOUND_S)
    views.close()


def test_a_healthy_viewer_takes_a_camera_run_and_nothing_is_dropped(viewer):
    """A run of a 10 Hz camera streamed to a viewer that reads: no drop said, nothing dropped."""
    _, url = viewer
    pipe = live_pipeline()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        pipe.run(duration=1.0, backend="zenoh", quiet=True, rerun=url)
    assert [str(w.message) for w in said if "Rerun" in str(w.message)] == []


#: a camera of 230 kB frames at 30 Hz: more than a stopped viewer's socket and gRPC window take
CAMERA = '''
import numpy as np
from retriever import Flow, Pipeline, Rate

class Camera(Flow):
    def setup(self):
        self.frame = np.zeros((240, 320, 3), dtype=np.uint8)

    def step(self):
        return {"rgb": self.frame}

with Pipeline("camera") as pipe:
    Camera() @ Rate(hz=30)
'''
#: how long `retriever run` may take to exit once its run is over and its view's close gave up
#: (CLOSE_S for the end's flush, then what the process's exit takes without Rerun's at-exit flush)
EXIT_BOUND_S = 30.0


def test_the_cli_exits_past_a_stopped_viewer_saying_it_did_not_take_the_end_and_its_log_is_complete(viewer,
                                                                                                  tmp_path):
    """Rerun's SDK flushes every stream at the process's exit (an atexit handler), and a viewer
    that takes nothing (SIGSTOP) holds that flush for ever: `retriever run --rerun` never ended
    though its run had and its view's close had given up after CLOSE_S. The CLI owns its process:
    when its view gave up, it drops the SDK's at-exit flush, and exits."""
    import os
    import signal
    import subprocess
    import time

    from retriever.log import read_log
    from tests.log.helpers import RETRIEVER, cli_env

    proc, url = viewer
    (tmp_path / "camera.py").write_text(CAMERA)
    log = tmp_path / "run.mcap"
    run = subprocess.Popen([str(RETRIEVER), "run", "camera.py", "--duration", "2", "--backend", "zenoh",
                            "--rerun", url, "--log", str(log)], cwd=tmp_path, env=cli_env(),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        said = []
        for line in run.stderr:  # the view is up (connected to the viewer): stop the viewer
            said.append(line)
            if "Rerun live view streaming to" in line:
                os.kill(proc.pid, signal.SIGSTOP)
                stopped = time.monotonic()
                break
        else:
            raise AssertionError("".join(said))
        out, err = run.communicate(timeout=EXIT_BOUND_S + 2.0)
        took = time.monotonic() - stopped
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    err = "".join(said) + err
    assert took < EXIT_BOUND_S, (took, err)
    assert re.search(rf"the Rerun live view stopped: LogError: the viewer at {re.escape(url)} did not take the end "
                     r"of the stream", err), err
    assert run.returncode == 0, err
    recorded = read_log(log)
    assert recorded.complete and recorded.end["status"] == "finished"


def test_the_sdks_flush_timeout_is_told_by_its_message_as_flush_timed_out_reads_it(viewer):
    """Rerun's SDK (0.26.2) raises a RuntimeError both when a flush's timeout passes and when its
    sink failed; only the message tells them apart (log/rerun_live.py's FLUSH_TIMED_OUT): pinned
    here against a viewer that takes nothing, so that an SDK that words it otherwise fails this
    test rather than stopping every view whose viewer is merely slow."""
    import os
    import signal

    from retriever.log.rerun_live import flush_timed_out

    proc, url = viewer
    stream = rr.RecordingStream("pinned", send_properties=False)
    stream.connect_grpc(url)
    stream.flush()
    os.kill(proc.pid, signal.SIGSTOP)
    tensor = np.random.default_rng(0).integers(0, 256, 4 << 20, dtype=np.uint8)
    for i in range(16):  # 64 MB: more than a stopped viewer's socket and gRPC window take
        stream.log("x", rr.Tensor(tensor))
    with pytest.raises(RuntimeError) as timed_out:
        stream.flush(timeout_sec=0.5)
    assert flush_timed_out(timed_out.value), str(timed_out.value)
    assert not flush_timed_out(RuntimeError("gRPC connection to rerun+http://127.0.0.1:1/proxy disconnected"))
    proc.kill()  # the stream's disconnect does not wait for a stopped viewer
    proc.wait()
    stream.disconnect()


class BreakingStream:
    """A stream whose flush raises an error that is none of the SDK's sink errors (a stand-in for
    an SDK bug, a panic): what no real stream can be made to do on purpose."""

    def flush(self, timeout_sec: float) -> None:
        raise ValueError(f"no flush for {timeout_sec} s")


def test_a_watch_that_fails_on_an_error_other_than_the_sdks_says_which_and_stops():
    """The watch's thread died silently on an error other than RuntimeError: the view went on
    handing the SDK what its sink was never checked to take, and said nothing. Now the watch
    keeps the error (its class and message) for the view's next call to say."""
    from retriever.log.rerun_live import SinkWatch

    watch = SinkWatch(BreakingStream())
    watch.handed = 100  # something to flush
    failed = poll(lambda: watch.failed, "failure of the watch", VIEWER_BOUND_S)
    assert failed == "ValueError: no flush for 0.5 s" and watch.gone is None
    watch.stop()
