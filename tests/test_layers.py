"""The layer order that ``retriever/__init__.py``'s docstring writes, checked (issue 37).

Every import in ``retriever/`` counts: at the top of a module, inside a function (lazy), and
under ``if TYPE_CHECKING:``. A module may import its own layer and the layers below it, never one
above; ``agents`` (above everything) is never imported; and no files import each other in a circle,
nor do the modules and packages the layers name (a package counts as one: ``retriever.log``'s
``__init__`` importing ``retriever.replay``, which imports ``retriever.log.reader``, is a circle).
The few imports that still climb are named below, each with why.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = "retriever"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE

#: Aliases kept on purpose: the public spellings that the paper uses, resolved on first use by
#: the package's ``__getattr__`` (an import inside it, so nothing is imported early). The only
#: imports that may climb a layer, and the only ones that may close a circle of layers' modules.
DOCUMENTED_ALIASES = {
    ("retriever.flow", "retriever.pipeline"): "the paper's `from retriever.flow import Pipeline` (Listing 4)",
}

#: Imports that climb and can only be undone inside the distributed runtime's files.
KNOWN_CLIMBS: dict[tuple[str, str], str] = {}


def _modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the package: dotted name -> (file, is a package's ``__init__``)."""
    found = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return found


MODULES = _modules()


def _module_of(name: str) -> str | None:
    """The module an imported name lives in: the longest prefix of it that is a module."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imported(module: str, path: Path, is_package: bool) -> list[tuple[str, int]]:
    """``(imported name, line)`` for every import in the file, wherever it stands."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # `from . import x` imports the module x when there is one; otherwise a name of `source`
            names += [(f"{source}.{alias.name}" if f"{source}.{alias.name}" in MODULES else source, node.lineno)
                      for alias in node.names]
    return names


def _edges() -> dict[tuple[str, str], list[int]]:
    """``(importer, imported module) -> lines`` over the package, plus imports of ``agents``."""
    edges: dict[tuple[str, str], list[int]] = defaultdict(list)
    for module, (path, is_package) in MODULES.items():
        for name, line in _imported(module, path, is_package):
            target = "agents" if name.split(".")[0] == "agents" else _module_of(name) if name.startswith(PACKAGE) else None
            if target is not None and target != module:
                edges[(module, target)].append(line)
    return edges


EDGES = _edges()


def _layers() -> list[list[str]]:
    """The layers written in ``retriever/__init__.py``'s docstring, lowest first: each row of its
    table is ``name   a b < c < d e``; ``<`` separates layers, spaces the modules of one layer."""
    doc = ast.get_docstring(ast.parse((PACKAGE_DIR / "__init__.py").read_text(encoding="utf-8")))
    assert doc is not None and "Layers, lowest first" in doc, "retriever/__init__.py's docstring lost its layers"
    rows = doc.split("Layers, lowest first", 1)[1].split("\n\n")[1]
    layers = []
    for row in rows.splitlines():
        _label, _, spec = row.strip().partition(" ")
        layers += [[f"{PACKAGE}.{m}" for m in layer.split()] for layer in spec.split("<")]
    return layers


LAYERS = _layers()
RANK = {module: rank for rank, layer in enumerate(LAYERS) for module in layer}


def _rank(module: str) -> int | None:
    """The layer of a module: that of the longest listed name it is or lies under; the package
    itself (its curated names) sits above every layer, below ``agents``."""
    if module == "agents":
        return len(LAYERS) + 1
    if module == PACKAGE:
        return len(LAYERS)
    name = module
    while name != PACKAGE:
        if name in RANK:
            return RANK[name]
        name = name.rpartition(".")[0]
    return None


def test_every_module_has_a_layer():
    listed = [m for layer in LAYERS for m in layer]
    assert sorted(m for m in listed if m not in MODULES) == [], "the docstring lists modules that do not exist"
    assert len(listed) == len(set(listed)), "a module is listed twice"
    assert sorted(m for m in MODULES if _rank(m) is None) == [], \
        "modules in no layer: add them to the layers in retriever/__init__.py's docstring"


def test_no_module_imports_a_layer_above_its_own():
    climbs = [f"{a} imports {b} (line {', '.join(map(str, sorted(set(lines))))})"
              for (a, b), lines in sorted(EDGES.items())
              if None not in (_rank(a), _rank(b)) and _rank(b) > _rank(a)
              and (a, b) not in DOCUMENTED_ALIASES and (a, b) not in KNOWN_CLIMBS]
    assert climbs == [], "imports of a higher layer (retriever/__init__.py draws the order):\n" + "\n".join(climbs)


@pytest.mark.parametrize("allowed", [DOCUMENTED_ALIASES, KNOWN_CLIMBS], ids=["aliases", "known"])
def test_each_allowed_climb_still_exists(allowed):
    """An exception that no import needs any more is deleted, so the check tightens as code moves."""
    stale = [f"{a} -> {b}" for (a, b) in allowed if (a, b) not in EDGES or _rank(b) <= _rank(a)]
    assert stale == [], "no longer needed; remove from tests/test_layers.py: " + ", ".join(stale)


def test_no_files_import_each_other_in_a_circle():
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in EDGES:
        graph[a].add(b)
    circles = [sorted(c) for c in _strongly_connected(sorted(MODULES), graph) if len(c) > 1]
    assert circles == []


def test_no_modules_or_packages_of_the_layers_import_each_other_in_a_circle():
    """A package imports as one: importing any of its files runs its ``__init__``. So a circle
    through packages (``log/__init__`` → ``replay`` → ``log/reader``) is one, though no file
    imports a file that imports it back. Only a documented alias may close one."""
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in EDGES:
        if (a, b) not in DOCUMENTED_ALIASES and _unit(a) != _unit(b):
            graph[_unit(a)].add(_unit(b))
    units = sorted({_unit(m) for m in MODULES})
    circles = [sorted(c) for c in _strongly_connected(units, graph) if len(c) > 1]
    assert circles == [], "modules and packages of the layers that import each other in a circle: " + \
        "; ".join(" ".join(c) for c in circles)


def _unit(module: str) -> str:
    """The module or package of the layer table that ``module`` is or lies under (the package
    itself, for its own curated names, or a module the table does not name)."""
    name = module
    while name != PACKAGE and name not in RANK:
        name = name.rpartition(".")[0]
    return name


def test_retriever_never_imports_agents():
    assert sorted(a for a, b in EDGES if b == "agents") == []


def _strongly_connected(nodes: list[str], graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iteratively: each circle of the graph (a single node when there is none)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                circle = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    circle.append(member)
                    if member == node:
                        break
                found.append(circle)
    return found
