"""Find the Pipeline a user means by ``FILE[:ATTR]`` (a Python file) or ``FILE.json`` (an IR)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from .errors import RetrieverError
from .ir import IR
from .pipeline import Pipeline


class LoadError(RetrieverError):
    """The file or attribute named on the command line does not give a Pipeline."""


def load_pipeline(target: str) -> Pipeline:
    """Load ``path/to/file.py[:attr]`` (the file's only Pipeline without ``:attr``) or an IR JSON file."""
    path_text, _, attr = target.partition(":")
    if len(path_text) == 1 and attr[:1] in ("\\", "/"):  # a Windows drive letter, not an attribute
        path_text, _, attr = target[2:].partition(":")
        path_text = target[:2] + path_text
    path = Path(path_text)
    if not path.is_file():
        raise LoadError(f"no such file: {path_text}\n    hint: give a Python file defining a Pipeline, e.g. "
                        "retriever run examples/quickstart.py")
    if path.suffix == ".json":
        return Pipeline.from_ir(IR.load(path))
    module = _import_file(path)
    if attr:
        obj = getattr(module, attr, None)
        if not isinstance(obj, Pipeline):
            found = _pipelines(module)
            raise LoadError(f"{path_text} has no Pipeline named '{attr}'"
                            + (f" (it has: {', '.join(found)})" if found else ""))
        return obj
    found = _pipelines(module)
    if len(found) == 1:
        return getattr(module, found[0])
    if not found:
        raise LoadError(f"{path_text} defines no Pipeline at module level\n"
                        "    hint: build it at module level: with Pipeline(\"name\") as pipe: ...")
    raise LoadError(f"{path_text} defines several Pipelines ({', '.join(found)})\n"
                    f"    hint: name one: {path_text}:{found[0]}")


def _pipelines(module) -> list[str]:
    return sorted(name for name, value in vars(module).items() if isinstance(value, Pipeline))


def _import_file(path: Path):
    """Import a file as a module named after it, with its folder on sys.path, so the IR's
    ``module:Class`` types stay importable for rebuilding and replay."""
    folder = str(path.resolve().parent)
    if folder not in sys.path:
        sys.path.insert(0, folder)
    name = path.stem
    existing = sys.modules.get(name)
    if existing is not None and Path(getattr(existing, "__file__", "") or "").resolve() == path.resolve():
        return existing
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise LoadError(f"cannot import {path} as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return module
