"""Replay and re-simulation: identical on deterministic runs, and divergence caught and named.

The random graphs of the schedule-independence suite (every policy, delays, latency, triggers,
cycles) are logged and replayed; flows that are nondeterministic on purpose must be caught.
"""

from __future__ import annotations

import hashlib
import json
import random
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from retriever.flow.core import settings_of
from retriever import (Flow, Latest, LogError, Pipeline, Queue, Rate, RetrieverWarning, SetupError, StepError, Trigger,
                       io)
from retriever.log import read_log
from retriever.replay import replay, resim
from tests.backends.test_schedule_independence import budget, graphs
from tests.log.helpers import cli

REPO = Path(__file__).resolve().parents[2]
QUICKSTART = REPO / "examples" / "quickstart.py"


# -- flows ------------------------------------------------------------------------------------
@io
@dataclass
class Reading:
    x: float


class Counter(Flow[None, Reading]):
    def __init__(self):
        self.k = 0

    def step(self) -> Reading:
        self.k += 1
        return Reading(x=float(self.k))


class Smoother(Flow[Reading, Reading]):
    """Deterministic and stateful: replay must rebuild its state from its own past steps."""

    def __init__(self, alpha: float = 0.5):
        self.alpha, self.y = alpha, 0.0

    def step(self, inp: Reading) -> Reading:
        self.y = self.alpha * inp.x + (1 - self.alpha) * self.y
        return Reading(x=self.y)


class Dice(Flow[Reading, Reading]):
    """Nondeterministic on purpose: an unseeded random draw."""

    def step(self, inp: Reading) -> Reading:
        return Reading(x=inp.x + random.random())


class Stopwatch(Flow[Reading, Reading]):
    """Nondeterministic on purpose: reads the wall clock."""

    def step(self, inp: Reading) -> Reading:
        return Reading(x=inp.x + time.perf_counter())


class Fragile(Flow[Reading, Reading]):
    """Raises on every third input; on_error decides what happens next."""

    def __init__(self):
        self.seen = 0

    def step(self, inp: Reading) -> Reading:
        self.seen += 1
        if self.seen % 3 == 0:
            raise ValueError(f"third input {inp.x}")
        return Reading(x=inp.x * 2)


#: what Oracle's step reads: the world outside the program, which changes after the run
OUTSIDE = {"answer": 1.0, "setups": 0}


class Oracle(Flow[Reading, Reading]):
    """Consults the world outside the program (as a model behind an endpoint would)."""

    def setup(self):
        OUTSIDE["setups"] += 1

    def step(self, inp: Reading) -> Reading:
        return Reading(x=inp.x * OUTSIDE["answer"])


class Weighted(Flow[Reading, Reading]):
    """Reads its weight from a file in setup(), as a policy loads its checkpoint."""

    def __init__(self, path: str):
        self.path = path

    def setup(self):
        self.weight = float(Path(self.path).read_text())

    def step(self, inp: Reading) -> Reading:
        return Reading(x=inp.x * self.weight)


class Batcher(Flow):
    """Untyped, Queue-fed: commit state (what was consumed) must replay exactly."""

    def step(self, x):
        return {"total": float(sum(x)), "count": len(x)}


class FailingCounter(Counter):
    """A source whose 3rd, 6th, ... steps raise (a sensor that drops out)."""

    def step(self) -> Reading:
        out = super().step()
        if self.k % 3 == 0:
            raise OSError(f"no reading at {self.k}")
        return out


class Refill(Flow):
    """Untyped: emits the array it holds, as it is or in a list, refilled in place each step (an
    emitted value is immutable: every refill after the first fails, and on_error skips the tick)."""

    def __init__(self, nested: bool = False):
        self.nested, self.held = nested, np.zeros(2)

    def step(self, x):
        self.held[:] = x
        return {"value": [self.held] if self.nested else self.held}


def chain(middle: type[Flow], *, on_error: str = "stop") -> Pipeline:
    with Pipeline("chain") as pipe:
        src = Counter() @ Rate(hz=50)
        # a budget for every failure of a 2 s run (on_error="restart" stops past max_restarts)
        mid = middle().configure(on_error=on_error, max_restarts=100) @ Rate(hz=20)
        sink = Smoother(alpha=0.25) @ Rate(hz=10)
        src.then(mid, sync=Latest()).then(sink, sync=Latest())
    return pipe


