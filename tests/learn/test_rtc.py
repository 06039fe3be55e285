"""Real-time chunking from event time (issue 36, section 2): what the timeline says the controller
plays of the previous chunk is checked against what the controller did play, read from a real
log's step records, at 30, 50 and 200 Hz."""

from __future__ import annotations

import numpy as np
import pytest

from retriever import ActionChunking, Latest, Pipeline, Rate, read_log
from retriever.replay import replay
from retriever.learn import ChunkTimeline, Leftover


def test_worked_example():
    """Controller at 200 Hz, policy latency 12.5 ms: a chunk from the tick at 0 arrives at
    12.5 ms; the tick at 100 ms sees the controller play that chunk's rows 18..: 3 of them
    (at 100, 105, 110 ms) before the new chunk (at 112.5 ms) takes over at 115 ms."""
    timeline = ChunkTimeline(control_hz=200, latency=0.0125)
    assert timeline.leftover(0) == Leftover((), 3)  # nothing plays yet; 0, 5, 10 ms pass before the chunk
    timeline.add(0, 40)
    left = timeline.leftover(100_000_000)
    assert left.delay == 3
    # chunk 0 started at 12.5 ms: the tick at 100 ms plays row floor(87.5 ms * 200 / s) = 17, then 18, 19 ...
    assert left.rows == tuple((0, r) for r in range(17, 40))


def test_held_last_row_and_no_latency():
    timeline = ChunkTimeline(control_hz=50, latency=0.0)
    timeline.add(0, 3)   # a chunk at tag (0, 1): the controller tick at (0, 0) does not see it
    # the tick at 100 ms: the chunk (rows at 20, 40 ms) is over: the controller holds row 2 at
    # (100, 0); the new chunk at (100, 1) is seen from 120 ms on
    assert timeline.leftover(100_000_000) == Leftover(((0, 2),), 1)


def test_a_chunk_still_on_its_way_at_the_tick_counts():
    """Latency longer than the policy's period: at the tick, the previous chunk has not started;
    the controller plays the one before it, then the previous one, then the new one."""
    timeline = ChunkTimeline(control_hz=10, latency=0.25)
    timeline.add(0, 10)            # plays from 250 ms
    timeline.add(200_000_000, 10)  # plays from 450 ms
    left = timeline.leftover(400_000_000)  # its chunk plays from 650 ms
    assert left.delay == 3  # ticks at 400, 500, 600 ms
    assert left.rows[:3] == ((0, 1), (1, 0), (1, 1))
    assert left.rows[3:] == tuple((1, r) for r in range(2, 10))


def test_chunk_rate_other_than_the_controllers():
    """ActionChunking(control_hz=25) behind a 50 Hz controller plays each row twice."""
    timeline = ChunkTimeline(control_hz=50, chunk_hz=25, latency=0.04)
    timeline.add(0, 4)
    left = timeline.leftover(60_000_000)
    assert left.delay == 2  # 60, 80 ms; the new chunk arrives at 100 ms
    assert left.rows == ((0, 0), (0, 1), (0, 1), (0, 2), (0, 2), (0, 3), (0, 3))


def test_bad_chunks_are_refused():
    with pytest.raises(ValueError, match="at least one row"):
        ChunkTimeline(control_hz=50).add(0, 0)


def rtc_pipeline(path, control_hz: float) -> Pipeline:
    """A counter, a chunking policy at 7 Hz (ticks off each controller's grid) with 70 ms latency,
    and a controller that plays its rows; every flow on LET and catching up, so that a real-time
    run is the virtual-time one."""
    from tests.learn.policies import Chunker, Counter, Player, rows_checkpoint

    catch_up = {"on_overrun": "catch_up"}
    with Pipeline("rtc", deadline=5.0) as pipe:
        source = Counter().named("counter").configure(latency=0.01, **catch_up) @ Rate(hz=10)
        policy = Chunker(str(rows_checkpoint(path)), steps=round(0.6 * control_hz), rtc=True, control_hz=control_hz) \
            .named("policy").configure(latency=0.07, **catch_up) @ Rate(hz=7)
        player = Player().named("player").configure(latency=1 / control_hz, **catch_up) @ Rate(hz=control_hz)
        source.then(policy, sync=Latest())
        policy.then(player, sync=ActionChunking(control_hz=control_hz), map={"chunk": "action"})
    return pipe


