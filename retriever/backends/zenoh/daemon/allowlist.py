"""A worker daemon's allowlist: which modules a flow class may come from (``--path``, ``--allow``),
checked before anything is imported, and the refusal that names the flag that would allow one.
"""

from __future__ import annotations

import importlib.machinery
import os
import sys
from fnmatch import fnmatchcase

#: flow classes from these packages (and their modules) are always allowed: Retriever's own flows.
#: Not ``agents`` (Retriever-0): its flows act on the world outside the program (a planner that
#: sends the daemon's API key to a URL its parameters give), so a worker opts in: --allow agents
ALWAYS_ALLOWED = ("retriever",)


def path_modules(paths: list[str]) -> list[str]:
    """The top-level modules and regular packages in the folders ``paths``: the names whose import
    finds them there. Not a folder without ``__init__.py`` (a namespace package: any regular
    package of its name elsewhere, ``venv`` or ``test`` in the standard library, is imported
    first), nor a name the interpreter imports before looking in any folder (built-in or frozen:
    ``sys``, ``os``)."""
    suffixes = sorted(importlib.machinery.all_suffixes(), key=len, reverse=True)
    found = set()
    for folder in paths:
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            if entry.is_dir():
                stem = entry.name if os.path.isfile(os.path.join(entry.path, "__init__.py")) else ""
            else:
                stem = next((entry.name[:-len(s)] for s in suffixes if entry.name.endswith(s)), "")
            if stem.isidentifier() and not stem.startswith("__") and not _imported_first(stem):
                found.add(stem)  # (not __init__, __pycache__)
    return sorted(found)


def _imported_first(name: str) -> bool:
    """Whether ``name`` is a built-in or frozen module, which no folder on the path can provide."""
    return name in sys.builtin_module_names or importlib.machinery.FrozenImporter.find_spec(name) is not None


def module_allowed(module: str, allow: list[str], paths: list[str]) -> bool:
    """Whether a flow class may be imported from ``module``: the module or a package holding it
    is in ALWAYS_ALLOWED, found in a ``paths`` folder, or matches an ``allow`` pattern (fnmatch,
    case-sensitive: ``mylab.*``)."""
    parts = module.split(".") if isinstance(module, str) else [""]
    if not all(part.isidentifier() and not (part.startswith("__") and part.endswith("__")) for part in parts):
        return False  # a dunder part (pkg.__main__) is a package's command line, not a module of flows
    patterns = [*ALWAYS_ALLOWED, *path_modules(paths), *allow]
    prefixes = [".".join(parts[:i]) for i in range(1, len(parts) + 1)]
    return any(fnmatchcase(prefix, pattern) for prefix in prefixes for pattern in patterns)


def refusal(module: str, allow: list[str], paths: list[str], worker: str | None = None) -> str:
    """Why a flow class from ``module`` is refused, and the flag that would allow it."""
    who = f"worker '{worker}'" if worker else "this worker"
    admitted = [f"{', '.join(ALWAYS_ALLOWED)} (always)"]
    if paths:
        admitted.append(f"modules in --path {' '.join(paths)}: {', '.join(path_modules(paths)) or 'none'}")
    if allow:
        admitted.append(f"--allow {' '.join(allow)}")
    top = module.split(".")[0]
    return (f"{who} does not import flow classes from module '{module}': its allowlist admits "
            f"{'; '.join(admitted)}\n"
            f"    hint: start the worker with --allow {module}, or with --path DIR for the folder holding {top}")
