"""The ``retriever`` command: thin — parse, call the public API, format results and errors."""

from __future__ import annotations

import sys
import traceback
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table

from .errors import RetrieverError, RetrieverWarning

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="Retriever: closed-loop robot agents with explicit time.")
_out = Console()
_err = Console(stderr=True, soft_wrap=True)
_state = {"debug": False}


@app.callback()
def _main(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False) -> None:
    _state["debug"] = debug


def _fail(exc: BaseException) -> None:
    if _state["debug"]:
        traceback.print_exception(exc)
    text = str(exc) if isinstance(exc, RetrieverError) else f"{type(exc).__name__}: {exc}"
    first, *rest = text.split("\n")
    _err.print(f"[bold red]error:[/] {first}", highlight=False, markup=True)
    listed = any(line.startswith("  - ") for line in rest)  # hints of listed problems stay under them
    for line in rest:
        if not listed and line.startswith("    hint:"):
            line = line.lstrip()
        _err.print(line, highlight=False, markup=False)
    if not _state["debug"] and not isinstance(exc, RetrieverError):
        _err.print("(run with --debug for the traceback)", highlight=False)
    raise typer.Exit(code=1)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, RetrieverWarning):
        _err.print(f"warning: {message}", highlight=False, markup=False)
    else:
        _err.print(f"warning: {category.__name__}: {message} ({filename}:{lineno})", highlight=False, markup=False)


warnings.showwarning = _show_warning


def _load(target: str):
    from ._loading import load_pipeline

    try:
        return load_pipeline(target)
    except Exception as exc:  # a user file may raise anything while it builds its graph
        _fail(exc)


@app.command()
def run(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]", help="Python file (and Pipeline name) or IR .json")],
    backend: Annotated[Optional[str], typer.Option(help="Backend: inproc (default).")] = None,
    duration: Annotated[float, typer.Option(help="Seconds to run (virtual time on inproc).")] = 10.0,
) -> None:
    """Run a pipeline and print per-node ticks, steps, skips and mean step time."""
    pipe = _load(target)
    try:
        trace = pipe.run(duration=duration, backend=backend)
    except Exception as exc:
        _fail(exc)
    table = Table(title=f"{pipe.name}: {duration:g} s on {backend or 'inproc'}", title_justify="left")
    for col in ("node", "ticks", "steps", "skips", "errors", "mean step"):
        table.add_column(col, justify="left" if col == "node" else "right")
    for node, s in sorted(pipe.stats().items()):
        table.add_row(node, str(s.ticks), str(s.steps), str(s.skips), str(s.errors), f"{s.mean_step_s * 1e6:.1f} µs")
    _out.print(table)
    _out.print(f"{len(trace.events)} events · {len(trace.steps)} steps · trace digest {trace.digest()[:16]}",
               highlight=False)


@app.command("ir")
def ir_command(
    target: Annotated[str, typer.Argument(metavar="FILE[:ATTR]", help="Python file (and Pipeline name) or IR .json")],
    format: Annotated[str, typer.Option("--format", "-f", help="json, dot or mermaid.")] = "json",
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Write here instead of stdout.")] = None,
) -> None:
    """Compile a pipeline to its IR (or a DOT / Mermaid picture of it)."""
    if format not in ("json", "dot", "mermaid"):
        _fail(RetrieverError(f"unknown format {format!r}\n    hint: use --format json, dot or mermaid"))
    pipe = _load(target)
    try:
        ir = pipe.build_ir()
        text = ir.to_json() if format == "json" else ir.visualize(format)
    except Exception as exc:
        _fail(exc)
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text, encoding="utf-8")
        _err.print(f"wrote {out}", highlight=False)


def main() -> None:
    app()
