"""``python -m agents.learn collect|train|evaluate``: the learning loop on Retriever-0's Pick.

    collect  --episodes N --seeds A:B -o DIR [--force]
             N Pick-only episodes of the scripted skill (seeds A, A+1, …: where the spice is,
             which drawer), in virtual time on inproc; one log per episode (DIR/pick-seedS.mcap)
             and DIR/episodes.json
    train    DIR -o policy.pt [--minutes M] [--max-epochs E]
             a small MLP by behaviour cloning on the successful episodes' pick_policy ticks
    evaluate --seeds A:B [--skill-policy PATH] [--out results.json]
             success of the Pick skill alone and of the whole task, per seed, mean ± std;
             the scripted Pick without PATH
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import asdict
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

_err = Console(stderr=True)
_out = Console()


def _bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), TextColumn("{task.fields[note]}"), console=_err)


def collect(episodes: int | None, seeds: str, out: Path, force: bool = False) -> list[dict]:
    from .episodes import parse_seeds, pick_episode
    pool = parse_seeds(seeds)
    count = len(pool) if episodes is None else episodes
    if not 0 < count <= len(pool):
        raise ValueError(f"--episodes {count}: give 1 to {len(pool)} (one seed each, from --seeds {seeds})")
    out.mkdir(parents=True, exist_ok=True)
    logs = [out / f"pick-seed{seed:05d}.mcap" for seed in pool[:count]]
    existing = [p for p in logs if p.exists()]
    if existing and not force:
        raise ValueError(f"{existing[0]} already exists ({len(existing)} of the logs do); pass --force to replace them")
    rows = []
    with _bar() as bar:
        task = bar.add_task("collecting Pick", total=count, note="")
        for seed, log in zip(pool[:count], logs):
            if log.exists():
                log.unlink()
            outcome = pick_episode(seed, "scripted", log=str(log))
            rows.append({**asdict(outcome), "log": log.name})
            done = sum(r["success"] for r in rows)
            bar.update(task, advance=1, note=f"{done}/{len(rows)} done, {outcome.wall:.2f} s wall each")
    (out / "episodes.json").write_text(json.dumps(rows, indent=1) + "\n")
    walls = [r["wall"] for r in rows]
    _out.print(f"{count} episodes in {out}: {sum(r['success'] for r in rows)} succeeded; "
               f"{statistics.mean(walls):.2f} s wall per episode (min {min(walls):.2f}, max {max(walls):.2f}), "
               f"{statistics.mean(r['seconds'] for r in rows):.1f} s of world time", highlight=False)
    return rows


def train_policy(folder: Path, out: Path, minutes: float, max_epochs: int) -> dict:
    from .bc import train
    from .dataset import load_dataset
    logs = sorted(folder.glob("*.mcap"))
    if not logs:
        raise ValueError(f"{folder}: no logs (*.mcap) to train on; collect them with python -m agents.learn collect")
    started = time.perf_counter()
    samples = load_dataset(logs)
    read_s = time.perf_counter() - started
    with _bar() as bar:
        task = bar.add_task("training", total=max_epochs, note="")
        module, summary = train(samples, budget_s=minutes * 60, max_epochs=max_epochs,
                                log=lambda epoch, loss: bar.update(task, completed=epoch, note=f"loss {loss:.4f}"))
    module.save(str(out))
    result = {**asdict(summary), "logs": len(logs), "read_s": round(read_s, 2), "policy": str(out)}
    _out.print(f"trained on {summary.samples} ticks of {summary.episodes} successful episodes (of {len(logs)} logs, "
               f"read in {read_s:.1f} s): {summary.epochs} epochs in {summary.seconds:.1f} s, "
               f"loss {summary.train_loss:.4f}, "
               f"held-out {summary.held_out_loss:.4f}; {summary.parameters} parameters → {out}", highlight=False)
    return result


def evaluate(seeds: str, policy: str | None, out: Path | None = None, task: bool = True) -> dict:
    from .episodes import parse_seeds, pick_episode, task_episode
    pool = parse_seeds(seeds)
    name = policy or "scripted"
    rows = {"skill": [], "task": []}
    with _bar() as bar:
        runs = [("skill", pick_episode)] + ([("task", task_episode)] if task else [])
        for what, run in runs:
            progress = bar.add_task(f"{what} with {Path(name).name}", total=len(pool), note="")
            for seed in pool:
                outcome = run(seed, policy or ("scripted" if what == "skill" else None))
                rows[what].append(asdict(outcome))
                ok = sum(r["success"] for r in rows[what])
                bar.update(progress, advance=1, note=f"{ok}/{len(rows[what])} succeeded")
    summary = {"policy": name, "seeds": f"{pool.start}:{pool.stop}"}
    for what, outcomes in rows.items():
        if outcomes:
            wins = [float(r["success"]) for r in outcomes]
            summary[what] = {"success_mean": statistics.mean(wins), "success_std": statistics.pstdev(wins),
                             "episodes": outcomes}
            _out.print(f"{what}: success {statistics.mean(wins):.2f} ± {statistics.pstdev(wins):.2f} over "
                       f"{len(wins)} seeds ({int(sum(wins))}/{len(wins)}); "
                       f"{statistics.mean(r['wall'] for r in outcomes):.2f} s wall per episode", highlight=False)
    if out is not None:
        out.write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.learn", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="Pick-only episodes of the scripted skill, one log each")
    c.add_argument("--skill", default="pick", choices=["pick"], help="the skill (Pick)")
    c.add_argument("--episodes", type=int, help="how many (default: one per seed of --seeds)")
    c.add_argument("--seeds", required=True, help="A:B, seeds A to B-1")
    c.add_argument("-o", "--out", type=Path, required=True, help="the folder of the logs")
    c.add_argument("--force", action="store_true", help="replace logs that exist")
    t = sub.add_parser("train", help="behaviour cloning of a small MLP on collected logs")
    t.add_argument("folder", type=Path, help="the folder collect wrote")
    t.add_argument("-o", "--out", type=Path, required=True, help="the TorchScript module to write (*.pt)")
    t.add_argument("--minutes", type=float, default=2.0, help="wall-time budget of the training")
    t.add_argument("--max-epochs", type=int, default=3000)
    t.add_argument("--json", type=Path, help="write the training summary here")
    e = sub.add_parser("evaluate", help="success of the skill and of the whole task over seeds")
    e.add_argument("--seeds", required=True, help="A:B, seeds A to B-1 (held out from collection)")
    e.add_argument("--skill-policy", help="a policy file (TorchScript); the scripted Pick without it")
    e.add_argument("--skill-only", action="store_true", help="only the Pick-only episodes, not the whole task")
    e.add_argument("--out", type=Path, help="write the results (JSON) here")
    args = parser.parse_args(argv)
    try:
        if args.command == "collect":
            collect(args.episodes, args.seeds, args.out, args.force)
        elif args.command == "train":
            result = train_policy(args.folder, args.out, args.minutes, args.max_epochs)
            if args.json:
                args.json.write_text(json.dumps(result, indent=1) + "\n")
        else:
            if args.skill_policy is not None:
                from ..skill_policies import check_skill_policy
                check_skill_policy(args.skill_policy)
            evaluate(args.seeds, args.skill_policy, args.out, task=not args.skill_only)
    except ValueError as exc:
        _err.print(f"error: {exc}", highlight=False)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
