"""The IR: a graph as explicit, versioned JSON — the deployment artifact (docs/semantics.md, The IR).

``pipe.build_ir()`` returns an :class:`IR`; ``IR.load(path)`` validates a saved one and reports
every problem at once; ``Pipeline.from_ir(ir)`` rebuilds a runnable pipeline from it alone.
Keys are sorted, so the JSON text is stable and a golden file can pin it.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .clocks import clock_from_ir
from .code import SHA256_HEX
from .codec import packb, unpackb
from .errors import CodecError, IRError
from .time import is_finite_number, max_microsteps_problem, seconds_problem
from .flow.core import NAME_MAX, NODE_ID, MAX_SPIN_S, ON_DEADLINE_MISS, ON_ERROR, ON_OVERRUN, REPLAY
from .sync import policy_from_ir

#: 1.1: constructor arguments JSON cannot hold exactly are tagged (:func:`param_to_ir`);
#: 1.2: ``metadata.module_folders`` (optional): where the flows of script files came from;
#: 1.3: ``metadata.code_sha256`` (optional): the sha256 of each flow module's file (code.py)
IR_VERSION = "1.4.0"
#: set on a module that Retriever imported from a script file (``retriever run FILE.py``): the
#: folder it put on ``sys.path`` for it, which the IR records so that it can import the module again
SCRIPT_FOLDER_ATTR = "__retriever_folder__"
#: the paper's three real-time modes: how a run escalates missed deadlines and overruns
REALTIME_MODES = ("hard", "soft", "best_effort")
#: seconds a real-time tick waits for an incomplete input edge, unless the edge says otherwise
DEFAULT_DEADLINE = 0.1
#: what a port name may be: one segment, as a node id (flow/core.py's NODE_ID) but of any length
#: (it names no file) (a log's topic is ``data/<node>/<port>``,
#: a key ``.../data/<node>/<port>``, a qualified name ``node.port``: a '/' or '.' in it splits them);
#: any Python identifier is one too (a dataclass field, a step() parameter: ``größe``)
PORT_NAME = r"[A-Za-z_][A-Za-z0-9_\-]*"
#: microsteps one instant may run before the run stops with a Zeno-loop error
DEFAULT_MAX_MICROSTEPS = 1000


def param_to_ir(value: Any) -> Any:
    """A constructor argument as the IR holds it: JSON values as they are; what JSON would
    change or cannot hold, tagged so that a worker rebuilds the very value (DESIGN §6: msgpack
    values). A tuple is ``{"$tuple": [...]}``; anything else the codec encodes (numpy arrays and
    scalars, bytes, non-finite floats, @io dataclasses, dicts with non-str or ``$`` keys) is
    ``{"$msgpack": base64 of retriever.codec.packb}``. Raises CodecError for what it cannot."""
    if value is None or isinstance(value, str) or (isinstance(value, int) and not isinstance(value, np.generic)):
        return value
    if isinstance(value, float) and not isinstance(value, np.generic) and math.isfinite(value):
        return value
    if type(value) is list:
        return [param_to_ir(v) for v in value]
    if type(value) is tuple:
        return {"$tuple": [param_to_ir(v) for v in value]}
    if type(value) is dict and all(isinstance(k, str) and not k.startswith("$") for k in value):
        return {k: param_to_ir(v) for k, v in value.items()}
    return {"$msgpack": base64.b64encode(packb(value)).decode("ascii")}


def param_from_ir(value: Any) -> Any:
    """The constructor argument that :func:`param_to_ir` stored. Raises ValueError for a
    malformed tag; a dataclass is rebuilt only as a value type this process registered (``@io``),
    never by importing or calling what the IR names."""
    if type(value) is list:
        return [param_from_ir(v) for v in value]
    if type(value) is not dict:
        return value
    if len(value) == 1 and "$tuple" in value and type(value["$tuple"]) is list:
        return tuple(param_from_ir(v) for v in value["$tuple"])
    if len(value) == 1 and "$msgpack" in value:
        try:
            return unpackb(base64.b64decode(value["$msgpack"], validate=True))
        except (TypeError, binascii.Error, CodecError, ValueError) as e:
            raise ValueError(f"a $msgpack value that does not decode ({type(e).__name__}: {e})") from None
    if any(k.startswith("$") for k in value):
        raise ValueError(f"an object with reserved key(s) {sorted(k for k in value if k.startswith('$'))} "
                         "(IR tags are {\"$tuple\": [...]} and {\"$msgpack\": base64})")
    return {k: param_from_ir(v) for k, v in value.items()}


class IR:
    """A compiled graph as data. Build with ``pipe.build_ir()`` or ``IR.load(path)``."""

    def __init__(self, doc: dict, *, source: str = "<memory>"):
        validate_doc(doc, source)
        self.doc = doc

    # -- accessors ---------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.doc["metadata"]["name"]

    @property
    def nodes(self) -> list[dict]:
        return self.doc["nodes"]

    @property
    def edges(self) -> list[dict]:
        return self.doc["edges"]

    @property
    def topology(self) -> dict:
        return self.doc["topology"]

    @property
    def warnings(self) -> list[str]:
        return list(self.doc["metadata"].get("warnings", []))

    def node(self, node_id: str) -> dict:
        for n in self.nodes:
            if n["id"] == node_id:
                return n
        raise KeyError(f"IR '{self.name}' has no node '{node_id}' (nodes: {', '.join(n['id'] for n in self.nodes)})")

    # -- serialization -------------------------------------------------------------------------
    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.doc, indent=indent, sort_keys=True, ensure_ascii=False) + "\n"

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(self.to_json(), encoding="utf-8")
        return path

    @classmethod
    def from_json(cls, text: str, *, source: str = "<string>") -> "IR":
        try:
            doc = json.loads(text, parse_int=_parse_int)
        except json.JSONDecodeError as e:
            raise IRError(source, [f"not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}"]) from None
        except RecursionError:
            raise IRError(source, ["not an IR: its JSON nests arrays or objects deeper than Python's recursion "
                                   "limit"]) from None
        huge = _huge_ints(doc)
        if huge:
            raise IRError(source, huge)
        return cls(doc, source=source)

    @classmethod
    def load(cls, path: str | Path) -> "IR":
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as e:
            raise IRError(str(path), [f"cannot read the file: {e.strerror or e}"]) from None
        except UnicodeDecodeError:
            raise IRError(str(path), ["not a text file (expected UTF-8 JSON)"]) from None
        return cls.from_json(text, source=str(path))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, IR) and self.doc == other.doc

    def __repr__(self) -> str:
        t = self.topology
        return f"<IR '{self.name}' v{self.doc['version']}: {t['node_count']} nodes, {t['edge_count']} edges>"

    # -- pictures ------------------------------------------------------------------------------
    def visualize(self, format: str = "dot") -> str:
        """The graph as Graphviz DOT (``"dot"``) or Mermaid (``"mermaid"``) text."""
        if format == "dot":
            return _to_dot(self)
        if format == "mermaid":
            return _to_mermaid(self)
        raise ValueError(f"unknown format {format!r}; expected 'dot' or 'mermaid'")


# Every text that reaches a picture comes from the IR file, which anyone may have written: the
# pipeline's name, port names, adapter parameters. So every one is escaped for the format it goes
# into (a name of `x"; n [image="/etc/passwd"]; "` made Graphviz read a local file), and labels
# are built as lists of lines that each format joins with its own line break.
def _clock_label(clock: dict) -> str:
    (kind, p), = clock.items()
    if kind == "Rate":
        return f"Rate {p['hz']} Hz"
    if kind == "Trigger":
        return "Trigger(" + ", ".join(map(str, p.get("ports", []))) + ")"
    return f"Hybrid {p['hz']} Hz + (" + ", ".join(map(str, p.get("trigger", []))) + ")"


def _adapter_label(adapter: dict) -> str:
    (name, p), = adapter.items()
    args = ", ".join(f"{k}={v}" for k, v in sorted(p.items()) if v is not None)
    return f"{name}({args})"


def _node_lines(n: dict) -> list[str]:
    latency = n["config"].get("latency") or 0
    return [n["id"], _clock_label(n["config"]["clock"]), *([f"latency {latency} s"] if latency else [])]


def _edge_lines(e: dict) -> list[str]:
    return [f"{e['source']['port']} → {e['destination']['port']}", _adapter_label(e["adapter"]),
            *([f"delay {e['delay']} s"] if e.get("delay") else [])]


def _dot_string(text: object) -> str:
    """``text`` as one quoted DOT string that shows it as it is: a quote cannot end the string, a
    backslash is no label escape (``\\N``, ``\\l``), a line break or control character breaks nothing."""
    out = []
    for ch in str(text):
        if ch in '"\\':
            out.append("\\" + ch)
        elif ch == "\n":
            out.append("\\n")
        elif ord(ch) < 0x20 or 0x7f <= ord(ch) < 0xa0:
            out.append(" ")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _dot_label(lines: list[str]) -> str:
    return '"' + "\\n".join(_dot_string(line)[1:-1] for line in lines) + '"'


def _to_dot(ir: IR) -> str:
    lines = [f"digraph {_dot_string(ir.name)} {{", "  rankdir=LR;",
             '  node [shape=box, style=rounded, fontname="Helvetica"];']
    for n in ir.nodes:
        lines.append(f"  {_dot_string(n['id'])} [label={_dot_label(_node_lines(n))}];")
    for e in ir.edges:
        lines.append(f"  {_dot_string(e['source']['node'])} -> {_dot_string(e['destination']['node'])} "
                     f"[label={_dot_label(_edge_lines(e))}];")
    lines.append("}")
    return "\n".join(lines) + "\n"


#: what Mermaid shows as it is inside a quoted label; anything else is written as an entity code
_MERMAID_PLAIN = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 _-.,:=+*/@?!'→")
#: words a Mermaid flowchart reads as statements, not node ids (at the start of a line or alone)
_MERMAID_WORDS = frozenset({"end", "subgraph", "graph", "flowchart", "style", "classdef", "class", "click",
                            "linkstyle", "direction", "call", "href", "callback", "default"})


def _mermaid_text(text: object) -> str:
    """``text`` for inside a quoted Mermaid label: every character outside a plain alphabet as a
    ``#NNN;`` entity code (quotes, brackets, pipes, ``<``, ``>``, ``&``, ``#``, backticks, line breaks)."""
    return "".join(ch if ch in _MERMAID_PLAIN else f"#{ord(ch)};" for ch in str(text))


