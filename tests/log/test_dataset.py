"""``retriever log export --format lerobot | npz``: a log as a training set (retriever/log/dataset.py,
retriever/log/frames.py). The LeRobot tests write and load with the real ``lerobot`` package,
offline; every frame is checked against what the log's step records say the flow consumed and
produced at that tick."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from retriever import read_log
from retriever.errors import LogError
from retriever.log.dataset import FORMATS, export_dataset
from retriever.log.frames import Recording
from retriever.replay import replay
from tests.log.dataset_flows import SIZE, build_camera, build_untyped, picture
from tests.log.helpers import assert_cli_error, cli

FPS = 10


@pytest.fixture(autouse=True)
def _offline(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # a LeRobot dataset is loaded from its folder, never fetched


def _lerobot():
    return pytest.importorskip("lerobot.datasets.lerobot_dataset",
                               reason="the LeRobot export needs the lerobot package (retriever-robotics[lerobot])")


def _run(path: Path, duration: float = 1.0, **options) -> Path:
    build_camera(**options).run(duration=duration, log=str(path))
    return path


def _logged_ticks(path: Path) -> list[dict]:
    """Per ok tick of the policy, from the log alone: its tag and the values of the events its
    step record names (Latest: one event per port)."""
    log = read_log(path)
    events = {e.id: e for e in log.iter_events()}
    ticks = []
    for step in sorted((s for s in log.iter_steps() if s.node == "policy"), key=lambda s: s.tag):
        if step.status != "ok":
            continue
        (image,), (joints,), (pose,) = (step.consumed[p] for p in ("image", "joints", "pose"))
        (action,) = (i for i in step.produced if i[1] == "action")
        value = lambda i: log.value(events[i], keep_unregistered=True)  # noqa: E731
        pose_value = value(pose)
        ticks.append({"t": step.tag[0], "image": value(image), "joints": value(joints),
                      "pose": np.array([pose_value.x, pose_value.y, *pose_value.q]), "action": value(action)})
    return ticks


def _empty_of_partials(folder: Path) -> None:
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")], "a partial export was left behind"


# -- LeRobot -----------------------------------------------------------------------------------
def test_lerobot_export_loads_offline_and_each_frame_is_what_the_flow_consumed_and_produced(tmp_path):
    lerobot = _lerobot()
    log = _run(tmp_path / "run.mcap")
    summary = export_dataset([log], tmp_path / "ds", flow="policy", format="lerobot",
                             maps={"joints": "observation.state"}, task="pick the cube")
    ticks = _logged_ticks(log)
    assert summary.frames == len(ticks) == 9 and summary.episodes == 1 and summary.fps == FPS
    assert dict(summary.left_out) == {"skipped": 1}  # tick 0: the camera's first image comes at (0, 1)
    assert summary.fields_left_out == ["pose.label"]

    dataset = lerobot.LeRobotDataset("retriever/ds", root=tmp_path / "ds", delta_timestamps={"action": [0, 1 / FPS]})
    assert dataset.fps == FPS and dataset.num_episodes == 1 and len(dataset) == len(ticks)
    assert dataset.meta.features["observation.pose"]["names"] == ["pose.x", "pose.y", "pose.q.0", "pose.q.1"]
    assert dataset.meta.camera_keys == ["observation.images.image"]  # an image feature, not a video
    timestamps = np.array(dataset.hf_dataset["timestamp"], dtype=np.float64)
    # the loader's own rule (LeRobotDataset's tolerance_s): consecutive timestamps 1/fps apart
    assert np.all(np.abs(np.diff(timestamps) - 1 / FPS) <= dataset.tolerance_s)
    for k, tick in enumerate(ticks):
        frame = dataset[k]
        assert abs(frame["timestamp"].item() - tick["t"] / 1e9) <= 1e-6  # the tick's tag, from the run's start
        pixels = (frame["observation.images.image"] * 255).round().to(dtype=__import__("torch").uint8)
        assert np.array_equal(pixels.permute(1, 2, 0).numpy(), tick["image"])  # PNG: exact
        assert np.array_equal(frame["observation.state"].numpy(), tick["joints"])
        assert np.array_equal(frame["observation.pose"].numpy(), tick["pose"])
        assert np.array_equal(frame["action"][0].numpy(), tick["action"])
        assert frame["task"] == "pick the cube"
    # tick k's image is the camera's latest: its tick 2k, the k-th image counted from 1 being picture(k)
    assert np.array_equal(ticks[0]["image"], picture(2))
    _empty_of_partials(tmp_path)


def test_a_multi_log_export_has_one_episode_per_log(tmp_path):
    lerobot = _lerobot()
    first, second = _run(tmp_path / "a.mcap", 1.0), _run(tmp_path / "b.mcap", 0.6)
    summary = export_dataset([first, second], tmp_path / "ds", flow="policy", format="lerobot")
    dataset = lerobot.LeRobotDataset("retriever/ds", root=tmp_path / "ds")
    assert summary.episodes == dataset.num_episodes == 2
    lengths = [len(_logged_ticks(first)), len(_logged_ticks(second))]
    assert summary.frames == len(dataset) == sum(lengths) == 9 + 5
    assert list(np.bincount(np.array(dataset.hf_dataset["episode_index"]))) == lengths
    second_start = dataset[lengths[0]]
    assert second_start["episode_index"].item() == 1 and second_start["frame_index"].item() == 0
    assert abs(second_start["timestamp"].item() - _logged_ticks(second)[0]["t"] / 1e9) <= 1e-6


def test_the_lerobot_export_prints_no_progress_bar_of_datasets_and_leaves_its_switch_as_it_was(tmp_path, capfd,
                                                                                               monkeypatch):
    """Hugging Face datasets prints a "Map: 100%|…" bar per episode LeRobot saves: off during the
    export (the caller has its own progress), on again after for the program's own uses."""
    _lerobot()
    import datasets

    monkeypatch.setattr(datasets.config, "HF_DATASETS_DISABLE_PROGRESS_BARS", None)  # the user did not choose
    datasets.enable_progress_bars()
    log = _run(tmp_path / "run.mcap")
    export_dataset([log, log], tmp_path / "ds", flow="policy", format="lerobot")
    assert "Map" not in capfd.readouterr().err
    assert not datasets.are_progress_bars_disabled()
    done = cli("log", "export", str(log), "--format", "lerobot", "--flow", "policy", "-o", str(tmp_path / "cli"))
    assert done.returncode == 0 and "Map" not in done.stderr, done.stderr


