"""What a run keeps in memory: ``keep="trace"`` (every value), ``keep="records"`` (ids, tags and
step records; the values only in the log) or ``keep="counters"`` (nothing: each record freed once
logged, the default of a logged real-time run). On zenoh, without a log, the values of a
``records`` run never reach the coordinator, and consumers hold no copies for it."""

from __future__ import annotations

import numpy as np
import pytest

from retriever import NOT_KEPT, BackendError, Flow, Pipeline, Rate, Trigger, ValuesNotKeptError, read_log
from retriever.replay import replay

from .zenoh.payload_flows import Camera, Viewer, frame

SIZE = 256 << 10  # 256 KiB frames: above the spill size, so the trace path of big values is taken


def _frames() -> Pipeline:
    with Pipeline("frames", deadline=1.0) as pipe:
        camera = Camera(SIZE).configure(name="camera") @ Rate(hz=10)
        viewer = Viewer().configure(name="viewer") @ Trigger("image")
        camera.then(viewer)
    return pipe


def _ids(trace) -> list:
    return sorted((e.tag, e.node, e.port, e.seq) for e in trace.events)


def test_on_inproc_records_hold_every_id_and_step_and_no_value(tmp_path):
    full = _frames().run(duration=1.0)
    pipe = _frames()
    kept = pipe.run(duration=1.0, keep="records", log=tmp_path / "run.mcap")
    assert _ids(kept) == _ids(full) and len(kept.steps) == len(full.steps) == 20
    assert [s[:4] for s in kept.canonical()[1]] == [s[:4] for s in full.canonical()[1]]
    assert all(e.value is NOT_KEPT for e in kept.events)
    assert not kept.values_kept and "values not kept" in repr(kept)
    for ask in (lambda: kept.values_of("camera", "image"), kept.digest, lambda: kept == full,
                lambda: kept.first_difference(full)):
        with pytest.raises(ValuesNotKeptError, match=r"keep='records'.*\n.*read_log\('.*run.mcap'\)"):
            ask()
    logged = read_log(tmp_path / "run.mcap").trace()  # the values are in the log, and it replays
    assert logged == full
    assert replay(read_log(tmp_path / "run.mcap")).identical


def test_a_records_trace_without_a_log_says_how_to_get_the_values():
    trace = _frames().run(duration=0.3, keep="records")
    with pytest.raises(ValuesNotKeptError, match=r"run it again with log="):
        trace.values_of("viewer", "k")


def test_keep_takes_only_what_it_names():
    with pytest.raises(BackendError, match=r"keep='everything' is none of 'trace', 'records', 'counters'\n    hint:"):
        _frames().run(duration=0.1, keep="everything")


def test_on_zenoh_without_a_log_a_records_run_sends_the_coordinator_no_values():
    pipe = _frames()
    trace = pipe.run(duration=1.0, backend="zenoh", quiet=True, keep="records")
    assert "garbage" not in pipe.counts(), pipe.counts()
    assert sorted(e.seq for e in trace.events if e.port == "image") == list(range(10))
    assert all(e.value is NOT_KEPT for e in trace.events)
    assert len(trace.steps) == 20
    # 10 frames of 256 KiB were sent; the coordinator got their ids and the step records only
    assert pipe.session.reported_bytes < SIZE, pipe.session.reported_bytes

    full = _frames()  # the same run keeping the trace: the frames come to the coordinator
    full.run(duration=1.0, backend="zenoh", quiet=True)
    assert full.session.reported_bytes > 10 * SIZE


def test_on_zenoh_with_a_log_a_records_run_logs_every_value_and_keeps_none(tmp_path):
    pipe = _frames()
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=1.0, backend="zenoh", quiet=True, keep="records", log=path)
    assert all(e.value is NOT_KEPT for e in trace.events) and len(trace.events) == 40
    log = read_log(path)
    images = sorted((e for e in log.trace().events if e.port == "image"), key=lambda e: e.seq)
    assert len(images) == 10
    for k, e in enumerate(images, 1):
        assert np.array_equal(e.value.reshape(-1), frame(k, SIZE)), k
    assert replay(log).identical


