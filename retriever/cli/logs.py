"""The commands that read a log: ``replay`` (re-execute it and compare), ``log cat``, ``log
recover`` and ``log export`` (``log info`` is log_info.py's)."""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from ..errors import RetrieverError
from . import console
from .console import cell, cleaning_up, fail, stop_on_signals, stop_signal, visible
from .inputs import load, read


def replay(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap", help="A log written by run --log / pipe.run(log=).")],
    pipeline: Annotated[Optional[str], typer.Option(metavar="FILE[:ATTR]",
                                                    help="Replay this pipeline instead of the log's IR.")] = None,
    resim: Annotated[bool, typer.Option("--resim", help="Re-run the whole graph from the logged sources.")] = False,
) -> None:
    """Re-execute a logged run and compare every output byte for byte (exit 0 only if identical)."""
    from ..replay import replay_file, resim_file

    # the log is read in two passes, neither keeping it: a log larger than memory replays (or re-simulates)
    run = resim_file if resim else replay_file
    try:
        with _ReplayProgress() as show:
            result = run(path, None if pipeline is None else (lambda: load(pipeline)), progress=show)
    except typer.Exit:
        raise
    except Exception as exc:
        fail(exc)
    source = f"--pipeline {pipeline}" if pipeline else "the IR in the log"
    if resim:
        console.out.print(f"re-simulated {path} to t={result.horizon_ns / 1e9:g} s with {source}: "
                          f"{result.steps_compared} steps and {result.events_compared} events compared",
                          highlight=False)
        if result.identical:
            console.out.print("[bold green]identical[/]: the log is one run of this graph", markup=True)
            return
        causes = "".join(f"\n  {escape(visible(change))}, which may be why" for change in result.code_changes)
        console.out.print(f"[bold red]DIVERGED[/]: {escape(visible(str(result.difference)))}" + causes,
                          highlight=False, markup=True)
        raise typer.Exit(code=1)
    table = Table(title=f"replay of {path} ({source})", title_justify="left")
    for col in ("node", "steps", "replayed", "identical", "divergent"):
        table.add_column(col, justify="left" if col == "node" else "right")
    for node, n in result.nodes.items():
        if n.from_log:
            table.add_row(cell(node), str(n.steps), "from the log", "", "")
        else:
            table.add_row(cell(node), str(n.steps), str(n.replayed), str(n.identical),
                          Text(str(n.divergent), style="bold red") if n.divergent else "0")
    console.out.print(table)
    if result.identical:
        cut = sum(n.cut for n in result.nodes.values())
        lost = sum(n.lost for n in result.nodes.values())
        notes = ([f"{cut} at the end not compared: the log was cut short and lost events they consumed or produced"]
                 if cut else []) + ([f"{lost} not compared: their outputs died unpublished with their process "
                                     "(retriever log info shows the fault)"] if lost else [])
        console.out.print(f"[bold green]identical[/]: {result.steps_replayed} steps replayed, every output byte for "
                          "byte" + "".join(f" ({note})" for note in notes), markup=True)
        return
    console.out.print(f"[bold red]DIVERGED[/]: {result.divergent_steps} of {result.steps_replayed} replayed steps "
                      f"differ{escape(visible(_code_changed(result.code_changes)))}. "
                      f"First:\n  {escape(visible(str(result.divergences[0])))}", highlight=False, markup=True)
    raise typer.Exit(code=1)


class _ReplayProgress:
    """The progress of ``retriever replay`` on stderr, when it is a terminal (a pipe or a file
    gets nothing: what scripts read there is warnings and errors): a bar for reading the log
    (checking it whole, by bytes), then one for replaying it (by steps); gone when it ends."""

    def __enter__(self):
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

        self._bar = Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(),
                             TextColumn("{task.fields[amount]}"), TimeRemainingColumn(), console=console.err,
                             transient=True, disable=not console.err.is_terminal)
        self._tasks: dict[str, object] = {}
        self._bar.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._bar.__exit__(*exc)

    def __call__(self, what: str, done: int, total: int) -> None:
        amount = (f"{done / 1e6:,.1f} of {total / 1e6:,.1f} MB" if what == "reading"
                  else f"{done:,} of {total:,} steps")
        task = self._tasks.get(what)
        if task is None:
            task = self._tasks[what] = self._bar.add_task(what, total=total, amount=amount)
        self._bar.update(task, completed=done, total=total, amount=amount)


def _code_changed(changes: list[str]) -> str:
    """The flow modules edited since the run, for a DIVERGED line: the likely cause."""
    return "".join(f"; {change}" for change in changes)


