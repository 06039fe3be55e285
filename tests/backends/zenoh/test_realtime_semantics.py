"""Real-time semantics of the Zenoh backend (docs/semantics.md: time, sync; docs/realtime.md).

Every test is a real run (0.5–2 s of pipeline time, one worker process per flow) observed only
through what the runtime reports: the trace (events and step records), ``pipe.counts()`` and
``pipe.stats()[node].counts`` (``garbage``, ``late``, ``incomplete``, ``overrun``,
``deadline_miss`` as the workers counted them) and the error a failed run raises. The flows live in ``semantics_flows.py``: importable
module-level classes with msgpack-able arguments, so each worker can rebuild its flow from the IR.

Timing: nothing here asserts that something is fast. The scenarios are built so that what they
check follows from lower bounds (``time.sleep(s)`` lasts at least ``s``; a frozen process answers
nothing) and from the loop's bookkeeping, never from how quickly a loaded machine schedules a
process. Where a check needs a margin, the margin is hundreds of milliseconds.

Step-record ``detail`` keys (zenoh/node/): ``incomplete`` (ports whose edge was not complete up to the
tick within its deadline), ``late`` ({port: [event id, ...]} events that arrived after their
tick ran, told on the next record), ``overrun_skipped`` (ticks skipped after a step outlasted its period, told on
the next record), ``restart_skipped`` (Rate ticks skipped while the flow's process restarted,
told on the next record), ``deadline_miss_ns``/``on_deadline_miss`` (a LET step finished after
tick + latency), ``error``/``on_error``.
"""

from __future__ import annotations

import re
import sys
from collections import Counter

import pytest

import retriever
from retriever import BackendError, CausalityError, Latest, Pipeline, Rate, StepError, Trigger, Window
from retriever.errors import RestartLimitError
from retriever.replay import replay
from retriever.trace import STEP_STATUSES, STEPPED

from ..test_conformance import _cycle_pipeline, quiet_build
from .semantics_flows import (
    BigStall,
    BigTicker,
    Echo,
    FailingTicker,
    Faulty,
    HoldsItself,
    PairProbe,
    PairSource,
    Probe,
    QuietSource,
    Sleepy,
    SlowEcho,
    Stall,
    Ticker,
    TimerSlack,
    Unsendable,
    timer_slack_ns,
    WindowProbe,
)

MS = 1_000_000
S = 1_000_000_000


# =============================================================================================
# Helpers
# =============================================================================================
def run(pipe: Pipeline, duration: float, **kw):
    return pipe.run(duration=duration, backend="zenoh", quiet=True, **kw)


def counts(pipe: Pipeline) -> Counter:
    """The run's counters (absent ones read 0); each is the sum of the nodes' own."""
    run_counts = pipe.counts()
    by_node = sum((Counter(s.counts) for s in pipe.stats().values()), Counter())
    assert +by_node == Counter(run_counts), (by_node, run_counts)
    return Counter(run_counts)


def events_by_id(trace) -> dict:
    by_id = {}
    for ev in trace.events:
        assert ev.id not in by_id, f"duplicate event id {ev.id}"
        by_id[ev.id] = ev
    return by_id


def detail(rec) -> dict:
    return rec.detail or {}


def check_trace_basics(pipe: Pipeline, trace) -> dict:
    """What holds for every real-time trace, whatever happened (returns events by id):

    - event ids are unique; per port, seqs run 0, 1, 2, … in tag order (dense, even across a
      restart or a dropped LET output);
    - one record per node and tick;
    - sampling rule (§3): every consumed event is in the trace and has tag ≤ the tick's tag, on
      complete and incomplete edges alike: an incomplete tick runs with *less*, never with later;
    - outputs (§3): a LET flow's carry exactly (t + latency, 0); an ASAP flow's are stamped at
      completion, strictly after the tick;
    - statuses (DESIGN §8) agree with the detail: ``incomplete`` names its edges, ``late`` its
      deadline miss, and a tick with an incomplete edge that stepped says ``incomplete`` unless
      it says ``late`` or ``overrun`` (which say more);
    - a skipped or failed tick produced nothing, nor did a late one whose outputs were dropped.
    """
    graph = pipe.compile()
    by_id = events_by_id(trace)
    per_port: dict = {}
    for ev in sorted(trace.events, key=lambda e: (e.tag, e.node, e.port, e.seq)):
        per_port.setdefault((ev.node, ev.port), []).append(ev.seq)
    for key, seqs in per_port.items():
        assert seqs == list(range(len(seqs))), f"{key}: seqs {seqs[:12]} are not 0, 1, 2, … in tag order"
    seen = set()
    for rec in trace.steps:
        assert (rec.node, rec.tag) not in seen, f"two records for {rec.node} at {rec.tag}"
        seen.add((rec.node, rec.tag))
        assert rec.status in STEP_STATUSES, rec
        if rec.status == "incomplete" or (rec.status in STEPPED and "incomplete" in detail(rec)):
            assert detail(rec)["incomplete"] and rec.status in ("incomplete", "late", "overrun"), rec
        assert (rec.status == "late") == ("deadline_miss_ns" in detail(rec) and rec.status != "error"), rec
        dropped = rec.status == "late" and detail(rec)["on_deadline_miss"] in ("drop", "error")
        if rec.status not in STEPPED or dropped:
            assert rec.produced == (), rec
        for ids in rec.consumed.values():
            for eid in ids:
                assert eid in by_id, f"{rec}: consumed {eid}, which is not in the trace"
                assert by_id[eid].tag <= rec.tag, f"{rec}: consumed {eid} tagged {by_id[eid].tag}, after the tick"
        latency = graph.nodes[rec.node].settings.latency_ns
        for eid in rec.produced:
            assert eid in by_id, f"{rec}: produced {eid}, which is not in the trace"
            tag = by_id[eid].tag
            if latency:
                assert tag == (rec.tag[0] + latency, 0), f"{rec}: LET output {eid} at {tag}"
            else:
                assert tag > rec.tag and tag[1] == 0, f"{rec}: ASAP output {eid} at {tag}, not after its tick"
    return by_id


def tick_index(tag, hz: int, offset_ns: int = 0) -> int:
    k, rest = divmod((tag[0] - offset_ns) * hz, S)
    assert rest == 0 and tag[1] == 0, f"{tag} is not a tick of Rate({hz})"
    return k


# =============================================================================================
# 1. on_error
# =============================================================================================
def faulty_pipeline(name: str, on_error: str, hz: int = 20) -> Pipeline:
    """counter @ Rate(hz) emits 0, 1, 2, … → faulty @ Trigger raises on x == 3, once."""
    with Pipeline(name) as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=hz)
        bad = Faulty(fail_at=[3], message="kaboom-17").configure(name="faulty", on_error=on_error) @ Trigger("x")
        src.then(bad, sync=Latest())
    return pipe


