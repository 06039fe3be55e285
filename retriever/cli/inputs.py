"""What commands read: a pipeline (a Python file or an IR) and a log; one that cannot be read
fails the command as every failure does."""

from __future__ import annotations

from pathlib import Path

from .console import fail


def load(target: str):
    from ..loading import load_pipeline

    try:
        return load_pipeline(target)
    except Exception as exc:  # a user file may raise anything while it builds its graph
        fail(exc)


def read(path: Path, salvage: bool = False):
    from ..log import read_log

    try:
        return read_log(path, salvage=salvage)
    except Exception as exc:
        fail(exc)