def logged(pipe: Pipeline, tmp_path: Path, duration: float = 2.0, name: str = "run.mcap"):
    path = tmp_path / name
    pipe.run(duration=duration, log=path)
    return read_log(path)


# -- identical ----------------------------------------------------------------------------------
def test_quickstart_replays_and_resimulates_identically(tmp_path):
    from retriever.loading import load_pipeline

    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()  # the module's pipeline is shared by every test that loads it
    log = logged(pipe, tmp_path, duration=5)
    report = replay(log)
    assert report.identical, report.divergences[:1]
    assert report.nodes["camera"].replayed == 0  # a source: its events are the input
    assert report.nodes["controller"].replayed == report.nodes["controller"].steps == 1000
    assert report.nodes["policy"].identical == 10
    again = resim(log)
    assert again.identical, again.difference
    assert again.steps_compared == 1160


@pytest.mark.parametrize("on_error", ["skip_tick", "restart", "stop"])
def test_a_source_that_raised_resimulates_identically(on_error, tmp_path):
    """A source's ticks come from the log in a re-simulation: a tick logged as an error is an
    error again, with the logged text, handled by ``on_error`` as in the run (it was an "ok"
    tick with no events, and --resim said DIVERGED)."""
    with Pipeline("failing_source") as pipe:
        src = FailingCounter().configure(on_error=on_error, max_restarts=100) @ Rate(hz=20)
        src.then(Smoother() @ Rate(hz=10), sync=Latest())
    if on_error == "stop":
        with pytest.raises(StepError, match="no reading at 3"):
            logged(pipe, tmp_path)
        log = read_log(tmp_path / "run.mcap")
    else:
        log = logged(pipe, tmp_path)
    errors = [s for s in log.trace().steps if s.status == "error"]
    assert errors and errors[0].detail["error"] == "OSError: no reading at 3", errors[:1]
    again = resim(log)
    assert again.identical, again.difference
    assert again.steps_compared > (0 if on_error == "stop" else 40)


def test_stateful_flows_replay_from_their_own_history(tmp_path):
    log = logged(chain(Smoother), tmp_path)
    report = replay(log)
    assert report.identical
    assert report.steps_replayed == report.nodes["smoother"].steps + report.nodes["smoother_2"].steps == 60


def test_queue_consumption_replays_exactly(tmp_path):
    with Pipeline("batches") as pipe:
        src = Counter() @ Rate(hz=30)
        batch = Batcher() @ Rate(hz=7)
        src.then(batch, sync=Queue(maxsize=3))
    log = logged(pipe, tmp_path)
    assert replay(log).identical
    assert resim(log).identical


@pytest.mark.parametrize("on_error", ["skip_tick", "restart"])
def test_error_steps_replay_with_the_same_error(tmp_path, on_error):
    log = logged(chain(Fragile, on_error=on_error), tmp_path)
    errors = [s for s in log.iter_steps() if s.status == "error"]
    assert errors and all("third input" in s.detail["error"] for s in errors)
    report = replay(log)
    assert report.identical, report.divergences[:1]
    assert resim(log).identical


@pytest.mark.parametrize("nested", [False, True])
def test_a_replayed_step_that_refills_the_array_it_emitted_fails_as_in_the_run(tmp_path, nested):
    """A re-executed step's outputs go to no consumer (the replay delivers the logged ones), and
    are still made read-only when it returns (docs/semantics.md, "An emitted value is
    immutable"): a flow that refills the array it emitted fails at its second step, as in the
    run, and the replay is identical, read whole and streamed."""
    from retriever.replay import replay_file

    with Pipeline("refill") as pipe:
        src = Counter() @ Rate(hz=50)
        src.then(Refill(nested).configure(on_error="skip_tick") @ Rate(hz=20), sync=Latest(), map={"x": "x"})
    log = logged(pipe, tmp_path, duration=0.5)
    steps = [s for s in log.iter_steps() if s.node == "refill"]
    statuses = [s.status for s in steps if s.status != "skipped"]  # (its first tick, before the counter's event)
    assert statuses[0] == "ok" and statuses[1:] == ["error"] * (len(statuses) - 1) and len(statuses) > 5, statuses
    assert all("read-only" in s.detail["error"] for s in steps if s.status == "error")
    for report in (replay(log), replay_file(log.path)):
        assert report.identical, report.divergences[:1]
        assert report.nodes["refill"].replayed == len(steps)


