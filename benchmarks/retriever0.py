"""Retriever-0's costs (issue 20, "Measured"): one whole episode's wall time on each backend, the
rate each flow kept on zenoh against its clock, the controller's tick lateness, and the world's
physics and render time per step.

    python benchmarks/retriever0.py --repeats 3 --json benchmarks/retriever0_results.json

The episode is the paper's (the spice in TR, seed 0). Reported: medians over ``--repeats`` runs
with min and max. Run it on a quiet machine: the zenoh episode is real time, 9 processes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from agents.episode import summarize  # noqa: E402
from agents.retriever0 import build  # noqa: E402

EPISODE_S = 80.0


def spread(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def episode(backend: str) -> dict:
    pipe = build(seed=0, drawer="TR")
    options = {"quiet": True} if backend == "zenoh" else {}
    started = time.perf_counter()
    trace = pipe.run(duration=EPISODE_S, backend=backend, **options)
    wall = time.perf_counter() - started
    ep = summarize(trace, pipe.build_ir())
    return {"wall_s": wall, "world_s": ep.duration, "score": ep.score, "skills": ep.skills,
            "rates": {r.node: {"hz": r.hz, "achieved_hz": r.achieved_hz, "late_p99_ms": r.late_p99_ms}
                      for r in ep.rates}}


def world_costs(ticks: int = 2000) -> dict:
    """Physics µs per 5 ms tick under the scripted Pick/Season motion, and render ms per frame."""
    from agents.skills import paper_trace, run_skills
    from agents.world import Layout, Sim
    sim = Sim(Layout.from_seed(0, "TR"))
    physics = []
    original = sim.advance

    def timed(seconds: float) -> None:
        t = time.perf_counter_ns()
        original(seconds)
        physics.append((time.perf_counter_ns() - t) / 1e3)

    sim.advance = timed
    run_skills(sim, paper_trace("TR"))
    renders = {}
    for camera, (h, w) in (("head", (96, 128)), ("wrist", (64, 64))):
        sim.render(camera, h, w)  # the renderer's creation, outside the timing
        times = []
        for _ in range(200):
            t = time.perf_counter_ns()
            sim.render(camera, h, w)
            times.append((time.perf_counter_ns() - t) / 1e6)
        renders[f"{camera}_{h}x{w}_ms"] = spread(times)
    sim.close()
    return {"physics_us_per_tick": spread(physics), "physics_p99_us": float(np.percentile(physics, 99)), **renders}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", default="inproc,zenoh")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    results: dict = {"world": world_costs()}
    print(f"physics per 5 ms tick: {results['world']['physics_us_per_tick']['median']:.0f} µs median, "
          f"p99 {results['world']['physics_p99_us']:.0f} µs; render head 96x128 "
          f"{results['world']['head_96x128_ms']['median']:.2f} ms, wrist 64x64 "
          f"{results['world']['wrist_64x64_ms']['median']:.2f} ms", flush=True)
    for backend in args.backends.split(","):
        runs = [episode(backend) for _ in range(args.repeats)]
        walls = [r["wall_s"] for r in runs]
        results[backend] = {"wall_s": spread(walls), "runs": runs}
        print(f"{backend}: episode of {runs[0]['world_s']:.1f} s world time in {statistics.median(walls):.1f} s wall "
              f"(median of {len(runs)}, {min(walls):.1f}–{max(walls):.1f}); scores {[r['score'] for r in runs]}",
              flush=True)
        if backend == "zenoh":
            for node in sorted(runs[0]["rates"]):
                rated = [r["rates"][node] for r in runs]
                if rated[0]["hz"]:
                    late = [x["late_p99_ms"] for x in rated if x["late_p99_ms"] is not None]
                    print(f"  {node:<13} {statistics.median(x['achieved_hz'] for x in rated):6.1f} / "
                          f"{rated[0]['hz']:g} Hz, tick lateness p99 {statistics.median(late):.1f} ms "
                          f"({min(late):.1f}–{max(late):.1f})")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
