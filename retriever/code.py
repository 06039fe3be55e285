"""Which code a run ran: the sha256 of each flow module's source file (docs/semantics.md, The IR; docs/log.md).

The IR records, in ``metadata.code_sha256``, the sha256 of the bytes of the file each node's
module was loaded from (the ``.py`` file, a package's ``__init__.py``; a compiled extension's
own file). A worker daemon compares its own copy before it runs a node, and replay compares the
files here before it compares values: a stale copy is named as such, not found as a divergence.

Only that module's file is hashed, not the modules it imports. Finding a file runs no code:
a module not yet imported is looked up the way the import system would (its top-level package
by the meta path finders, each further part in its parent's search locations), never imported.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import re
import sys
from collections.abc import Iterable

#: a recorded hash: the hex digest of sha256 (lowercase, as hashlib writes it)
SHA256_HEX = re.compile(r"[0-9a-f]{64}")


def module_file(name: str) -> str | None:
    """The file the import system loads for module ``name`` (dotted), or None when it has none
    (built-in, namespace package, not found). Nothing is imported or executed to find it."""
    loaded = sys.modules.get(name)
    if loaded is not None:
        spec = getattr(loaded, "__spec__", None)
        if spec is not None and spec.has_location and spec.origin:
            return spec.origin
        file = getattr(loaded, "__file__", None)
        return file if isinstance(file, str) else None
    parts = name.split(".")
    try:
        spec = importlib.util.find_spec(parts[0])  # a top-level name: no parent is imported
        for i in range(1, len(parts)):
            if spec is None or not spec.submodule_search_locations:
                return None
            spec = importlib.machinery.PathFinder.find_spec(".".join(parts[:i + 1]),
                                                            list(spec.submodule_search_locations))
    except (ImportError, ValueError):
        return None
    return spec.origin if spec is not None and spec.has_location else None


def file_sha256(path: str) -> str | None:
    """The hex sha256 of the file's bytes, or None when it cannot be read."""
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return None


def module_sha256(name: str) -> str | None:
    """The sha256 of module ``name``'s file as this process would load it, or None without one."""
    path = module_file(name)
    return None if path is None else file_sha256(path)


def code_hashes(modules: Iterable[str]) -> dict[str, str]:
    """``{module: sha256}`` for those of ``modules`` that have a file (``__main__``, a script
    run as a program, is left out: no other process imports it by that name)."""
    hashes = {}
    for name in sorted(set(modules) - {"__main__"}):
        digest = module_sha256(name)
        if digest is not None:
            hashes[name] = digest
    return hashes


def code_mismatch(module: str, recorded: str) -> str | None:
    """How this process's copy of ``module`` differs from the ``recorded`` sha256, or None when
    it is the same file's bytes."""
    path = module_file(module)
    if path is None:
        return f"module {module} is not found here (the run's has sha256 {recorded})"
    here = file_sha256(path)
    if here == recorded:
        return None
    return f"the code of module {module} differs from the run's (run sha256 {recorded}, here {here} in {path})"


def code_mismatches(recorded: dict[str, str], modules: Iterable[str] | None = None) -> list[str]:
    """:func:`code_mismatch` for each recorded module (or those of ``modules`` recorded), one a line."""
    names = sorted(recorded if modules is None else set(modules) & set(recorded))
    return [problem for name in names if (problem := code_mismatch(name, recorded[name])) is not None]
