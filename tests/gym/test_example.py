"""examples/gym_cartpole.py runs as its docstring and docs/learning.md ("Gymnasium") say."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest

pytest.importorskip("gymnasium")

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "gym_cartpole.py"


def test_the_pilots_return_falls_once_its_latency_outlasts_what_the_pole_forgives(capsys):
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    assert capsys.readouterr().out.splitlines() == [
        f"latency {ms:4d} ms: return {mean} (10 seeds; 500 is CartPole-v1's most)"
        for ms, mean in [(0, " 500.0 ±   0.0"), (15, " 500.0 ±   0.0"), (35, " 500.0 ±   0.0"),
                         (55, " 153.6 ±  61.8"), (75, "  26.6 ±   1.5")]]
