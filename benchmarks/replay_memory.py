"""Memory and time of ``retriever replay`` against the length of the log (issue 42).

A log of ``examples/quickstart.py`` (camera 30 Hz, policy 2 Hz with LET 0.3 s, controller
200 Hz; about 18 kB of log and 200 steps a virtual second) is written for each length, a multiple
of ``--seconds`` of virtual time, by this checkout (``retriever run --log --keep counters``). Then, ``--repeats`` times,
for each code (``--code DIR``: a checkout whose ``retriever`` is put first on ``PYTHONPATH``; by
default this one; give two to compare), interleaved:

- ``retriever replay LOG`` (``python -m retriever.cli``) in a process of its own, started by a
  wrapper whose only child it is: the wrapper's ``RUSAGE_CHILDREN`` gives the replay's peak RSS
  (``ru_maxrss``) and CPU time (user + system); wall time is measured around it. It includes the
  interpreter's start and imports (about 1-2 s of CPU here);
- the same pipeline's unlogged in-process run over the same virtual time (``keep="counters"``),
  timed inside its process: what a replay re-executes, its limit (issue 42: read + replay within
  1.5x of it).

It prints one row per code and length: medians with [min-max] over the repeats, and how much
the peak RSS grows per MB of log between the shortest and the longest. The replay must say
``identical``; a run that does not is an error. ``--resim`` measures ``retriever replay --resim
LOG`` instead (the whole graph re-run from the logged sources; its steps column counts the steps
compared).

    .venv/bin/python benchmarks/replay_memory.py                                   # 1x 2x 4x of 750 s, 3 repeats
    .venv/bin/python benchmarks/replay_memory.py --code . --code /path/to/old/checkout
    .venv/bin/python benchmarks/replay_memory.py --lengths 16 --repeats 1          # a 216 MB log
    .venv/bin/python benchmarks/replay_memory.py --resim                           # the same, of --resim

``--json FILE`` writes every measurement. Logs go to a temporary folder, removed at the end
(``--logs DIR`` keeps them there, and reuses those already there).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
QUICKSTART = ROOT / "examples" / "quickstart.py"

_WRAPPER = """\
import resource, subprocess, sys, time
start = time.perf_counter()
done = subprocess.run(sys.argv[1:], capture_output=True, text=True)
wall = time.perf_counter() - start
usage = resource.getrusage(resource.RUSAGE_CHILDREN)
print(usage.ru_maxrss, usage.ru_utime + usage.ru_stime, wall)
sys.stdout.write(done.stdout + done.stderr)
sys.exit(done.returncode)
"""

_RUN = """\
import sys, time
sys.path.insert(0, sys.argv[1])
from quickstart import pipe
cpu, wall = time.process_time(), time.perf_counter()
pipe.run(duration=float(sys.argv[2]), keep="counters")
print(time.process_time() - cpu, time.perf_counter() - wall)
"""


def env_for(code: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FORCE_COLOR")}
    env.update(PYTHONPATH=str(code), NO_COLOR="1", TERM="dumb", COLUMNS="200")
    return env


def revision(code: Path) -> str:
    """The commit of a checkout (``-dirty`` if changed), or the folder's name (an exported tree)."""
    done = subprocess.run(["git", "rev-parse", "--show-toplevel", "--short", "HEAD"], capture_output=True, text=True,
                          cwd=code, check=False)
    top, _, head = done.stdout.strip().partition("\n")
    if done.returncode != 0 or Path(top).resolve() != code.resolve():
        return code.name
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                           cwd=code, check=False).stdout.strip()
    return head + ("-dirty" if dirty else "")


def make_log(path: Path, seconds: float) -> None:
    if path.exists():
        return
    subprocess.run([sys.executable, "-m", "retriever.cli", "run", str(QUICKSTART), "--duration", str(seconds), "--log",
                    str(path), "--keep", "counters"], check=True, env=env_for(ROOT), stdout=subprocess.DEVNULL)


def replay_once(code: Path, log: Path, resim: bool = False) -> dict:
    flags = ["--resim"] if resim else []
    done = subprocess.run([sys.executable, "-c", _WRAPPER, sys.executable, "-m", "retriever.cli", "replay", *flags,
                           str(log)], capture_output=True, text=True, env=env_for(code), cwd=code)
    first, _, output = done.stdout.partition("\n")
    if done.returncode != 0 or "identical:" not in output:
        raise SystemExit(f"replay of {log} with {code} did not say identical (exit {done.returncode}):\n{output}"
                         f"{done.stderr}")
    if resim:  # "re-simulated LOG to t=... s with ...: N steps and M events compared"
        steps = int(output.split(" steps and ")[0].split()[-1])
    else:
        steps = int(output.split("identical: ")[1].split()[0])
    rss_kib, cpu, wall = first.split()
    return {"peak_rss_mb": int(rss_kib) / 1024, "cpu_s": float(cpu), "wall_s": float(wall), "steps_replayed": steps}