@pytest.mark.parametrize("latest", [False, True])
def test_a_step_that_writes_into_its_input_fails_in_the_replay_as_in_the_run(tmp_path, latest):
    """The values the replay delivers are decoded from the log (the codec's copies, writable):
    they are made read-only as the run's were (docs/semantics.md, "An emitted value is
    immutable"), so a consumer that wrote into its input fails in the replay as in the run; it
    ran there, and the replay diverged at its first tick. Decoded as read (a Trigger input) and
    when a tick takes it (a Latest input's, put off), read whole and streamed."""
    from retriever.replay import replay_file
    from tests.backends.test_conformance import ArrayRamp, TripleInPlace

    with Pipeline("writes-input") as pipe:
        ramp = ArrayRamp().named("ramp") @ Rate(5)
        bad = TripleInPlace().named("bad").configure(on_error="skip_tick")
        if latest:
            ramp.then(bad @ Rate(5, offset=0.1), map={"value": "x"}, sync=Latest())
        else:
            ramp.then(bad @ Trigger("x"), map={"value": "x"})
    log = logged(pipe, tmp_path, duration=1.0)
    steps = [s for s in log.iter_steps() if s.node == "bad"]
    assert [s.status for s in steps] == ["error"] * 5
    assert all("read-only" in s.detail["error"] for s in steps)
    for report in (replay(log), replay_file(log.path)):
        assert report.identical, report.divergences[:1]
        assert report.nodes["bad"].replayed == 5


def test_a_run_stopped_by_an_error_is_logged_and_replays(tmp_path):
    path = tmp_path / "stopped.mcap"
    with pytest.raises(StepError, match="fragile"):
        chain(Fragile).run(duration=2.0, log=path)
    log = read_log(path)
    assert log.end["status"] == "error" and "third input" in log.end["error"]
    assert log.iter_steps().__next__() is not None
    assert replay(log).identical


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(spec=graphs())
def test_random_graphs_replay_and_resimulate_identically(spec, tmp_path_factory):
    """Every policy, delay, latency, trigger and cycle the schedule-independence suite draws."""
    tmp = tmp_path_factory.mktemp("random")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        pipe = spec.build()
        with budget():  # each execution re-runs the same steps, so spends the same
            live = pipe.run(duration=1.0, log=tmp / "r.mcap")
        log = read_log(tmp / "r.mcap")
        assert log.trace() == live
        with budget():
            report = replay(log, spec.build())
        assert report.identical, f"{spec}\n{report.divergences[:1]}"
        with budget():
            again = resim(log, spec.build())
        assert again.identical, f"{spec}\n{again.difference}"


# -- divergence -------------------------------------------------------------------------------
@pytest.mark.parametrize("culprit", [Dice, Stopwatch])
def test_nondeterministic_flow_is_caught_and_named(tmp_path, culprit):
    log = logged(chain(culprit), tmp_path)
    report = replay(log)
    assert not report.identical
    node = culprit.__name__.lower()
    # every tick diverges but the first, at t=0, which had no input yet (a skip, verified as such)
    assert report.nodes[node].replayed == 40 and report.nodes[node].divergent == 39
    assert report.nodes["smoother"].divergent == 0  # fed the *logged* outputs, so unaffected
    first = report.divergences[0]
    assert (first.node, first.port, first.what) == (node, "x", "value")
    assert first.tag == (50_000_000, 0)
    assert first.logged != first.replayed
    assert f"{node}.x at tick t=0.050000000s" in str(first)