def test_npz_holds_the_same_frames_and_features_as_the_lerobot_export(tmp_path):
    lerobot = _lerobot()
    log = _run(tmp_path / "run.mcap")
    export_dataset([log], tmp_path / "ds", flow="policy", format="lerobot")
    npz = export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    dataset = lerobot.LeRobotDataset("retriever/ds", root=tmp_path / "ds")
    arrays = np.load(tmp_path / "np" / "episode_000000.npz")
    assert set(arrays.files) == {*(f.key for f in npz.features), "timestamp", "frame_index", "tick_ns", "task"}
    assert set(f.key for f in npz.features) | {"timestamp", "frame_index", "episode_index", "index", "task_index"} \
        == set(dataset.meta.features)
    for k in range(len(dataset)):
        frame = dataset[k]
        image = (frame["observation.images.image"] * 255).round().numpy().astype(np.uint8).transpose(1, 2, 0)
        assert np.array_equal(arrays["observation.images.image"][k], image)
        for key in ("observation.joints", "observation.pose", "action"):
            assert np.array_equal(arrays[key][k], frame[key].numpy())
        assert abs(arrays["timestamp"][k] - frame["timestamp"].item()) <= 1e-6


# -- npz ---------------------------------------------------------------------------------------
def test_npz_frames_are_the_logged_ticks(tmp_path):
    log = _run(tmp_path / "run.mcap")
    summary = export_dataset([log, log], tmp_path / "np", flow="policy", format="npz")
    info = json.loads((tmp_path / "np" / "info.json").read_text())
    assert info["fps"] == FPS and [e["frames"] for e in info["episodes"]] == [9, 9]
    assert info["features"]["observation.images.image"] == {"kind": "image", "dtype": "uint8",
                                                            "shape": [SIZE, SIZE, 3]}
    ticks = _logged_ticks(log)
    for n in range(2):
        arrays = np.load(tmp_path / "np" / f"episode_{n:06d}.npz")
        assert list(arrays["tick_ns"]) == [t["t"] for t in ticks]
        assert list(arrays["task"]) == ["pick cube"] * len(ticks)  # the pipeline's name by default
        for k, tick in enumerate(ticks):
            assert np.array_equal(arrays["observation.images.image"][k], tick["image"])
            assert np.array_equal(arrays["observation.joints"][k], tick["joints"])
            assert np.array_equal(arrays["observation.pose"][k], tick["pose"])
            assert np.array_equal(arrays["action"][k], tick["action"])
    assert summary.frames == 18 and summary.bytes == sum(p.stat().st_size for p in (tmp_path / "np").iterdir())