def test_on_error_stop_raises_step_error_naming_node_and_user_message():
    pipe = faulty_pipeline("err_stop", "stop")
    with pytest.raises(StepError) as info:
        run(pipe, 1.5)
    err = info.value
    assert err.node == "faulty"
    assert "faulty" in str(err) and "kaboom-17 at x=3" in str(err), str(err)
    assert "ValueError" in str(err)
    assert err.tag[0] > 0
    # where in the flow's code, from the worker: the raise line of Faulty.step
    assert re.search(r'worker traceback:\n.*File ".*semantics_flows\.py", line \d+, in step\n.*raise ValueError',
                     str(err), re.DOTALL), str(err)
    # the failing tick is in the trace, flushed before the worker reported the failure
    errors = [s for s in pipe.trace.steps_of("faulty") if s.status == "error"]
    assert len(errors) == 1, pipe.trace.steps_of("faulty")
    rec = errors[0]
    assert rec.tag == err.tag
    assert detail(rec)["error"] == "ValueError: kaboom-17 at x=3" and detail(rec)["on_error"] == "stop"
    assert rec.consumed == {"x": (("counter", "value", 3),)}
    assert not [s for s in pipe.trace.steps_of("faulty") if s.tag > rec.tag], "faulty ticked after it failed"


def test_on_error_skip_tick_records_the_error_and_goes_on_with_the_same_state():
    pipe = faulty_pipeline("err_skip", "skip_tick")
    trace = run(pipe, 1.0)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("faulty")
    errors = [s for s in recs if s.status == "error"]
    assert len(errors) == 1, recs
    bad = errors[0]
    assert bad.consumed == {"x": (("counter", "value", 3),)}
    assert bad.produced == ()
    assert detail(bad) == {"error": "ValueError: kaboom-17 at x=3", "on_error": "skip_tick"}
    later = [s for s in recs if s.tag > bad.tag]
    assert len(later) >= 3 and all(s.status == "ok" for s in later), later
    # same process, same state: the call counter counts the failed call too and never resets
    reports = [by_id[s.produced[0]].value for s in recs if s.status == "ok"]
    assert len({r["pid"] for r in reports}) == 1
    assert [r["calls"] for r in reports] == [i + 1 for i in range(len(recs)) if recs[i].status == "ok"]
    assert 3 not in [r["x"] for r in reports]
    assert counts(pipe)["garbage"] == 0


@pytest.mark.parametrize("on_error", ["skip_tick", "stop"])
def test_a_source_that_fails_or_outputs_nothing_is_recorded_as_any_flow(on_error):
    """A Rate source's ticks take the loop's short pass (node/source.py, PlainSource.one_pass): its error, a tick
    that outputs nothing, and its consumer see what a flow with inputs would."""
    with Pipeline(f"src_{on_error}") as pipe:
        src = FailingTicker(fail_at=[3], quiet_at=[5]).configure(name="src", on_error=on_error) @ Rate(hz=20)
        src.then(Faulty(fail_at=[]).configure(name="sink") @ Trigger("x"), sync=Latest())
    if on_error == "stop":
        with pytest.raises(StepError, match=r"src.*source failed at k=3"):
            run(pipe, 1.0)
        recs = pipe.trace.steps_of("src")
        assert [s.status for s in recs] == ["ok"] * 3 + ["error"], recs
        return
    trace = run(pipe, 1.0)
    recs = trace.steps_of("src")
    assert [s.status for s in recs] == ["ok"] * 3 + ["error"] + ["ok"] * (len(recs) - 4), recs
    assert detail(recs[3]) == {"error": "ValueError: source failed at k=3", "on_error": "skip_tick"}
    assert recs[3].produced == () and recs[5].produced == ()
    assert [len(s.produced) for s in recs[:8]] == [1, 1, 1, 0, 1, 0, 1, 1]
    by_id = check_trace_basics(pipe, trace)
    seen = [by_id[s.produced[0]].value["x"] for s in trace.steps_of("sink")]
    assert seen == [k for k in range(len(recs)) if k not in (3, 5)][:len(seen)] and len(seen) >= 10, seen


def test_a_quiet_source_keeps_every_record_and_its_consumer_on_time():
    """A source whose steps return nothing runs in node/source.py's PlainSource.run_quiet, a lean loop of its
    own: each tick still has its record (an error and an overrun too, and the ticks the overrun
    skipped are counted), the events it does emit arrive where a flow with inputs would put
    them, and its consumer, on the same Rate, ticks on time throughout."""
    with Pipeline("quiet_src") as pipe:
        src = QuietSource(emit_at=[6, 7, 14], fail_at=[3], sleep_at={9: 0.12}).configure(
            name="src", on_error="skip_tick") @ Rate(hz=20)
        src.then(Probe().configure(name="sink") @ Rate(hz=20), sync=Latest(), deadline=0.3)
    trace = run(pipe, 1.0)
    recs = trace.steps_of("src")
    statuses = [s.status for s in recs]
    assert statuses[:10] == ["ok"] * 3 + ["error"] + ["ok"] * 5 + ["overrun"], statuses
    assert detail(recs[3]) == {"error": "ValueError: quiet source failed at k=3", "on_error": "skip_tick"}
    skipped = counts(pipe)["overrun"]
    assert skipped >= 1 and detail(recs[10]) == {"overrun_skipped": skipped}, (skipped, recs[10])
    assert len(recs) + skipped == 20, (len(recs), skipped)  # every tick with t < 1 s ran or was skipped
    by_id = check_trace_basics(pipe, trace)
    emitted = [by_id[s.produced[0]].value for s in recs if s.produced]
    assert emitted == [6, 7, 14], emitted
    sink = trace.steps_of("sink")
    assert len(sink) == 20 and all(s.status == "ok" for s in sink), [s.status for s in sink]
    seen = [by_id[s.consumed["x"][0]].value if s.consumed.get("x") else None for s in sink]
    assert seen[:7] == [None] * 7 and seen[7:9] == [6, 7] and 14 in seen, seen  # (the tick before's)


def test_sys_exit_in_a_step_is_that_steps_error_as_in_process():
    """sys.exit(3) in a step ended its worker process, and the run with a process that "exited
    with code 3"; in-process it is the step's error (tests/test_errors.py): here too."""
    with Pipeline("exits") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        bad = Faulty(fail_at=[3], exit_code=3).configure(name="faulty", on_error="skip_tick") @ Trigger("x")
        src.then(bad, sync=Latest())
    trace = run(pipe, 1.0)
    recs = trace.steps_of("faulty")
    errors = [s for s in recs if s.status == "error"]
    assert [detail(s) for s in errors] == [{"error": "SystemExit: 3", "on_error": "skip_tick"}], recs
    assert all(s.status == "ok" for s in recs if s.tag > errors[0].tag) and recs[-1].tag > errors[0].tag
    with Pipeline("exits_stop") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(Faulty(fail_at=[3], exit_code=3).configure(name="faulty") @ Trigger("x"), sync=Latest())
    with pytest.raises(StepError, match=r"faulty\.step\(\) raised (RemoteError: )?SystemExit: 3"):
        run(pipe, 1.0)


