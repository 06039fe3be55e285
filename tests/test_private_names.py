"""No module in ``retriever/`` reads another module's private names (issue 37).

A leading underscore says "this module's business": a module may use its own private names as it
likes, and another module asks for what it needs through a public name. Checked over the AST of
every module, in the three forms that can be told apart without knowing types:

- ``from m import _x``: a private name imported from another module (no module of the package
  is private: each has a public name, checked below);
- ``obj._x``, read, written or called, ``self._x`` included, where no class and no top level of
  this module defines ``_x`` but another module of ``retriever`` does: ``_x`` can only be that
  module's (for ``self``, inherited from a base class there). A name this module defines too is
  taken as its own: without types the check cannot tell, and it errs towards silence;
- ``def _x`` in a class that overrides a private member of a base class in another module (a
  private hook customised from outside).

Dunder names are public protocol. KNOWN lists the exceptions (none today): the check fails on any
other case, and on a KNOWN case that no longer occurs, so the list stays true.

Code that uses the package from outside (tests, benchmarks, agents, examples) asks through public
names too: it imports no private name, patches none, reads no private attribute the package
defines, replaces none of the package's attributes by assignment, and patches nothing on a
private module; a seam a test or benchmark needs is a public property, option or hook
(KNOWN_OUTSIDE lists the files still waiting for theirs).
"""

from __future__ import annotations

import ast
from collections import defaultdict
from functools import cache
from pathlib import Path

PACKAGE = "retriever"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE


#: Private names still read across modules: none. An exception, if one must be made, goes here
#: with its reason (the check fails on any other, and on one of these that no longer occurs),
#: keyed by the reading module and the name.
KNOWN: dict[tuple[str, str], str] = {}


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _modules() -> dict[str, tuple[Path, bool, ast.Module]]:
    """Every module of the package: dotted name -> (file, is a package's ``__init__``, its AST)."""
    found = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if is_package else parts)] = (path, is_package,
                                                                ast.parse(path.read_text(encoding="utf-8")))
    return found


MODULES = _modules()


