"""``python -m agents.learn collect|export|train|evaluate|all``: the learning loop on Retriever-0's Pick.

    collect  --episodes N --seeds A:B -o DIR [--force]
             N Pick-only episodes of the scripted skill (seeds A, A+1, …: where the spice is,
             which drawer), in virtual time on inproc; one log per episode (DIR/pick-seedS.mcap)
             and DIR/episodes.json
    export   DIR -o DATASET [--format lerobot|npz] [--force]
             the successful episodes' logs as a dataset (retriever log export --flow pick_policy)
    train    DATASET -o CHECKPOINT [--minutes M] [--max-epochs E] [--force]
             a small MLP by behaviour cloning on the dataset, saved as a checkpoint directory
             (policy.json, model.safetensors) that retriever.learn.TorchPolicy runs
    evaluate --seeds A:B [--skill-policy CHECKPOINT] [--out results.json]
             success of the Pick skill alone and of the whole task, per seed, mean ± std;
             the scripted Pick without CHECKPOINT
    all      --episodes N --train-seeds A:B --eval-seeds C:D --minutes M -o DIR [--results RDIR]
             collect → export → train → evaluate the learned Pick and the scripted one;
             RDIR (default DIR) gets results.json and learning_loop.png
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import asdict
from pathlib import Path

from retriever.errors import RetrieverError
from retriever.log import RunEnd
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

#: plain text, never markup (a message or a path may hold brackets: "retriever-robotics[lerobot]"),
#: and no line breaks of rich's own: a message piped to a file or a test stays whole
_err = Console(stderr=True, markup=False, soft_wrap=True)
_out = Console(markup=False, soft_wrap=True)
MINUTES_HELP = ("wall-time budget of the training (inf: none; a seed then trains the same weights every time, "
                "which a budget that ends the training does not)")
MAX_EPOCHS_HELP = ("at most this many epochs; the learning rate anneals (cosine) over whichever of the two limits "
                   "comes first")
#: the packages of the lerobot extra that training and a learned policy import
EXTRA_MODULES = ("torch", "safetensors", "lerobot")


def _bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TimeRemainingColumn(), TextColumn("{task.fields[note]}"), console=_err)


def _write_json(path: Path, value) -> None:
    """``value`` as ``path``'s JSON, replaced at once (a reader never sees half a file)."""
    part = path.with_name(path.name + ".part")
    part.write_text(json.dumps(value, indent=1) + "\n")
    os.replace(part, path)


def collect(episodes: int | None, seeds: str, out: Path, force: bool = False) -> list[dict]:
    from .episodes import parse_seeds, pick_episode
    pool = parse_seeds(seeds)
    count = len(pool) if episodes is None else episodes
    if not 0 < count <= len(pool):
        raise ValueError(f"--episodes {count}: give 1 to {len(pool)} (one seed each, from --seeds {seeds})")
    logs = [out / f"pick-seed{seed:05d}.mcap" for seed in pool[:count]]
    existing = [p for p in logs if p.exists()]
    if existing and not force:
        raise ValueError(f"{existing[0]} already exists ({len(existing)} of the logs do); pass --force to replace them")
    listing = out / "episodes.json"
    if listing.exists() and not force:
        raise ValueError(f"{listing} lists episodes collected before; collect into another folder, or pass --force "
                         "to replace the list with this collection's episodes")
    out.mkdir(parents=True, exist_ok=True)
    # the list says only what this collection finished: an interrupted one leaves no stale rows
    listing.unlink(missing_ok=True)
    rows = []
    with _bar() as bar:
        task = bar.add_task("collecting Pick", total=count, note="")
        for seed, log in zip(pool[:count], logs):
            if log.exists():
                log.unlink()
            outcome = pick_episode(seed, "scripted", log=str(log))
            rows.append({**asdict(outcome), "log": log.name})
            _write_json(listing, rows)
            done = sum(r["success"] for r in rows)
            bar.update(task, advance=1, note=f"{done}/{len(rows)} succeeded, the last in {outcome.wall:.2f} s wall")
    walls = [r["wall"] for r in rows]
    _out.print(f"{count} episodes in {out}: {sum(r['success'] for r in rows)} succeeded; "
               f"{statistics.mean(walls):.2f} s wall per episode (min {min(walls):.2f}, max {max(walls):.2f}), "
               f"{statistics.mean(r['seconds'] for r in rows):.1f} s of world time", highlight=False)
    return rows


