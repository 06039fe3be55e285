"""Instructions of ``retriever replay`` and ``--resim`` against the unlogged run, counted (issue 42).

Issue 42's target: read + replay of the quickstart log in at most 1.5x the time of the same
pipeline's unlogged in-process run over the same virtual time; resim likewise. CPU time on a shared
2-core VM moves by 10-50% between runs, so this counts instructions instead, with valgrind
(``cachegrind --cache-sim=no``), one process per mode, each less a process that makes the same
imports and builds the same pipeline (``imports``):

- ``run``: ``pipe.run(duration=SECONDS, keep="counters")`` of ``examples/quickstart.py``, unlogged;
- ``replay``: ``replay_file(LOG)`` (both readings and the replay; it must be identical);
- ``resim``: ``resim_file(LOG)`` likewise.

The log is written by this checkout (``retriever run examples/quickstart.py --duration SECONDS
--log LOG --keep counters``) unless ``--log`` names one. The counted processes import this
checkout's ``retriever`` (its folder first on ``PYTHONPATH``), not the one a venv has installed. Compile the tree first when it was
exported with ``git archive``: a machine with ``PYTHONDONTWRITEBYTECODE=1`` (this one) would
otherwise compile every module in every counted process.

    python -m compileall -q retriever examples
    .venv/bin/python benchmarks/replay_instructions.py                # 60 s log, ~4 min
    .venv/bin/python benchmarks/replay_instructions.py --seconds 20 --log /tmp/q20.mcap
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = ("imports", "run", "replay", "resim")


def counted(mode: str, log: Path, seconds: float) -> int:
    """The instructions of one process running ``mode`` (valgrind's ``I refs``)."""
    # this tree's retriever first (a venv may have another checkout installed editable)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0", "PYTHONPATH": path}
    done = subprocess.run(["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null",
                           sys.executable, __file__, "--mode", mode, "--log", str(log), "--seconds", str(seconds)],
                          cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    found = re.search(r"I\s+refs:\s+([\d,]+)", done.stderr)
    if found is None:
        raise SystemExit(f"valgrind said no instruction count for {mode}:\n{done.stderr[-2000:]}")
    return int(found.group(1).replace(",", ""))


def run_mode(mode: str, log: Path, seconds: float) -> None:
    """What a counted process does (every mode builds the pipeline, so ``imports`` takes it away)."""
    from retriever.loading import load_pipeline
    from retriever.replay import replay_file, resim_file

    pipe = load_pipeline(str(ROOT / "examples" / "quickstart.py"))
    if mode == "run":
        pipe.run(duration=seconds, keep="counters")
    elif mode == "replay":
        assert replay_file(log).identical, "the replay was not identical"
    elif mode == "resim":
        assert resim_file(log).identical, "the re-simulation was not identical"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="virtual time of the run and of its log")
    parser.add_argument("--log", type=Path, help="the quickstart log to replay (written if missing)")
    parser.add_argument("--mode", choices=MODES, help=argparse.SUPPRESS)  # a counted process
    args = parser.parse_args()
    if args.mode:
        run_mode(args.mode, args.log, args.seconds)
        return 0
    with tempfile.TemporaryDirectory() as scratch:
        log = args.log or Path(scratch) / "quickstart.mcap"
        if not log.exists():
            subprocess.run([sys.executable, "-m", "retriever.cli", "run", str(ROOT / "examples" / "quickstart.py"),
                            "--duration", str(args.seconds), "--log", str(log), "--keep", "counters"],
                           cwd=ROOT, check=True, capture_output=True)
        counts = {mode: counted(mode, log, args.seconds) for mode in MODES}
    base = counts["imports"]
    run = counts["run"] - base
    print(f"instructions (M), {args.seconds:g} s quickstart log, less the imports ({base / 1e6:,.1f}M):")
    print(f"  run     {run / 1e6:10,.1f}M")
    for mode in ("replay", "resim"):
        own = counts[mode] - base
        print(f"  {mode:7s} {own / 1e6:10,.1f}M   {own / run:.2f}x the run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
