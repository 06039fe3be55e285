"""Crash safety: a real ``retriever run --log`` subprocess killed with SIGKILL leaves a file from
which every event written before the kill can be recovered, and the recovered log replays."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from retriever import LogError, read_log
from retriever.loading import load_pipeline
from retriever.codec import packb
from retriever.log import recover
from retriever.replay import replay, resim
from tests.log.helpers import CHUNK, QUICKSTART, RETRIEVER, ROOT, assert_cli_error, cli, cli_env, records

TIMEOUT_S = 60.0  # generous: this is a 2-core machine that may be busy
POLL_S = 0.05


def _run_until(args: list[str], tmp_path: Path, ready, what: str) -> None:
    """Start ``retriever ARGS``, poll (bounded) until ``ready()``, then SIGKILL it by PID and reap it."""
    with open(tmp_path / "stdout.txt", "wb") as out, open(tmp_path / "stderr.txt", "wb") as err:
        proc = subprocess.Popen([str(RETRIEVER), *map(str, args)], stdout=out, stderr=err, cwd=ROOT, env=cli_env())
        try:
            deadline = time.monotonic() + TIMEOUT_S
            while not ready():
                assert proc.poll() is None, (f"the run exited ({proc.returncode}) before it was killed: "
                                             + (tmp_path / "stderr.txt").read_text())
                assert time.monotonic() < deadline, f"no {what} after {TIMEOUT_S:g} s"
                time.sleep(POLL_S)
            os.kill(proc.pid, signal.SIGKILL)
            assert proc.wait(timeout=TIMEOUT_S) == -signal.SIGKILL
        finally:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=TIMEOUT_S)


def _logged_a_while(path: Path, size: int = 200_000) -> bool:
    """The file passed ``size`` bytes and holds at least one complete chunk (a large chunk write
    can be observed, and killed, half done: then there would be nothing to recover)."""
    data = path.read_bytes() if path.exists() else b""
    return len(data) > size and any(op == CHUNK and offset + 9 + length <= len(data)
                                    for op, offset, length in records(data))


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> Path:
    """The quickstart run for 100000 virtual seconds (hours of wall time), killed once its log
    passed 200 KB."""
    tmp_path = tmp_path_factory.mktemp("killed")
    log = tmp_path / "killed.mcap"
    _run_until(["run", QUICKSTART, "--duration", "100000", "--log", log], tmp_path,
               lambda: _logged_a_while(log), "200 KB of log with a complete chunk")
    return log


def test_a_killed_log_is_refused_with_a_recover_hint(killed: Path):
    with pytest.raises(LogError, match=r"cannot be read: .*\n    hint: `retriever log recover .*killed\.mcap`"):
        read_log(killed)
    salvaged = read_log(killed, salvage=True)
    assert not salvaged.complete
    assert salvaged.end is None, "a killed writer wrote no end record"
    assert salvaged.run["pipeline"] == "quickstart"
    assert_cli_error(cli("replay", killed), r"^error: .*killed\.mcap cannot be read", hint=r"`retriever log recover ")


def test_recovered_events_are_those_of_a_fresh_run(killed: Path, tmp_path: Path):
    """Every recovered event and step record equals the one at the same place in a fresh,
    shorter run of the same (deterministic) pipeline covering them; replay and resim agree."""
    result = recover(killed, tmp_path / "recovered.mcap")
    assert result.events > 0 and result.steps > 0
    log = read_log(result.output)
    assert log.complete and log.damage is None and log.end is None
    assert log.metadata["retriever.recovered"]["messages"] == str(result.messages)
    events, steps = list(log.iter_events()), list(log.iter_steps())
    assert (len(events), len(steps)) == (result.events, result.steps)

    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()
    try:
        horizon_s = max(e.tag[0] for e in events) / 1e9 + 1.0
        fresh = pipe.run(duration=horizon_s)
    finally:
        pipe.reset()
    assert len(fresh.events) > len(events) and len(fresh.steps) > len(steps)
    for logged, again in zip(events, fresh.events):  # the file holds the trace in recording order
        assert (logged.tag, logged.node, logged.port, logged.seq) == again[:4]
        assert packb(log.value(logged)) == packb(again.value), logged.id
    assert steps == fresh.steps[:len(steps)]

    assert replay(log).identical
    report = resim(log)
    assert report.identical, report.difference
    assert report.steps_compared > 0


def test_cli_recover_and_replay_a_killed_log(killed: Path, tmp_path: Path):
    saved = tmp_path / "saved.mcap"
    result = cli("log", "recover", killed, "-o", saved)
    assert result.returncode == 0, result.stderr
    assert f"into {saved}" in result.stdout
    replayed = cli("replay", saved)
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "identical:" in replayed.stdout


SLOW = '''
import time

from retriever import Flow, Pipeline, Rate


class Model(Flow):
    """A stand-in for a real model: 4 ms of wall time per step; reports progress on stdout."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        time.sleep(0.004)
        if self.k % 50 == 0:
            print(f"step {self.k}", flush=True)
        return {"k": self.k}


with Pipeline("slow") as pipe:
    Model() @ Rate(hz=100)
'''


def test_a_killed_run_of_slow_steps_loses_at_most_the_flush_interval(tmp_path: Path):
    """writer.py: "The chunk is closed and the file flushed at least every flush_interval seconds
    of wall time, which bounds what a kill -9 can take". After 300 steps of 4 ms (1.2 s) at most
    the last 0.1 s (~25 steps) may be lost; in fact all of them are."""
    script = tmp_path / "slow.py"
    script.write_text(SLOW, encoding="utf-8")
    log = tmp_path / "slow.mcap"
    stdout = tmp_path / "stdout.txt"
    _run_until(["run", script, "--duration", "100000", "--log", log], tmp_path,
               lambda: "step 300" in (stdout.read_text() if stdout.exists() else ""), "300 steps")
    result = recover(log)
    assert result.events >= 200, f"only {result.events} of 300 events survived the kill"
