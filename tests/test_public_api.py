"""The public API is curated: every exported name exists, is listed once, and is defined once
(the Trio check: implementation in private modules, re-exported through a few public namespaces)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from collections import defaultdict
from pathlib import Path

import pytest

import retriever

PUBLIC_NAMESPACES = ["retriever", "retriever.flow", "retriever.flow.adapter"]
PACKAGE_DIR = Path(retriever.__file__).parent


def _public_objects():
    for name in retriever.__all__:
        obj = getattr(retriever, name)
        if inspect.isclass(obj) or inspect.isfunction(obj):
            yield name, obj


def _top_level_definitions() -> dict[str, list[str]]:
    """Every top-level ``class``/``def`` in the package, by name -> modules defining it."""
    found: dict[str, list[str]] = defaultdict(list)
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts).removesuffix(".__init__")
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                found[node.name].append(module)
    return found


@pytest.mark.parametrize("namespace", PUBLIC_NAMESPACES)
def test_all_names_exist(namespace):
    module = importlib.import_module(namespace)
    missing = [name for name in module.__all__ if not hasattr(module, name)]
    assert missing == []


@pytest.mark.parametrize("namespace", PUBLIC_NAMESPACES)
def test_all_is_sorted_without_duplicates(namespace):
    names = list(importlib.import_module(namespace).__all__)
    assert names == sorted(names)
    assert len(names) == len(set(names))


@pytest.mark.parametrize("namespace", PUBLIC_NAMESPACES[1:])
def test_sub_namespaces_export_the_same_objects_as_the_top_level(namespace):
    module = importlib.import_module(namespace)
    for name in module.__all__:
        assert name in retriever.__all__, f"{namespace}.{name} is public but not in retriever.__all__"
        assert getattr(module, name) is getattr(retriever, name), name


def test_each_public_class_and_function_is_defined_exactly_once():
    definitions = _top_level_definitions()
    for name, obj in _public_objects():
        modules = definitions.get(name, [])
        assert len(modules) == 1, f"{name} is defined in {modules or 'no module'}; expected exactly one"
        assert obj.__module__ == modules[0], f"retriever.{name} is {obj.__module__}.{name}, defined in {modules[0]}"
        assert obj.__qualname__ == name


def test_public_objects_come_from_inside_the_package():
    for name, obj in _public_objects():
        assert obj.__module__.startswith("retriever."), f"{name} comes from {obj.__module__}"


def test_every_public_object_is_exported_under_one_name():
    seen: dict[int, str] = {}
    for name in retriever.__all__:
        obj = getattr(retriever, name)
        if inspect.isclass(obj) or inspect.isfunction(obj):
            assert id(obj) not in seen, f"{name} and {seen[id(obj)]} are the same object"
            seen[id(obj)] = name


def test_public_names_have_docstrings():
    undocumented = [name for name, obj in _public_objects() if not inspect.getdoc(obj)]
    assert undocumented == []


def test_exceptions_derive_from_retriever_error():
    errors = [obj for _, obj in _public_objects()
              if inspect.isclass(obj) and issubclass(obj, Exception) and not issubclass(obj, Warning)]
    assert len(errors) >= 8
    assert all(issubclass(e, retriever.RetrieverError) for e in errors)
    assert issubclass(retriever.RetrieverWarning, UserWarning)


def test_every_module_imports():
    for info in pkgutil.walk_packages(retriever.__path__, "retriever."):
        importlib.import_module(info.name)
