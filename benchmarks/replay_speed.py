"""Time of ``retriever replay`` against the unlogged run it re-executes, side by side (issue 42).

Issue 42's target: a replay of the quickstart log in at most 1.5x the time of the same pipeline's
unlogged in-process run over the same virtual time. A log of ``examples/quickstart.py`` of
``--seconds`` of virtual time is written once (by this checkout; see replay_memory.py). Then, for
``--rounds`` rounds, for each code (``--code DIR``: a checkout put first on ``PYTHONPATH``; by
default this one; give two to compare), interleaved, each in a process of its own:

- **run**: ``pipe.run(duration=SECONDS, keep="counters")``, unlogged, timed inside its process
  (CPU and wall), imports excluded;
- **replay**: ``replay_file(LOG)`` (what ``retriever replay`` runs: both readings of the log and
  the replay), timed inside its process the same way; it must say ``identical``;
- **cli**: ``retriever replay LOG`` (``python -m retriever.cli``) as a whole, the interpreter's
  start, imports and the table included: its CPU from ``RUSAGE_CHILDREN`` of a wrapper whose only
  child it is, its wall around it.

It prints one row per code: medians with [min-max] over the rounds, and the ratios replay/run and
cli/run, of CPU (the less disturbed by a loaded machine) and of wall. The load average at the
start and the end is printed: the machine may be shared.

    .venv/bin/python benchmarks/replay_speed.py                           # 750 s, 5 rounds
    .venv/bin/python benchmarks/replay_speed.py --code . --code /path/to/old/checkout --rounds 5

``--json FILE`` writes every measurement; ``--logs DIR`` keeps the log there (and reuses it).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from replay_memory import QUICKSTART, env_for, make_log, replay_once, revision, run_once  # noqa: E402

_REPLAY = """\
import sys, time
from retriever.replay import replay_file
cpu, wall = time.process_time(), time.perf_counter()
report = replay_file(sys.argv[1])
cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
assert report.identical, report.divergences[:1]
print(cpu, wall, report.steps_replayed)
"""


def replay_inside(code: Path, log: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", _REPLAY, str(log)], capture_output=True, text=True,
                          env=env_for(code), cwd=code)
    if done.returncode != 0:
        raise SystemExit(f"replay_file({log}) with {code} failed:\n{done.stdout}{done.stderr}")
    cpu, wall, steps = done.stdout.split()
    return {"replay_cpu_s": float(cpu), "replay_wall_s": float(wall), "steps_replayed": int(steps)}


def spread(values: list[float], fmt: str) -> str:
    median = statistics.median(values)
    return f"{median:{fmt}} [{min(values):{fmt}}-{max(values):{fmt}}]" if len(values) > 1 else f"{median:{fmt}}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=750.0, help="virtual seconds of the log and the run")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--code", type=Path, action="append", help="a checkout to time (repeatable)")
    parser.add_argument("--logs", type=Path, help="keep the log in this folder (and reuse it)")
    parser.add_argument("--json", type=Path, help="write every measurement here")
    args = parser.parse_args()
    codes = [c.resolve() for c in (args.code or [Path(__file__).resolve().parent.parent])]
    temporary = None if args.logs else tempfile.TemporaryDirectory(prefix="replay_speed_")
    folder = args.logs or Path(temporary.name)
    folder.mkdir(parents=True, exist_ok=True)
    load_start = os.getloadavg()
    print(f"load average at start {' '.join(f'{x:.2f}' for x in load_start)} ({os.cpu_count()} CPUs); "
          f"codes: {', '.join(f'{c} ({revision(c)})' for c in codes)}", flush=True)
    log = folder / f"quickstart_{args.seconds:g}s.mcap"
    make_log(log, args.seconds)
    print(f"log: {QUICKSTART.name}, {args.seconds:g} s virtual, {log.stat().st_size / 1e6:.1f} MB", flush=True)
    results: dict[str, list[dict]] = {str(c): [] for c in codes}
    for round_ in range(args.rounds):
        for code in codes:
            measured = run_once(code, args.seconds) | replay_inside(code, log)
            cli = replay_once(code, log)
            measured |= {"cli_cpu_s": cli["cpu_s"], "cli_wall_s": cli["wall_s"], "cli_peak_rss_mb": cli["peak_rss_mb"]}
            results[str(code)].append(measured)
            print(f"  round {round_ + 1}, {code.name}: {json.dumps(measured)}", flush=True)
    load_end = os.getloadavg()
    print(f"load average at end {' '.join(f'{x:.2f}' for x in load_end)}\n")
    head = (f"{'code':<14} │ {'run CPU s':>18} {'replay CPU s':>18} {'cli CPU s':>18} │ {'replay/run':>10} "
            f"{'cli/run':>8} │ {'run wall s':>18} {'replay wall s':>18} {'replay/run':>10}")
    print(head)
    print("─" * len(head))
    for code in codes:
        rows = results[str(code)]

        def col(key: str) -> list[float]:
            return [r[key] for r in rows]

        run_cpu, run_wall = statistics.median(col("run_cpu_s")), statistics.median(col("run_wall_s"))
        print(f"{revision(code):<14} │ {spread(col('run_cpu_s'), '.2f'):>18} {spread(col('replay_cpu_s'), '.2f'):>18} "
              f"{spread(col('cli_cpu_s'), '.2f'):>18} │ "
              f"{statistics.median(col('replay_cpu_s')) / run_cpu:>9.2f}x "
              f"{statistics.median(col('cli_cpu_s')) / run_cpu:>7.2f}x │ "
              f"{spread(col('run_wall_s'), '.2f'):>18} {spread(col('replay_wall_s'), '.2f'):>18} "
              f"{statistics.median(col('replay_wall_s')) / run_wall:>9.2f}x")
    print("\nrun: the unlogged in-process run, timed inside its process; replay: replay_file(LOG) the same way; "
          "cli: `retriever replay LOG` as a process (interpreter start and imports included); median [min-max] "
          "over the rounds; ratios of medians (issue 42's target: replay/run <= 1.5)")
    if args.json:
        args.json.write_text(json.dumps({"codes": {str(c): revision(c) for c in codes}, "seconds": args.seconds,
                                         "log_bytes": log.stat().st_size, "load_start": load_start,
                                         "load_end": load_end, "results": results}, indent=1))
    if temporary is not None:
        temporary.cleanup()


if __name__ == "__main__":
    main()
