"""``retriever deploy --config deploy.toml``: the deploy flags a file may hold, read and checked at once."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from ....errors import BackendError
from ....trace import KEEP
from ..daemon import ENDPOINT
from ..wire import check_chunk
from .loss import WORKER_LOSS

#: what a deploy.toml may hold, with the kind of each value: the flags of retriever deploy
DEPLOY_CONFIG = {"connect": "endpoints", "listen": "endpoints", "router": "endpoints", "namespace": "text", "placement": "path",
                 "duration": "seconds", "log": "path", "secret": "path", "insecure": "bool", "virtual_time": "bool",
                 "keep": "keep", "on_worker_loss": "text", "lease": "seconds", "max_clock_offset": "seconds",
                 "tls_ca": "path", "tls_cert": "path", "tls_key": "path"}


def load_deploy_config(path: str | os.PathLike) -> dict:
    """The settings of ``retriever deploy --config deploy.toml`` (DEPLOY_CONFIG; relative paths
    are relative to the file's folder); every problem at once, one a line."""
    path = Path(path)
    try:
        values = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as e:
        raise BackendError(f"cannot read the deploy config {path}: {e}") from None
    problems = [f"'{key!s:.40}' is no setting of retriever deploy (it takes: {', '.join(DEPLOY_CONFIG)})"
                for key in values if key not in DEPLOY_CONFIG]
    settings = {}
    for key, kind in DEPLOY_CONFIG.items():
        if key not in values:
            continue
        value = values[key]
        if kind == "endpoints":
            value = [value] if isinstance(value, str) else value
            ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
        elif kind == "seconds":
            ok = type(value) in (int, float) and 0 < value <= 1e9
        elif kind == "bool":
            ok = isinstance(value, bool)
        elif kind == "keep":
            ok = value in KEEP
        else:
            ok = isinstance(value, str)
            if ok and kind == "path":
                value = str(path.parent / value) if not os.path.isabs(value) else value
        if not ok:
            problems.append(f"'{key}' must be {DEPLOY_KINDS[kind]}, got {value!r:.60}")
        else:
            _check_deploy_value(key, kind, value, problems)
        settings[key] = value
    if problems:
        raise BackendError(f"the deploy config {path} has problems:\n" + "\n".join(f"  - {p}" for p in problems))
    return settings


def _check_deploy_value(key: str, kind: str, value, problems: list[str]) -> None:
    """A value of the right kind that the deployment would still refuse later, one problem per
    run: said now, with the others. The files it names are read, and judged, by their readers."""
    if kind == "endpoints":
        for endpoint in value:
            if not ENDPOINT.fullmatch(endpoint):
                problems.append(f"'{key}': {endpoint!r:.60} is no Zenoh endpoint: write PROTOCOL/ADDRESS, "
                                f"e.g. tcp/10.0.0.2:7447 (tls/... with TLS)")
    elif key == "namespace":
        try:
            check_chunk("'namespace'", value)
        except ValueError as e:
            problems.append(str(e))
    elif key == "on_worker_loss" and value not in WORKER_LOSS:
        problems.append(f"'on_worker_loss' must be one of {', '.join(WORKER_LOSS)}, got {value!r:.60}")


DEPLOY_KINDS = {"endpoints": "an endpoint or a list of them (\"tcp/HOST:PORT\")", "seconds": "a positive number of seconds (at most 1e9)",
                "bool": "true or false", "text": "a string", "path": "a file path (a string)",
                "keep": "\"records\" (values only in the log), \"trace\" (every value in memory) or \"counters\" "
                        "(nothing but counters)"}
