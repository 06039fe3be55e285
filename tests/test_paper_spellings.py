"""The seed paper's spellings of the API (issue 19 §4): its imports, flows with ``run``, its
backend names and ``blocking=``; and its Listing 4 as printed (tests/listings/), on each backend it names."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from retriever import BackendError, StepError, read_log
from retriever.replay import replay
from tests.paper_flows import build, build_ending

ROOT = Path(__file__).resolve().parents[1]
LISTING4 = ROOT / "tests" / "listings" / "listing4_latency.py"


@pytest.mark.parametrize("backend", ["in-process", "multiprocessing"])
def test_a_flow_whose_method_is_run_steps_on_the_papers_backend_names(backend):
    pipe = build()
    options = {"quiet": True} if backend == "multiprocessing" else {}
    trace = pipe.run(backend=backend, duration=0.5, blocking=True, **options)
    assert [e.value.tolist() for e in trace.events_of("source")][:2] == [[1, 1, 1, 1], [2, 2, 2, 2]]
    assert len(trace.steps_of("sink")) == 10 and all(s.status == "ok" for s in trace.steps_of("sink"))
    assert pipe.session.backend_name == ("inproc" if backend == "in-process" else "zenoh")


@pytest.mark.parametrize("backend", ["dora", "multiprocessing", "in-process"])
def test_the_papers_latency_benchmark_runs_as_printed_on_each_backend_it_names(backend, tmp_path):
    """issue 19 §4: Listing 4, as printed (argparse at import, ``run`` methods, blocking=True),
    started as its authors did: ``python listing4_latency.py --backend B`` in a directory that has
    its results folder. Its sink writes a CSV row from its second step on, in the worker's working
    directory: the caller's, on every backend."""
    results = tmp_path / "experiments" / "benchmarks" / "results"
    results.mkdir(parents=True)
    done = subprocess.run([sys.executable, str(LISTING4), "--backend", backend, "--duration", "1"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-3000:]
    rows = (results / f"retriever_{backend}_benchmark_results.csv").read_text().splitlines()
    assert rows[0] == "name,platform,size,latency_ns" and rows[1].startswith(f"Retriever {backend},COMPUTER_PERF,")


def test_a_run_in_the_background_returns_a_handle_with_the_same_trace():
    handle = build().run(duration=2.0, blocking=False)
    assert handle.wait(timeout=60) == build().run(duration=2.0)
    assert handle.done


def test_a_background_run_stops_when_its_handle_says_so():
    pipe = build()
    handle = pipe.run(duration=1e6, blocking=False)  # 11 days of virtual time: it would take minutes
    while pipe.session is None or not pipe.session.trace.raw_steps:  # bounded by the run's start
        pass
    handle.stop()
    with pytest.raises(KeyboardInterrupt):
        handle.wait(timeout=60)
    assert handle.done and 0 < len(pipe.trace.steps) < 1e6 * 40


def test_a_handle_asked_to_stop_once_its_run_is_over_stops_nothing_after():
    """stop() once the run is over is a no-op: no request is left for the next run to meet."""
    pipe = build()
    handle = pipe.run(duration=1.0, blocking=False)
    handle.wait(timeout=60)
    handle.stop()
    with pytest.raises(BackendError, match="needs a duration"):  # refused as itself, not as a Ctrl-C
        pipe.run(duration=None)
    pipe.run(duration=1.0)
    assert pipe.now == 2.0


@pytest.mark.parametrize("backend", ["in-process", "multiprocessing"])
def test_sys_exit_0_in_a_step_ends_the_whole_run_cleanly_and_the_log_replays(backend, tmp_path):
    """issue 19 §4: the paper's benchmark ends with sys.exit(0) in a step. That ends the run, as
    a clean stop: the step's record is ok with detail exit 0, nothing ticks after it, and pipe.run
    returns the trace (not the step's error)."""
    options = {"quiet": True} if backend == "multiprocessing" else {}
    log = tmp_path / "run.mcap"
    pipe = build_ending(at=5)
    trace = pipe.run(backend=backend, duration=30.0, log=log, **options)  # the exit comes long before
    source = trace.steps_of("source")
    assert [s.status for s in source] == ["ok"] * 5 and source[-1].detail == {"exit": 0}, source
    assert source[-1].tag == (200_000_000, 0) and not source[-1].produced
    assert all(s.tag < (300_000_000, 0) for s in trace.steps), "nothing ran long after the exit"
    assert read_log(log).end["status"] == "finished"
    assert replay(read_log(log)).identical


@pytest.mark.parametrize("backend", ["multiprocessing", "dora"])
def test_what_was_sent_before_a_sys_exit_still_reaches_its_consumer(backend):
    """sys.exit(0) at the source's 5th tick ends the run then, as if that were its end: its 4
    big frames (8 MiB each, the last one sent 50 ms before the exit, or less on a slow machine)
    may still be on their way, and each reaches the sink within its deadline (generous here: on
    a loaded machine dora's daemon took 0.3 s to deliver them), which still steps on it (the run
    does not stop every flow at once). No tick runs past the exit: the sink steps on nothing more."""
    pipe = build_ending(at=5, size=1 << 20, deadline=10.0)
    trace = pipe.run(backend=backend, duration=30.0, quiet=True)
    source = trace.steps_of("source")  # (a step may overrun its 50 ms on a loaded machine: its ticks skip)
    assert len(source) == 5 and source[-1].detail == {"exit": 0}
    assert [s.consumed["data"][0][2] for s in trace.steps_of("sink")] == [0, 1, 2, 3]
    exit_tag = trace.steps_of("source")[-1].tag
    assert all(s.tag < (exit_tag[0] + 1_000_000_000, 0) for s in trace.steps), "a tick long after the exit"


def test_sys_exit_with_another_code_is_that_steps_error():
    with pytest.raises(StepError, match=r"source\.step\(\) raised SystemExit: 3"):
        build_ending(at=3, code=3).run(duration=1.0)