def log_cat(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap")],
    node: Annotated[Optional[str], typer.Option(help="Only this node's events.")] = None,
    port: Annotated[Optional[str], typer.Option(help="Only this output port.")] = None,
    steps: Annotated[bool, typer.Option("--steps", help="Print step records instead of events.")] = False,
    limit: Annotated[Optional[int], typer.Option(help="Print at most this many.")] = None,
    brief: Annotated[bool, typer.Option("--brief", help="Arrays as their dtype and shape, not their values.")] = False,
    full: Annotated[bool, typer.Option("--full", help="Arrays whole (by default one of more than 16 elements is "
                                                      "its dtype, shape and range).")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line (arrays up to 1024 elements "
                                                         "as lists, bigger ones summarised).")] = False,
    start: Annotated[Optional[float], typer.Option("--from", metavar="S", help="Only tags at or after S s.")] = None,
    end: Annotated[Optional[float], typer.Option("--to", metavar="S", help="Only tags before S s.")] = None,
) -> None:
    """Print decoded events (or step records), in tag order."""
    import json

    from ..log.views import to_json
    from ..log.show import show_value
    from ..time import format_tag, seconds_problem

    if brief and full:
        fail(RetrieverError("--brief and --full ask for arrays both ways\n    hint: pass one of them"))
    arrays = "brief" if brief else "full" if full else "summary"
    for flag, seconds in (("--from", start), ("--to", end)):
        problem = None if seconds is None else seconds_problem(flag, seconds)
        if problem is not None:
            fail(RetrieverError(f"{problem}\n    hint: seconds from the run's start, e.g. {flag} 1.5"))
    if limit is not None and limit < 0:
        fail(RetrieverError(f"--limit {limit}: expected a count >= 0"))
    log = read(path)
    lo = None if start is None else round(start * 1e9)
    hi = None if end is None else round(end * 1e9)

    def in_range(tag) -> bool:
        return (lo is None or tag[0] >= lo) and (hi is None or tag[0] < hi)

    def say(text: str) -> None:
        console.out.print(text, highlight=False, markup=False, soft_wrap=True)

    shown = 0
    try:
        if steps:
            records = sorted((s for s in log.iter_steps() if (node is None or s.node == node) and in_range(s.tag)),
                             key=lambda s: (s.tag, s.node))
            for s in records[:limit]:
                if as_json:
                    say(json.dumps({"tag_ns": s.tag[0], "microstep": s.tag[1], "node": s.node, "status": s.status,
                                    "consumed": {p: [list(i) for i in ids] for p, ids in s.consumed.items()},
                                    "produced": [list(i) for i in s.produced], "detail": to_json(s.detail),
                                    "wall_ns": s.wall_ns}))
                else:
                    consumed = {p: [f"{n}.{q}#{i}" for n, q, i in ids] for p, ids in s.consumed.items()}
                    produced = [f"{n}.{q}#{i}" for n, q, i in s.produced]
                    extra = f" {s.detail}" if s.detail else ""
                    say(f"{format_tag(s.tag)}  {s.node}  {s.status}{extra}  consumed={consumed} produced={produced} "
                        f"wall={s.wall_ns / 1e3:.1f}µs")
                shown += 1
        else:
            events = sorted((e for e in log.iter_events() if (node is None or e.node == node)
                             and (port is None or e.port == port) and in_range(e.tag)),
                            key=lambda e: (e.tag, e.node, e.port, e.seq))
            for e in events[:limit]:
                value = log.value(e, keep_unregistered=True)
                if as_json:
                    say(json.dumps({"tag_ns": e.tag[0], "microstep": e.tag[1], "node": e.node, "port": e.port,
                                    "seq": e.seq, "value": show_value(value, arrays) if brief else to_json(value)}))
                else:
                    say(f"{format_tag(e.tag)}  {e.node}.{e.port} #{e.seq}  {show_value(value, arrays)}")
                shown += 1
    except Exception as exc:
        fail(exc)
    if shown == 0:
        known = sorted({f"{c.metadata.get('node')}.{c.metadata.get('port')}" for c in log.channels.values()
                        if c.metadata.get("node")})
        what = (f"the log's ports are: {', '.join(known)}" if known and not steps
                else "the log has no step records" if steps and not any(True for _ in log.iter_steps())
                else "the log has no Retriever events" if not known else "no step record in that range or of that node")
        console.err.print(f"nothing matched; {what}", highlight=False)


