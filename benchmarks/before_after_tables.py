"""Tables of a before/after comparison of two commits (benchmarks/reports/redesign_before_after.md).

The comparison runs ``step_overhead``, ``latency``, ``idle_cpu`` and ``control_jitter`` of each
side from its own worktree, alternating which side goes first, and keeps each run's stdout as
``OUT/<bench>.<side>.r<round>.out`` and one line per run in a runs file::

    | bench | side | round | start (UTC) | load1 start | load1 end | rc |

This script reads both and prints, per benchmark, one markdown row per metric: the median over
the runs of each side with IQR and min–max, the ratio of the medians (second side over first), a
bootstrap 95% interval of that ratio (runs resampled within each side), and how many rounds gave
the second side the higher figure. Only rounds where both sides exited 0 count, so that a round
that failed on one side does not tilt the comparison. Then the 1-minute load per benchmark and
side. The interval is of the noise between runs, not within them: each run gives one figure.

    python benchmarks/before_after_tables.py --out OUT --runs runs.md [--bench idle_cpu] [--sides before,after]
"""
from __future__ import annotations

import argparse
import random
import re
import statistics
from pathlib import Path

BENCHES = ("control_jitter", "idle_cpu", "latency", "step_overhead")


def num(text: str) -> float:
    return float(text.replace(",", ""))


def control_jitter(text: str) -> dict[str, float]:
    row = r"\s+│\s+(\d+)\s+(\d+)\s+│\s+(\d+)\s+(\d+)\s+(\d+)\s+│\s+(\d+)"
    ctrl = re.search(r"retriever-zenoh ctrl" + row, text)
    bare = re.search(r"bare sleep loop" + row, text)
    return {"ctrl p50 µs": num(ctrl[3]), "ctrl p99 µs": num(ctrl[4]), "ctrl missed": num(ctrl[2]),
            "ctrl ≥1 period late": num(ctrl[6]), "bare p99 µs (same run)": num(bare[4]),
            "ctrl p99 / bare p99": num(re.search(r"p99 ([\d.]+)x the bare", text)[1]),
            "ctrl CPU %": num(re.search(r"ctrl ([\d.]+)%", text)[1])}


def idle_cpu(text: str) -> dict[str, float]:
    def percent(label: str) -> float:
        return num(re.search(re.escape(label) + r"\s+│\s+([\d.]+)", text)[1])

    worker, inbox = percent("retriever-zenoh worker"), percent("zenoh session + inbox loop")
    return {"worker %": worker, "coordinator %": percent("retriever coordinator"),
            "inbox loop % (same run)": inbox, "bare sleep loop % (same run)": percent("bare sleep loop"),
            "worker/inbox loop": worker / inbox}


def latency(text: str) -> dict[str, float]:
    out = {}
    for size in ("64 B", "16 KiB", "1 MiB"):
        m = re.search(r"^\s*" + re.escape(size) + r" │\s+(\d+)\s+(\d+) │\s+(\d+)\s+(\d+) │\s+([\d.]+)", text, re.M)
        out[f"{size} zenoh median µs"] = num(m[3])
        out[f"{size} zenoh p99 µs"] = num(m[4])
        out[f"{size} raw median µs (same run)"] = num(m[1])
        out[f"{size} zenoh/raw"] = num(m[5])
    return out


def step_overhead(text: str) -> dict[str, float]:
    out = {}
    for chain in ("typed-rate-5", "untyped-rate-5", "typed-rate-10", "typed-trigger-10"):
        m = re.search(r"^" + re.escape(chain) + r"\s.*?│.*?│.*?│\s+([\d.]+)×.*?│.*?│\s+([\d.]+)\s+([\d.]+)",
                      text, re.M)
        out[f"{chain} inproc µs/step"] = num(m[2])
        out[f"{chain} hand µs/step"] = num(m[3])
        out[f"{chain} inproc/hand"] = num(m[1])
    return out


PARSERS = {"control_jitter": control_jitter, "idle_cpu": idle_cpu, "latency": latency, "step_overhead": step_overhead}


def fmt(x: float) -> str:
    if x == 0:
        return "0"
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:.3g}"


