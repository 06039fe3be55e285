"""The fuzz campaign (benchmarks/fuzz.py) in brief: every target, a few hundred inputs from a
fixed seed, no crash, no code executed, no forged record accepted. The recorded campaign and
its table are in benchmarks/reports/fuzz.md."""

from __future__ import annotations

import pytest

from benchmarks import fuzz

INPUTS = 300


@pytest.fixture(scope="module")
def campaign():
    campaign = fuzz.Campaign(seed=17)
    yield campaign
    campaign.close()


@pytest.mark.parametrize("name", fuzz.TARGET_NAMES)
def test_a_fuzzed_entry_point_only_returns_or_raises_its_own_error(campaign, name):
    outcome = fuzz.fuzz_target(campaign.target(name), campaign.guard, inputs=INPUTS, save=False)
    assert outcome.inputs == INPUTS
    assert outcome.refused > 0, "no input was refused: the mutations no longer reach the decoder"
    assert (outcome.crashes, outcome.code_executed, outcome.forged_accepted) == (0, 0, 0), outcome.findings


def test_the_guard_sees_code_run_and_the_marker_file(campaign):
    import os

    def run_code():
        exec("1")  # noqa: S102 - what the guard must see
        campaign.marker.touch()

    _, error, flagged = campaign.guard.call(run_code)
    assert error is None
    assert any(f.startswith("exec ") for f in flagged) and "marker file" in flagged[-1]
    assert not os.path.exists(campaign.marker)


def test_the_guard_stops_a_signal_and_a_process_start_it_does_not_permit(campaign):
    import os
    import subprocess

    target = campaign.target("spawn-signal")
    sentinel = target.sentinel.pid
    for call in (lambda: os.kill(sentinel, 9), lambda: subprocess.Popen(["true"])):
        _, error, flagged = campaign.guard.call(call)
        assert isinstance(error, fuzz.Blocked) and flagged
    _, error, flagged = campaign.guard.call(lambda: os.kill(sentinel, 0), may=lambda event, args: args == (sentinel, 0))
    assert error is None and not flagged
    assert target.sentinel.poll() is None
