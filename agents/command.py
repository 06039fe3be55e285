"""The ``retriever demo`` command: Retriever-0 on a task in a MuJoCo world.

The library never imports the agents (``retriever/__init__.py`` draws the layers): the command
reaches the CLI through the ``retriever.commands`` entry point group (pyproject.toml:
``demo = "agents.command:demo"``), and reports through the CLI's public seam
(``retriever.cli.fail``, ``out``, ``err``, ``stop_on_signals``). What it imports at the top is
light, since every ``retriever`` command loads it; the agent itself is imported when it runs.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from retriever import cli
from retriever.backends import canonical
from retriever.errors import BackendError, RetrieverError, SetupError


def _skill_policy(spec: str | None) -> str | None:
    """The demo's --skill-policy: the bare word 'scripted', or a checkpoint directory made
    absolute (the flow may run in another process and directory; ./scripted is a directory)."""
    if spec is None or spec == "scripted":
        return spec
    return str(Path(spec).absolute())


def _remove_if_empty(out: Path, made_out: bool) -> None:
    """After a run that a flow's ``setup()`` stopped before its first tick: remove the pictures
    folder the demo made for it, if still empty (the run removed its log itself)."""
    if made_out and out.is_dir() and not any(out.iterdir()):
        out.rmdir()


def demo(
    seed: Annotated[int, typer.Option(help="The episode's seed: where the spice is, its mass and place, "
                                           "the drawers' friction (bag task: the target's mass and place).")] = 0,
    drawer: Annotated[Optional[str], typer.Option(metavar="TL|TR|BL|BR",
                                                  help="Hide the spice in this drawer (default: by the seed).")] = None,
    backend: Annotated[str, typer.Option(help="zenoh: real time, one process per flow; inproc: virtual time, "
                                              "as fast as it goes.")] = "zenoh",
    duration: Annotated[float, typer.Option(help="At most this many seconds (world time); the episode ends "
                                                  "earlier when the task is done.")] = 120.0,
    planner_latency: Annotated[float, typer.Option(help="Seconds the planner thinks per plan chunk "
                                                         "(its declared latency).")] = 2.0,
    planner: Annotated[str, typer.Option(metavar="scripted|openai:URL#MODEL",
                                         help="The planner: the scripted VLM stand-in (no network), or a model "
                                              "behind an OpenAI-compatible endpoint (key in $OPENAI_API_KEY).")
                       ] = "scripted",
    task: Annotated[str, typer.Option(metavar="drawers|bag", help="The task.")] = "drawers",
    ablation: Annotated[str, typer.Option(help="full, no-plan-chunking, no-skill-progress, human-in-the-loop "
                                               "or vla-only (paper Table II).")] = "full",
    slip_prob: Annotated[float, typer.Option(help="Probability that the grasp slips (failure injection).")] = 0.0,
    teleop: Annotated[Optional[Path], typer.Option(metavar="FILE", help="A teleop schedule (JSON list of "
                                                   "{t_start, payload: 'Pick(spice)'}; bag task: 'Pick(target)').")] = None,
    skill_policy: Annotated[Optional[str], typer.Option(metavar="DIR", help="Run the Pick skill with this "
                                                         "trained policy (a checkpoint directory of python -m "
                                                         "agents.learn train, docs/learning.md) in its own flow, "
                                                         "or 'scripted'.")] = None,
    log: Annotated[Path, typer.Option(help="The episode's MCAP log.")] = Path("run.mcap"),
    force: Annotated[bool, typer.Option("--force", help="Overwrite the --log file if it exists.")] = False,
    out: Annotated[Path, typer.Option(help="Where to save the pictures (PNG).")] = Path("retriever0"),
) -> None:
    """Run Retriever-0 on the drawer (or bag) task in a MuJoCo world: live skill, belief and progress lines,
    then the skill trace, task progress, rates per flow, a contact sheet and a timeline (PNG), and a
    log that `retriever replay` re-executes."""
    try:
        from .demo import DemoError, check_rendering, rate_notes, rate_table, report, run_episode
        from .pictures import contact_sheet, timeline
        from .planner import PlannerError, make_planner
        from .retriever0 import AgentConfig, build
    except ImportError as exc:
        cli.fail(RetrieverError(f"the Retriever-0 agent is not installed ({exc})\n    hint: install the project "
                             "itself, which includes it: pip install -e ."))
    if canonical(backend) not in ("zenoh", "inproc"):
        cli.fail(BackendError(f"backend {backend!r}: the demo runs on zenoh or inproc"))
    pipe, made_out = None, False
    try:
        if not 0 < duration < float("inf"):
            raise DemoError(f"--duration {duration!r}: give the seconds of world time the episode may take (> 0)")
        if os.path.lexists(log) and not force:  # as retriever run: said before the rendering check and the run
            raise DemoError(f"the log {log} already exists; the demo does not overwrite a file\n"
                            "    hint: pass --force to replace it, or --log another path")
        config = AgentConfig(seed=seed, task=task, drawer=drawer, ablation=ablation, planner=planner,
                             planner_latency=planner_latency, slip_prob=slip_prob,
                             teleop=str(teleop) if teleop else None, verbose=True,
                             skill_policy=_skill_policy(skill_policy))
        config.check()
        if teleop is not None:
            from .flows import load_schedule
            load_schedule(str(teleop), task)
        if planner.startswith("openai:"):
            make_planner(planner, task).check_reachable()
        check_rendering()
        try:
            made_out = not out.exists()
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DemoError(f"--out {out}: cannot make a folder for the pictures there ({exc.strerror})") from None
        where = "the target in the bag" if task == "bag" else f"the spice in {drawer or 'a drawer the seed chose'}"
        cli.err.print(f"Retriever-0 on {canonical(backend)}, {task} task: seed {seed}, {where}; logging to {log}",
                   highlight=False)
        cli.stop_on_signals()  # stop like Ctrl-C: the log is finished, not torn
        pipe = build(config)
        trace, episode, wall = run_episode(config, backend=canonical(backend), duration=duration, log=str(log),
                                           overwrite=force, pipe=pipe)
    except KeyboardInterrupt:
        cli.err.print(f"interrupted; the episode so far is in {log} (retriever replay {log} re-executes it)",
                   highlight=False)
        # during the logged run the pipeline's own handler took the signal (it stops between ticks)
        signum = cli.stop_signal() or getattr(getattr(pipe, "session", None), "stop_signal", None)
        raise typer.Exit(code=128 + (signum or signal.SIGINT)) from None
    except (DemoError, ValueError, PlannerError) as exc:
        cli.fail(RetrieverError(str(exc)))
    except SetupError as exc:
        _remove_if_empty(out, made_out)
        cli.fail(exc)
    except RetrieverError as exc:
        cli.fail(exc)
    for line in report(episode, wall, canonical(backend)):
        cli.out.print(line, highlight=False, soft_wrap=True)
    columns, rows = rate_table(episode)
    rates = Table(title="rates", title_justify="left")
    for col in columns:
        rates.add_column(col, justify="left" if col == "flow" else "right")
    for row in rows:
        rates.add_row(*row)
    cli.out.print(rates)
    for line in rate_notes(episode, canonical(backend)):
        cli.out.print(line, highlight=False, soft_wrap=True)
    sheet = contact_sheet(trace, episode, out / "contact_sheet.png")
    line = timeline(trace, episode, out / "timeline.png")
    cli.out.print(f"pictures: {sheet or '(no camera frames)'}, {line}; replay it: retriever replay {log}",
               highlight=False, soft_wrap=True)