def export(folder: Path, out: Path, format: str = "lerobot", force: bool = False) -> dict:
    from .dataset import export as export_logs
    rows = _listing(folder)
    logs = [folder / r["log"] for r in rows if r["success"]]
    if not logs:
        raise ValueError(f"{folder}: none of its {len(rows)} episodes succeeded: nothing to learn from")
    if out.exists() and not force:
        raise ValueError(f"{out} already exists; pass --force to replace it")
    for log in logs:
        ending = _ending(log)
        if ending != RunEnd.FINISHED:
            raise ValueError(f"{log}: its run did not end normally ({ending}); collect that seed again "
                             f"(python -m agents.learn collect --force)")
    with _bar() as bar:
        task = bar.add_task(f"exporting ({format})", total=len(logs), note="")

        def progress(log, _, tick, ticks):
            bar.update(task, completed=log + tick / max(ticks, 1))
        summary = export_logs(logs, out, format=format, overwrite=force, progress=progress)
    _out.print(str(summary), highlight=False)
    # "of": the episodes collected, of which "logs" succeeded and were exported
    return {"logs": len(logs), "of": len(rows), "format": format, "frames": summary.frames, "bytes": summary.bytes,
            "seconds": round(summary.seconds, 2), "dataset": str(out)}


def _listing(folder: Path) -> list[dict]:
    """The episodes ``collect`` listed in ``folder/episodes.json``, each with its log's file name
    (in ``folder``) and whether it succeeded; a ValueError says what is wrong with the file."""
    episodes = folder / "episodes.json"
    if not episodes.is_file():
        raise ValueError(f"{folder}: no episodes.json; collect the logs with python -m agents.learn collect")
    try:
        rows = json.loads(episodes.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise ValueError(f"{episodes} is not readable JSON ({type(e).__name__}); collect the logs again "
                         "(python -m agents.learn collect --force)") from None
    good = type(rows) is list and all(
        type(r) is dict and type(r.get("success")) is bool and type(r.get("log")) is str
        and r["log"] == Path(r["log"]).name and r["log"] not in ("", ".", "..") for r in rows)
    if not good:
        raise ValueError(f"{episodes} is not the list collect writes (an entry per episode with its 'log', a file "
                         "name in that folder, and 'success'); collect the logs again (python -m agents.learn "
                         "collect --force)")
    return rows


def _ending(log: Path) -> str:
    """How the run of ``log`` ended: its end record's status ("finished" when it ran to its end)."""
    from retriever import read_log
    run = read_log(log, salvage=True)
    if not run.complete or run.end is None:
        return "the log is incomplete"
    return run.end.get("status", "no status")


def _check_budget(minutes: float, max_epochs: int) -> None:
    if not minutes > 0:
        raise ValueError(f"--minutes {minutes}: give a positive number of minutes to train")
    if max_epochs <= 0:
        raise ValueError(f"--max-epochs {max_epochs}: give a positive number of epochs")


def _check_checkpoint_out(out: Path, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ValueError(f"-o {out}: a file is there; the checkpoint is a directory (give a new path)")
    if out.exists() and any(out.iterdir()) and not force:
        raise ValueError(f"-o {out} already exists; pass --force to replace the checkpoint in it")


def _ended(ended_by: str, minutes: float) -> str:
    from .bc import MAX_EPOCHS
    return "--max-epochs ended it" if ended_by == MAX_EPOCHS else f"the {minutes:g}-minute budget ended it"


def _loss(value: float | None) -> str:
    return "none" if value is None else f"{value:.4f}"


def train_policy(dataset: Path, out: Path, minutes: float, max_epochs: int, losses: list | None = None,
                 force: bool = False) -> dict:
    from .bc import save, train
    from .dataset import load_dataset
    _check_budget(minutes, max_epochs)
    _check_checkpoint_out(out, force)
    started = time.perf_counter()
    samples = load_dataset(dataset)
    read_s = time.perf_counter() - started
    with _bar() as bar:
        task = bar.add_task("training", total=max_epochs, note="")

        def log(epoch, loss, epochs):  # epochs: max_epochs, or fewer once the time budget is seen to end first
            bar.update(task, completed=epoch, total=epochs, note=f"loss {loss:.4f}")
            if losses is not None:
                losses.append(loss)
        module, config, summary = train(samples, budget_s=minutes * 60, max_epochs=max_epochs, log=log)
    save(module, config, out, summary)
    result = {**asdict(summary), "read_s": round(read_s, 2), "policy": str(out)}
    held = ("no episode held out" if summary.held_out_loss is None
            else f"held-out loss {summary.held_out_loss:.4f} on {summary.held_out_episodes} episodes")
    _out.print(f"trained on {summary.samples} frames of {summary.episodes} episodes (read in {read_s:.1f} s): "
               f"{summary.epochs} epochs in {summary.seconds:.1f} s ({_ended(summary.ended_by, minutes)}), "
               f"loss {_loss(summary.train_loss)}, {held}; "
               f"{summary.parameters} parameters → {out}", highlight=False)
    return result


def evaluate(seeds: str, policy: str | None, out: Path | None = None, task: bool = True, label: str = "") -> dict:
    """Success over ``seeds`` (``label``, such as "learned", begins each line printed)."""
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
            _out.print(f"{label + ' ' if label else ''}{what}: success {statistics.mean(wins):.2f} ± {statistics.pstdev(wins):.2f} over "
                       f"{len(wins)} seeds ({int(sum(wins))}/{len(wins)}); "
                       f"{statistics.mean(r['wall'] for r in outcomes):.2f} s wall per episode", highlight=False)
    if out is not None:
        out.write_text(json.dumps(summary, indent=1) + "\n")
    return summary


def loop(episodes: int, train_seeds: str, eval_seeds: str, minutes: float, out: Path, results: Path | None = None,
         format: str = "lerobot", max_epochs: int = 3000, force: bool = False, command: str | None = None) -> dict:
    """The whole loop into ``out`` (logs/, dataset/, policy/), the results into ``results``
    (``command``: how it was run, for the record)."""
    from .episodes import parse_seeds
    from .plot import plot_loop
    held_out, collected_from = parse_seeds(eval_seeds), parse_seeds(train_seeds)
    _check_budget(minutes, max_epochs)
    if held_out.start < collected_from.stop and collected_from.start < held_out.stop:
        raise ValueError(f"--eval-seeds {eval_seeds} overlaps --train-seeds {train_seeds}: evaluate on held-out seeds")
    results = results or out
    started = time.perf_counter()
    collected = collect(episodes, train_seeds, out / "logs", force)
    collect_s = time.perf_counter() - started
    exported = export(out / "logs", out / "dataset", format, force)
    losses: list[float] = []
    training = train_policy(out / "dataset", out / "policy", minutes, max_epochs, losses, force)
    learned = evaluate(eval_seeds, str(out / "policy"), label="learned")
    scripted = evaluate(eval_seeds, None, label="scripted")
    summary = {
        "command": command,
        "collected": {"episodes": len(collected), "succeeded": sum(r["success"] for r in collected),
                      "seeds": train_seeds, "seconds": round(collect_s, 1),
                      "wall_per_episode": round(statistics.mean(r["wall"] for r in collected), 3)},
        "dataset": exported, "training": {**training, "loss_per_epoch": [round(x, 6) for x in losses]},
        "evaluation": {"seeds": eval_seeds, "learned": learned, "scripted": scripted},
        "seconds": round(time.perf_counter() - started, 1), "environment": _environment(),
    }
    results.mkdir(parents=True, exist_ok=True)
    (results / "results.json").write_text(json.dumps(summary, indent=1) + "\n")
    plot_loop(summary, results / "learning_loop.png")
    _out.print(f"results: {results / 'results.json'}, {results / 'learning_loop.png'}; the whole loop took "
               f"{summary['seconds']:.0f} s", highlight=False)
    return summary


def _environment() -> dict:
    """What the results were measured with: the packages' versions and the code's git commit
    (None outside a git checkout; ``dirty`` when files differ from it)."""
    import platform
    import subprocess
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str | None:
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
        dirty = bool(subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                                    capture_output=True, text=True, timeout=10).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, False
    return {"python": platform.python_version(), "commit": commit, "dirty": dirty,
            **{name: installed(name) for name in ("torch", "lerobot", "numpy", "mujoco", "retriever-robotics")},
            "cpus": os.cpu_count()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.learn", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="Pick-only episodes of the scripted skill, one log each")
    c.add_argument("--skill", default="pick", choices=["pick"], help="the skill (Pick)")
    c.add_argument("--episodes", type=int, help="how many (default: one per seed of --seeds)")
    c.add_argument("--seeds", required=True, help="A:B, seeds A to B-1")
    c.add_argument("-o", "--out", type=Path, required=True, help="the folder of the logs")
    c.add_argument("--force", action="store_true", help="replace logs that exist")
    x = sub.add_parser("export", help="the successful episodes' logs as a dataset (LeRobot or npz)")
    x.add_argument("folder", type=Path, help="the folder collect wrote")
    x.add_argument("-o", "--out", type=Path, required=True, help="the dataset folder to write")
    x.add_argument("--format", choices=["lerobot", "npz"], default="lerobot")
    x.add_argument("--force", action="store_true", help="replace the dataset if it exists")
    t = sub.add_parser("train", help="behaviour cloning of a small MLP on an exported dataset")
    t.add_argument("dataset", type=Path, help="the folder export wrote")
    t.add_argument("-o", "--out", type=Path, required=True, help="the checkpoint directory to write")
    t.add_argument("--minutes", type=float, default=2.0, help=MINUTES_HELP)
    t.add_argument("--max-epochs", type=int, default=3000, help=MAX_EPOCHS_HELP)
    t.add_argument("--json", type=Path, help="write the training summary here")
    t.add_argument("--force", action="store_true", help="replace the checkpoint if it exists")
    e = sub.add_parser("evaluate", help="success of the skill and of the whole task over seeds")
    e.add_argument("--seeds", required=True, help="A:B, seeds A to B-1 (held out from collection)")
    e.add_argument("--skill-policy", help="a checkpoint directory (train's); the scripted Pick without it")
    e.add_argument("--skill-only", action="store_true", help="only the Pick-only episodes, not the whole task")
    e.add_argument("--out", type=Path, help="write the results (JSON) here")
    a = sub.add_parser("all", help="collect, export, train, and evaluate the learned Pick against the scripted one")
    a.add_argument("--episodes", type=int, help="episodes to collect (default: one per seed of --train-seeds)")
    a.add_argument("--train-seeds", required=True, help="A:B, the seeds to collect from")
    a.add_argument("--eval-seeds", required=True, help="C:D, the held-out seeds to evaluate on")
    a.add_argument("--minutes", type=float, default=5.0, help=MINUTES_HELP)
    a.add_argument("--max-epochs", type=int, default=3000, help=MAX_EPOCHS_HELP)
    a.add_argument("--format", choices=["lerobot", "npz"], default="lerobot", help="the dataset's format")
    a.add_argument("-o", "--out", type=Path, required=True, help="the folder of the logs, dataset and checkpoint")
    a.add_argument("--results", type=Path, help="where results.json and learning_loop.png go (default: -o)")
    a.add_argument("--force", action="store_true", help="replace logs, dataset and checkpoint that exist")
    args = parser.parse_args(argv)
    try:
        if args.command == "collect":
            collect(args.episodes, args.seeds, args.out, args.force)
        elif args.command == "export":
            export(args.folder, args.out, args.format, args.force)
        elif args.command == "train":
            result = train_policy(args.dataset, args.out, args.minutes, args.max_epochs, force=args.force)
            if args.json:
                args.json.write_text(json.dumps(result, indent=1) + "\n")
        elif args.command == "all":
            command = "python -m agents.learn " + " ".join(sys.argv[1:] if argv is None else argv)
            loop(args.episodes, args.train_seeds, args.eval_seeds, args.minutes, args.out, args.results, args.format,
                 args.max_epochs, args.force, command)
        else:
            if args.skill_policy is not None:
                from ..skill_policies import check_skill_policy
                check_skill_policy(args.skill_policy)
            evaluate(args.seeds, args.skill_policy, args.out, task=not args.skill_only)
    except (ValueError, RetrieverError) as exc:
        _err.print(f"error: {exc}", highlight=False)
        return 2
    except ModuleNotFoundError as exc:
        if exc.name not in EXTRA_MODULES:
            raise
        _err.print(f"error: {args.command} needs {exc.name}, which cannot be imported here\n    hint: pip install "
                   "'retriever-robotics[lerobot]' (torch, safetensors and lerobot)", highlight=False)
        return 2
    except KeyboardInterrupt:
        _err.print(f"interrupted: {args.command} stopped by Ctrl-C", highlight=False)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