@pytest.mark.parametrize("mode", ["rerun", "log"])
def test_a_flow_replayed_from_the_log_is_not_called_again(tmp_path, mode, monkeypatch):
    """replay="log": the replay takes the flow's outputs from the log (its step and setup() are
    not called: the world it consulted has changed) and re-executes and compares its consumers.
    Re-run (the default), the same flow is caught diverging."""
    monkeypatch.setitem(OUTSIDE, "answer", 2.0)
    with Pipeline("chain") as pipe:
        src = Counter() @ Rate(hz=50)
        oracle = Oracle().configure(replay=mode) @ Rate(hz=20)
        sink = Smoother(alpha=0.25) @ Rate(hz=10)
        src.then(oracle, sync=Latest()).then(sink, sync=Latest())
    log = logged(pipe, tmp_path)
    assert pipe.build_ir().doc["nodes"][1]["config"].get("replay") == (None if mode == "rerun" else "log")
    monkeypatch.setitem(OUTSIDE, "answer", 3.0)  # the world answers differently now
    monkeypatch.setitem(OUTSIDE, "setups", 0)
    report, again = replay(log), resim(log)
    if mode == "log":
        assert report.identical and again.identical, again.difference
        assert report.nodes["oracle"].from_log and report.nodes["oracle"].replayed == 0
        assert report.nodes["smoother"].replayed == 20 and report.nodes["smoother"].identical == 20
        assert OUTSIDE["setups"] == 0
    else:
        assert not report.identical and not again.identical
        assert report.divergences[0].node == "oracle" and OUTSIDE["setups"] == 2


def test_a_replay_whose_flow_cannot_be_set_up_says_the_replay_could_not_start_and_why(tmp_path):
    weights = tmp_path / "weights.txt"
    weights.write_text("2.0")
    with Pipeline("chain") as pipe:
        (Counter() @ Rate(hz=50)).then(Weighted(str(weights)) @ Rate(hz=20), sync=Latest())
    log = logged(pipe, tmp_path)
    weights.unlink()  # the checkpoint moved since the run
    said = (r"^weighted\.setup\(\) raised FileNotFoundError: .*weights\.txt'?, before its first tick: the replay "
            r"could not start\n    hint: a replay sets 'weighted' up again, in this process: it needs here what it "
            r"needed in the run")
    for again in (replay, resim):
        with pytest.raises(SetupError, match=said) as raised:
            again(log)
        assert isinstance(raised.value.__cause__, FileNotFoundError)
        assert "the run did not start" not in str(raised.value)
    done = cli("replay", str(log.path))
    assert done.returncode == 1 and "the replay could not start" in done.stderr and "run did not" not in done.stderr


def test_replay_setting_is_checked(tmp_path):
    with pytest.raises(ValueError, match="replay='never' is not one of 'rerun', 'log'"):
        Oracle().configure(replay="never")
    from retriever.ir import IR
    with Pipeline("chain") as pipe:
        (Counter() @ Rate(hz=50)).then(Oracle().configure(replay="log") @ Rate(hz=20), sync=Latest())
    doc = pipe.build_ir().doc
    assert settings_of(Pipeline.from_ir(IR(doc)).flows[1]).replay == "log"
    doc["nodes"][1]["config"]["replay"] = "sometimes"
    with pytest.raises(Exception, match="node 'oracle'.config.replay: 'sometimes' is not one of rerun, log"):
        IR(doc)


def test_changed_step_is_caught_by_replay_with_another_pipeline(tmp_path):
    log = logged(chain(Smoother), tmp_path)
    with Pipeline("chain") as changed:
        src = Counter() @ Rate(hz=50)
        mid = Smoother(alpha=0.9) @ Rate(hz=20)  # same ids, different behaviour
        sink = Smoother(alpha=0.25) @ Rate(hz=10)
        src.then(mid, sync=Latest()).then(sink, sync=Latest())
    report = replay(log, changed)
    assert report.nodes["smoother"].divergent > 0 and report.nodes["smoother_2"].divergent == 0