def check_leftovers(log, control_hz: int) -> int:
    """At each policy tick, the leftover it computed is, row for row, what the log's step records
    say the controller played from that tick until the new chunk arrived, and after that what the
    previous chunk's tag gives by ActionChunking's rule; the new chunk's first row is the one
    played first. Returns the number of ticks checked."""
    events = {e.id: e for e in log.iter_events()}
    value = {i: log.value(e) for i, e in events.items()}
    steps = sorted(log.iter_steps(), key=lambda s: s.tag)
    plays = [s for s in steps if s.node == "player"]  # skipped too: before the first chunk
    ticks = [s for s in steps if s.node == "policy" and s.produced]
    last_play = plays[-1].tag

    def played_at(record):
        """(chunk seq, row) the controller played at this record: the consumed chunk, the row
        found by its value (every row of the run is unique)."""
        (chunk_id,) = record.consumed["action"]
        (out,) = record.produced
        (row,) = np.flatnonzero((value[chunk_id] == value[out]).all(axis=1))
        return chunk_id[2], int(row)

    checked = 0
    for tick in ticks:
        produced = {e[1]: e for e in tick.produced}
        left, delay = value[produced["leftover"]], int(value[produced["delay"]])
        new_chunk = produced["chunk"]
        if events[new_chunk].tag > last_play:
            continue  # the run ended before the controller saw it
        later = [p for p in plays if p.tag >= (tick.tag[0], 0)]
        first_new = next(i for i, p in enumerate(later) if p.consumed.get("action") == (new_chunk,))
        assert delay == first_new, tick.tag
        assert played_at(later[first_new]) == (new_chunk[2], 0)
        checked += 1
        if tick is ticks[0]:  # no chunk was playing: nothing to join
            assert len(left) == 0 and all(p.status == "skipped" for p in later[:delay])
            continue
        assert [tuple(r) for r in left[:delay]] == [played_at(p) for p in later[:delay]], tick.tag
        if len(left) > delay:  # what the previous chunk would still play: ActionChunking's rule on its tag
            seq = left[0][0]
            old = next(e for e in events.values() if e.node == "policy" and e.port == "chunk" and e.seq == seq)
            ticks_after = later[delay:len(left)]  # the run may end first
            rest = [(seq, (p.tag[0] - old.tag[0]) * control_hz // 10**9) for p in ticks_after]
            assert [tuple(r) for r in left[delay:delay + len(rest)]] == rest
            if len(rest) == len(left) - delay:
                assert rest[-1][1] == len(value[old.id]) - 1  # to its last row
    return checked


@pytest.mark.parametrize("control_hz", [30, 50, 200])
def test_leftover_is_what_the_controller_played(tmp_path, control_hz):
    pytest.importorskip("torch", reason="the policy flow runs a torch module")
    rtc_pipeline(tmp_path / "ckpt", control_hz).run(duration=3.0, log=tmp_path / "run.mcap")
    assert check_leftovers(read_log(tmp_path / "run.mcap"), control_hz) == 20  # 7 Hz; the first tick saw no count


def test_in_real_time_on_zenoh_too(tmp_path):
    """On zenoh, each flow in its own process: the policy's count of ticks is its tick's time
    there too (catching up, never skipping), so the leftovers match what the controller played;
    and the run replays bit for bit."""
    pytest.importorskip("torch", reason="the policy flow runs a torch module")
    rtc_pipeline(tmp_path / "ckpt", 50).run(duration=3.0, backend="zenoh", quiet=True, log=tmp_path / "run.mcap")
    log = read_log(tmp_path / "run.mcap")
    assert check_leftovers(log, 50) >= 15
    assert replay(log).identical


def test_rates_and_times_are_checked():
    with pytest.raises(ValueError, match="ChunkTimeline: control_hz must be a finite number > 0, got 0"):
        ChunkTimeline(control_hz=0)
    with pytest.raises(ValueError, match="chunk_hz must be a finite number > 0, got -1; latency"):
        ChunkTimeline(control_hz=50, chunk_hz=-1, latency=-0.1)