def test_a_text_port_mapped_to_task_gives_each_frame_its_task(tmp_path):
    log = _run(tmp_path / "run.mcap", note=True)
    with pytest.raises(LogError, match=r"port 'note' of the flow carries text .*\n.*hint: leave it out with "
                                       r"--exclude note, or make it the task: --map note=task"):
        export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    assert not (tmp_path / "np").exists()
    export_dataset([log], tmp_path / "np", flow="policy", format="npz", maps=["note=task"])
    tasks = list(np.load(tmp_path / "np" / "episode_000000.npz")["task"])
    assert tasks == [f"pick the cube {k % 2}" for k in range(2, 20, 2)]  # the camera's k-th note, k = 2, 4, ...
    export_dataset([log], tmp_path / "np2", flow="policy", format="npz", exclude=["note"], task="stack")
    assert set(np.load(tmp_path / "np2" / "episode_000000.npz")["task"]) == {"stack"}


def test_a_gap_between_frames_is_refused_or_splits_the_episode(tmp_path):
    # the camera is silent on its ticks 7 to 9 (0.3 to 0.4 s): the policy's Latest is stale at 0.4 s
    log = _run(tmp_path / "run.mcap", pause=(7, 9))
    statuses = [s.status for s in sorted(read_log(log).iter_steps(), key=lambda s: s.tag) if s.node == "policy"]
    assert statuses == ["skipped", "ok", "ok", "ok", "skipped", "ok", "ok", "ok", "ok", "ok"]
    with pytest.raises(LogError, match=r"a gap between two frames of 'policy': the 1 tick\(s\) before "
                                       r"t=0\.500000000s m=0 are no frame \(1 skipped\)(.|\n)*hint: pass --gaps split"):
        export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    assert not (tmp_path / "np").exists()
    _empty_of_partials(tmp_path)
    summary = export_dataset([log], tmp_path / "np", flow="policy", format="npz", gaps="split")
    assert summary.episodes == 2 and summary.frames == 8 and dict(summary.left_out) == {"skipped": 2}
    second = np.load(tmp_path / "np" / "episode_000001.npz")
    assert list(second["tick_ns"]) == [int(k * 1e8) for k in range(5, 10)]