def test_on_error_restart_runs_a_fresh_flow_in_a_new_process():
    pipe = faulty_pipeline("err_restart", "restart")
    trace = run(pipe, 2.0)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("faulty")
    errors = [s for s in recs if s.status == "error"]
    assert len(errors) == 1, recs
    bad = errors[0]
    assert detail(bad) == {"error": "ValueError: kaboom-17 at x=3", "on_error": "restart"}
    assert bad.consumed == {"x": (("counter", "value", 3),)}
    before = [by_id[s.produced[0]].value for s in recs if s.tag < bad.tag]
    after = [by_id[s.produced[0]].value for s in recs if s.tag > bad.tag]
    assert [r["x"] for r in before] == [0, 1, 2]
    assert after, "no step succeeded after the restart"
    assert all(s.status == "ok" for s in recs if s.tag > bad.tag)
    old_pid = {r["pid"] for r in before}
    new_pid = {r["pid"] for r in after}
    assert len(old_pid) == 1 and len(new_pid) == 1 and old_pid != new_pid, (old_pid, new_pid)
    assert pipe.session.worker_pids()["faulty"] == new_pid.pop()
    # fresh state (reset()): the new process counts its calls from 1 again
    assert [r["calls"] for r in after] == list(range(1, len(after) + 1))
    # the failed tick is not re-run, and later ticks consume later events
    assert min(r["x"] for r in after) > 3
    # the restarted flow continues the port's seqs (checked dense in check_trace_basics)
    assert [e.seq for e in trace.events_of("faulty", "report")] == list(range(len(before) + len(after)))


def test_on_error_restart_stops_past_its_restart_budget():
    """A flow that fails on every input, under on_error="restart" with max_restarts=2: its third
    failure stops the run with the in-process RestartLimitError naming it, and the restarts are
    counted (it was restarted 18 times in 5 s, and the run returned as if nothing happened)."""
    with Pipeline("restart_budget") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        bad = Faulty(fail_at=list(range(10_000)), message="always").configure(
            name="faulty", on_error="restart", max_restarts=2, restart_window=60.0) @ Trigger("x")
        src.then(bad, sync=Latest())
    with pytest.raises(RestartLimitError, match=r"^flow 'faulty' failed again after 2 restart\(s\) within 60 s "
                                                r"\(max_restarts=2, restart_window=60\): ValueError: always at x=\d+ "
                                                r"\(tick at t=\d+\.\d+s m=0\)\n    hint: fix what makes 'faulty' fail"):
        run(pipe, 30.0)  # a bound only: the third failure ends the run
    assert pipe.stats()["faulty"].counts.get("restarts") == 2
    assert [s.status for s in pipe.trace.steps_of("faulty")].count("error") == 3


def test_a_run_that_ends_while_a_restarted_flow_starts_stops_its_new_process_at_once(capfd):
    """The run ends while a restarted flow's new process is still starting (importing, waiting
    for its neighbours): that process has nothing to send, so it is told to stop at once. It
    was left to the stop's grace, then its stacks were printed and it was SIGKILLed."""
    with Pipeline("restart_at_end") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        bad = Faulty(fail_at=[9, 10, 11, 12], message="late").configure(name="faulty", on_error="restart") @ Trigger("x")
        src.then(bad, sync=Latest())
    run(pipe, 0.5)  # x = 9 at 0.4 s: the new process cannot be ready by 0.5 s
    assert counts(pipe)["restarts"] == 1
    err = capfd.readouterr().err
    assert "did not stop within" not in err and "SIGKILL" not in err, err


def test_on_error_restart_of_a_let_flow_publishes_the_outputs_it_held():
    """A LET flow holds each output until tick + latency. When a step raises and the flow's
    process is restarted, the outputs it still held are published first: their seqs are in
    earlier step records, and a gap in a stream's seqs would leave every consumer of it
    incomplete for the rest of the run."""
    with Pipeline("let_restart") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        bad = Faulty(fail_at=[3], message="kaboom-18").configure(name="faulty", on_error="restart",
                                                                  latency=0.15) @ Trigger("x")
        src.then(bad, sync=Latest())
    trace = run(pipe, 2.0)
    check_trace_basics(pipe, trace)  # every produced event is in the trace; seqs dense
    recs = trace.steps_of("faulty")
    bad_tick = next(s for s in recs if s.status == "error").tag
    held = [s for s in recs if s.produced and bad_tick[0] - 150 * MS < s.tag[0] < bad_tick[0]]
    assert held, "no output was held when the step raised"  # x = 1, 2: due after x = 3's tick
    assert any(s.tag > bad_tick and s.produced for s in recs), "no step succeeded after the restart"


def test_a_restarted_flow_takes_over_its_inputs_and_pending_ticks_and_the_log_replays(tmp_path):
    """A restart spawns a new process, which takes over the old one's state (input buffers and
    streams, ticks due, seqs) once it listens to the same inputs: no input is lost meanwhile.
    So a triggered flow runs a tick for every event (late, after the restart), a Rate flow skips
    the ticks that came due meanwhile but the newest (counted as ``restart_skipped`` and told on
    its next record), and the log replays bit for bit, the replay resetting the flow at the
    error record; its consumer gets every output of both processes. Before the takeover the new
    process started with empty buffers: its first tick was skipped as missing and the replay
    diverged there; the ticks due meanwhile had no record and were not counted."""
    with Pipeline("takeover", deadline=1.0) as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        on_events = Faulty(fail_at=[3], with_pid=False).configure(name="on_events", on_error="restart") @ Trigger("x")
        on_rate = Faulty(fail_at=[5, 6], with_pid=False).configure(name="on_rate", on_error="restart") @ Rate(hz=10)
        sink = Probe().configure(name="sink") @ Trigger("x")
        src.then(on_events, sync=Latest())
        src.then(on_rate, sync=Latest())
        on_events.then(sink, sync=Latest(), map={"report": "x"})
    path = tmp_path / "run.mcap"
    seconds = 5  # time enough for a slow restart (a loaded 2-core machine took over 2.5 s)
    trace = run(pipe, float(seconds), log=path)
    by_id = check_trace_basics(pipe, trace)
    assert counts(pipe)["garbage"] == 0

    # every event of the counter triggered a tick of on_events that consumed it, restart or not
    events = trace.events_of("counter", "value")
    recs = trace.steps_of("on_events")
    assert [s.tag for s in recs] == [e.tag for e in events if e.tag[0] < seconds * S]
    assert [s.consumed["x"] for s in recs] == [(e.id,) for e in events if e.tag[0] < seconds * S]
    assert [s.status for s in recs].count("error") == 1
    reports = [by_id[s.produced[0]].value for s in recs if s.status == "ok"]
    assert [r["x"] for r in reports] == [x for x in range(len(recs)) if x != 3]
    assert [r["calls"] for r in reports] == [1, 2, 3] + list(range(1, len(reports) - 2))  # reset
    # downstream, the new process's outputs continue the old one's stream: nothing stalls
    produced = [s.produced for s in recs if s.produced and by_id[s.produced[0]].tag[0] < seconds * S]
    assert [s.consumed["x"] for s in trace.steps_of("sink")] == produced

    # on_rate: each of its 50 ticks ran or was skipped while its flow restarted, and says so
    recs = trace.steps_of("on_rate")
    errors = [s for s in recs if s.status == "error"]
    assert len(errors) == 1, recs
    skipped = pipe.stats()["on_rate"].counts.get("restart_skipped", 0)
    assert len(recs) + skipped == seconds * 10, (len(recs), skipped)
    after = [s for s in recs if s.tag > errors[0].tag]
    assert after and all(s.status == "ok" for s in after), after
    assert detail(after[0]).get("restart_skipped", 0) == skipped, after[0]
    assert all(tick_index(s.tag, 10) == k for k, s in enumerate(recs[:recs.index(errors[0]) + 1]))

    report = replay(retriever.read_log(path))
    assert report.identical, report.divergences[:3]
    assert report.nodes["on_events"].replayed == len(trace.steps_of("on_events"))