def _mermaid_label(lines: list[str]) -> str:
    return '"' + "<br/>".join(_mermaid_text(line) for line in lines) + '"'


def _mermaid_ids(ir: IR) -> dict[str, str]:
    """Each node's Mermaid id: its own when Mermaid reads it as an id, else a made-up one (its
    label still shows the real one)."""
    ids: dict[str, str] = {}
    for i, n in enumerate(ir.nodes):
        nid = n["id"]
        if not (re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", nid) and nid.lower() not in _MERMAID_WORDS):
            nid = f"node_{i}"
        while nid in ids.values() or any(m["id"] == nid and m is not n for m in ir.nodes):
            nid += "_"
        ids[n["id"]] = nid
    return ids


def _to_mermaid(ir: IR) -> str:
    ids = _mermaid_ids(ir)
    lines = ["flowchart LR"]
    for n in ir.nodes:
        lines.append(f"  {ids[n['id']]}[{_mermaid_label(_node_lines(n))}]")
    for e in ir.edges:
        lines.append(f"  {ids[e['source']['node']]} -->|{_mermaid_label(_edge_lines(e))}| "
                     f"{ids[e['destination']['node']]}")
    return "\n".join(lines) + "\n"


class _HugeInt(str):
    """The digits of a JSON integer longer than Python converts (sys.get_int_max_str_digits), kept
    so that from_json can name where it stood instead of failing in the middle of json.loads."""


def _parse_int(digits: str) -> int | _HugeInt:
    try:
        return int(digits)
    except ValueError:
        return _HugeInt(digits)


def _huge_ints(doc: Any) -> list[str]:
    """One problem per oversized integer in ``doc``, named by where it stands: a node's by its id
    and its param (``node 'camera'.params.gain``), any other by its JSON path."""
    problems: list[str] = []

    def walk(value: Any, where: str) -> None:
        if isinstance(value, _HugeInt):
            sign = 1 if value.startswith("-") else 0
            problems.append(f"{where}: an integer of {len(value) - sign} digits; at most "
                            f"{sys.get_int_max_str_digits()} are read\n"
                            f"    hint: write so large a number as a string and convert it in the flow")
        elif isinstance(value, dict):
            for key, item in value.items():
                walk(item, f"{where}.{key}" if where else str(key))
        elif isinstance(value, list):
            for i, item in enumerate(value):
                walk(item, f"{where}[{i}]")

    if isinstance(doc, dict):
        for key, value in doc.items():
            if key == "nodes" and isinstance(value, list):
                for i, n in enumerate(value):
                    nid = n.get("id") if isinstance(n, dict) else None
                    walk(n, f"node '{nid}'" if isinstance(nid, str) and re.fullmatch(NODE_ID, nid) else f"nodes[{i}]")
            else:
                walk(value, key)
    else:
        walk(doc, "the document")
    return problems


# ---------------------------------------------------------------------------------------------
# Validation of a document (every problem at once)
# ---------------------------------------------------------------------------------------------
def _expect(problems: list[str], where: str, value: Any, kind: type | tuple, what: str) -> bool:
    if isinstance(value, kind):
        return True
    problems.append(f"{where}: expected {what}, got {json.dumps(value) if _dumpable(value) else type(value).__name__}")
    return False


def _dumpable(value: Any) -> bool:
    try:
        json.dumps(value)
        return True
    except (TypeError, ValueError):
        return False


def is_type_path(value: object) -> bool:
    """Whether ``value`` has the form of an IR node ``type``, ``module:QualName``, both parts dotted
    identifiers: checked before anything is imported (an IR is code: loading it imports these)."""
    if not isinstance(value, str):
        return False
    module, colon, qualname = value.partition(":")
    return bool(colon) and _is_dotted(module) and _is_dotted(qualname)


def _is_dotted(name: object) -> bool:
    return isinstance(name, str) and all(part.isidentifier() for part in name.split("."))


def _check_seconds(problems: list[str], where: str, name: str, value: Any) -> None:
    problem = seconds_problem(name, value)
    if problem is not None:
        problems.append(f"{where}: {problem}")


def validate_doc(doc: Any, source: str) -> None:
    """Check an IR document's shape, all of it, and raise one IRError that lists every problem."""
    if not isinstance(doc, dict):
        raise IRError(source, [f"the document must be a JSON object, got {type(doc).__name__}"])
    problems = _top_level_problems(doc)
    if problems:
        raise IRError(source, problems)
    _check_metadata(problems, doc["metadata"])
    ids: dict[str, dict] = {}
    for i, n in enumerate(doc["nodes"]):
        _check_node(problems, i, n, ids)
    for i, e in enumerate(doc["edges"]):
        _check_edge(problems, i, e, ids)
    if problems:
        raise IRError(source, problems)


def _top_level_problems(doc: dict) -> list[str]:
    problems: list[str] = []
    version = doc.get("version")
    if not isinstance(version, str):
        problems.append(f"'version' is missing (expected \"{IR_VERSION}\")")
    elif version.split(".")[0] != IR_VERSION.split(".")[0]:
        problems.append(f"version {version!r} is not supported by this Retriever (it reads {IR_VERSION}); "
                        "rebuild the IR with this version: retriever ir FILE --out PATH")
    for key, kind, what in (("metadata", dict, "an object"), ("nodes", list, "a list"),
                            ("edges", list, "a list"), ("topology", dict, "an object")):
        if key not in doc:
            problems.append(f"'{key}' is missing (expected {what})")
        else:
            _expect(problems, f"'{key}'", doc[key], kind, what)
    return problems


def _check_metadata(problems: list[str], meta: dict) -> None:
    if not isinstance(meta.get("name"), str) or not meta["name"]:
        problems.append("metadata.name: expected the pipeline name (a non-empty string)")
    if meta.get("realtime", "soft") not in REALTIME_MODES:
        problems.append(f"metadata.realtime: expected one of {', '.join(REALTIME_MODES)}, got {meta.get('realtime')!r}")
    _check_seconds(problems, "metadata.deadline", "deadline", meta.get("deadline", DEFAULT_DEADLINE))
    folders = meta.get("module_folders", {})
    if not (isinstance(folders, dict) and all(_is_dotted(module) and isinstance(folder, str)
                                              for module, folder in folders.items())):
        problems.append(f"metadata.module_folders: expected an object of module name: folder, got {folders!r}")
    hashes = meta.get("code_sha256", {})
    if not (isinstance(hashes, dict) and all(_is_dotted(module) and isinstance(digest, str)
                                             and SHA256_HEX.fullmatch(digest) for module, digest in hashes.items())):
        problems.append("metadata.code_sha256: expected an object of module name: sha256 (64 lowercase hex digits), "
                        f"got {hashes!r:.120}")
    problem = max_microsteps_problem(meta.get("max_microsteps", DEFAULT_MAX_MICROSTEPS))
    if problem is not None:
        problems.append(f"metadata.max_microsteps: {problem}")


def _check_node(problems: list[str], i: int, n: Any, ids: dict[str, dict]) -> None:
    """Check ``nodes[i]``; a node with a valid id goes in ``ids``, which the edges are checked against."""
    where = f"nodes[{i}]"
    if not _expect(problems, where, n, dict, "an object"):
        return
    nid = n.get("id")
    if not isinstance(nid, str) or not re.fullmatch(NODE_ID, nid):
        problems.append(f"{where}.id: expected a node name of letters, digits, _ and -, at most {NAME_MAX} (it "
                        f"becomes a key-space segment and names files), got {nid!r:.60}")
        return
    where = f"node '{nid}'"
    if nid in ids:
        problems.append(f"{where}: duplicate node id")
    ids[nid] = n
    if not is_type_path(n.get("type")) and (n.get("rebuildable", True) or not isinstance(n.get("type"), str)):
        problems.append(f"{where}.type: expected 'module:Class' (dotted identifiers, e.g. "
                        f"'my_robot.flows:Camera'), got {n.get('type')!r}")
    _expect(problems, f"{where}.params", n.get("params"), dict, "an object")
    for key in ("inputs", "outputs"):
        if _expect(problems, f"{where}.{key}", n.get(key), dict, "an object of port: type"):
            problems.extend(f"{where}.{key}: {port_name_problem(port)}" for port in n[key]
                            if port_name_problem(port) is not None)
    config = n.get("config")
    if _expect(problems, f"{where}.config", config, dict, "an object"):
        _check_config(problems, f"{where}.config", config)


def port_name_problem(port: Any) -> str | None:
    """What makes ``port`` no port name (:data:`PORT_NAME`, or a Python identifier), or None."""
    if isinstance(port, str) and (port.isidentifier() or re.fullmatch(PORT_NAME, port)):
        return None
    return (f"{port!r:.60} is not a port name: letters, digits, _ and -, not starting with a digit or - "
            "(a port is one segment of the log's topic data/<node>/<port> and of the key space)")


def _check_config(problems: list[str], where: str, config: dict) -> None:
    try:
        clock_from_ir(config.get("clock"))
    except (ValueError, TypeError, OverflowError) as e:
        problems.append(f"{where}.clock: {e}".split("\n")[0])
    _check_seconds(problems, f"{where}.latency", "latency", config.get("latency", 0))
    for key, allowed in (("on_error", ON_ERROR), ("on_overrun", ON_OVERRUN),
                         ("on_deadline_miss", ON_DEADLINE_MISS), ("replay", REPLAY)):
        if key in config and config[key] not in allowed:
            problems.append(f"{where}.{key}: {config[key]!r} is not one of {', '.join(allowed)}")
    restarts = config.get("max_restarts", 0)
    if type(restarts) is not int or restarts < 0:
        problems.append(f"{where}.max_restarts: expected an integer >= 0, got {restarts!r}")
    spin = config.get("spin", 0)
    if not is_finite_number(spin) or not 0 <= spin <= MAX_SPIN_S:
        problems.append(f"{where}.spin: expected seconds from 0 to {MAX_SPIN_S:g}, got {spin!r:.40}")
    process = config.get("process")
    if process is not None and not (isinstance(process, str) and re.fullmatch(NODE_ID, process)):
        problems.append(f"{where}.process: expected a name (letters, digits, _ and -, at most {NAME_MAX}), "
                        f"got {process!r:.40}")
    window = config.get("restart_window", 1.0)
    if not isinstance(window, (int, float)) or isinstance(window, bool) or not window > 0:
        problems.append(f"{where}.restart_window: expected seconds > 0, got {window!r}")


def _check_edge(problems: list[str], i: int, e: Any, ids: dict[str, dict]) -> None:
    where = f"edges[{i}]"
    if not _expect(problems, where, e, dict, "an object"):
        return
    for end, ports_key in (("source", "outputs"), ("destination", "inputs")):
        ref = e.get(end)
        if not isinstance(ref, dict) or not isinstance(ref.get("node"), str) or not isinstance(ref.get("port"), str):
            problems.append(f"{where}.{end}: expected {{\"node\": ..., \"port\": ...}}, got {ref!r}")
            continue
        node = ids.get(ref["node"])
        if node is None:
            problems.append(f"{where}.{end}: unknown node '{ref['node']}'")
        elif isinstance(node.get(ports_key), dict) and ref["port"] not in node[ports_key]:
            problems.append(f"{where}.{end}: node '{ref['node']}' has no {ports_key[:-1]} port '{ref['port']}'")
    try:
        policy_from_ir(e.get("adapter"))
    except (ValueError, TypeError, OverflowError) as err:
        problems.append(f"{where}.adapter: {err}")
    _check_seconds(problems, f"{where}.delay", "delay", e.get("delay", 0))
    qsize = e.get("qsize", 10)
    if not isinstance(qsize, int) or isinstance(qsize, bool) or qsize < 1:
        problems.append(f"{where}.qsize: expected an integer >= 1, got {qsize!r}")
    if e.get("deadline") is not None:
        _check_seconds(problems, f"{where}.deadline", "deadline", e["deadline"])