def test_incomplete_late_and_error_ticks_are_left_out_and_an_overrun_tick_is_a_frame(tmp_path):
    log = read_log(_run(tmp_path / "run.mcap"))
    recording = Recording.of_log(log)
    policy = sorted((s for s in recording.steps if s.node == "policy"), key=lambda s: s.tag)
    said = {policy[1].tag: "error", policy[3].tag: "overrun", policy[5].tag: "incomplete", policy[6].tag: "late"}
    steps = [s._replace(status=said[s.tag]) if s.node == "policy" and s.tag in said else s for s in recording.steps]
    changed = Recording("changed", recording.ir, steps, recording.event)
    with pytest.raises(LogError, match=r"the 2 tick\(s\) before t=0\.700000000s m=0 are no frame \(1 incomplete, "
                                       r"1 late\)"):
        export_dataset([changed], tmp_path / "np", flow="policy", format="npz")
    summary = export_dataset([changed], tmp_path / "np", flow="policy", format="npz", gaps="split")
    assert dict(summary.left_out) == {"skipped": 1, "error": 1, "incomplete": 1, "late": 1}
    ticks = [list(np.load(tmp_path / "np" / f"episode_{n:06d}.npz")["tick_ns"]) for n in range(summary.episodes)]
    assert ticks == [[int(k * 1e8) for k in (2, 3, 4)], [int(k * 1e8) for k in (7, 8, 9)]]  # 3: the overrun


def test_a_port_with_a_value_now_and_then_is_left_out_unless_mapped(tmp_path):
    log = _run(tmp_path / "run.mcap")
    summary = export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    assert summary.sparse == {"flag": (2, 9)}  # the camera's images 8 and 16, of the policy's 9 ok ticks
    assert "flag (2 of 9)" in str(summary) and "action.flag" not in [f.key for f in summary.features]
    # mapped, it is in every frame: ticks 4 and 8 have it, the 3 between are a gap
    with pytest.raises(LogError, match=r"the 3 tick\(s\) before t=0\.800000000s m=0 are no frame \(3 without a value "
                                       r"on flag\)"):
        export_dataset([log], tmp_path / "np2", flow="policy", format="npz", maps={"flag": "action.flag"})


