"""Memory of a long logged run: every process's RSS over ten minutes of a robot-shaped pipeline.

A 30 Hz 640×480×3 uint8 camera → a 10 Hz policy (Latest) → a 200 Hz controller (Latest), logged
(``benchmarks/zenoh_flows.py``: RGBCamera, ChunkPolicy, JointController), run

- on ``zenoh`` for ``--minutes`` of real time, as a user would write it: ``pipe.run(duration,
  backend="zenoh", log=path)`` (a logged real-time run keeps only counters by default);
- on ``inproc`` for as much virtual time, with ``keep="counters"`` (a virtual-time run keeps
  its trace by default: that is what tests want; a long one says so).

Each backend runs in a process of its own (this script with ``--one``). Every 10 s (of run time:
wall on zenoh, virtual on inproc) it reads ``VmRSS`` from ``/proc/<pid>/status`` of every process
of the run (itself, which coordinates and logs, and on zenoh each flow's worker) and the log's
size; the last sample, taken as the processes end, is not judged. Target: after the first minute, every process's
RSS stays within 50 MB of its value at one minute; only the log grows. It also reports the log's
write rate, and that no frame was dropped: every camera frame the camera stepped is in the log,
with seqs 0..n-1 and none missing.

    .venv/bin/python benchmarks/memory.py                     # 10 min on each backend, ~25 min
    .venv/bin/python benchmarks/memory.py --minutes 2 --backends zenoh

Writes ``benchmarks/memory_results/memory.json`` and ``memory.png`` (``--out``). The logs (about
17 GB each for ten minutes) go to a temporary folder on the same disk and are removed.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))  # zenoh_flows: the workers get this path from the coordinator

from zenoh_flows import ChunkPolicy, JointController, RGBCamera  # noqa: E402

from retriever import Latest, Pipeline, Rate  # noqa: E402

BOUND_MB = 50.0
SAMPLE_EVERY_S = 10.0
SETTLED_S = 60.0


def build(camera_hz: float = 30.0, policy_hz: float = 10.0, control_hz: float = 200.0) -> Pipeline:
    with Pipeline("memory", deadline=1.0) as pipe:
        camera = RGBCamera().configure(name="camera") @ Rate(hz=camera_hz)
        policy = ChunkPolicy().configure(name="policy") @ Rate(hz=policy_hz)
        controller = JointController().configure(name="controller") @ Rate(hz=control_hz)
        camera.then(policy, sync=Latest())
        policy.then(controller, sync=Latest())
    return pipe


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def run_zenoh(seconds: float, log: Path) -> dict:
    pipe = build()
    handle = pipe.run(duration=seconds, backend="zenoh", log=log, blocking=False, quiet=True)
    session = None
    while not handle.done and (session is None or getattr(session, "t0", None) is None):
        session = pipe.session
        time.sleep(0.01)
    if handle.done:
        handle.wait()  # raises what stopped it
    pids = {"coordinator (this process)": os.getpid(), **session.worker_pids()}
    samples = []
    t0_wall = session.t0 / 1e9
    due = 0.0
    while not handle.done:
        now = time.time() - t0_wall
        if now >= due:
            samples.append({"t": round(now, 2), "rss_mb": {name: rss_mb(pid) for name, pid in pids.items()},
                            "log_bytes": log.stat().st_size if log.exists() else 0})
            due += SAMPLE_EVERY_S
        time.sleep(0.05)
    handle.wait()
    return {"samples": samples, "stats": {n: vars(s) for n, s in pipe.stats().items()},
            "counts": dict(pipe.counts()), "keep": session.keep, "run_s": seconds}


def run_inproc(seconds: float, log: Path) -> dict:
    pipe = build()
    handle = pipe.run(duration=seconds, backend="inproc", log=log, keep="counters", blocking=False)
    samples, due, started = [], 0.0, time.monotonic()
    name = "this process (the run, the log)"
    while not handle.done:
        session = pipe.session
        writer = getattr(session, "log", None)
        t = writer.last_step_ns / 1e9 if writer is not None else 0.0
        if t >= due:
            samples.append({"t": round(t, 2), "rss_mb": {name: rss_mb(os.getpid())},
                            "log_bytes": log.stat().st_size if log.exists() else 0})
            due += SAMPLE_EVERY_S
        time.sleep(0.02)
    handle.wait()
    samples.append({"t": seconds, "rss_mb": {name: rss_mb(os.getpid())}, "log_bytes": log.stat().st_size})
    return {"samples": samples, "stats": {n: vars(s) for n, s in pipe.stats().items()}, "counts": {},
            "keep": pipe.session.keep, "run_s": seconds, "wall_s": round(time.monotonic() - started, 1)}


def frames_in_log(log: Path) -> dict:
    """Every camera frame in the log, seqs 0..n-1? Streamed with the plain ``mcap`` reader, one
    message at a time (reading a 17 GB log whole would take this process's memory with it)."""
    from mcap.reader import make_reader

    seqs, end = [], None
    with open(log, "rb") as f:
        reader = make_reader(f)
        for _, _, message in reader.iter_messages(topics=["data/camera/pixels"]):
            seqs.append(message.sequence)
        end = next((m.metadata for m in reader.iter_metadata() if m.name == "retriever.end"), None)
    seqs.sort()
    missing = (seqs[-1] + 1 - len(seqs)) if seqs else 0
    return {"frames_logged": len(seqs), "first_seq": seqs[0] if seqs else None,
            "last_seq": seqs[-1] if seqs else None, "missing": missing,
            "steps_logged": int(end["steps"]) if end else None}


def verdicts(result: dict) -> dict:
    """Per process: RSS at one minute, the largest move from it after, and whether it is within BOUND_MB."""
    samples = [s for s in result["samples"] if s["t"] < result["run_s"]]  # not the processes' ends
    at_minute = next((s for s in samples if s["t"] >= SETTLED_S), None)
    out = {}
    for name in samples[0]["rss_mb"]:
        if at_minute is None or at_minute["rss_mb"].get(name) is None:
            out[name] = {"verdict": "n/a (shorter than a minute)"}
            continue
        base = at_minute["rss_mb"][name]
        later = [s["rss_mb"][name] for s in samples if s["t"] >= SETTLED_S and s["rss_mb"].get(name) is not None]
        drift = max(abs(x - base) for x in later)
        out[name] = {"rss_at_1min_mb": round(base, 1), "max_mb": round(max(later), 1),
                     "max_move_after_1min_mb": round(drift, 1), "verdict": "PASS" if drift <= BOUND_MB else "FAIL"}
    return out


def plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(results), figsize=(6.2 * len(results), 4.2), squeeze=False)
    for ax, (backend, result) in zip(axes[0], results.items()):
        ts = [s["t"] / 60 for s in result["samples"]]
        for name in result["samples"][0]["rss_mb"]:
            ax.plot(ts, [s["rss_mb"].get(name) for s in result["samples"]], marker=".", label=name)
        ax.axvline(SETTLED_S / 60, color="grey", lw=0.8, ls=":")
        ax.set_xlabel("run time (min)" + (" (virtual)" if backend == "inproc" else ""))
        ax.set_ylabel("RSS (MB)")
        ax.set_title(f"{backend}: keep={result['keep']!r}", fontsize=10)
        twin = ax.twinx()
        twin.plot(ts, [s["log_bytes"] / 1e9 for s in result["samples"]], color="black", lw=1.0, ls="--",
                  label="log size (GB)")
        twin.set_ylabel("log size (GB)")
        ax.legend(fontsize=7, loc="center left")
    fig.suptitle("RSS of every process of a logged run: 30 Hz 640×480 RGB camera → 10 Hz policy → 200 Hz "
                 "controller", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--backends", default="zenoh,inproc")
    parser.add_argument("--out", type=Path, default=HERE / "memory_results")
    parser.add_argument("--log-dir", type=Path, default=None, help="where the logs go (default: a temporary folder)")
    parser.add_argument("--one", nargs=3, metavar=("BACKEND", "LOG", "JSON"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    seconds = args.minutes * 60
    if args.one:  # one backend's run, in a process of its own: nothing else of this script in its RSS
        backend, log, out = args.one
        result = (run_zenoh if backend == "zenoh" else run_inproc)(seconds, Path(log))
        Path(out).write_text(json.dumps(result))
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    folder = Path(tempfile.mkdtemp(prefix="retriever-memory-", dir=args.log_dir))
    results: dict = {}
    try:
        for backend in [b.strip() for b in args.backends.split(",") if b.strip()]:
            log = folder / f"{backend}.mcap"
            print(f"{backend}: {args.minutes:g} min, logging to {log} ...", flush=True)
            started = time.monotonic()
            out = folder / f"{backend}.json"
            subprocess.run([sys.executable, __file__, "--minutes", str(args.minutes), "--one", backend, str(log),
                            str(out)], check=True)
            result = json.loads(out.read_text())
            result.setdefault("wall_s", round(time.monotonic() - started, 1))
            size = log.stat().st_size
            result["log_bytes"] = size
            result["log_write_mb_per_s"] = round(size / 1e6 / result["run_s"], 1)
            result["frames"] = frames_in_log(log)
            frames = result["frames"]
            frames["camera_steps"] = result["stats"]["camera"]["steps"]
            frames["none_dropped"] = (frames["missing"] == 0 and frames["first_seq"] == 0
                                      and frames["frames_logged"] == frames["camera_steps"])
            result["verdicts"] = verdicts(result)
            log.unlink()
            results[backend] = result
            for name, v in result["verdicts"].items():
                print(f"  {name:<32} {v}", flush=True)
            print(f"  log {size / 1e9:.2f} GB, {result['log_write_mb_per_s']} MB/s; frames {result['frames']}",
                  flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=HERE).stdout.strip()
    record = {"date": datetime.date.today().isoformat(), "commit": commit, "minutes": args.minutes,
              "bound_mb": BOUND_MB, "command": "python " + " ".join(sys.argv), "results": results}
    (args.out / "memory.json").write_text(json.dumps(record, indent=1) + "\n")
    plot(results, args.out / "memory.png")
    ok = all(v.get("verdict") in ("PASS", "n/a (shorter than a minute)") for r in results.values()
             for v in r["verdicts"].values()) and all(r["frames"]["none_dropped"] for r in results.values())
    print(f"{'PASS' if ok else 'FAIL'}: wrote {args.out / 'memory.json'} and {args.out / 'memory.png'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