def log_recover(
    path: Annotated[Path, typer.Argument(metavar="LOG.mcap", help="A log whose writer was killed or that was damaged.")],
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Default: LOG.recovered.mcap.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the output file if it exists.")] = False,
) -> None:
    """Rebuild a readable log from one whose writer was killed (everything before the damage)."""
    from ..log import recover

    try:
        result = recover(path, out, overwrite=force)
    except Exception as exc:
        fail(exc)
    if result.output is None:
        console.out.print(f"{path} is complete and undamaged; nothing to recover", highlight=False)
        return
    console.out.print(f"recovered {result.events} events and {result.steps} steps into {result.output}\n"
                      f"  {path}: {result.damage}\n  next: retriever replay {result.output}", highlight=False)


def log_export(
    paths: Annotated[list[Path], typer.Argument(metavar="LOG.mcap...", help="Logs written by run --log / "
                                                "pipe.run(log=); a dataset takes several (one episode each).")],
    format: Annotated[str, typer.Option("--format", help="foxglove: an MCAP with Foxglove's schemas; ros2: an MCAP "
                                        "of ROS 2 messages (CDR); rerun: a Rerun recording (.rrd); lerobot: a "
                                        "LeRobot dataset; npz: the same frames as NumPy arrays.")] = "foxglove",
    out: Annotated[str, typer.Option("--out", "-o", help="The file (foxglove, ros2, rerun) or folder (lerobot, "
                                      "npz) to write; - for standard output, a pipe (ros2, rerun: | rerun -).")] = ...,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the output if it exists.")] = False,
    flow: Annotated[Optional[str], typer.Option("--flow", metavar="NODE", help="lerobot, npz: the Rate flow whose "
                                                "ticks are the frames.")] = None,
    maps: Annotated[Optional[list[str]], typer.Option("--map", metavar="PORT=KEY", help="Name a port's feature "
                                                      "(repeatable): joints=observation.state; a text port =task "
                                                      "gives each frame's task.")] = None,
    task: Annotated[Optional[str], typer.Option("--task", metavar="TEXT", help="The task of every frame "
                                                "(default: the pipeline's name).")] = None,
    exclude: Annotated[Optional[list[str]], typer.Option("--exclude", metavar="PORT", help="Leave a port (or "
                                                         "PORT.FIELD) out of the frames (repeatable).")] = None,
    gaps: Annotated[str, typer.Option("--gaps", help="A gap between two frames (ticks that are no frame): refuse, "
                                      "or split the episode there.")] = "refuse",
    repo_id: Annotated[Optional[str], typer.Option("--repo-id", help="lerobot: the dataset's repo id (default: "
                                                   "retriever/<folder name>).")] = None,
) -> None:
    """Write a log for another tool. --format foxglove: a view that opens in the Foxglove app (images
    as RawImage, numbers as JSON it plots, the step records and the graph; wall-clock times; needs
    pip install 'retriever-robotics\\[foxglove]'). --format ros2: the ROS 2 profile of MCAP (ros2msg
    schemas, CDR; images as sensor_msgs/msg/Image, numbers as std_msgs, step records as JSON text; event
    time as log time; pip install 'retriever-robotics\\[ros2]'). --format rerun: a .rrd for Rerun (images,
    plotted scalars, step records; event-time and wall-time timelines; pip install
    'retriever-robotics\\[rerun]'). --format lerobot | npz --flow NODE: a training
    set, one frame per tick of a Rate flow: what it consumed and produced there (docs/learning.md;
    lerobot needs pip install 'retriever-robotics\\[lerobot]'). Stopped by Ctrl-C or SIGTERM, it leaves
    nothing behind (the export is written beside OUT, then renamed) and exits 128 + the signal; with
    -o -, a reader that goes away (| head) ends it quietly with 141 (128 + SIGPIPE)."""
    stop_on_signals()  # SIGTERM stops it as Ctrl-C does: the half-written file is removed, not left
    from ..log.outputs import abandon_stdout, stdout_written, to_stdout

    before = _identity(out)
    try:
        _export(paths, format, out, force, flow, maps, task, exclude, gaps, repo_id)
    except BrokenPipeError:  # `| head`: the reader has what it wanted; quiet, 128 + SIGPIPE as Unix tools exit
        abandon_stdout()
        raise typer.Exit(code=128 + signal.SIGPIPE) from None
    except KeyboardInterrupt:
        cleaning_up()
        signum = stop_signal() or signal.SIGINT
        if to_stdout(out):
            written = stdout_written()  # None: nothing began to write it, or Rerun's SDK did (not counted)
            written = (0, 0) if written is None and format != "rerun" else written
            least, most = written or (0, 0)
            amount = f"{least}" if least == most else f"{least} to {most}"
            done = (f"standard output may hold part of the {format} export (not a whole one)" if written is None
                    else "nothing was written to standard output" if most == 0
                    else f"{amount} bytes of the {format} export were written to standard output (not a whole one)")
        else:
            done = f"{out} " + (
                "was written before it stopped" if _identity(out) not in (None, before) else "was not written")
        console.err.print(f"interrupted by {signal.Signals(signum).name}: {done}", highlight=False)
        raise typer.Exit(code=128 + signum) from None


