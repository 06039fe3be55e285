"""Where every command prints, and how it fails: ``out`` (results, stdout) and ``err`` (progress,
warnings, errors, stderr), whose strings are never markup and show their control characters
escaped; ``fail`` (``error: …``, its ``hint: …``, the traceback only with --debug); the warnings
of a run; and the signal that stopped a command."""

from __future__ import annotations

import os
import signal
import traceback
import warnings
from typing import NoReturn

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from ..errors import Interrupted, RetrieverError, RetrieverWarning, StarvedFlowWarning, ViewDroppedWarning

_state = {"debug": False}


def visible(text: str) -> str:
    """``text`` with its control characters shown escaped (``\\x1b``), newlines and tabs kept: a
    log's or an IR's strings reach the terminal, where an escape sequence could retitle it,
    recolour it or plant a hyperlink."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() or c in "\n\t" else repr(c)[1:-1] for c in text)


#: wider than any table's natural width: what a table is measured against
_UNBOUNDED_COLUMNS = 100_000


class _Uncut:
    """A table at its natural width, past the terminal's edge if it must be: a name cut to fit
    (``contro…``) names nothing. A terminal wraps the long lines; a pipe or a file keeps them."""

    def __init__(self, table: Table):
        self.table = table

    def __rich_console__(self, console, options):
        natural = console.measure(self.table, options=options.update_width(_UNBOUNDED_COLUMNS)).maximum
        yield from console.render(self.table, options.update_width(max(options.max_width, natural)))


class _Console(Console):
    """Rich's console, but a string is never markup unless the call says ``markup=True`` (whose
    text escapes what it interpolates), its control characters are shown escaped, and a table
    is never cut to the terminal's width."""

    def print(self, *objects, **kwargs) -> None:
        if any(isinstance(o, Table) for o in objects):
            kwargs["crop"] = False
        super().print(*(visible(o) if isinstance(o, str) else _Uncut(o) if isinstance(o, Table) else o
                        for o in objects), **kwargs)


def cell(value: object) -> Text:
    """A table cell holding a value that may come from a file: plain text, never markup."""
    return Text(visible(str(value)))


#: where a command prints its results (stdout) and its progress and errors (stderr): strings are
#: never markup nor emoji codes, and their control characters are shown escaped
out = _Console(markup=False, emoji=False)  # no emoji codes either: "127.0.0.1:-1:" is not 👎
err = _Console(stderr=True, soft_wrap=True, markup=False, emoji=False)


def set_debug(debug: bool) -> None:
    """--debug: failures show their traceback."""
    _state["debug"] = debug


def fail(exc: BaseException) -> NoReturn:
    """Report ``exc`` as every command does (``error:``, its ``hint:``; the traceback with
    --debug) and exit 1."""
    if _state["debug"]:
        traceback.print_exception(exc)
    text = str(exc) if isinstance(exc, RetrieverError) else f"{type(exc).__name__}: {exc}"
    first, *rest = text.split("\n")
    err.print(f"[bold red]error:[/] {escape(visible(first))}", highlight=False, markup=True)
    listed = any(line.startswith("  - ") for line in rest)  # hints of listed problems stay under them
    for line in rest:
        if not listed and line.startswith("    hint:"):
            line = line.lstrip()
        err.print(line, highlight=False, markup=False)
    for note in getattr(exc, "__notes__", ()):  # what became of the run's files (RunLog.end)
        err.print(note, highlight=False, markup=False)
    if not _state["debug"] and not isinstance(exc, RetrieverError):
        err.print("(run with --debug for the traceback)", highlight=False)
    raise typer.Exit(code=1)


#: warnings about how the run went (its starved flows, what a live view dropped), held back to be
#: printed under its table
_after_summary: list[str] = []


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, (StarvedFlowWarning, ViewDroppedWarning)):
        _after_summary.append(f"warning: {message}")
    elif issubclass(category, RetrieverWarning):
        err.print(f"warning: {message}", highlight=False, markup=False)
    else:
        err.print(f"warning: {category.__name__}: {message} ({filename}:{lineno})", highlight=False, markup=False)


warnings.showwarning = _show_warning


def print_held_warnings() -> None:
    """Print the warnings held back to go under the run's table (its starved flows, what a live
    view dropped)."""
    for text in _after_summary:
        err.print(text, highlight=False, markup=False)
    _after_summary.clear()


def _interrupt(signum, frame) -> None:
    _state.setdefault("signal", signum)
    if not _state.get("cleaning"):
        raise Interrupted(signum)
    if not _state.get("ignored"):  # (raised there, it would cut the clean-up short)
        _state["ignored"] = signum
        return
    signal.signal(signum, signal.SIG_DFL)  # asked a third time: the clean-up hangs; end at once
    os.kill(os.getpid(), signum)


def stop_on_signals() -> None:
    """From now on SIGTERM and SIGINT (Ctrl-C) stop the command as an :class:`Interrupted` (a
    KeyboardInterrupt), and :func:`stop_signal` says which signal it was. A SIGINT the command
    was started to ignore (a shell's background job: the terminal's Ctrl-C is not for it) stays
    ignored. Once the command cleans up (:func:`cleaning_up`), the next stop signal is ignored and
    the one after it ends the process at once."""
    for key in ("signal", "cleaning", "ignored"):  # a command's before this one, in the same process
        _state.pop(key, None)
    signal.signal(signal.SIGTERM, _interrupt)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _interrupt)


def cleaning_up(ignored_one: bool = False) -> None:
    """The command has taken its stop signal and cleans up (removes a half-written file, prints
    what ran), then ends: one more stop signal (Ctrl-C pressed twice) no longer raises, where it
    would cut that short or print a traceback at the interpreter's end; a third ends the process
    at once, by the signal's default (a clean-up that hangs is not a trap). ``ignored_one``: a
    second was ignored already (a logged run's, as its log ended): the next ends it at once."""
    _state["cleaning"] = True
    if ignored_one:
        _state["ignored"] = True


def stop_signal() -> int | None:
    """The signal that stopped the command through :func:`stop_on_signals` or a run, if any."""
    return _state.get("signal")
