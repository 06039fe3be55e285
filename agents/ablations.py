"""The paper's Table II in simulation: Retriever-0 and its ablations over many seeds.

    python -m agents.ablations --seeds 20 --slip-prob 0.3 [--task drawers|bag]

Each (condition, seed) is one episode in virtual time (deterministic: the same seed gives the same
trace digest, recorded in the CSV), with failures injected: with probability ``--slip-prob``
(decided by the seed) the first grasp slips a second after it lifted. Conditions (paper Sec. VI):

- ``full``: Retriever-0 as in the demo;
- ``no-plan-chunking``: the planner proposes one skill at a time and the monitor waits for it;
- ``no-skill-progress``: the monitor switches skills on a timeout instead of on progress;
- ``human-in-the-loop``: a scripted operator takes over after a failed skill (teleop override);
- ``vla-only``: no planner and no belief, one fixed skill order.

It writes ``ablations.csv`` (one row per episode), ``ablations.md`` (the table: time to best
progress and task progress, mean ± std) and ``ablations.png`` to ``benchmarks/ablations/<task>/``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .retriever0 import ABLATIONS

REPO = Path(__file__).resolve().parents[1]
EPISODE_S = 150.0
FIELDS = ("condition", "seed", "task", "drawer", "score", "best_at", "finished", "gave_up", "failures", "replans",
          "duration", "skills", "digest", "wall_s", "error")


def episode(condition: str, seed: int, slip_prob: float, duration: float = EPISODE_S, task: str = "drawers") -> dict:
    """One episode in virtual time; a row of the CSV."""
    from .episode import summarize
    from .retriever0 import build
    from .world import Layout
    started = time.perf_counter()
    pipe = build(seed=seed, ablation=condition, slip_prob=slip_prob, task=task)
    trace = pipe.run(duration=duration, backend="inproc")
    ep = summarize(trace, pipe.build_ir())
    return {"condition": condition, "seed": seed, "task": task,
            "drawer": Layout.from_seed(seed).target_drawer if task == "drawers" else "",
            "score": ep.score, "best_at": round(ep.best_at, 3) if ep.score > 0 else "", "finished": ep.finished,
            "gave_up": ep.gave_up, "failures": ep.failures, "replans": ep.replans, "duration": round(ep.duration, 3),
            "skills": " > ".join(ep.skills), "digest": trace.digest()[:16],
            "wall_s": round(time.perf_counter() - started, 2), "error": ""}


def run_all(conditions, seeds, slip_prob: float, jobs: int, progress=None, task: str = "drawers") -> list[dict]:
    """Every (condition, seed) episode, ``jobs`` at a time, in order, each in a process of its own
    that hands back its row as JSON (nothing pickled); an episode that raised is a row with its
    ``error`` (and no score), not the end of the others."""
    tasks = [(c, s) for c in conditions for s in seeds]
    rows = []
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(_episode_in_a_process, c, s, slip_prob, task) for c, s in tasks]
        for future in futures:
            rows.append(future.result())
            if progress is not None:
                progress(rows[-1])
    return rows


def _episode_in_a_process(condition: str, seed: int, slip_prob: float, task: str) -> dict:
    command = [sys.executable, "-m", "agents.ablations", "--episode", condition, str(seed), repr(slip_prob), task]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    lines = done.stdout.strip().splitlines()
    try:
        answer = json.loads(lines[-1])
    except (IndexError, ValueError):
        last = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
        answer = {"error": f"the episode's process failed: {last}"}
    if "error" in answer and "condition" not in answer:
        return {**dict.fromkeys(FIELDS, ""), "condition": condition, "seed": seed, "task": task, "score": 0.0,
                "error": answer["error"]}
    return answer


def _episode_answer(condition: str, seed: int, slip_prob: float, task: str) -> dict:
    """``--episode``: one episode's row, or its error, for the process that asked."""
    try:
        return episode(condition, seed, slip_prob, EPISODE_S, task)
    except Exception as e:
        return {"error": f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"}


def _mean_std(values: list[float]) -> str:
    if not values:
        return "–"
    spread = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):.1f} ± {spread:.1f}"


def table(rows: list[dict], conditions) -> str:
    """Markdown: per condition, time to best progress (episodes with any progress) and task progress."""
    lines = ["| condition | episodes | time to best progress (s) | task progress (%) | 100% | gave up |",
             "|---|---|---|---|---|---|"]
    for c in conditions:
        mine = [r for r in rows if r["condition"] == c and not r["error"]]
        scores = [100 * r["score"] for r in mine]
        times = [r["best_at"] for r in mine if r["score"] > 0]
        lines.append(f"| {c} | {len(mine)} | {_mean_std(times)} | {_mean_std(scores)} | "
                     f"{sum(r['score'] == 1.0 for r in mine)} | {sum(bool(r['gave_up']) for r in mine)} |")
    return "\n".join(lines)


