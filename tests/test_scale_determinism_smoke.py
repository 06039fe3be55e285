"""The scale and determinism-cost benchmarks (benchmarks/scale_latency.py, determinism_cost.py) in
their quickest mode: every run finishes, every row is measured, the CSV and the plot are written.
The recorded runs are in benchmarks/README.md."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, out: Path) -> str:
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=120, cwd=ROOT,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_scale_latency_quick(tmp_path):
    out = _run("scale_latency.py", tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "scale_latency.csv")))
    assert {(r["backend"], r["shape"]) for r in rows} == {(b, s) for b in ("inproc", "zenoh") for s in ("chain", "fan")}
    for r in rows:
        assert r["error"] == "", r
        assert int(r["lat_n"]) > 0 and 0 < float(r["lat_p10_us"]) <= float(r["lat_p50_us"]) <= float(r["lat_p90_us"])
        assert int(r["steps"]) > 0 and float(r["ticks_per_s"]) > 0
    assert (tmp_path / "scale_latency.png").stat().st_size > 0
    assert "load average at start" in out


def test_determinism_cost_quick(tmp_path):
    out = _run("determinism_cost.py", tmp_path)
    rows = list(csv.DictReader(open(tmp_path / "determinism_cost.csv")))
    combos = {(r["waiting"], r["logging"]) for r in rows}
    assert combos == {(w, g) for w in ("on", "off") for g in ("on", "off")}
    for r in rows:
        assert r["error"] == "", r
    latency = [r for r in rows if r["kind"] == "latency"]
    assert len(latency) == 4 and all(int(r["lat_n"]) > 0 for r in latency)
    # waiting off: the join's ticks ran without their producers' promises, and their records say so
    assert all(int(r["incomplete"]) > 0 for r in latency if r["waiting"] == "off")
    assert (tmp_path / "determinism_cost.png").stat().st_size > 0
    assert "load average at start" in out