def test_a_restart_across_the_runs_end_still_runs_the_tick_triggered_before_it():
    """The step at x = 18 (t = 0.9 s of a 1 s run) raises; x = 19 triggers a tick at 0.95 s while
    the flow restarts. The new process takes over after the end, when the counter has finished
    (it does not wait for an answer from a finished node), and runs that tick late."""
    with Pipeline("restart_at_end") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        bad = Faulty(fail_at=[18], with_pid=False).configure(name="faulty", on_error="restart") @ Trigger("x")
        src.then(bad, sync=Latest())
    trace = run(pipe, 1.0)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("faulty")
    assert [s.consumed["x"] for s in recs] == [(e.id,) for e in trace.events_of("counter", "value")]
    assert [s.status for s in recs][-3:] == ["ok", "error", "ok"]
    assert by_id[recs[-1].produced[0]].value == {"calls": 1, "x": 19}


def test_an_output_that_cannot_be_sent_stops_the_run_naming_its_port_and_time():
    """In-process an output goes by reference; between processes it must encode. One that cannot
    stops the run with the node, port and event time, not as a crash of the worker."""
    with Pipeline("unsendable") as pipe:
        Unsendable().configure(name="odd") @ Rate(hz=10)
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "odd.value: the event at t=0.2" in msg and "cannot be sent to another process" in msg, msg
    assert "cannot encode a value of type builtins.object" in msg and "crashed" not in msg, msg
    assert [s.tag[0] for s in pipe.trace.steps_of("odd")] == [0, 100 * MS]  # the two before it


def test_an_output_that_holds_itself_stops_the_run_naming_its_port_and_time():
    """A list appended to itself can be neither made read-only (an emitted value is immutable)
    nor sent: the run stops with the node, port and tick and what is wrong with the value, not
    with a RecursionError from deep in the worker (a crash)."""
    with Pipeline("holds_itself") as pipe:
        HoldsItself().configure(name="odd") @ Rate(hz=10)
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "odd.value: the step at t=0.100000000s m=0 returned a value the run cannot send or record: cannot " \
           "encode a list nested too deeply (it may contain itself" in msg, msg
    assert "RecursionError" not in msg and "crashed" not in msg, msg
    assert [s.tag[0] for s in pipe.trace.steps_of("odd")] == [0]  # the one before it


# =============================================================================================
# 2. Edge deadlines: complete, incomplete, late
# =============================================================================================
def test_busy_asap_producer_still_completes_its_edges():
    """An ASAP producer blocked in step() (time.sleep, 0.6 s) promises, through its progress
    queryable, that its next output is stamped no earlier than its clock: the consumer's edge is
    complete up to every tick and the consumer does not wait for the deadline (0.2 s, far
    shorter than the block). The blocked step's output is stamped at completion."""
    with Pipeline("busy_asap") as pipe:
        prod = Sleepy(sleep=0.6, at=[2]).configure(name="prod") @ Rate(hz=10)
        probe = Probe().configure(name="probe") @ Rate(hz=20)
        prod.then(probe, sync=Latest(), deadline=0.2)
    trace = run(pipe, 1.2)
    by_id = check_trace_basics(pipe, trace)
    assert counts(pipe)["incomplete"] == 0, [s for s in trace.steps_of("probe") if "incomplete" in detail(s)]
    assert not [s for s in trace.steps_of("probe") if "incomplete" in detail(s)]
    blocked = next(s for s in trace.steps_of("prod") if by_id[s.produced[0]].value == 2)
    assert blocked.tag == (200 * MS, 0)
    assert by_id[blocked.produced[0]].tag[0] >= blocked.tag[0] + 600 * MS  # stamped when it finished
    # while it was blocked, the probe's ticks saw the previous value (the newest with tag ≤ τ)
    during = [s for s in trace.steps_of("probe") if 250 * MS <= s.tag[0] < 800 * MS]
    assert during
    for s in during:
        assert [by_id[i].value for i in s.consumed["x"]] == [1], s


def test_blocked_let_producer_makes_the_edge_incomplete_and_its_late_event_is_never_consumed_early(tmp_path):
    """A LET producer (latency 50 ms) blocked 0.8 s in its tick at 0.2 s promises nothing past
    0.25 s (its output's tag) until it finishes: the consumer's ticks from 0.25 s wait the edge's
    deadline (30 ms), then run with what they have, marked incomplete. The output (tag 0.25 s)
    arrives after those ticks ran: it is late, counted and told by id on the consumer's next
    record, no tick before that one consumes it, and the log replays (the replay puts it in the
    consumer's buffer at that record, as the run did)."""
    with Pipeline("blocked_let") as pipe:
        prod = Sleepy(sleep=0.8, at=[2]).configure(name="prod", latency=0.05) @ Rate(hz=10)
        probe = Probe().configure(name="probe") @ Rate(hz=20)
        prod.then(probe, sync=Latest(), deadline=0.03)
    path = tmp_path / "blocked.mcap"
    trace = run(pipe, 1.5, log=path)
    check_trace_basics(pipe, trace)
    recs = trace.steps_of("probe")
    incomplete = [s for s in recs if "incomplete" in detail(s)]
    assert incomplete, recs
    assert all(detail(s)["incomplete"] == ["x"] for s in incomplete)
    assert counts(pipe)["incomplete"] == len(incomplete)
    # the tick at the blocked output's own tag could not complete (the frontier stood at 0.25 s)
    assert (250 * MS, 0) in [s.tag for s in incomplete], incomplete
    # no tick saw the blocked tick's output (tag 0.25 s): while it was blocked (it finishes at
    # 1.0 s at the earliest; 100 ms of margin for a loaded machine), ticks ran incomplete with
    # the output before it
    late_event = next(e for e in trace.events_of("prod") if e.value == 2)
    assert late_event.tag == (250 * MS, 0)
    blocked_window = [s for s in recs if 300 * MS <= s.tag[0] < 900 * MS]
    assert blocked_window and all("incomplete" in detail(s) for s in blocked_window), blocked_window
    for s in blocked_window:
        assert s.consumed["x"] == (("prod", "value", 1),), s
    # it arrived after ticks at or past its tag had run: late, counted, told on a later record
    assert counts(pipe)["late"] >= 1
    assert pipe.stats()["probe"].counts["late"] == counts(pipe)["late"]  # the consumer counted them
    told = [tuple(i) for s in recs for ids in detail(s).get("late", {}).values() for i in ids]
    assert 1 <= len(told) <= counts(pipe)["late"]
    assert late_event.id in told, told
    assert all(set(detail(s).get("late", {})) <= {"x"} for s in recs)
    # … and consumed by no tick before the record that names it (the first whose buffer had it)
    named_at = next(s.tag for s in recs if late_event.id in
                    [tuple(i) for ids in detail(s).get("late", {}).values() for i in ids])
    assert all(late_event.id not in ids for s in recs if s.tag < named_at for ids in s.consumed.values())
    # given to the replay's consumer before that record, its ticks from 0.3 s would consume it
    report = replay(retriever.read_log(path))
    assert report.identical, "\n".join(map(str, report.divergences))
    assert report.nodes["probe"].replayed == len(recs)
    # the producer's own record says it missed its LET deadline; its output kept tag t + latency
    blocked = next(s for s in trace.steps_of("prod") if s.tag == (200 * MS, 0))
    assert detail(blocked)["on_deadline_miss"] == "publish_late"
    assert detail(blocked)["deadline_miss_ns"] >= 700 * MS
    # once it caught up, the edge completes again
    assert any("incomplete" not in detail(s) for s in recs if s.tag > incomplete[-1].tag)