# -- bad input ---------------------------------------------------------------------------------
def test_bad_input_is_a_clear_error_and_writes_nothing(tmp_path):
    good = _run(tmp_path / "run.mcap")
    trigger = _run(tmp_path / "trigger.mcap", trigger=True)
    data = good.read_bytes()
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(data[: len(data) // 2])
    out = tmp_path / "ds"
    cases = [
        (dict(logs=[good], flow="planner"), r"run\.mcap has no flow 'planner' \(its flows: camera, policy\)"),
        (dict(logs=[trigger], flow="policy"), r"flow 'policy' in .*trigger\.mcap runs on a Trigger clock, not a Rate"),
        (dict(logs=[good, torn], flow="policy"), r"torn\.mcap cannot be read: .*its writer was stopped"),
        (dict(logs=[good], flow="policy", maps={"nothing": "observation.state"}),
         r"--map names 'nothing', which no feature comes from"),
        (dict(logs=[good], flow="policy", format="parquet"), r"unknown dataset format 'parquet'"),
    ]
    for options, message in cases:
        with pytest.raises(LogError, match=message):
            export_dataset(out=out, **{"format": "npz", **options})
        assert not out.exists(), options
        _empty_of_partials(tmp_path)


def test_an_unmappable_value_is_refused_with_the_port_and_the_fix(tmp_path):
    from retriever.log.frames import UnmappableError

    log = read_log(_run(tmp_path / "run.mcap"))
    recording = Recording.of_log(log)
    forged = lambda event_id: ((lambda got: got if event_id[1] != "joints" else (got[0], {1, 2}))  # noqa: E731
                               (recording.event(event_id)))
    with pytest.raises(UnmappableError, match=r"port 'joints' of the flow carries a set, which no feature holds"
                                              r"(.|\n)*hint: leave it out with --exclude joints"):
        export_dataset([Recording(recording.name, recording.ir, recording.steps, forged)], tmp_path / "np",
                       flow="policy", format="npz")
    assert not (tmp_path / "np").exists()


def test_an_existing_output_is_kept_unless_forced(tmp_path):
    log = _run(tmp_path / "run.mcap")
    (tmp_path / "np").mkdir()
    (tmp_path / "np" / "mine.txt").write_text("keep me")
    with pytest.raises(LogError, match=r"np exists(.|\n)*hint: pass --force"):
        export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    assert (tmp_path / "np" / "mine.txt").read_text() == "keep me"
    export_dataset([log], tmp_path / "np", flow="policy", format="npz", overwrite=True)
    assert sorted(p.name for p in (tmp_path / "np").iterdir()) == ["episode_000000.npz", "info.json"]
    _empty_of_partials(tmp_path)


#: an export into OUT that stops, once its partial folder is there, until its stdin has a line
#: (the test kills it there): argv = OUT LOG LOG
_EXPORT_THAT_WAITS = """
import sys
import tests.log.dataset_flows  # the logs' value types
from retriever.log.dataset import export_dataset

def progress(log, logs, tick, ticks):
    if log == 1:  # the first log's episode is written: the partial folder exists
        print("writing", flush=True)
        sys.stdin.readline()

export_dataset(sys.argv[2:], sys.argv[1], flow="policy", format="npz", progress=progress)
"""


def test_a_killed_exports_folder_is_removed_by_the_next_export_beside_it_and_said(tmp_path):
    import signal
    import subprocess
    import sys

    from tests.log.helpers import cli_env

    log = _run(tmp_path / "run.mcap")
    out = tmp_path / "datasets"
    out.mkdir()
    killed = subprocess.Popen([sys.executable, "-c", _EXPORT_THAT_WAITS, str(out / "first"), str(log), str(log)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=cli_env())
    try:
        assert killed.stdout.readline() == "writing\n"
        left = out / f".first.{killed.pid}.partial"
        assert (left / "episode_000000.npz").is_file()
    finally:
        killed.send_signal(signal.SIGKILL)
        killed.wait(timeout=60)
        killed.stdout.close()
        killed.stdin.close()
    assert killed.returncode == -signal.SIGKILL and left.is_dir() and not (out / "first").exists()
    live = out / f".other.{os.getpid()}.partial"  # this test's process runs: a live export's folder
    others = [out / f".first.{killed.pid}.partial.keep", out / ".first.x1.partial", out / "first.1.partial"]
    for folder in (live, *others):
        folder.mkdir()
    (out / ".file.1.partial").write_text("not a folder")

    done = cli("log", "export", str(log), "--format", "npz", "--flow", "policy", "-o", str(out / "second"))
    assert done.returncode == 0, done.stderr
    assert not left.exists() and (out / "second" / "info.json").is_file()
    assert f"  removed 1 unfinished folder(s) that killed exports had left in {out}: {left.name}\n" in done.stdout
    assert all(p.exists() for p in (live, *others, out / ".file.1.partial"))


def test_a_partial_folder_of_another_user_or_a_live_process_is_left_alone(tmp_path, monkeypatch):
    import subprocess
    import sys

    from retriever.log.dataset import reap_partials

    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait(timeout=60)
    stale, running = tmp_path / f".a.{ended.pid}.partial", tmp_path / f".b.{os.getppid()}.partial"
    stale.mkdir()
    running.mkdir()
    uid = os.getuid()
    monkeypatch.setattr(os, "getuid", lambda: uid + 1)  # as another user sees them
    assert reap_partials(tmp_path) == [] and stale.is_dir()
    monkeypatch.setattr(os, "getuid", lambda: uid)
    assert reap_partials(tmp_path) == [stale.name]
    assert not stale.exists() and running.is_dir()


# -- a real-time run and its replay -------------------------------------------------------------
def test_the_export_of_a_zenoh_run_equals_the_export_of_its_replay(tmp_path):
    log_path = tmp_path / "rt.mcap"
    build_camera().run(duration=1.5, backend="zenoh", log=str(log_path), quiet=True)
    log = read_log(log_path)
    replayed = replay(log, keep_trace=True)  # the policy's steps re-executed: its actions computed again
    assert replayed.identical and replayed.nodes["policy"].replayed >= 10
    live = export_dataset([log], tmp_path / "live", flow="policy", format="npz", gaps="split")
    again = export_dataset([Recording.of_trace(replayed.trace, log.ir, "the replay")], tmp_path / "again",
                           flow="policy", format="npz", gaps="split")
    assert live.frames == again.frames >= 10 and live.features == again.features
    assert live.episodes == again.episodes and live.left_out == again.left_out
    for n in range(live.episodes):
        a, b = (np.load(tmp_path / side / f"episode_{n:06d}.npz") for side in ("live", "again"))
        assert a.files == b.files
        for key in a.files:
            assert np.array_equal(a[key], b[key]), key


# -- the command -------------------------------------------------------------------------------
def test_the_command_prints_frames_fps_and_size_and_refuses_clearly(tmp_path):
    log = _run(tmp_path / "run.mcap")
    done = cli("log", "export", str(log), str(log), "--format", "npz", "--flow", "policy", "-o", str(tmp_path / "np"),
               "--map", "joints=observation.state")
    assert done.returncode == 0, done.stderr
    first = done.stdout.splitlines()[0]
    assert first.startswith(f"wrote {tmp_path / 'np'} (npz): 18 frames in 2 episode(s) at 10 fps, ") and " kB" in first
    assert "observation.state" in done.stdout and "ticks left out: 2 skipped" in done.stdout
    refused = cli("log", "export", str(log), "--format", "npz", "--flow", "nope", "-o", str(tmp_path / "other"))
    assert_cli_error(refused, r"run\.mcap has no flow 'nope' \(its flows: camera, policy\)", "pass the node id")
    assert not (tmp_path / "other").exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


# -- the output, the keys and the values it refuses ---------------------------------------------
def test_an_output_that_is_holds_or_lies_inside_a_log_is_refused_even_forced(tmp_path):
    (tmp_path / "logs").mkdir()
    log = _run(tmp_path / "logs" / "run.mcap")
    data = log.read_bytes()
    cases = [(log, "is the log"), (tmp_path / "logs", "is a folder that holds the log"),
             (tmp_path, "is a folder that holds the log"), (log / "ds", "is inside the log")]
    for out, what in cases:
        with pytest.raises(LogError, match=rf"the output .* {what} .*run\.mcap: writing it would replace the log"):
            export_dataset([log], out, flow="policy", format="npz", overwrite=True)
        assert log.read_bytes() == data
    # the same path spelled otherwise, through the command
    done = cli("log", "export", str(log), "--format", "npz", "--flow", "policy", "--force",
               "-o", str(tmp_path / "logs" / ".." / "logs" / "run.mcap"))
    assert_cli_error(done, r"is the log .*run\.mcap: writing it would replace the log", "-o a folder apart")
    assert log.read_bytes() == data


def test_an_output_inside_a_file_is_a_clear_error(tmp_path):
    log = _run(tmp_path / "run.mcap")
    (tmp_path / "afile").write_text("mine")
    with pytest.raises(LogError, match=r"the output .*afile/sub lies inside .*afile, which is a file, not a folder"):
        export_dataset([log], tmp_path / "afile" / "sub", flow="policy", format="npz")
    assert (tmp_path / "afile").read_text() == "mine"
    _empty_of_partials(tmp_path)


@pytest.mark.parametrize("format,key", [("npz", "timestamp"), ("npz", "tick_ns"), ("lerobot", "index"),
                                        ("lerobot", "episode_index"), ("lerobot", "task_index"),
                                        ("lerobot", "frame_index"), ("lerobot", "timestamp")])
def test_a_map_to_a_key_the_format_writes_itself_is_refused(tmp_path, format, key):
    log = _run(tmp_path / "run.mcap")
    with pytest.raises(LogError, match=rf"--map joints={key}: '{key}' is a key the {format} format writes of its own"
                                       r"(.|\n)*hint: map 'joints' to another key"):
        export_dataset([log], tmp_path / "ds", flow="policy", format=format, maps={"joints": key})
    assert not (tmp_path / "ds").exists()


def test_a_map_to_a_key_with_a_slash_is_refused(tmp_path):
    log = _run(tmp_path / "run.mcap")
    with pytest.raises(LogError, match=r"--map joints=observation/state: a feature key has no '/'"
                                       r"(.|\n)*hint: --map joints=observation\.state"):
        export_dataset([log], tmp_path / "ds", flow="policy", format="lerobot", maps={"joints": "observation/state"})


def _run_untyped(path: Path, kind: str = "float") -> Path:
    build_untyped(kind).run(duration=0.5, log=str(path))
    return path


def test_an_untyped_flows_output_that_no_edge_reads_is_its_action(tmp_path):
    log = _run_untyped(tmp_path / "run.mcap")
    summary = export_dataset([log], tmp_path / "np", flow="pol", format="npz")
    assert [(f.key, f.source) for f in summary.features] == [("observation.state", "v"), ("action", "a")]
    arrays = np.load(tmp_path / "np" / "episode_000000.npz")
    assert arrays["action"].tolist() == [[2.0]] * summary.frames and summary.frames == 4


@pytest.mark.parametrize("kind,what", [("big_int", r"an int beyond int64 \(1180591620717411303425"),
                                       ("empty", r"a float64 array of shape \(0,\) with no element"),
                                       ("complex", r"a complex128 array of shape \(1,\)")])
@pytest.mark.parametrize("format", FORMATS)
def test_a_value_no_feature_holds_is_refused_in_both_formats(tmp_path, kind, what, format):
    if format == "lerobot":
        _lerobot()
    log = _run_untyped(tmp_path / "run.mcap", kind)
    with pytest.raises(LogError, match=rf"port 'v' of the flow carries {what}(.|\n)*hint: leave it out with "
                                       r"--exclude v"):
        export_dataset([log], tmp_path / "ds", flow="pol", format=format)
    assert not (tmp_path / "ds").exists()
    _empty_of_partials(tmp_path)


def test_nan_and_inf_values_are_named_in_the_summary(tmp_path):
    log = _run_untyped(tmp_path / "run.mcap", "nan_at_3")
    summary = export_dataset([log], tmp_path / "np", flow="pol", format="npz")
    assert summary.non_finite == {"v": (1, f"t=0.300000000s m=0 in {log}")}  # the sender's 3rd value
    assert f"NaN or infinite values (a dataset's statistics take them in): v in 1 frame(s), first at t=0.300000000s " \
           f"m=0 in {log}" in str(summary)
    clean = export_dataset([_run_untyped(tmp_path / "clean.mcap")], tmp_path / "np2", flow="pol", format="npz")
    assert clean.non_finite == {} and "NaN" not in str(clean)


def test_a_wide_state_vector_names_its_elements_once_and_not_beyond_the_limit(tmp_path, monkeypatch):
    from retriever import features
    from retriever.log.frames import NAMED_ELEMENTS_LIMIT

    lerobot = _lerobot()
    log = _run(tmp_path / "run.mcap")
    calls = []
    named = features.element_names
    monkeypatch.setattr(features, "element_names", lambda *a: calls.append(a) or named(*a))
    export_dataset([log], tmp_path / "np", flow="policy", format="npz")
    assert len(calls) == 5  # joints, pose.x, pose.y, pose.q, action: at the first frame only, of 9
    monkeypatch.undo()
    wide = _run_untyped(tmp_path / "wide.mcap", "wide")
    summary = export_dataset([wide], tmp_path / "ds", flow="pol", format="lerobot")
    assert summary.features[0].shape == (5000,) > (NAMED_ELEMENTS_LIMIT,) and summary.features[0].names == ()
    dataset = lerobot.LeRobotDataset("retriever/ds", root=tmp_path / "ds")
    assert dataset.meta.features["observation.state"]["names"] is None
    assert dataset.meta.features["action"]["names"] == ["a.0"]
