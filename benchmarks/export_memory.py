"""Peak memory of ``retriever log export LOG --format rerun|ros2|foxglove`` against the log (issue 42).

The logs, written by this checkout (kept in ``--logs DIR`` and reused): ``frames`` (tests'
``build_frames``: 64 KiB of noise a frame at 30 Hz, about 2 MB a second; 2, 16, 64 and 256 s:
4 MB to 506 MB), ``numbers`` (the same graph with frames of 16 bytes: 150 small records a
second; 16 and 128 s) and ``quickstart`` (examples/quickstart.py, 450 records a second, most of
them step records; 25, 200 and 1,600 s). Then, ``--repeats`` times, for each log and each code
(``--code DIR``: a checkout or a ``git archive`` export whose ``retriever`` goes first on
``PYTHONPATH``; give two to compare), interleaved: the export, in a process of its own started
by a wrapper whose only child it is (``RUSAGE_CHILDREN``: its peak RSS), as
tests/log/test_export_stream.py measures it. It prints a Markdown table: peak RSS and wall time,
median [min-max] over the repeats, and the output's size.

    .venv/bin/python benchmarks/export_memory.py --code NEW --code OLD --logs /tmp/export_logs
    .venv/bin/python benchmarks/export_memory.py --only frames_256s quickstart_1600s --repeats 1
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
LOGS = {"frames_2s": ("frames", 2.0), "frames_16s": ("frames", 16.0), "frames_64s": ("frames", 64.0),
        "frames_256s": ("frames", 256.0), "numbers_16s": ("numbers", 16.0), "numbers_128s": ("numbers", 128.0),
        "quickstart_25s": ("quickstart", 25.0), "quickstart_200s": ("quickstart", 200.0),
        "quickstart_1600s": ("quickstart", 1600.0)}
FRAME_BYTES = {"frames": 1 << 16, "numbers": 16}

_MAKE_FRAMES = """\
import sys
from retriever.backends.inproc import InprocSession
from retriever.log import LogWriter
from tests.log.log_flows import build_frames
InprocSession.LOG_BATCH = 16  # a chunk every 16 steps, as tests/log/test_replay_stream.py's _frames_log
LogWriter.__init__.__kwdefaults__["flush_interval"] = 0.0
build_frames(int(sys.argv[1])).run(duration=float(sys.argv[2]), log=sys.argv[3], keep="counters")
"""

_WRAPPER = """\
import resource, subprocess, sys, time
start = time.perf_counter()
done = subprocess.run(sys.argv[1:], capture_output=True, text=True)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, time.perf_counter() - start, done.returncode)
sys.stdout.write(done.stdout + done.stderr)
"""


def env_for(code: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "FORCE_COLOR")}
    env.update(PYTHONPATH=str(code), NO_COLOR="1", TERM="dumb", COLUMNS="200")
    return env


def make_log(path: Path, kind: str, seconds: float) -> None:
    if path.exists():
        return
    if kind == "quickstart":
        command = ["-m", "retriever.cli", "run", str(ROOT / "examples" / "quickstart.py"), "--duration", str(seconds),
                   "--log", str(path), "--keep", "counters"]
    else:
        command = ["-c", _MAKE_FRAMES, str(FRAME_BYTES[kind]), str(seconds), str(path)]
    subprocess.run([sys.executable, *command], check=True, env=env_for(ROOT), cwd=ROOT, stdout=subprocess.DEVNULL)


def export_once(code: Path, log: Path, format: str, out: Path) -> tuple[float, float, int]:
    """Peak RSS (MB) and wall time (s) of one export, and the size of what it wrote."""
    done = subprocess.run([sys.executable, "-c", _WRAPPER, sys.executable, "-m", "retriever.cli", "log", "export",
                           str(log), "--format", format, "-o", str(out), "--force"],
                          capture_output=True, text=True, env=env_for(code), cwd=code)
    first, _, output = done.stdout.partition("\n")
    peak, wall, returncode = first.split()
    if returncode != "0" or f"wrote {out}" not in output:
        raise SystemExit(f"export of {log} with {code} failed (exit {returncode}):\n{output}")
    return int(peak) / 1024, float(wall), out.stat().st_size


def spread(values: list[float], fmt: str) -> str:
    median = statistics.median(values)
    return f"{median:{fmt}} [{min(values):{fmt}}–{max(values):{fmt}}]" if len(values) > 1 else f"{median:{fmt}}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", type=Path, action="append", help="a checkout to export with (repeatable)")
    parser.add_argument("--format", default="rerun", choices=["rerun", "ros2", "foxglove"])
    parser.add_argument("--only", nargs="+", choices=list(LOGS), help="these logs (default: all but the two longest)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--logs", type=Path, required=True, help="the logs' folder (made, and reused)")
    args = parser.parse_args()
    codes = [c.resolve() for c in (args.code or [ROOT])]
    names = args.only or [n for n in LOGS if n not in ("frames_256s", "quickstart_1600s")]
    args.logs.mkdir(parents=True, exist_ok=True)
    for name in names:
        make_log(args.logs / f"{name}.mcap", *LOGS[name])
    print(f"load average at start {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    results: dict[tuple[str, Path], list[tuple[float, float, int]]] = {}
    for _ in range(args.repeats):
        for name in names:
            for n, code in enumerate(codes):
                out = args.logs / f"out_{n}.{args.format}"
                results.setdefault((name, code), []).append(export_once(code, args.logs / f"{name}.mcap", args.format,
                                                                        out))
    print(f"load average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| log | size | code | peak RSS MB | wall s | output |\n| --- | --- | --- | --- | --- | --- |")
    for name in names:
        for code in codes:
            rows = results[(name, code)]
            print(f"| {name} | {(args.logs / f'{name}.mcap').stat().st_size / 1e6:.1f} MB | {code.name} | "
                  f"{spread([r[0] for r in rows], '.0f')} | {spread([r[1] for r in rows], '.1f')} | "
                  f"{rows[0][2] / 1e6:.2f} MB |")


if __name__ == "__main__":
    main()
