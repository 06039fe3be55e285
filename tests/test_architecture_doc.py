"""docs/architecture.md stays true: its diagrams are the docstrings' they say they copy, every
file it links or names exists, and each owner it names is there."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
TEXT = PAGE.read_text(encoding="utf-8")

#: each diagram, by the file whose module docstring it copies (in the order the page shows them)
SOURCES = [
    "retriever/tick.py",
    "retriever/backends/zenoh/coordinator/__init__.py",
    "retriever/backends/zenoh/coordinator/__init__.py",
    "retriever/backends/zenoh/coordinator/hosting.py",
    "retriever/backends/zenoh/worker.py",
    "retriever/backends/zenoh/node/__init__.py",
]
#: the one owner of each concept, as the page names them (module, name)
OWNERS = [("retriever.tick", "select_inputs"), ("retriever.tick", "decide"),
          ("retriever.placement", "assign"), ("retriever.placement", "check_assignment"),
          ("retriever.placement", "place"), ("retriever.placement", "move"),
          ("retriever.backends.zenoh.command", "worker_command"), ("retriever.pipeline", "Pipeline")]


def _diagrams() -> list[str]:
    """The fenced blocks after the map (the map itself is the page's own)."""
    blocks = re.findall(r"```\n(.*?)```", TEXT, re.S)
    return blocks[1:]


def _dedented_docstring(path: str) -> list[str]:
    doc = ast.get_docstring(ast.parse((ROOT / path).read_text(encoding="utf-8")), clean=True) or ""
    return [line[4:] if line.startswith("    ") else line for line in doc.splitlines()]


def test_the_page_shows_a_diagram_of_each_source():
    assert len(_diagrams()) == len(SOURCES)


@pytest.mark.parametrize("index", range(len(SOURCES)))
def test_each_diagram_is_its_docstrings(index):
    block = _diagrams()[index].rstrip("\n").splitlines()
    lines = _dedented_docstring(SOURCES[index])
    found = any(lines[i:i + len(block)] == block for i in range(len(lines) - len(block) + 1))
    assert found, f"docs/architecture.md's diagram {index + 1} differs from {SOURCES[index]}'s docstring: copy it again"


def test_every_link_and_file_named_exists():
    linked = re.findall(r"\]\((\.\./[^)#]+)", TEXT)
    missing = [link for link in linked if not (PAGE.parent / link).exists()]
    files = set(re.findall(r"\b[a-z_0-9]+\.py\b", TEXT)) | set(re.findall(r"\b([a-z_]+)/ ", _the_map()))
    here = {p.name for p in (ROOT / "retriever").rglob("*.py")} | {p.name for p in (ROOT / "tests").rglob("*.py")}
    dirs = {p.name for p in (ROOT / "retriever").rglob("*") if p.is_dir()}
    missing += sorted(f for f in files if f not in here and f not in dirs)
    assert missing == []


def _the_map() -> str:
    return re.findall(r"```\n(.*?)```", TEXT, re.S)[0]


@pytest.mark.parametrize("module, name", OWNERS)
def test_each_owner_named_is_there(module, name):
    assert re.search(rf"\b{name}\b", TEXT), f"the page no longer names {name}: drop it here"
    assert hasattr(importlib.import_module(module), name)
