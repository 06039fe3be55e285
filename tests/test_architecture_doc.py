"""docs/architecture.md stays true: its diagrams are the docstrings' they say they copy, every
file it links or names exists, and each owner it names is there. And the package's maps (the
page's, and the package docstrings that map their package) put every module of ``retriever/`` on
a map, by its path, each with a line saying its job."""

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
    "retriever/backends/zenoh/worker/__init__.py",
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
    """A link names a file from the page's folder; a file named in the prose (outside the fenced
    blocks, which the tests below and above check) is one file of ``retriever/`` named by the end
    of its path (``host.py`` alone would be either backend's: the page writes ``zenoh/host.py``),
    or a file named from the repo's top (``tests/...``)."""
    linked = re.findall(r"\]\((\.\./[^)#]+)", TEXT)
    missing = [link for link in linked if not (PAGE.parent / link).exists()]
    prose = re.sub(r"```\n.*?```|\]\([^)]*\)", "", TEXT, flags=re.S)
    modules = [p.relative_to(ROOT).as_posix() for p in (ROOT / "retriever").rglob("*.py")]
    for named in sorted(set(_NAMED.findall(prose))):
        found = [named] if (ROOT / named).is_file() else [m for m in modules if m.endswith("/" + named)]
        if len(found) != 1:
            missing.append(f"{named}: {'no file' if not found else 'which of ' + ', '.join(found)}")
    assert missing == []


def _the_map() -> str:
    return re.findall(r"```\n(.*?)```", TEXT, re.S)[0]


# ---------------------------------------------------------------------------------------------
# The maps: every module on one, by its path
# ---------------------------------------------------------------------------------------------
#: every map of the package: where it is, the folder its paths start from, and its text
MAPS = {
    "docs/architecture.md": ("", _the_map()),
    **{path: (path.rsplit("/", 1)[0], "\n".join(_dedented_docstring(path)))
       for path in ("retriever/backends/zenoh/__init__.py", "retriever/backends/zenoh/node/__init__.py",
                    "retriever/backends/zenoh/coordinator/__init__.py", "retriever/backends/zenoh/worker/__init__.py",
                    "retriever/backends/zenoh/daemon/__init__.py", "retriever/backends/zenoh/deploy/__init__.py",
                    "retriever/backends/zenoh/protocol/__init__.py", "retriever/backends/zenoh/link/__init__.py",
                    "retriever/backends/dora/__init__.py",
                    "retriever/replay/__init__.py")},
}
#: a line of a map that names files or folders (``name.py``, ``name/``, several: ``a.py, b.py``),
#: then what they do; a line below it indented further goes on saying it
_ENTRY = re.compile(r"( *)((?:[\w.]+(?:\.py|/))(?:, [\w.]+(?:\.py|/))*)(?: +(\S.*))?$")
#: a file named in what an entry says: from the entry's folder, or from the repo's top (retriever/...)
_NAMED = re.compile(r"(?<![\w/.])((?:[\w.]+/)*[\w.]+\.py)\b")


def _entries(base: str, text: str) -> list[tuple[str, str]]:
    """(path from the repo's top, what the map says of it) of each file and folder ``text`` names
    as an entry. A folder's entry holds the entries indented below it."""
    entries: list[tuple[str, str]] = []
    folders: list[tuple[int, str]] = []  # (indent, path) of the folders the next entry may be in
    said: list[str] | None = None
    indent = 0
    for line in text.splitlines():
        if said is not None and line.strip() and len(line) - len(line.lstrip()) > indent \
                and not _ENTRY.fullmatch(line):
            said.append(line.strip())  # the entry's description goes on
            continue
        said = None
        match = _ENTRY.fullmatch(line)
        if not match:
            continue
        indent = len(match[1])
        while folders and folders[-1][0] >= indent:
            folders.pop()
        parent = folders[-1][1] if folders else base
        said = [match[3] or ""]
        names = match[2].split(", ")
        for name in names:
            path = f"{parent}/{name}".lstrip("/")
            entries.append((path, said))
            if name.endswith("/") and len(names) == 1:
                folders.append((indent, path.rstrip("/")))
    return [(path, " ".join(words).strip()) for path, words in entries]


def _all_entries() -> dict[str, list[tuple[str, str]]]:
    return {where: _entries(base, text) for where, (base, text) in MAPS.items()}


def test_every_module_of_the_package_is_on_a_map():
    on_a_map = {path.rstrip("/") for entries in _all_entries().values() for path, _ in entries}
    modules = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "retriever").rglob("*.py"))
    off = [m for m in modules
           if m not in on_a_map and not (m.endswith("/__init__.py") and m[:-len("/__init__.py")] in on_a_map)]
    assert off == [], ("modules on no map: add each, with a line saying its job, to the map of its package "
                       f"(one of {', '.join(MAPS)}): {off}")


@pytest.mark.parametrize("where", MAPS)
def test_each_map_names_files_that_are_there_and_says_their_job(where):
    base, _ = MAPS[where]
    problems = []
    for path, said in _all_entries()[where]:
        if not (ROOT / path).exists():
            problems.append(f"{path}: no such file or folder")
        elif path.endswith(".py") and not said:
            problems.append(f"{path}: the map says nothing of its job")
        parent = path.rstrip("/").rsplit("/", 1)[0]
        for named in _NAMED.findall(said):
            full = named if named.startswith("retriever/") else f"{parent}/{named}"
            if not (ROOT / full).is_file():
                problems.append(f"{path} names {named}, which is not {full}")
    assert problems == [], f"{where}'s map: " + "; ".join(problems)


@pytest.mark.parametrize("module, name", OWNERS)
def test_each_owner_named_is_there(module, name):
    assert re.search(rf"\b{name}\b", TEXT), f"the page no longer names {name}: drop it here"
    assert hasattr(importlib.import_module(module), name)
