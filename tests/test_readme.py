"""The README's pipeline, as a user copies it: run as a script, and by `retriever run` on both
backends (it runs as shown: a module-level pipe.run must not break `retriever run` or zenoh)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RETRIEVER = Path(sys.executable).parent / "retriever"


@pytest.fixture(scope="module")
def readme_pipeline(tmp_path_factory) -> Path:
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## A pipeline\n", 1)[1]
    block = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    path = tmp_path_factory.mktemp("readme") / "agent.py"
    path.write_text(block)
    return path


def _run(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FORCE_COLOR")}
    env.update(PYTHONPATH=str(ROOT), NO_COLOR="1", COLUMNS="200")
    return subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=180)


def test_the_readme_pipeline_runs_as_a_script(readme_pipeline):
    done = _run([sys.executable, str(readme_pipeline)], readme_pipeline.parent)
    assert done.returncode == 0, done.stderr
    assert re.fullmatch(r"[0-9a-f]{64}\n", done.stdout), done.stdout


def test_the_readme_ir_command_writes_an_ir_that_retriever_run_runs(readme_pipeline):
    wrote = _run([str(RETRIEVER), "ir", str(readme_pipeline), "--out", "agent.ir.json"], readme_pipeline.parent)
    assert wrote.returncode == 0, wrote.stderr
    done = _run([str(RETRIEVER), "run", "agent.ir.json", "--duration", "0.5"], readme_pipeline.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert re.search(r"camera\s.*\b15\b", done.stdout), done.stdout


@pytest.mark.parametrize("backend", ["inproc", "zenoh"])
def test_the_readme_pipeline_runs_under_retriever_run(readme_pipeline, backend):
    done = _run([str(RETRIEVER), "run", str(readme_pipeline), "--backend", backend, "--duration", "0.5"],
                readme_pipeline.parent)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"agent: 0.5 s on {backend}" in done.stdout, done.stdout
    assert re.search(r"camera\s.*\b15\b", done.stdout), done.stdout  # 30 Hz for 0.5 s: its own run only