def run_once(code: Path, seconds: float) -> dict:
    done = subprocess.run([sys.executable, "-c", _RUN, str(QUICKSTART.parent), str(seconds)], capture_output=True,
                          text=True, env=env_for(code), cwd=code, check=True)
    cpu, wall = done.stdout.split()
    return {"run_cpu_s": float(cpu), "run_wall_s": float(wall)}


def spread(values: list[float], fmt: str) -> str:
    median = statistics.median(values)
    return f"{median:{fmt}} [{min(values):{fmt}}-{max(values):{fmt}}]" if len(values) > 1 else f"{median:{fmt}}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=750.0, help="virtual seconds of the 1x log")
    parser.add_argument("--lengths", type=float, nargs="+", default=[1, 2, 4], help="multiples of --seconds")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--code", type=Path, action="append", help="a checkout to replay with (repeatable)")
    parser.add_argument("--no-run", action="store_true", help="do not time the unlogged run")
    parser.add_argument("--resim", action="store_true", help="measure retriever replay --resim instead")
    parser.add_argument("--logs", type=Path, help="keep the logs in this folder (and reuse them)")
    parser.add_argument("--json", type=Path, help="write every measurement here")
    args = parser.parse_args()
    codes = [c.resolve() for c in (args.code or [ROOT])]
    temporary = None if args.logs else tempfile.TemporaryDirectory(prefix="replay_memory_")
    folder = args.logs or Path(temporary.name)
    folder.mkdir(parents=True, exist_ok=True)
    print(f"load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}; "
          f"codes: {', '.join(f'{c} ({revision(c)})' for c in codes)}", flush=True)
    logs = {}
    for length in args.lengths:
        seconds = args.seconds * length
        logs[length] = folder / f"quickstart_{seconds:g}s.mcap"
        started = time.perf_counter()
        make_log(logs[length], seconds)
        print(f"log {length:g}x: {seconds:g} s virtual, {logs[length].stat().st_size / 1e6:.1f} MB "
              f"({time.perf_counter() - started:.0f} s)", flush=True)
    results: dict[tuple[str, float], list[dict]] = {}
    for repeat in range(args.repeats):
        for length in args.lengths:
            for code in codes:
                measured = replay_once(code, logs[length], args.resim)
                if not args.no_run:
                    measured |= run_once(code, args.seconds * length)
                results.setdefault((str(code), length), []).append(measured)
                print(f"  repeat {repeat + 1}, {length:g}x, {code.name}: {json.dumps(measured)}", flush=True)
    load_end = os.getloadavg()
    print(f"load average at end {' '.join(f'{x:.2f}' for x in load_end)}\n")
    head = (f"{'code':<14} {'length':>6} {'log MB':>7} {'steps':>9} │ {'peak RSS MB':>20} {'wall s':>20} "
            f"{'CPU s':>20} │ {'run CPU s':>9} {'CPU/run':>8}")
    print(head)
    print("─" * len(head))
    for code in codes:
        for length in args.lengths:
            rows = results[(str(code), length)]
            run = statistics.median(r["run_cpu_s"] for r in rows) if not args.no_run else None
            cpu = statistics.median(r["cpu_s"] for r in rows)
            print(f"{revision(code):<14} {length:>5g}x {logs[length].stat().st_size / 1e6:>7.1f} "
                  f"{rows[0]['steps_replayed']:>9,} │ {spread([r['peak_rss_mb'] for r in rows], '.0f'):>20} "
                  f"{spread([r['wall_s'] for r in rows], '.1f'):>20} {spread([r['cpu_s'] for r in rows], '.1f'):>20} │ "
                  + (f"{run:>9.2f} {cpu / run:>7.1f}x" if run else f"{'':>9} {'':>8}"))
        short, long = min(args.lengths), max(args.lengths)
        if long > short:
            grown = (statistics.median(r["peak_rss_mb"] for r in results[(str(code), long)])
                     - statistics.median(r["peak_rss_mb"] for r in results[(str(code), short)]))
            megabytes = (logs[long].stat().st_size - logs[short].stat().st_size) / 1e6
            print(f"{'':<14} peak RSS grew {grown:+.0f} MB from {short:g}x to {long:g}x: "
                  f"{grown / megabytes:+.2f} MB per MB of log")
    command = "retriever replay --resim LOG" if args.resim else "retriever replay LOG"
    print(f"\npeak RSS, wall and CPU: `{command}` in a process of its own (interpreter start and imports "
          "included), median [min-max] over the repeats; run CPU s: the unlogged in-process run over the same "
          "virtual time; CPU/run: the replay's CPU over it")
    if args.json:
        args.json.write_text(json.dumps({"codes": {str(c): revision(c) for c in codes}, "seconds": args.seconds,
                                         "resim": args.resim,
                                         "logs": {str(k): v.stat().st_size for k, v in logs.items()},
                                         "load_end": load_end,
                                         "results": [{"code": c, "length": n, "runs": rows}
                                                     for (c, n), rows in results.items()]}, indent=1))
    if temporary is not None:
        temporary.cleanup()


if __name__ == "__main__":
    main()