class Tick(Flow):
    def step(self):
        return {"k": 1}


class Count(Flow):
    def __init__(self):
        self.n = 0

    def step(self, k):
        self.n += k
        return {"n": self.n}


def _fast(hz: float = 1000.0) -> Pipeline:
    with Pipeline("fast") as pipe:
        (Tick().configure(name="tick") @ Rate(hz=hz)).then(Count().configure(name="viewer") @ Trigger("k"))
    return pipe


def test_on_inproc_a_counters_run_holds_a_bounded_number_of_records_and_reads_its_trace_from_the_log(tmp_path):
    """20 000 steps logged: the trace never held more than a hand-over's worth of records (a test
    that cannot pass while records are retained), and afterwards it reads back from the log as
    the trace kept in memory would be."""
    pipe = _fast()
    trace = pipe.run(duration=10.0, keep="counters", log=tmp_path / "run.mcap")
    assert sum(s.steps for s in pipe.stats().values()) == 20_000
    assert 0 < pipe.session.retained_peak <= 2 * pipe.session.LOG_BATCH + 2
    assert trace == _fast().run(duration=10.0) and len(trace.steps) == 20_000
    assert "read back from" in repr(trace)
    log = read_log(tmp_path / "run.mcap")
    assert log.end["steps"] == "20000" and log.end["events"] == "20000" and replay(log).identical


def test_a_counters_run_without_a_log_keeps_counters_and_says_where_the_records_would_be():
    pipe = _fast()
    trace = pipe.run(duration=10.0, keep="counters")
    assert pipe.stats()["viewer"].steps == 10_000 and pipe.session.retained_peak <= 2 * pipe.session.LOG_BATCH + 2
    assert len(trace.raw_steps) == 0 and "counters only" in repr(trace)
    for ask in (lambda: trace.events, lambda: trace.steps_of("viewer"), trace.digest, lambda: len(trace)):
        with pytest.raises(ValuesNotKeptError, match=r"kept only counters \(keep='counters'\)\n    hint: pipe.stats"):
            ask()


def test_pipe_step_with_keep_counters_keeps_counters_only():
    """Driving a run step by step from Python: keep="counters" bounds memory there too (the trace
    held every value)."""
    pipe = _fast()
    for _ in range(10):
        trace = pipe.step(0.1, keep="counters") if pipe.now == 0 else pipe.step(0.1)
        assert len(trace.raw_events) == len(trace.raw_steps) == 0
    assert pipe.stats()["viewer"].steps == 1000
    with pytest.raises(ValuesNotKeptError, match=r"kept only counters"):
        trace.latest("tick", "k")


def test_the_trace_of_a_counters_run_reads_back_from_its_log_from_another_directory(tmp_path, monkeypatch):
    """The log's path is taken whole when the run ends: a relative ``log=`` and a later chdir
    still find it."""
    monkeypatch.chdir(tmp_path)
    pipe = _fast()
    trace = pipe.run(duration=1.0, keep="counters", log="run.mcap")
    monkeypatch.chdir("/")
    assert len(trace.steps) == 2_000 and trace.log_path == str(tmp_path / "run.mcap")


def test_a_logged_run_on_zenoh_keeps_only_counters_by_default_and_its_trace_reads_back_from_the_log(tmp_path):
    pipe = _fast(hz=200.0)
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=3.0, backend="zenoh", quiet=True, log=path)
    session = pipe.session
    assert session.keep == "counters"
    steps = sum(s.steps for s in pipe.stats().values())
    assert steps >= 1000 and session.retained_peak < steps / 5, (session.retained_peak, steps)
    assert len(trace.steps_of("tick")) == 600 and trace == read_log(path).trace()
    assert replay(read_log(path)).identical
    unlogged = _fast(hz=200.0)  # without a log, the default is still the whole trace
    unlogged.run(duration=0.5, backend="zenoh", quiet=True)
    assert unlogged.session.keep == "trace" and unlogged.trace.values_kept
