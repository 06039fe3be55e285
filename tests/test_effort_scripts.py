"""The development-effort scripts (benchmarks/effort.py, paper Appendix F-A) do their job: the
Retriever one writes a CSV row per payload of every size, on inproc and on dora, and the dora
one does the same with dora's runtime; the counts stay what benchmarks/reports/effort.md records."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import effort

ROOT = Path(__file__).resolve().parents[1]
SIZES = [2**i for i in range(6, 25)]


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(f))


@pytest.mark.parametrize("backend", ["inproc", "dora"])
def test_the_retriever_script_measures_every_size(backend, tmp_path):
    env = {**os.environ, "POINTS": "1", "BACKEND": backend, "OUT": str(tmp_path / "out.csv"),
           "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks/effort/retriever/latency.py")], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = _rows(tmp_path / "out.csv")
    assert rows[0] == ["size", "latency_ns"] and [int(r[0]) for r in rows[1:]] == SIZES
    assert all(int(r[1]) > 0 for r in rows[1:])


def test_the_dora_script_measures_every_size(tmp_path):
    for name in ("pub.py", "sub.py", "dataflow.yml"):
        shutil.copy(ROOT / "benchmarks/effort/dora" / name, tmp_path)
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "POINTS": "1", "OUT": "out.csv", "PATH": bin_dir + os.pathsep + os.environ["PATH"]}
    done = subprocess.run([str(Path(bin_dir) / "dora"), "run", "dataflow.yml", "--log-level", "error"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    rows = _rows(tmp_path / "out.csv")
    assert rows[0] == ["size", "latency_ns"] and [int(r[0]) for r in rows[1:]] == SIZES


def test_the_counts_are_the_recorded_ones():
    assert effort.code_lines(effort.HERE / "retriever/latency.py") == 38
    assert [effort.code_lines(effort.HERE / f) for f in effort.SCRIPTS["dora-rs (ours)"]] == [17, 12, 13]