def quantile(xs: list[float], p: float) -> float:
    """Linear interpolation between order statistics (numpy's default)."""
    xs = sorted(xs)
    k = (len(xs) - 1) * p
    lo = int(k)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def bootstrap_ratio(first: list[float], second: list[float], n: int = 4000, seed: int = 37) -> tuple[float, float]:
    """95% interval of median(second) / median(first), each side's runs resampled on their own."""
    rng = random.Random(seed)
    ratios = []
    for _ in range(n):
        m_first = statistics.median(rng.choices(first, k=len(first)))
        m_second = statistics.median(rng.choices(second, k=len(second)))
        if m_first > 0:
            ratios.append(m_second / m_first)
    return quantile(ratios, 0.025), quantile(ratios, 0.975)


def cell(xs: list[float]) -> str:
    return (f"{fmt(statistics.median(xs))} ({fmt(quantile(xs, .25))}–{fmt(quantile(xs, .75))}; "
            f"{fmt(min(xs))}–{fmt(max(xs))})")


def read_runs(path: Path) -> list[dict]:
    runs = []
    for line in path.read_text().splitlines():
        f = [x.strip() for x in line.strip().strip("|").split("|")]
        if len(f) == 7 and f[2].isdigit():
            runs.append({"bench": f[0], "side": f[1], "round": int(f[2]), "start": f[3],
                         "load": (float(f[4]), float(f[5])), "rc": int(f[6])})
    return runs


def table(bench: str, out: Path, runs: list[dict], sides: tuple[str, str]) -> list[str]:
    ok = {(r["side"], r["round"]) for r in runs if r["bench"] == bench and r["rc"] == 0}
    rounds = sorted(r for s, r in ok if s == sides[0] and (sides[1], r) in ok)
    if not rounds:
        return []
    first, second = sides
    values = {(s, r): PARSERS[bench]((out / f"{bench}.{s}.r{r}.out").read_text()) for s in sides for r in rounds}
    lines = [f"#### {bench}", "",
             f"| metric | {first}: median (IQR; min–max) | {second}: median (IQR; min–max) | {second}/{first} "
             f"| 95% CI | rounds {second} > {first} |", "|---|---|---|---|---|---|"]
    for metric in values[first, rounds[0]]:
        a = [values[first, r][metric] for r in rounds]
        b = [values[second, r][metric] for r in rounds]
        if statistics.median(a) == 0:
            ratio, ci = f"n/a ({first} median 0)", "n/a"
        else:
            lo, hi = bootstrap_ratio(a, b)
            ratio, ci = f"**{statistics.median(b) / statistics.median(a):.2f}**", f"{lo:.2f}–{hi:.2f}"
        higher = sum(y > x for x, y in zip(a, b))
        ties = sum(y == x for x, y in zip(a, b))
        count = f"{higher} of {len(rounds)}" + (f", {ties} ties" if ties else "")
        lines.append(f"| {metric} | {cell(a)} | {cell(b)} | {ratio} | {ci} | {count} |")
    return lines + [""]


def loads(runs: list[dict], benches: list[str]) -> list[str]:
    per: dict[tuple[str, str], list[float]] = {}
    for r in runs:
        if r["bench"] in benches:
            per.setdefault((r["bench"], r["side"]), []).extend(r["load"])
    lines = [f"load {b} {s}: {statistics.median(v):.2f} ({min(v):.2f}–{max(v):.2f})" for (b, s), v in sorted(per.items())]
    every = [x for v in per.values() for x in v]
    if every:
        lines.append(f"load all: median {statistics.median(every):.2f}, range {min(every):.2f}–{max(every):.2f}, "
                     f"{len(every)} readings")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder of <bench>.<side>.r<round>.out files")
    p.add_argument("--runs", type=Path, required=True, help="the runs file, one markdown row per run")
    p.add_argument("--bench", action="append", choices=BENCHES, help="only these benchmarks (default all)")
    p.add_argument("--sides", default="before,after", help="first,second: the ratio is second/first")
    args = p.parse_args(argv)
    benches = args.bench or list(BENCHES)
    sides = tuple(args.sides.split(","))
    runs = read_runs(args.runs)
    for bench in benches:
        print("\n".join(table(bench, args.out, runs, sides)))
    print("\n".join(loads(runs, benches)))
    failed = [r for r in runs if r["rc"] != 0 and r["bench"] in benches]
    for r in failed:
        print(f"failed: {r['bench']} {r['side']} round {r['round']} rc {r['rc']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
