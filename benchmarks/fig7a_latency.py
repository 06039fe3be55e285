"""Paper Fig. 7a: one-way message latency vs payload size: five systems (and dora's daemon route), one run.

    retriever-inproc  Retriever in-process (virtual time): the hand-off from the source's step
                      returning to the sink's step starting (no transport: the array goes by reference)
    retriever-zenoh   Retriever on the Zenoh runtime, a process per flow
    retriever-dora    Retriever on the dora backend, a dora node per flow
    raw-zenoh         zenoh-python written the plainest way: ``put(array.tobytes())``, a subscriber
                      iterating ``for sample in subscriber:`` (latency.py's raw-iter side)
    raw-dora          dora-rs written the plainest way: a timer-driven publisher node and a
                      subscriber node (benchmarks/dora_latency/), run with ``dora run``
    raw-dora-bp       the same dataflow with the input ``queue_policy: backpressure``: dora's route
                      through its daemon, which the dora backend takes (dora's direct route lost
                      messages: docs/dora.md); the transport the retriever-dora side really has

Diagnostic sides (not run unless named in ``--sides``; benchmarks/shm_ring.py,
benchmarks/reports/shm_channel.md): raw-zenoh's processes and settings carrying only a 40-byte
handle, the payload written by the publisher into a slot of a shared-memory ring of its own in
/dev/shm (the array copied in once):

    raw-zenoh-shm-copy  the subscriber copies the slot out (an array it owns), then checks the
                        slot's generation (seqlock)
    raw-zenoh-shm-view  the subscriber takes a read-only view of the slot, no copy (as dora's)
    raw-unix-shm-copy   raw-zenoh-shm-copy with the handles over a Unix datagram socket, no Zenoh

and Retriever on Zenoh with such a ring under its transport (a prototype over the transport's
public tap, benchmarks/shm_ring_flows.py: messages of 64 KiB or more):

    retriever-zenoh-ring-copy  the sink's loop gets bytes copied out of the slot
    retriever-zenoh-ring-view  the sink's loop gets a view of the slot (nothing holds it)
    retriever-unix-ring-copy   ring-copy, the handles over a Unix datagram socket, not Zenoh

The Retriever sides run ``src = PayloadSource(size) @ Rate(hz) ──frame──▶ LatencySink() @
Trigger("frame")`` (benchmarks/zenoh_flows.py); every side takes ``time.time_ns()`` right before
the send and right after the array is in the receiver's hands, on one machine (one clock). Per
size, each side runs ``--rounds`` times, interleaved (the order reversed every other round), each
run dropping its first ``--warmup`` messages. Written: a CSV of every sample (``--csv``), a table of
medians with p10-p90 per side and the ratios Retriever/transport (stdout), and the log-log plot
(median line, p10-p90 band) as PNG (``--png``).

    .venv/bin/python benchmarks/fig7a_latency.py                       # 10 sizes, 64 B ... 16 MiB, ~7 min
    .venv/bin/python benchmarks/fig7a_latency.py --sizes 64 1Mi --samples 40 --rounds 1   # a smoke run
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402

from latency import fmt_size, parse_size, quantile, run_raw, run_retriever  # noqa: E402

SIDES = ("retriever-inproc", "retriever-zenoh", "retriever-dora", "raw-zenoh", "raw-dora", "raw-dora-bp")
DIAGNOSTIC_SIDES = ("raw-zenoh-shm-copy", "raw-zenoh-shm-view", "raw-unix-shm-copy",
                    "retriever-zenoh-ring-copy", "retriever-zenoh-ring-view", "retriever-unix-ring-copy")
DEFAULT_SIZES = ["64", "256", "1Ki", "4Ki", "16Ki", "64Ki", "256Ki", "1Mi", "4Mi", "16Mi"]
DORA_PAIR = HERE / "dora_latency"


def run_raw_dora(size: int, total: int, hz: float, warmup: int, backpressure: bool = False) -> dict:
    """The two-node dora dataflow of benchmarks/dora_latency/, its timer at ``hz``; ``backpressure``:
    its input through dora's daemon."""
    with tempfile.TemporaryDirectory(prefix="fig7a-dora-") as tmp:
        flow = (DORA_PAIR / "dataflow.yml").read_text()
        flow = flow.replace("dora/timer/millis/50", f"dora/timer/millis/{round(1000 / hz)}")
        flow = flow.replace("path: pub.py", f"path: {DORA_PAIR / 'pub.py'}")
        flow = flow.replace("path: sub.py", f"path: {DORA_PAIR / 'sub.py'}")
        if backpressure:
            flow = flow.replace("data: pub/data",
                                "data: {source: pub/data, queue_size: 100000, queue_policy: backpressure}")
        (Path(tmp) / "dataflow.yml").write_text(flow)
        out = Path(tmp) / "got.json"
        bin_dir = str(Path(sys.executable).parent)
        env = {**os.environ, "SIZE": str(size), "TOTAL": str(total), "OUT": str(out),
               "PATH": bin_dir + os.pathsep + os.environ.get("PATH", "")}
        done = subprocess.run([shutil.which("dora", path=env["PATH"]), "run", "dataflow.yml", "--log-level", "error"],
                              cwd=tmp, env=env, capture_output=True, text=True, timeout=total / hz + 120)
        if done.returncode != 0 or not out.exists():
            raise SystemExit(f"raw dora run failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
        got = sorted(json.loads(out.read_text()))
    if any(n != size for *_, n in got):
        raise SystemExit("raw dora: a payload of the wrong size")
    # dora's timer starts before a late subscriber reads (on a loaded machine up to a second
    # late), and a backpressure input keeps what it missed: those messages waited for the
    # subscriber's start, no transport. Kept: from the first one that came within a period (and
    # past the warm-up), as the Retriever sides, whose sources start once their consumers are ready.
    caught_up = next((seq for seq, s, r, _ in got if r - s < 1e9 / hz), len(got))
    return {"lat": [r - s for seq, s, r, _ in got if seq >= max(warmup, caught_up)], "received": len(got)}


def run_side(side: str, size: int, total: int, hz: float, warmup: int) -> dict:
    if side == "raw-zenoh":
        return run_raw(size, total, hz, warmup, extra_sub=False, iterate=True)
    if side in DIAGNOSTIC_SIDES:
        from shm_ring import run_shm
        from shm_ring_flows import run_retriever_ring

        ring_modes = {"retriever-zenoh-ring-copy": "copy", "retriever-zenoh-ring-view": "view",
                      "retriever-unix-ring-copy": "unix"}
        if side in ring_modes:
            return run_retriever_ring(size, total, hz, warmup, ring_modes[side])
        return run_shm(size, total, hz, warmup, {"raw-zenoh-shm-copy": "copy", "raw-zenoh-shm-view": "view",
                                                 "raw-unix-shm-copy": "unix"}[side])
    if side in ("raw-dora", "raw-dora-bp"):
        return run_raw_dora(size, total, hz, warmup, backpressure=side == "raw-dora-bp")
    return run_retriever(size, total, hz, warmup, side.removeprefix("retriever-"))


def band(lat_ns: list[int]) -> dict:
    s = sorted(lat_ns)
    return {"n": len(s), "med": quantile(s, 0.5) / 1e3, "p10": quantile(s, 0.1) / 1e3, "p90": quantile(s, 0.9) / 1e3}


def plot(rows: dict, sizes: list[int], sides: list[str], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    styles = {"retriever-inproc": ("tab:gray", ":"), "retriever-zenoh": ("tab:blue", "-"),
              "retriever-dora": ("tab:orange", "-"), "raw-zenoh": ("tab:blue", "--"), "raw-dora": ("tab:orange", "--"),
              "raw-dora-bp": ("tab:red", "-."), "raw-zenoh-shm-copy": ("tab:green", "--"),
              "raw-zenoh-shm-view": ("tab:green", ":"), "raw-unix-shm-copy": ("tab:olive", "--"),
              "retriever-zenoh-ring-copy": ("tab:purple", "-"), "retriever-zenoh-ring-view": ("tab:purple", ":"),
              "retriever-unix-ring-copy": ("tab:brown", "-")}
    for side in sides:
        xs = [s for s in sizes if rows[s][side]["n"]]
        color, line = styles[side]
        ax.plot(xs, [rows[s][side]["med"] for s in xs], line, marker="o", ms=3, color=color, label=side)
        ax.fill_between(xs, [rows[s][side]["p10"] for s in xs], [rows[s][side]["p90"] for s in xs],
                        color=color, alpha=0.15, linewidth=0)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xticks(sizes, [fmt_size(s).replace(" ", "") for s in sizes], rotation=45)
    ax.set_xlabel("payload")
    ax.set_ylabel("one-way latency (µs): median, p10-p90 band")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, metavar="N", help="payload sizes; suffixes Ki, Mi")
    p.add_argument("--sides", default=",".join(SIDES),
                   help=f"comma-separated, of {', '.join(SIDES)}; diagnostics: {', '.join(DIAGNOSTIC_SIDES)}")
    p.add_argument("--hz", type=float, default=20.0, help="messages per second (default 20)")
    p.add_argument("--samples", type=int, default=100, help="samples kept per size and side (default 100)")
    p.add_argument("--warmup", type=int, default=5, help="first messages of each run dropped (default 5)")
    p.add_argument("--rounds", type=int, default=2, help="runs per size and side, interleaved (default 2)")
    p.add_argument("--csv", type=Path, default=HERE / "fig7a_results" / "latency.csv")
    p.add_argument("--png", type=Path, default=HERE / "fig7a_results" / "latency.png")
    args = p.parse_args(argv)
    sizes = [parse_size(s) for s in args.sizes]
    sides = [s.strip() for s in args.sides.split(",") if s.strip()]
    unknown = sorted(set(sides) - set(SIDES) - set(DIAGNOSTIC_SIDES))
    if unknown:
        p.error(f"unknown side(s) {unknown}; of {', '.join(SIDES + DIAGNOSTIC_SIDES)}")
    per_round = args.warmup + -(-args.samples // args.rounds)

    from importlib.metadata import version

    stamp = datetime.datetime.now().isoformat(timespec="seconds")
    machine = (f"python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} cpus; eclipse-zenoh "
               f"{version('eclipse-zenoh')}, dora-rs {version('dora-rs')}; {stamp}")
    print("Fig. 7a: one-way latency vs payload, five systems and dora's daemon route, interleaved")
    print(machine)
    print(f"{args.hz:g} Hz, {args.rounds} rounds per size, each {args.warmup} warm-up + "
          f"{per_round - args.warmup} samples per side; load average {os.getloadavg()[0]:.2f}")
    rows: dict[int, dict] = {}
    samples: list[tuple] = []
    for size in sizes:
        t = time.perf_counter()
        lat: dict[str, list] = {side: [] for side in sides}
        received = dict.fromkeys(sides, 0)
        for r in range(args.rounds):
            for side in sides if r % 2 == 0 else sides[::-1]:
                out = run_side(side, size, per_round, args.hz, args.warmup)
                lat[side] += out["lat"]
                received[side] += out["received"]
        rows[size] = {side: {**band(lat[side]), "received": received[side]} for side in sides}
        samples += [(size, side, v) for side in sides for v in lat[side]]
        print(f"  {fmt_size(size):>8}: " + ", ".join(f"{side} {rows[size][side]['med']:.0f} µs" for side in sides)
              + f"  [{time.perf_counter() - t:.0f} s]", flush=True)
    print()
    print(f"{'payload':>8} │ " + " │ ".join(f"{side:>22}" for side in sides)
          + " │ ret-zenoh/raw-zenoh │ ret-dora/raw-dora │ ret-dora/raw-dora-bp")
    print(f"{'':>8} │ " + " │ ".join(f"{'median (p10-p90) µs':>22}" for _ in sides) + " │")
    for size in sizes:
        r = rows[size]
        cells = [f"{r[s]['med']:>7.0f} ({r[s]['p10']:.0f}-{r[s]['p90']:.0f})" for s in sides]

        def ratio(a: str, b: str) -> str:
            return f"{r[a]['med'] / r[b]['med']:.2f}" if a in r and b in r and r[b]["med"] else "-"
        print(f"{fmt_size(size):>8} │ " + " │ ".join(f"{c:>22}" for c in cells)
              + f" │ {ratio('retriever-zenoh', 'raw-zenoh'):>19} │ {ratio('retriever-dora', 'raw-dora'):>17}"
              + f" │ {ratio('retriever-dora', 'raw-dora-bp'):>20}")
    short = [f"{side} {fmt_size(size)}: {rows[size][side]['received']}/{per_round * args.rounds}"
             for size in sizes for side in sides if rows[size][side]["received"] < per_round * args.rounds]
    print("every message received -> " + ("yes" if not short else "NO: " + "; ".join(short)))
    print(f"load average at end {os.getloadavg()[0]:.2f}")
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with open(args.csv, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["size_bytes", "side", "latency_ns"])
        w.writerows(samples)
    args.png.parent.mkdir(parents=True, exist_ok=True)
    plot(rows, sizes, sides, args.png, f"one-way latency, {args.hz:g} Hz, same machine, interleaved ({stamp})")
    print(f"wrote {args.csv} and {args.png}")
    return 0


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