def test_an_output_at_another_tag_is_caught_though_its_record_and_value_are_the_same(tmp_path):
    """A step whose record and output value are the logged ones but whose output comes at another
    tag (here the middle flow given a latency: its output at the tick's time + 10 ms, not at the
    tick's next microstep) diverges at its output's tag, every step of it that ran, read whole or streamed."""
    from retriever.replay import replay_file

    log = logged(chain(Smoother), tmp_path)
    with Pipeline("chain") as changed:
        src = Counter() @ Rate(hz=50)
        mid = Smoother().configure(latency=0.01) @ Rate(hz=20)  # same ids, same values, later outputs
        sink = Smoother(alpha=0.25) @ Rate(hz=10)
        src.then(mid, sync=Latest()).then(sink, sync=Latest())
    for report in (replay(log, changed), replay_file(log.path, changed)):
        mid = report.nodes["smoother"]
        assert mid.replayed > 30 and mid.divergent == mid.replayed - 1 and mid.identical == 1, mid  # (its first tick skipped)
        assert report.nodes["smoother_2"].divergent == 0 and report.nodes["smoother_2"].identical > 0
        first = report.divergences[0]
        assert (first.node, first.what, first.port) == ("smoother", "output tag", "x"), first
        assert (first.tag, first.logged, first.replayed) == ((50_000_000, 0), "t=0.050000000s m=1", "t=0.060000000s m=0")


def test_a_survey_holds_the_step_records_it_leaves_unchecked_up_to_a_bound(tmp_path):
    """The survey of a log file keeps the sequences of the step records it did not find plain
    (here the skipped ticks' records, with detail: 51), which the replay reads again whole; past
    ``max_unchecked`` of them, or once a chunk is taken as message tuples (a log read whole),
    none: every record is read again whole (its memory does not grow with such records). The
    replay says the same either way."""
    from retriever.log.reader import scan_log
    from retriever.replay import LogSurvey, replay_file

    with Pipeline("skips") as pipe:
        src = Counter() @ Rate(hz=10, offset=1.0)
        mid = Smoother() @ Rate(hz=50)  # its ticks before the first reading: skipped
        src.then(mid, sync=Latest())
    path = tmp_path / "skips.mcap"
    pipe.run(duration=2.0, log=path)
    surveys = []
    for bound in (10_000, 50):
        survey = LogSurvey(path, max_unchecked=bound)
        scan_log(path, survey.take, take_chunk=survey.take_chunk)
        surveys.append(survey.unchecked)
    skipped = {m.sequence for m in read_log(path).messages
               if m.channel_id in {c.id for c in read_log(path).channels.values() if c.topic == "steps"}
               and b"missing" in m.data}
    assert surveys[0] == skipped and len(skipped) > 50 and surveys[1] is None
    whole = LogSurvey(path)
    whole.take(read_log(path).channels, [(m.log_time, 0, m.channel_id, m.sequence, m.publish_time, m.data)
                                         for m in read_log(path).messages])
    assert whole.unchecked is None
    streamed, read_whole = replay_file(path), replay(read_log(path))
    assert streamed.identical and read_whole.identical and streamed.nodes == read_whole.nodes
    assert streamed.nodes["smoother"].replayed == 100


def test_changed_policy_is_reported_as_different_inputs(tmp_path):
    log = logged(chain(Smoother), tmp_path)
    with Pipeline("chain") as changed:
        src = Counter() @ Rate(hz=50)
        mid = Smoother() @ Rate(hz=20)
        sink = Smoother(alpha=0.25) @ Rate(hz=10)
        src.then(mid, sync=Latest(), delay=0.03).then(sink, sync=Latest())
    first = replay(log, changed).divergences[0]
    assert first.node == "smoother" and first.what.startswith("inputs") and first.port == "x"


def test_replay_with_a_pipeline_lacking_a_logged_node_is_an_error(tmp_path):
    log = logged(chain(Smoother), tmp_path)
    with Pipeline("other") as other:
        Counter() @ Rate(hz=50)
    with pytest.raises(LogError, match="smoother.*does not have"):
        replay(log, other)