def test_an_output_that_came_after_its_consumers_last_tick_is_withheld_from_the_replay_too(tmp_path):
    """The LET producer is blocked past the run's end in its tick at 0.7 s: its output (tag 0.75 s)
    comes after the consumer's last tick, so no record names it late, and the consumer's ticks
    from 0.75 s ran incomplete without it. Their records say what each stream had (``had_below``):
    the replay withholds the output from them, as the run did (it gave it to them: DIVERGED). A
    consumer killed while behind its producers is the same case (a cold review's find)."""
    with Pipeline("after_the_last_tick") as pipe:
        prod = Sleepy(sleep=0.6, at=[7]).configure(name="prod", latency=0.05) @ Rate(hz=10)
        probe = Probe().configure(name="probe") @ Rate(hz=20)
        prod.then(probe, sync=Latest(), deadline=0.03)
    path = tmp_path / "after.mcap"
    trace = run(pipe, 1.0, log=path)
    recs = trace.steps_of("probe")
    log = retriever.read_log(path)
    blocked = next(e for e in log.iter_events() if e.node == "prod" and e.tag == (750 * MS, 0))
    named = {tuple(i) for s in recs for ids in detail(s).get("late", {}).values() for i in ids}
    assert blocked.id not in named and all(blocked.id not in ids for s in recs for ids in s.consumed.values())
    incomplete = [s for s in recs if s.tag >= (750 * MS, 0)]
    assert incomplete and all(detail(s)["incomplete"] == ["x"] for s in incomplete), incomplete
    assert all(detail(s)["had_below"] == {"x": [["prod", "value", 7]]} for s in incomplete), incomplete
    report = replay(log)
    assert report.identical, "\n".join(map(str, report.divergences))
    assert report.nodes["probe"].replayed == len(recs)


def test_a_slow_policys_late_outputs_still_reach_the_ticks_after_they_arrive_and_the_log_replays(tmp_path):
    """issue 19, §2: a LET policy (latency 0.2 s) whose step takes 0.3 s at two of its ticks and
    is on time at the others. Its late outputs are never applied to the controller's ticks that
    ran before they arrived, but every tick after, by their tags, as any other event: the
    controller goes on with the late output, not the one before it (it used to run on the stale
    one, or starve, for ever). The record that first had it names it; the log replays."""
    with Pipeline("slow_policy") as pipe:
        policy = Sleepy(sleep=0.3, at=[1, 3]).configure(name="policy", latency=0.2) @ Rate(hz=2)
        controller = Probe().configure(name="controller") @ Rate(hz=50)
        policy.then(controller, sync=Latest(), deadline=0.02)
    path = tmp_path / "slow.mcap"
    trace = run(pipe, 2.5, log=path)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("controller")
    named = {tuple(i): s.tag for s in recs for ids in detail(s).get("late", {}).values() for i in ids}
    late_outputs = {e.id for e in trace.events_of("policy") if e.value in (1, 3)}
    assert late_outputs <= set(named), (late_outputs, named)  # the slow ticks' outputs came late
    assert counts(pipe)["late"] >= 2
    for event_id in late_outputs:
        tag = by_id[event_id].tag
        before = [s for s in recs if tag <= s.tag < named[event_id]]
        after = [s for s in recs if named[event_id] <= s.tag < (tag[0] + 450 * MS, 0)]  # next output: +0.5 s
        assert before and after, (event_id, named[event_id])
        assert all(event_id not in s.consumed.get("x", ()) for s in before), before
        # Latest takes the newest event with tag ≤ τ: the late one, until the policy's next output
        assert all(s.consumed.get("x") == (event_id,) for s in after), after
    # the on-time outputs were consumed too, as always
    for e in trace.events_of("policy"):
        if e.value in (0, 2, 4) and e.tag[0] < 2500 * MS:
            assert any(s.consumed.get("x") == (e.id,) for s in recs if s.tag >= e.tag), e
    report = replay(retriever.read_log(path))
    assert report.identical, "\n".join(map(str, report.divergences))
    assert report.nodes["controller"].replayed == len(recs)


@pytest.mark.parametrize("keep", ["trace", "counters"])
def test_a_flow_whose_inputs_always_came_too_late_to_use_is_named_with_the_fix(keep):
    """Every output of a policy overruns its latency by 0.1 s, and its consumer takes only events
    at most 50 ms old (Latest(staleness=0.05)): each arrives too stale to use, so the consumer
    never steps. The run stands (its policies said so), with a warning naming the edge and the
    fix; it used to end silently with exit 0. A producer into the same port that never emits is
    not named, even without the step records that say which edge was late (keep="counters")."""
    with Pipeline("always_late") as pipe:
        policy = Sleepy(sleep=0.3).configure(name="policy", latency=0.2) @ Rate(hz=2)
        consumer = Echo().configure(name="consumer") @ Rate(hz=50)
        policy.then(consumer, sync=Latest(staleness=0.05), deadline=0.02)
        silent = QuietSource(emit_at=[]).configure(name="silent") @ Rate(hz=2)
        silent.then(consumer, sync=Latest(staleness=0.05), deadline=0.02)
    with pytest.warns(retriever.RetrieverWarning, match=r"flow 'consumer' never stepped in this run: its inputs "
                      r"were late, \d+ event\(s\) on policy\.value → consumer\.x arrived after the ticks they were "
                      r"for(.|\n)*hint: Latest\(staleness=0\.05\) on policy → consumer takes no event older than its "
                      r"staleness(.|\n)*give the producer a latency= that covers its step(.|\n)*"
                      r"policy\.then\(consumer, deadline=seconds\)") as caught:
        run(pipe, 1.6, keep=keep)
    assert not any("silent" in str(w.message) for w in caught if "never stepped" in str(w.message))
    assert pipe.stats()["consumer"].steps == 0 and counts(pipe)["late"] >= 2


def test_frozen_asap_producer_makes_the_edge_incomplete(tmp_path):
    """An ASAP producer whose whole process is frozen (SIGSTOP for 0.5 s: a machine hiccup, not a
    busy step) can neither publish nor answer progress queries: the consumer's edge is not
    complete up to its ticks; each waits the deadline (30 ms) and runs with older inputs. The log
    replays."""
    with Pipeline("frozen_asap") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        stall = Stall(seconds=0.5, at=[4]).configure(name="stall") @ Trigger("x")
        probe = Probe().configure(name="probe") @ Rate(hz=20, offset=0.01)
        src.then(stall, sync=Latest())
        stall.then(probe, sync=Latest(), deadline=0.03)
    path = tmp_path / "frozen.mcap"
    trace = run(pipe, 1.5, log=path)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("probe")
    incomplete = [s for s in recs if "incomplete" in detail(s)]
    assert incomplete, recs
    assert all(detail(s)["incomplete"] == ["x"] for s in incomplete)
    assert counts(pipe)["incomplete"] == len(incomplete)
    frozen_at = next(s.tag for s in trace.steps_of("stall") if s.consumed["x"] == (("counter", "value", 4),))
    # the stall is frozen from its tick at frozen_at for at least 0.5 s: the probe's ticks in that
    # window ran with what had arrived before (never the frozen tick's output, stamped after it
    # thawed), and some of them could not complete
    stall_events = trace.events_of("stall")
    window = [s for s in recs if frozen_at <= s.tag < (frozen_at[0] + 500 * MS, 0)]
    assert window and any("incomplete" in detail(s) for s in window), window
    for s in window:
        newest = [e for e in stall_events if e.tag <= s.tag][-1]
        assert s.consumed["x"] == (newest.id,) and newest.value <= 3, s
    # the stall ran every trigger tick once it thawed, and the edge completed again
    assert [by_id[s.produced[0]].value for s in trace.steps_of("stall")] == list(range(len(trace.steps_of("stall"))))
    assert any("incomplete" not in detail(s) for s in recs if s.tag > incomplete[-1].tag)
    report = replay(retriever.read_log(path))
    assert report.identical, "\n".join(map(str, report.divergences))