def plot(rows: list[dict], conditions, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax_p, ax_t) = plt.subplots(1, 2, figsize=(10, 3.6))
    for i, c in enumerate(conditions):
        mine = [r for r in rows if r["condition"] == c and not r["error"]]
        scores = [100 * r["score"] for r in mine]
        times = [r["best_at"] for r in mine if r["score"] > 0]
        ax_p.bar(i, statistics.mean(scores) if scores else 0,
                 yerr=statistics.stdev(scores) if len(scores) > 1 else 0, color=f"C{i}", capsize=4)
        if times:
            ax_t.bar(i, statistics.mean(times), yerr=statistics.stdev(times) if len(times) > 1 else 0,
                     color=f"C{i}", capsize=4)
    for ax, label in ((ax_p, "task progress (%)"), (ax_t, "time to best progress (s)")):
        ax.set_xticks(range(len(conditions)), conditions, rotation=20, fontsize=8)
        ax.set_ylabel(label)
    seeds = len({r["seed"] for r in rows})
    fig.suptitle(f"Retriever-0 ablations in simulation, {rows[0]['task']} task ({seeds} seeds, mean ± std)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--episode"]:  # one episode, in a process run_all started
        condition, seed, slip_prob, task = argv[1:5]
        print(json.dumps(_episode_answer(condition, int(seed), float(slip_prob), task)))
        return 0
    parser = argparse.ArgumentParser(prog="python -m agents.ablations", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="episodes per condition (seeds 0..N-1)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--conditions", default=",".join(ABLATIONS),
                        help="comma-separated, of: " + ", ".join(ABLATIONS))
    parser.add_argument("--slip-prob", type=float, default=0.3, help="probability that an episode's grasp slips")
    parser.add_argument("--jobs", type=int, default=2, help="episodes run at once (processes)")
    parser.add_argument("--task", choices=("drawers", "bag"), default="drawers")
    parser.add_argument("--out", type=Path, help="default: benchmarks/ablations/<task>")
    args = parser.parse_args(argv)
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    unknown = [c for c in conditions if c not in ABLATIONS]
    if unknown:
        parser.error(f"unknown condition(s) {', '.join(unknown)}: choose from {', '.join(ABLATIONS)}")
    if args.seeds < 1 or args.jobs < 1 or args.first_seed < 0 or not 0 <= args.slip_prob <= 1:
        parser.error("--seeds and --jobs must be >= 1, --first-seed >= 0 and --slip-prob in [0, 1]")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    args.out = args.out or Path("benchmarks/ablations") / args.task
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with open(args.out / "ablations.csv", "w", newline="") as f:  # a row per episode as it ends: ^C keeps them
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()

        def done(r: dict) -> None:
            writer.writerow(r)
            f.flush()
            if r["error"]:
                print(f"{r['condition']:<18} seed {r['seed']:>3}: FAILED {r['error']}", flush=True)
                return
            print(f"{r['condition']:<18} seed {r['seed']:>3} ({r['drawer'] or r['task']}): "
                  f"{100 * r['score']:3.0f}% best at {r['best_at'] or '–'} s"
                  f"{'  gave up: ' + r['gave_up'] if r['gave_up'] else ''}", flush=True)
        try:
            rows = run_all(conditions, seeds, args.slip_prob, args.jobs, task=args.task, progress=done)
        except KeyboardInterrupt:
            print(f"interrupted: the episodes that ended are in {args.out / 'ablations.csv'}")
            return 130
    text = table(rows, conditions)
    (args.out / "ablations.md").write_text(
        f"{text}\n\n{args.task} task, {len(seeds)} seeds ({seeds.start}..{seeds.stop - 1}), slip probability "
        f"{args.slip_prob}, virtual time; `python -m agents.ablations --task {args.task} --seeds {args.seeds} "
        f"--slip-prob {args.slip_prob}` "
        f"({time.perf_counter() - started:.0f} s wall, {args.jobs} job{'s' if args.jobs != 1 else ''})\n")
    plot(rows, conditions, args.out / "ablations.png")
    print(text)
    print(f"wrote {args.out / 'ablations.csv'}, {args.out / 'ablations.md'}, {args.out / 'ablations.png'}")
    failed = [r for r in rows if r["error"]]
    if failed:
        print(f"{len(failed)} episode(s) failed (their rows say why); the table leaves them out")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
