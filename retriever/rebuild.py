"""Rebuild flows from the IR (docs/semantics.md, The IR): what ``Pipeline.from_ir`` and a worker process do.

An IR file is code: its node ``type`` names a class that is imported and called. So everything
that can be checked without running anything is checked first, for every node (``check_node``:
rebuildable, params that decode, a module that can be found), and a class is called only when
it is a Flow (``construct_node``).
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import sys
from typing import Any

from .clocks import clock_from_ir
from .flow.core import Flow
from .ir import param_from_ir


def _construct(cls: type, params: dict) -> Flow:
    args: list = []
    kwargs: dict = {}
    sig = inspect.signature(cls.__init__) if cls.__init__ is not object.__init__ else None
    if sig is None:
        if params:
            raise TypeError(f"__init__ takes no arguments, the IR gives {sorted(params)}")
        return cls()
    declared = list(sig.parameters.values())[1:]
    names = {p.name for p in declared}
    unknown = sorted(set(params) - names)
    if unknown and not any(p.kind is p.VAR_KEYWORD for p in declared):
        raise TypeError(f"__init__ has no parameter {', '.join(map(repr, unknown))} "
                        f"(it takes: {', '.join(sorted(names)) or 'nothing'})")
    for p in declared:
        if p.name not in params:
            continue
        value = params[p.name]
        if p.kind is p.POSITIONAL_ONLY:
            args.append(value)
        elif p.kind is p.VAR_POSITIONAL:
            args.extend(value)
        elif p.kind is p.VAR_KEYWORD:
            kwargs.update(value)
        else:
            kwargs[p.name] = value
    return cls(*args, **kwargs)


def rebuild_node(node: dict, flows: dict[str, Flow], problems: list[str]) -> None:
    """Rebuild one node of a validated IR into ``flows`` (or say why not in ``problems``)."""
    params = check_node(node, problems)
    if params is not None:
        construct_node(node, params, flows, problems)


def check_node(node: dict, problems: list[str], folders: dict[str, str] | None = None) -> dict | None:
    """What can be checked of a node before importing its module: that it is rebuildable, that its
    params decode (which imports nothing) and that its module can be found (without running it)."""
    nid = node["id"]
    if not node.get("rebuildable", True):
        problems.append(f"node '{nid}' cannot be rebuilt from the IR: {node.get('rebuild_problem')}")
        return None
    params = {}
    for name, value in node["params"].items():
        try:
            params[name] = param_from_ir(value)
        except ValueError as e:
            problems.append(f"node '{nid}': params.{name} is {e}")
        except RecursionError:  # an IR decoded from msgpack (a spec a daemon got) is not depth-checked as JSON is
            problems.append(f"node '{nid}': params.{name} nests arrays or objects deeper than Python's recursion limit")
    module = node["type"].partition(":")[0]
    top = module.partition(".")[0]
    if top not in sys.modules and importlib.util.find_spec(top) is None:
        folder = (folders or {}).get(module)
        where = (f"the IR was built with it from {folder}: run there, or PYTHONPATH={folder}"
                 if folder and folder not in sys.path else
                 f"run from the folder that holds {top}.py (or the {top} package), or add that folder to PYTHONPATH")
        problems.append(f"node '{nid}': cannot import {node['type']} (No module named '{top}')\n    hint: {where}")
        return None
    return params if len(params) == len(node["params"]) else None


def import_type(path: str) -> Any:
    """Import ``module:QualName`` (an IR node's checked ``type``): an IR file is code."""
    module_name, _, qualname = path.partition(":")
    obj: Any = importlib.import_module(module_name)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    return obj


def construct_node(node: dict, params: dict, flows: dict[str, Flow], problems: list[str]) -> None:
    """Import the node's class, refuse anything but a Flow subclass, call it with ``params``."""
    nid = node["id"]
    try:
        flow_cls = import_type(node["type"])
    except (ImportError, AttributeError) as e:
        problems.append(f"node '{nid}': cannot import {node['type']} ({e})")
        return
    if not (isinstance(flow_cls, type) and issubclass(flow_cls, Flow)):
        problems.append(f"node '{nid}': {node['type']} is not a Flow class")
        return
    try:
        flow = _construct(flow_cls, params)
    except Exception as e:
        problems.append(f"node '{nid}': {node['type']}(**{params!r}) raised {type(e).__name__}: {e}")
        return
    config = node["config"]
    flow.configure(name=nid, latency=config.get("latency", 0.0), on_error=config.get("on_error"),
                   on_overrun=config.get("on_overrun"), on_deadline_miss=config.get("on_deadline_miss"),
                   max_restarts=config.get("max_restarts"), restart_window=config.get("restart_window"),
                   replay=config.get("replay"), spin=config.get("spin"), process=config.get("process"))
    flows[nid] = flow @ clock_from_ir(config["clock"])