# =============================================================================================
# 3. LET deadline misses
# =============================================================================================
def let_miss_pipeline(name: str, on_deadline_miss: str, **pipe_kw) -> Pipeline:
    """let @ Rate(10), latency 50 ms, sleeps 0.3 s in its tick at 0.2 s → probe @ Trigger."""
    with Pipeline(name, **pipe_kw) as pipe:
        let = Sleepy(sleep=0.3, at=[2]).configure(
            name="let", latency=0.05, on_deadline_miss=on_deadline_miss) @ Rate(hz=10)
        probe = Probe().configure(name="probe") @ Trigger("x")
        let.then(probe, sync=Latest())
    return pipe


def test_let_deadline_miss_publish_late_keeps_the_let_tag_and_flags_the_record():
    pipe = let_miss_pipeline("miss_late", "publish_late")
    trace = run(pipe, 1.0)
    by_id = check_trace_basics(pipe, trace)  # every LET output at exactly t + latency
    miss = next(s for s in trace.steps_of("let") if s.tag == (200 * MS, 0))
    assert miss.status == "late"
    assert detail(miss)["on_deadline_miss"] == "publish_late"
    assert detail(miss)["deadline_miss_ns"] >= 250 * MS  # finished ≥ 0.5 s, due at 0.25 s
    assert len(miss.produced) == 1
    out = by_id[miss.produced[0]]
    assert out.tag == (250 * MS, 0) and out.value == 2
    assert counts(pipe)["deadline_miss"] >= 1
    assert counts(pipe)["deadline_miss"] == sum("deadline_miss_ns" in detail(s) for s in trace.steps_of("let"))
    # published, late but whole: the trigger consumer ticked at its tag and got it
    got = next(s for s in trace.steps_of("probe") if s.tag == out.tag)
    assert got.consumed == {"x": (out.id,)}


def test_let_deadline_miss_drop_publishes_nothing_for_that_step():
    pipe = let_miss_pipeline("miss_drop", "drop")
    trace = run(pipe, 1.0)
    by_id = check_trace_basics(pipe, trace)  # seqs stay dense across the drop
    miss = next(s for s in trace.steps_of("let") if s.tag == (200 * MS, 0))
    assert miss.status == "late" and detail(miss)["on_deadline_miss"] == "drop"
    assert detail(miss)["deadline_miss_ns"] >= 250 * MS
    assert miss.produced == ()
    assert 2 not in trace.values_of("let", "value")
    assert not [e for e in trace.events_of("let") if e.tag == (250 * MS, 0)]
    assert all(s.produced == () for s in trace.steps_of("let") if "deadline_miss_ns" in detail(s))
    assert all(len(s.produced) == 1 for s in trace.steps_of("let") if "deadline_miss_ns" not in detail(s))
    assert 2 not in [by_id[i].value for s in trace.steps_of("probe") for i in s.consumed["x"]]
    assert counts(pipe)["deadline_miss"] >= 1


def test_let_deadline_miss_error_stops_the_run_naming_the_node():
    pipe = let_miss_pipeline("miss_error", "error")
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "let missed its LET deadline" in msg and "t=0.200000" in msg, msg
    assert "hint: raise latency=, or set on_deadline_miss='publish_late' or 'drop'" in msg, msg
    miss = next(s for s in pipe.trace.steps_of("let") if s.tag == (200 * MS, 0))
    assert miss.status == "late" and miss.produced == ()  # the run stopped, its outputs dropped
    assert detail(miss)["on_deadline_miss"] == "error"


# =============================================================================================
# 4. Overruns
# =============================================================================================
def test_overrun_skips_the_ticks_that_came_due_and_says_so():
    """Rate(10) whose every step sleeps 0.25 s (2.5 periods): after each step the ticks that came
    due meanwhile but the newest are skipped, counted and told on the next record."""
    with Pipeline("overrun_skip") as pipe:
        Sleepy(sleep=0.25).configure(name="slow") @ Rate(hz=10)
    trace = run(pipe, 1.0)
    check_trace_basics(pipe, trace)
    recs = trace.steps_of("slow")
    ks = [tick_index(s.tag, 10) for s in recs]
    assert ks[0] == 0 and len(recs) < 10
    assert any(detail(s).get("overrun_skipped", 0) >= 1 for s in recs)
    # the gap between consecutive ticks is exactly what the later record says was skipped
    for prev, k, rec in zip(ks, ks[1:], recs[1:]):
        assert k - prev - 1 == detail(rec).get("overrun_skipped", 0), (prev, k, rec)
    # every tick below the end either ran once or was counted skipped once
    assert len(recs) + counts(pipe)["overrun"] == 10, (len(recs), counts(pipe))
    assert pipe.stats()["slow"].counts == {"overrun": 10 - len(recs)}
    assert all(s.status == "overrun" and len(s.produced) == 1 for s in recs)


def test_overrun_with_catch_up_runs_every_tick_late_in_order():
    """on_overrun="catch_up" (a simulator's physics): the ticks that came due meanwhile all run,
    late, in order; none is skipped, so a LET flow's trace is the virtual-time one."""
    with Pipeline("overrun_catch_up") as pipe:
        Sleepy(sleep=0.25).configure(name="slow", on_overrun="catch_up", latency=0.05) @ Rate(hz=10)
    trace = run(pipe, 1.0)
    check_trace_basics(pipe, trace)
    recs = trace.steps_of("slow")
    assert [tick_index(s.tag, 10) for s in recs] == list(range(10))
    assert not any("overrun_skipped" in detail(s) for s in recs)
    assert pipe.stats()["slow"].counts["overrun"] == 10
    with Pipeline("overrun_catch_up") as virtual:
        Sleepy(sleep=0.0).configure(name="slow", on_overrun="catch_up", latency=0.05) @ Rate(hz=10)
    reference = virtual.run(duration=1.0, backend="inproc")
    assert [e.value for e in trace.events_of("slow")] == [e.value for e in reference.events_of("slow")]
    assert [e.tag for e in trace.events_of("slow")] == [e.tag for e in reference.events_of("slow")]


def test_overrun_with_on_overrun_error_stops_the_run():
    with Pipeline("overrun_error") as pipe:
        Sleepy(sleep=0.25).configure(name="slow", on_overrun="error") @ Rate(hz=10)
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "slow overran its period" in msg and "t=0.000000" in msg, msg
    assert "on_overrun='skip'" in msg  # the hint