def test_cli_replay_exit_status_and_report(tmp_path):
    """Exit 0 and 'identical' for the quickstart; exit 1, DIVERGED and the culprit otherwise."""
    cli = [str(Path(sys.executable).parent / "retriever")]
    path = tmp_path / "q.mcap"
    done = subprocess.run([*cli, "run", str(QUICKSTART), "--duration", "2", "--log", str(path)],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    done = subprocess.run([*cli, "replay", str(path)], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "identical" in done.stdout and "controller" in done.stdout
    done = subprocess.run([*cli, "replay", "--resim", str(path)], capture_output=True, text=True, cwd=tmp_path,
                          timeout=120)
    assert done.returncode == 0 and "identical" in done.stdout, done.stdout + done.stderr

    noisy = tmp_path / "noisy.py"
    noisy.write_text(
        "import random\n"
        "from retriever import Flow, Pipeline, Rate, Latest\n"
        "class Tick(Flow):\n    def step(self):\n        return {'x': 1.0}\n"
        "class Noisy(Flow):\n    def step(self, x):\n        return {'y': x + random.random()}\n"
        "with Pipeline('noisy') as pipe:\n    (Tick() @ Rate(hz=10)).then(Noisy() @ Rate(hz=10), sync=Latest())\n")
    log = tmp_path / "noisy.mcap"
    subprocess.run([*cli, "run", str(noisy), "--duration", "1", "--log", str(log)], check=True,
                   capture_output=True, cwd=tmp_path, timeout=120)
    done = subprocess.run([*cli, "replay", str(log)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 1
    assert "DIVERGED" in done.stdout and "noisy.y at tick t=0.1" in done.stdout
    assert "Traceback" not in done.stdout + done.stderr


DRIFTING = ("from retriever import Flow, Pipeline, Rate, Latest\n"
            "class Tick(Flow):\n    def __init__(self):\n        self.k = 0\n"
            "    def step(self):\n        self.k += 1\n        return {'x': float(self.k)}\n"
            "class Scale(Flow):\n    def step(self, x):\n        return {'y': x * 2}\n"
            "with Pipeline('drifting') as pipe:\n"
            "    (Tick() @ Rate(hz=10)).then(Scale() @ Rate(hz=10), sync=Latest())\n")


def test_replay_says_which_flow_module_changed_since_the_run_before_it_compares(tmp_path):
    """A run of a module edited afterwards: replay and --resim warn, before comparing, that its
    code differs from the run's, with both sha256; a DIVERGED line names it as the likely cause."""
    module = tmp_path / "drifting.py"
    module.write_text(DRIFTING, encoding="utf-8")
    log = tmp_path / "drifting.mcap"
    assert cli("run", module, "--duration", "1", "--log", log, cwd=tmp_path).returncode == 0
    done = cli("replay", log, cwd=tmp_path)
    assert done.returncode == 0 and "warning" not in done.stderr, done.stdout + done.stderr
    run_sha = hashlib.sha256(module.read_bytes()).hexdigest()

    for edit, diverges in (("# a comment\n", False), ("x * 2", True)):
        module.write_text(DRIFTING.replace("x * 2", "x * 3") if edit == "x * 2" else DRIFTING + edit, encoding="utf-8")
        here_sha = hashlib.sha256(module.read_bytes()).hexdigest()
        change = (f"the code of module drifting differs from the run's (run sha256 {run_sha}, here {here_sha} "
                  f"in {module})")
        for resim_flag in ((), ("--resim",)):
            done = cli("replay", *resim_flag, log, cwd=tmp_path)
            assert done.returncode == (1 if diverges else 0), done.stdout + done.stderr
            assert done.stderr.startswith(f"warning: {change}: what the replay finds different may come from that "
                                          "change\n"), done.stderr
            printed = " ".join(done.stdout.split())  # rich wraps long lines
            if diverges and not resim_flag:
                assert f"DIVERGED: 9 of 10 replayed steps differ; {change}. First: scale.y at tick t=0.1" in printed, \
                    done.stdout
            elif diverges:
                assert "DIVERGED: " in printed and f" {change}, which may be why" in printed, done.stdout
            else:
                assert "identical" in done.stdout, done.stdout


def test_replay_from_another_directory_finds_the_flow_classes(tmp_path):
    """The log records where the flows were imported from; replay works from any directory."""
    from retriever.loading import load_pipeline

    path = tmp_path / "q.mcap"
    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()  # the module's pipeline is shared by every test that loads it
    pipe.run(duration=1, log=path)
    code = ("import sys; from retriever.log import read_log; from retriever.replay import replay; "
            f"r = replay(read_log({str(path)!r})); sys.exit(0 if r.identical else 1)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr


def test_log_only_at_the_start_of_a_run(tmp_path):
    pipe = chain(Smoother)
    pipe.step(0.5)
    with pytest.raises(Exception, match="from T0"):
        pipe.run(duration=1, log=tmp_path / "late.mcap")
    pipe.reset()
    pipe.run(duration=1, log=tmp_path / "ok.mcap")
    with pytest.raises(Exception, match="reset"):
        pipe.run(duration=1)  # the logged run is finished; continuing it would go unrecorded
    assert np.isfinite(read_log(tmp_path / "ok.mcap").trace().values_of("smoother", "x")[-1])


def test_what_workers_said_of_their_code_is_read_from_a_hostile_log_as_text_only():
    from types import SimpleNamespace

    from retriever.replay import MAX_SAID, ran_other_code

    def said(deployment):
        return ran_other_code(SimpleNamespace(run={"deployment": deployment}))

    assert said(json.dumps({"ran_other_code": {"w": ["node 'a': the code of module m differs"]}})) == [
        "in the run, worker 'w' ran node 'a': the code of module m differs"]
    for hostile in ("not json", "[1]", json.dumps({"ran_other_code": [1]}), json.dumps({"ran_other_code": {"w": "x"}}),
                    "[" * 100_000 + "]" * 100_000):
        assert said(hostile) == []
    long = said(json.dumps({"ran_other_code": {"w" * 1000: ["x" * 10_000, 7]}}))
    assert len(long) == 1 and len(long[0]) < 60 + MAX_SAID + 40


def test_forged_source_records_are_caught_against_the_sources_clock(tmp_path):
    """A source is not re-executed, so a forged record of it replayed as identical (issue 40 §4:
    8,000 of them in a log). Replay checks each record against its node's clock: one between the
    ticks of a 50 Hz source, or a second one at a tick, is a divergence that names the node."""
    from retriever.log.writer import LogFile, LogWriter

    pipe = chain(Smoother)
    pipe.run(duration=1.0)
    graph = pipe.compile()
    trace = pipe.trace
    forged = [("counter", (20_000_000 * k + 7_000_000, 0), {}, (), "ok", None, 0, 0) for k in range(5)]
    forged.append(("counter", (40_000_000, 0), {}, (), "ok", None, 0, 0))  # its third tick, again
    trace.raw_steps.extend(forged)
    writer = LogWriter(LogFile(tmp_path / "forged.mcap"), graph, backend="zenoh")
    writer.write(trace)
    writer.close(trace, 1_000_000_000)
    report = replay(read_log(tmp_path / "forged.mcap"))
    assert not report.identical
    assert report.nodes["counter"].divergent == len(forged), report.nodes["counter"]
    assert {(d.node, d.what) for d in report.divergences} == {("counter", "tick")}, report.divergences
    assert "no tick of Rate(hz=50) there" in str(report.divergences[0])
    assert report.nodes["smoother"].divergent == 0 and report.nodes["smoother"].identical > 0


def test_the_replays_clock_check_is_may_tick_at():
    """The replay checks each record's tag against its node's clock remembering the tick after
    the last one found (records come tick after tick): it says what ``clock.may_tick_at`` says,
    for ticks in order, ticks left out, repeated, before the first, between two, at microstep 1."""
    import random

    from retriever import Rate, Trigger
    from retriever.replay import TickCheck

    class Graph:
        nodes = {}

    class Node:
        def __init__(self, clock):
            self.clock = clock

    rng = random.Random(7)
    for clock in (Rate(hz=50), Rate(hz=3, offset=0.1), Rate(hz=7), Rate(hz=1e9 / 3), Trigger()):
        Graph.nodes = {"n": Node(clock)}
        on_clock = TickCheck(Graph)
        times = [clock.tick_time(k) for k in range(40)] if not clock.triggered else list(range(0, 400, 10))
        tags = []
        for t in times:
            tags += rng.choice([[(t, 0)], [], [(t, 0), (t, 0)], [(t + 1, 0), (t, 0)], [(t, 1), (t, 0)], [(t - 1, 0)]])
        tags += [(-5, 0), (times[3], 0), (times[2] + 1, 0), (times[4], 0)]
        assert [on_clock("n", tag) for tag in tags] == [clock.may_tick_at(tag) for tag in tags], clock