def _export(paths: list[Path], format: str, out: str, force: bool, flow: str | None, maps: list[str] | None,
            task: str | None, exclude: list[str] | None, gaps: str, repo_id: str | None) -> None:
    from ..log.outputs import NOT_STREAMED, abandon_stdout, stdout_stream, to_stdout

    if to_stdout(out) and format in NOT_STREAMED:
        try:
            stdout_stream(format)  # says why this format is not written to standard output
        except Exception as exc:
            fail(exc)
    if format in ("lerobot", "npz"):
        _export_dataset(paths, format, Path(out), force, flow, maps or [], task, exclude or [], gaps, repo_id)
        return
    if format not in VIEWS:
        fail(RetrieverError(f"unknown export format {format!r}\n    hint: use --format foxglove, ros2, rerun, "
                            "lerobot or npz"))
    if len(paths) != 1:
        fail(RetrieverError(f"--format {format} exports one log, got {len(paths)}\n    hint: export each apart"))
    try:  # the export reads the log itself, streamed: never held whole (reader.log_records)
        said = VIEWS[format](paths[0], out, force)
    except BrokenPipeError:
        raise  # the reader of standard output went away (log_export)
    except Exception as exc:
        if to_stdout(out):  # each write was flushed: what Python may still hold is what failed, and
            abandon_stdout()  # would fail again at exit, a second error
        fail(exc)
    if to_stdout(out):  # standard output is the export's: what was written is said on stderr
        console.err.print(f"wrote standard output: {said}", highlight=False)
    else:
        console.out.print(f"wrote {out}: {said}", highlight=False)


def _foxglove(log, out: str, force: bool) -> str:
    from ..log.foxglove import export_foxglove

    written = export_foxglove(log, out, overwrite=force)
    return f"{sum(written.values())} messages on {len(written)} topics; open it in the Foxglove app"


def _ros2(log, out: str, force: bool) -> str:
    from ..log.ros2 import export_ros2

    done = export_ros2(log, out, overwrite=force)
    said = f"{sum(done.written.values())} messages on {len(done.written)} topics (ROS 2 MCAP)"
    said += f"; {done.as_json} values with no standard message as JSON text" if done.as_json else ""
    if done.renamed:  # names that met once made ROS names: each kept apart
        moved = ", ".join(f"{what} on {topic}" for what, topic in sorted(done.renamed.items()))
        said += f"; names that make one ROS name kept apart: {moved}"
    return said


def _rerun(log, out: str, force: bool) -> str:
    from ..log.outputs import to_stdout
    from ..log.rerun import export_rerun

    done = export_rerun(log, out, overwrite=force)
    said = f"{sum(done.written.values())} rows on {len(done.written)} entities; "
    if done.renamed:  # names that made one entity: each kept apart
        moved = ", ".join(f"{what} on {entity}" for what, entity in sorted(done.renamed.items()))
        said += f"entities kept apart: {moved}; "
    return said + ("a viewer reads it from a pipe: | rerun -" if to_stdout(out) else f"open it with: rerun {out}")


#: --format → the export of one log to a viewer's file, and what it says it wrote
VIEWS = {"foxglove": _foxglove, "ros2": _ros2, "rerun": _rerun}


def _export_dataset(paths: list[Path], format: str, out: Path, force: bool, flow: str | None, maps: list[str],
                    task: str | None, exclude: list[str], gaps: str, repo_id: str | None) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from ..log.dataset import export_dataset

    if flow is None:
        fail(RetrieverError(f"--format {format} needs the flow whose ticks are the frames\n"
                            "    hint: --flow NODE (a flow on a Rate clock: retriever log info LOG lists them)"))
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console.err, transient=True, disable=not console.err.is_terminal) as bar:
        ticks = bar.add_task("reading", total=None)

        def progress(log: int, logs: int, done: int, total: int) -> None:
            bar.update(ticks, description=f"log {log + 1}/{logs}: ticks", completed=done, total=total)

        try:
            summary = export_dataset(paths, out, flow=flow, format=format, maps=maps, task=task, exclude=exclude,
                                     gaps=gaps, repo_id=repo_id, overwrite=force, progress=progress)
        except Exception as exc:
            fail(exc)
    console.out.print(str(summary), highlight=False, soft_wrap=True)


def _identity(path: str | Path) -> tuple[int, int, int, int] | None:
    """What tells the file or folder at ``path`` from another or from its earlier self (None: none)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size