# =============================================================================================
# 5. realtime="hard" / "best_effort"
# =============================================================================================
def test_hard_realtime_stops_at_the_first_incomplete_edge():
    with Pipeline("hard_incomplete", realtime="hard") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=10)
        stall = Stall(seconds=0.8, at=[3]).configure(name="stall") @ Trigger("x")
        probe = Probe().configure(name="probe") @ Rate(hz=10, offset=0.01)
        src.then(stall, sync=Latest())
        stall.then(probe, sync=Latest(), deadline=0.15)
    with pytest.raises(BackendError) as info:
        run(pipe, 1.5)
    msg = str(info.value)
    assert "probe: input(s) x not complete up to the tick" in msg and "realtime='hard'" in msg, msg
    recs = pipe.trace.steps_of("probe")
    incomplete = [s for s in recs if "incomplete" in detail(s)]
    assert len(incomplete) == 1 and incomplete[0] == recs[-1], recs  # the first one stopped it
    assert incomplete[0].status == "skipped" and incomplete[0].consumed == {}  # before stepping


def test_hard_realtime_stops_at_an_overrun_even_with_on_overrun_skip():
    with Pipeline("hard_overrun", realtime="hard") as pipe:
        Sleepy(sleep=0.25, at=[1]).configure(name="slow", on_overrun="skip") @ Rate(hz=10)
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "slow overran its period" in msg and "t=0.100000" in msg and "realtime='hard'" in msg, msg


def test_hard_realtime_stops_at_a_let_deadline_miss_even_with_publish_late():
    pipe = let_miss_pipeline("hard_let", "publish_late", realtime="hard")
    with pytest.raises(BackendError) as info:
        run(pipe, 1.0)
    msg = str(info.value)
    assert "let missed its LET deadline" in msg and "t=0.200000" in msg, msg
    assert "realtime='soft', where on_deadline_miss (now 'publish_late') decides" in msg, msg


@pytest.mark.parametrize("stop", ["deadline_miss_drop", "deadline_miss_error", "hard_incomplete"])
def test_a_log_whose_steps_dropped_outputs_or_stopped_the_run_replays(tmp_path, stop):
    """What the run did at a step, the replay does: a LET step that missed its deadline had its
    outputs dropped (``drop``; ``error``, which also stops the run), so the replay drops what
    the step returns and reuses its seqs; a tick that realtime="hard" stopped before stepping
    (an incomplete edge) is not stepped again. Without that, the first diverges at the step
    and at every later output's seq, the others at the stopping record."""
    on_miss = {"deadline_miss_drop": "drop", "deadline_miss_error": "error"}.get(stop, "publish_late")
    with Pipeline(stop, realtime="hard" if stop == "hard_incomplete" else "soft") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=10)
        if stop == "hard_incomplete":
            mid = Stall(seconds=0.8, at=[3]).configure(name="mid") @ Trigger("x")
        else:  # the LET flow's step at x == 2 sleeps 0.3 s: 0.25 s past its deadline
            mid = SlowEcho(sleep=0.3, at=[2]).configure(
                name="mid", latency=0.05, on_deadline_miss=on_miss) @ Trigger("x")
        probe = Probe().configure(name="probe") @ Rate(hz=10, offset=0.01)
        src.then(mid, sync=Latest())
        mid.then(probe, sync=Latest(), deadline=0.15)
    path = tmp_path / "run.mcap"
    if stop == "deadline_miss_drop":
        trace = run(pipe, 1.0, log=path)
    else:
        with pytest.raises(BackendError):
            run(pipe, 1.5, log=path)
        trace = pipe.trace
    check_trace_basics(pipe, trace)
    node = "probe" if stop == "hard_incomplete" else "mid"
    last = trace.steps_of(node)[-1] if stop != "deadline_miss_drop" else next(
        s for s in trace.steps_of(node) if s.status == "late")
    assert last.status == ("skipped" if stop == "hard_incomplete" else "late"), last
    report = replay(retriever.read_log(path))
    assert report.identical, "\n".join(map(str, report.divergences))
    stopped = 1 if stop == "hard_incomplete" else 0  # the tick that did not step is not replayed
    assert report.nodes[node].replayed == len(trace.steps_of(node)) - stopped


def test_best_effort_never_stops_for_overruns_or_deadline_misses():
    with Pipeline("best_effort", realtime="best_effort") as pipe:
        Sleepy(sleep=0.25).configure(name="slow", on_overrun="error") @ Rate(hz=10)
        let = Sleepy(sleep=0.3, at=[2]).configure(
            name="let", latency=0.05, on_deadline_miss="error", on_overrun="error") @ Rate(hz=10)
        probe = Probe().configure(name="probe") @ Trigger("x")
        let.then(probe, sync=Latest())
    trace = run(pipe, 1.0)  # does not raise
    by_id = check_trace_basics(pipe, trace)
    c = counts(pipe)
    assert c["overrun"] >= 2 and c["deadline_miss"] >= 1, c
    assert any(detail(s).get("overrun_skipped", 0) >= 1 for s in trace.steps_of("slow"))
    assert trace.steps_of("slow")[-1].tag[0] >= 500 * MS  # it went on after its overruns
    miss = next(s for s in trace.steps_of("let") if s.tag == (200 * MS, 0))
    # counted, flagged, and published late (an "error" miss is downgraded to publish_late)
    assert miss.status == "late" and detail(miss)["on_deadline_miss"] == "publish_late"
    assert detail(miss)["deadline_miss_ns"] >= 250 * MS
    assert by_id[miss.produced[0]].tag == (250 * MS, 0)
    assert all(s.status == "overrun" for s in trace.steps_of("slow"))
    assert all(s.status in STEPPED for s in trace.steps)


# =============================================================================================
# 6. Sampling rule and causality in an ASAP run; its log replays
# =============================================================================================
def test_mixed_rate_asap_run_is_causal_and_its_log_replays(tmp_path):
    with Pipeline("mixed", deadline=1.0) as pipe:
        cam = Ticker().configure(name="cam") @ Rate(hz=30)
        pol = Echo().configure(name="pol") @ Rate(hz=10)
        ctrl = Probe().configure(name="ctrl") @ Trigger("x")
        mon = WindowProbe().configure(name="mon") @ Rate(hz=5, offset=0.015)  # between cam's ticks
        cam.then(pol, sync=Latest())
        pol.then(ctrl, sync=Latest())
        cam.then(mon, sync=Window(buffer_size=3))
    path = tmp_path / "run.mcap"
    trace = run(pipe, 1.5, log=path)
    by_id = check_trace_basics(pipe, trace)
    assert counts(pipe)["garbage"] == 0
    complete = [s for s in trace.steps if "incomplete" not in detail(s)]
    assert len(complete) > 20
    for s in complete:
        for ids in s.consumed.values():
            assert all(by_id[i].tag <= s.tag for i in ids), s
        assert all(by_id[i].tag > s.tag for i in s.produced), s
    # every node ran; trigger ticks are at the tags of the events that triggered them
    assert {s.node for s in trace.steps} == {"cam", "pol", "ctrl", "mon"}
    for s in trace.steps_of("ctrl"):
        assert by_id[s.consumed["x"][0]].tag == s.tag, s
    # Window hands the newest ≤ 3 events with tag ≤ τ, oldest first
    for s in trace.steps_of("mon"):
        ids = s.consumed.get("x", ())
        assert len(ids) <= 3 and [by_id[i].tag for i in ids] == sorted(by_id[i].tag for i in ids), s
    log = retriever.read_log(path)
    report = replay(log)
    assert report.identical, report.divergences[:3]
    assert sum(n.replayed for n in report.nodes.values()) == len(trace.steps) - len(trace.steps_of("cam"))


