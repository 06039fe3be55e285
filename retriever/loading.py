"""Find the Pipeline a user means by ``FILE[:ATTR]`` (a Python file) or ``FILE.json`` (an IR)."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

from .errors import LoadError
from .ir import IR, SCRIPT_FOLDER_ATTR
from .pipeline import Pipeline


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
        ir = IR.load(path)
        _add_import_folders(ir, path)
        return Pipeline.from_ir(ir)
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


def _add_import_folders(ir: IR, path: Path) -> None:
    """Put where the IR's flows can be imported from on ``sys.path``: first the folders it recorded
    for the modules of script files (those that exist here), last the IR file's folder and the
    working directory, so that an IR saved from a script runs beside that script too."""
    recorded = [folder for folder in ir.doc["metadata"].get("module_folders", {}).values() if os.path.isdir(folder)]
    for folder in reversed(recorded):
        if folder not in sys.path:
            sys.path.insert(0, folder)
    for folder in (str(path.resolve().parent), os.getcwd()):
        if folder not in sys.path:
            sys.path.append(folder)


def _package_module(path: Path) -> tuple[str, str] | None:
    """``(root folder, dotted name)`` when the file is a module of a package (its folder has an
    ``__init__.py``): ``agents/retriever0.py`` is ``agents.retriever0``, relative imports and all."""
    path = path.resolve()
    parts = [path.stem]
    folder = path.parent
    while (folder / "__init__.py").is_file() and folder.parent != folder:
        parts.insert(0, folder.name)
        folder = folder.parent
    if len(parts) == 1 or not all(part.isidentifier() for part in parts):
        return None
    return str(folder), ".".join(parts)


def _import_file(path: Path):
    """Import a file as a module named after it, with its folder on sys.path, so the IR's
    ``module:Class`` types stay importable for rebuilding and replay; a module of a package that
    uses relative imports (which fail so) is imported by its dotted name instead, with the
    package's parent folder on sys.path."""
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
    setattr(module, SCRIPT_FOLDER_ATTR, folder)  # an IR of its flows records it (metadata.module_folders)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except ImportError as exc:
        sys.modules.pop(name, None)
        package = _package_module(path)
        if package is None or "relative import" not in str(exc):
            raise
        return _import_package_module(path, *package)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return module


def _import_package_module(path: Path, root: str, dotted: str):
    if root not in sys.path:
        sys.path.insert(0, root)
    module = importlib.import_module(dotted)
    if Path(getattr(module, "__file__", "") or "").resolve() != path.resolve():
        raise LoadError(f"{path} is module {dotted}, but importing {dotted} gives {module.__file__}\n"
                        f"    hint: another {dotted} comes first on sys.path; run from {root}")
    return module