def _source(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` reads from."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[:len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _bound_at_top(tree: ast.Module) -> set[str]:
    """Names the module binds at its top level (defs, classes, assignments, imports)."""
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        else:
            names.update(n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store))
    return names


def _class_members(cls: ast.ClassDef) -> set[str]:
    """What a class defines: its body's names, its ``__slots__``, and each ``self.x``/``cls.x`` it sets."""
    names: set[str] = set()
    for node in cls.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            stored = {n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
            names |= stored
            if "__slots__" in stored and node.value is not None:
                names.update(c.value for c in ast.walk(node.value) if isinstance(c, ast.Constant)
                             and isinstance(c.value, str))
    names.update(n.attr for n in ast.walk(cls) if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
                 and isinstance(n.value, ast.Name) and n.value.id in ("self", "cls"))
    return names


def _classes(tree: ast.Module) -> list[ast.ClassDef]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]


def _defined(tree: ast.Module) -> set[str]:
    """Every name this module defines, at its top level or as a member of one of its classes."""
    names = _bound_at_top(tree)
    for cls in _classes(tree):
        names |= _class_members(cls)
    return names


DEFINED = {module: _defined(tree) for module, (_path, _pkg, tree) in MODULES.items()}
DEFINED_BY: dict[str, set[str]] = defaultdict(set)
for _module, _names in DEFINED.items():
    for _name in _names:
        DEFINED_BY[_name].add(_module)


@cache
def _imported(module: str) -> dict[str, tuple[str, str]]:
    """Local name -> (module, name) for each name ``module`` imports from a module of the package."""
    _path, is_package, tree = MODULES[module]
    found = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            source = _source(module, is_package, node)
            if source in MODULES:
                found.update({a.asname or a.name: (source, a.name) for a in node.names})
    return found


def _class_in(module: str, name: str) -> ast.ClassDef | None:
    return next((c for c in MODULES[module][2].body if isinstance(c, ast.ClassDef) and c.name == name), None)


def _bases_elsewhere(module: str, cls: ast.ClassDef) -> list[tuple[str, ast.ClassDef]]:
    """The classes, in other modules of the package, that ``cls`` derives from (all the way up)."""
    found, todo, seen = [], [(module, cls)], set()
    while todo:
        where, klass = todo.pop()
        imported = _imported(where)
        for base in klass.bases:
            if not isinstance(base, ast.Name):
                continue
            source, name = imported.get(base.id, (where, base.id))
            parent = _class_in(source, name) if source in MODULES else None
            if parent is None or (source, name) in seen:
                continue
            seen.add((source, name))
            todo.append((source, parent))
            if source != module:
                found.append((source, parent))
    return found


def _foreign_modules(tree: ast.Module) -> set[str]:
    """The names a module binds with ``import X`` to a module outside this package (``os`` in
    ``os._exit``): their private names are that library's business, not this check's."""
    return {alias.asname or alias.name.partition(".")[0]
            for node in ast.walk(tree) if isinstance(node, ast.Import)
            for alias in node.names if alias.name.partition(".")[0] != PACKAGE}


#: the builtins that read or write an attribute named by a string
BY_NAME = ("getattr", "hasattr", "setattr", "delattr")
#: named tuples' public methods, underscored so as not to clash with field names
NAMEDTUPLE_API = frozenset({"_make", "_replace", "_asdict", "_fields", "_field_defaults"})


def _private_reads(module: str) -> dict[tuple[str, str], list[str]]:
    """``(module, private name) -> where and how`` for each private name of another module that
    ``module`` uses."""
    _path, is_package, tree = MODULES[module]
    own = DEFINED[module]
    foreign = _foreign_modules(tree)
    found: dict[tuple[str, str], list[str]] = defaultdict(list)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            source = _source(module, is_package, node)
            for alias in node.names:
                if _is_private(alias.name) and source != module:
                    found[(module, alias.name)].append(f"line {node.lineno}: from {source} import {alias.name}")
        elif (isinstance(node, ast.Attribute) and _is_private(node.attr) and node.attr not in own
              and not (isinstance(node.value, ast.Name) and node.value.id in foreign)):
            owners = sorted(DEFINED_BY[node.attr] - {module})
            if owners:
                found[(module, node.attr)].append(f"line {node.lineno}: {ast.unparse(node)} (of {' or '.join(owners)})")
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in BY_NAME
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str)
              and _is_private(node.args[1].value) and node.args[1].value not in own | NAMEDTUPLE_API):
            name = node.args[1].value  # getattr(obj, "_x"): obj._x spelled otherwise
            owners = sorted(DEFINED_BY[name] - {module})
            if owners:
                found[(module, name)].append(f"line {node.lineno}: {ast.unparse(node)[:80]} (of {' or '.join(owners)})")
    for cls in _classes(tree):
        methods = {n.name: n.lineno for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        for source, parent in _bases_elsewhere(module, cls):
            for name in sorted(set(methods) & _class_members(parent)):
                if _is_private(name):
                    found[(module, name)].append(f"line {methods[name]}: {cls.name}.{name} overrides "
                                                 f"{source}.{parent.name}.{name}")
    return found


def _all_private_reads() -> dict[tuple[str, str], list[str]]:
    return {key: where for module in MODULES for key, where in _private_reads(module).items()}


ALL_READS = _all_private_reads()


def test_no_module_of_the_package_is_private():
    """A module's name says what it is, with no underscore (``__init__`` and ``__main__`` aside):
    no check here needs the exemption a private module would."""
    private = sorted(m for m in MODULES if any(_is_private(part) for part in m.split(".")))
    assert private == [], "private modules (give each a public name): " + ", ".join(private)


def test_no_module_reads_another_modules_private_names():
    new = [f"{module} uses {name}: " + "; ".join(where)
           for (module, name), where in sorted(ALL_READS.items()) if (module, name) not in KNOWN]
    assert new == [], ("private names of another module (use or add a public name in the module that owns it):\n"
                       + "\n".join(new))


def test_each_known_case_still_occurs():
    """A case fixed is deleted from KNOWN, so the check tightens as code moves."""
    stale = sorted(f"{module}: {name}" for module, name in KNOWN if (module, name) not in ALL_READS)
    assert stale == [], "no longer read; remove from KNOWN in tests/test_private_names.py: " + ", ".join(stale)


#: the folders of code that uses the package from outside: what they may use is its public names
OUTSIDE = ("tests", "benchmarks", "agents", "examples")


def _outside_uses(path: Path) -> list[str]:
    """In a test, benchmark, agent or example: each private name imported from a module of the
    package, and each private name patched (``monkeypatch.setattr(x, "_y", ...)``,
    ``mock.patch.object(x, "_y", ...)``, ``setattr(x, "_y", ...)``, or by its dotted path:
    ``monkeypatch.setattr("retriever.m._y", ...)``, ``mock.patch("retriever.m._y")``): a seam a
    test or benchmark needs is a public one."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == PACKAGE:
            found += [f"line {node.lineno}: from {node.module} import {a.name}" for a in node.names
                      if _is_private(a.name)]
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id) in ("setattr", "object")
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
              and isinstance(node.args[1].value, str) and _is_private(node.args[1].value)):
            found.append(f"line {node.lineno}: {ast.unparse(node)[:80]}")
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
              and (node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id) in ("setattr", "patch")
              and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and node.args[0].value.split(".")[0] == PACKAGE
              and any(_is_private(part) for part in node.args[0].value.split("."))):
            found.append(f"line {node.lineno}: {ast.unparse(node)[:80]}")
    return found


def test_tests_and_benchmarks_use_public_seams():
    root = PACKAGE_DIR.parent
    found = [f"{path.relative_to(root)} {use}" for folder in OUTSIDE for path in sorted((root / folder).rglob("*.py"))
             for use in _outside_uses(path)]
    assert found == [], ("private names of the package used from outside it (give the module a public seam):\n"
                         + "\n".join(found))


#: every private name the package defines: at a module's top level, or as a class's member
#: (``def _x``, a class attribute, ``self._x = ...``): ``obj._x`` outside the package reads one of these
PRIVATE_DEFINED = frozenset(name for names in DEFINED.values() for name in names if _is_private(name))


def _package_bindings(tree: ast.Module) -> dict[str, str]:
    """Local name -> the dotted name it stands for, for each name a file binds by importing from
    the package (``from retriever.x import Y``, ``import retriever.x as y``, ``import retriever``)."""
    bound = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] == PACKAGE:
            bound.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == PACKAGE:
                    bound[a.asname or PACKAGE] = a.name if a.asname else PACKAGE
    return bound


def _root(node: ast.expr) -> str | None:
    """The name an attribute chain starts from (``node`` in ``node.NodeLoop.run``)."""
    while isinstance(node, ast.Attribute):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


def _outside_reads_and_replacements(path: Path) -> list[str]:
    """In a test, benchmark, agent or example: each ``obj._x`` (``self``/``cls``, another library's
    module and a named tuple's methods aside) where the package defines ``_x`` and this file does
    not (a class of its own may have a ``_x``); and each
    attribute of the package's set by plain assignment (``Outputs.publish = timed``: a method or
    a setting replaced for good)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    own, bound = _defined(tree) | NAMEDTUPLE_API, _package_bindings(tree)
    foreign = {name for name in _foreign_modules(tree) if name not in bound}
    found = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr in PRIVATE_DEFINED and node.attr not in own
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls", *foreign))):
            found.append(f"line {node.lineno}: reads {ast.unparse(node)}")
        elif isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                for leaf in (target.elts if isinstance(target, ast.Tuple) else [target]):
                    if isinstance(leaf, ast.Attribute) and _root(leaf) in bound:
                        found.append(f"line {node.lineno}: sets {ast.unparse(leaf)}")
    return found


#: files outside the package that still replace its attributes, with why (the check fails on any
#: other, and on one of these that no longer does)
KNOWN_OUTSIDE: dict[str, str] = {}


def _outside_replacements() -> dict[str, list[str]]:
    root = PACKAGE_DIR.parent
    found = {str(path.relative_to(root)): _outside_reads_and_replacements(path)
             for folder in OUTSIDE for path in sorted((root / folder).rglob("*.py"))}
    return {path: uses for path, uses in found.items() if uses}


def test_tests_and_benchmarks_read_and_replace_nothing_private():
    found = [f"{path} {use}" for path, uses in _outside_replacements().items() if path not in KNOWN_OUTSIDE
             for use in uses]
    stale = sorted(set(KNOWN_OUTSIDE) - set(_outside_replacements()))
    assert stale == [], "replaces nothing of the package now; remove from KNOWN_OUTSIDE: " + ", ".join(stale)
    assert found == [], ("private attributes of the package read, or its attributes replaced, from outside it "
                         "(give the object a public property, option or hook):\n" + "\n".join(found))