def test_let_pipeline_without_incomplete_edges_has_no_late_events():
    """DESIGN §5: with LET flows and no incomplete edges, a real-time run is as deterministic as
    a virtual-time run. pair @ Rate(25), latency 40 ms, emits k on ports a and b; probe @ Rate(25)
    ticks exactly when each pair is released, at τ = (k + 1) · 40 ms, and must see both halves
    of pair k (tag τ ≤ τ): never a late event, never [k - 1, k] or an older pair.

    Regression: at e6109b6 a producer's frontier could overtake its own data (zenoh-python runs
    each subscriber's callback on its own thread, so a progress message, a query reply or the
    other port's data message reached the inbox first; and the progress queryable promised past
    outputs taken off ``held`` but not yet put): 2–13 late events per run here. Fixed in 0351d30
    (streams taken in seq order, progress gated on the seqs it follows, ``sending``)."""
    with Pipeline("let_pairs", deadline=1.0) as pipe:
        pair = PairSource().configure(name="pair", latency=0.04) @ Rate(hz=25)
        probe = PairProbe().configure(name="probe") @ Rate(hz=25)
        pair.then(probe, sync=Latest())
    trace = run(pipe, 2.0)
    by_id = check_trace_basics(pipe, trace)
    recs = trace.steps_of("probe")
    assert not [s for s in recs if "incomplete" in detail(s)], "deadline=1.0 s: no edge should be incomplete"
    assert [tick_index(s.tag, 25) for s in recs] == list(range(50))
    wrong = []
    for s in recs[1:]:
        want = tick_index(s.tag, 25) - 1
        if by_id[s.produced[0]].value != [want, want]:
            wrong.append((s.tag, by_id[s.produced[0]].value, want, detail(s)))
    assert counts(pipe)["late"] == 0 and not wrong, (counts(pipe), wrong[:5])


# =============================================================================================
# Backpressure (messages are published with CongestionControl.BLOCK: none is dropped)
# =============================================================================================
def test_a_consumer_frozen_for_a_moment_still_gets_every_event():
    """A consumer whose process is frozen for 0.8 s (SIGSTOP: a hiccup, a debugger, swap) while a
    camera sends it 2 MB frames at 25 Hz: once it thaws, it must tick on every frame the camera
    published (a Trigger flow ticks at the tag of each event arriving on its trigger port, §3),
    the ones sent while it was frozen and the ones after."""
    with Pipeline("frozen_consumer", deadline=0.05) as pipe:
        cam = BigTicker(size=2_000_000).configure(name="cam") @ Rate(hz=25)
        stall = BigStall(seconds=0.8, at=[3]).configure(name="stall") @ Trigger("x")
        cam.then(stall, sync=Latest())
    trace = run(pipe, 1.2)
    check_trace_basics(pipe, trace)
    sent = [e.value[0] for e in trace.events_of("cam")]
    got = trace.values_of("stall", "value")
    assert len(sent) >= 20
    assert got[-1:] == sent[-1:], f"the consumer's last frame is {got[-1:]}, the camera's {sent[-1:]}"
    assert got == sent, f"frames the consumer never got: {sorted(set(sent) - set(got))}"


# =============================================================================================
# 6. Zeno loops (docs/semantics.md, Causality)
# =============================================================================================
def test_a_zeno_loop_stops_the_run_with_the_error_it_stops_with_in_process():
    """monitor ⇄ policy, both zero-latency triggers, never stop: in-process the instant runs past
    max_microsteps and the run stops with a CausalityError naming the cycle and the tag. On
    zenoh each output is stamped when its step ends (ASAP), so time moves on at every hop; the
    microstep counts the hops instead, and the run stops at the same count with the same error
    (before this, it busy-looped for the whole duration and returned a trace)."""
    errors = {}
    for backend in ("inproc", "zenoh"):
        pipe = _cycle_pipeline(limit=10**9, max_microsteps=50)
        quiet_build(pipe)
        with pytest.raises(CausalityError) as caught:
            pipe.run(duration=3.0, backend=backend, **({"quiet": True} if backend == "zenoh" else {}))
        errors[backend] = caught.value
        assert max(s.tag[1] for s in pipe.trace.steps) <= 50, backend
    inproc, zenoh = errors["inproc"], errors["zenoh"]
    assert zenoh.cycle == inproc.cycle and set(zenoh.cycle) == {"monitor", "policy"}
    assert zenoh.tag[1] == inproc.tag[1] == 50
    assert zenoh.tag[0] > 0  # the instant began at the kick's HLC time, and time went on meanwhile
    same = re.compile(r"the instant at t=\d+\.\d+s m=50 ran past max_microsteps=50 around the cycle "
                      r"(monitor → policy → monitor|policy → monitor → policy)\n"
                      r"    hint: break the cycle in time: give a flow on it latency=")
    assert same.search(str(inproc)) and same.search(str(zenoh)), (str(inproc), str(zenoh))
    assert str(zenoh).replace(f"{zenoh.tag[0] / 1e9:.9f}", "T") == str(inproc).replace("0.000000000", "T")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is Linux's")
@pytest.mark.parametrize("virtual_time", [False, True])
def test_in_real_time_a_workers_loop_waits_with_no_timer_slack(virtual_time):
    """Linux ends a thread's timed wait up to its timer slack late (50 µs by default): a worker's
    loop, which waits for ticks, asks for 1 ns in real time. In virtual time it keeps what it had."""
    with Pipeline(f"slack_{virtual_time}") as pipe:
        TimerSlack().configure(name="slack") @ Rate(hz=20)
    run(pipe, 0.2, virtual_time=virtual_time)
    slacks = {ev.value for ev in pipe.trace.events}
    assert slacks == ({timer_slack_ns()} if virtual_time else {1}), slacks


@pytest.mark.parametrize("virtual_time", [False, True])
def test_a_flow_configured_to_spin_busy_waits_for_its_ticks_in_real_time_only(virtual_time):
    """configure(spin=): the worker stops sleeping that long before each Rate tick and busy-waits
    to it, and counts the time (spin_ns); the ticks are the same. A flow without spin never spins.
    At 4 Hz, and before the first tick (the run's start margin), the waits are longer than one
    timed wait of the loop (100 ms): it spun the whole rest of each (1.3 s of 2 s at 2 Hz)."""
    with Pipeline(f"spin_{virtual_time}") as pipe:
        Ticker().configure(name="ctrl", spin=0.001) @ Rate(hz=4)
        Ticker().configure(name="plain") @ Rate(hz=4)
    run(pipe, 1.0, virtual_time=virtual_time)
    stats = pipe.stats()
    assert [stats[n].steps for n in ("ctrl", "plain")] == [4, 4]
    assert "spin_ns" not in stats["plain"].counts
    if virtual_time:
        assert "spin_ns" not in stats["ctrl"].counts
    else:  # 4 ms in all, were the loop never kept from the CPU: 200 ms leaves room for a loaded machine
        assert 0 < stats["ctrl"].counts["spin_ns"] < 200 * MS, stats["ctrl"].counts
