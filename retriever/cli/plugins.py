"""Commands that other packages add, through the ``retriever.commands`` entry point group."""

from __future__ import annotations

from importlib.metadata import entry_points

import typer

from ..errors import RetrieverError
from .console import fail

#: the entry point group whose entries ("name = module:function") become commands of `retriever`;
#: the project registers `demo` there (agents/command.py): the agents sit above the library,
#: which never imports them
COMMANDS_GROUP = "retriever.commands"


def add_registered_commands(app: typer.Typer) -> None:
    """Each entry of COMMANDS_GROUP as a command of ``app``; one that cannot be imported is still listed,
    and says why when it is run, instead of breaking every other command."""
    for entry in entry_points(group=COMMANDS_GROUP):
        if any(c.name == entry.name for c in app.registered_commands):
            continue
        try:
            app.command(name=entry.name)(entry.load())
        except Exception as exc:  # noqa: BLE001 (whatever stops a plugin's import, the command says it)
            app.command(name=entry.name, help=f"(cannot be loaded: {type(exc).__name__})",
                        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
                        )(_unloadable(entry.name, entry.value, exc))


def _unloadable(name: str, value: str, exc: Exception):
    def command() -> None:
        fail(RetrieverError(f"the command '{name}' ({value}) cannot be loaded: {type(exc).__name__}: {exc}\n"
                           "    hint: install the project itself, which includes it: pip install -e ."))

    return command
