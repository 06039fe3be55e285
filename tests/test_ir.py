"""The IR: golden JSON, round trip to an identical trace, validation of loaded documents, pictures."""

from __future__ import annotations

import copy
import hashlib
import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from retriever import IR, IRError, Pipeline, Rate
from retriever.ir import NAME_MAX
from tests import ir_flows

GOLDEN = Path(__file__).parent / "golden" / "small_pipeline.ir.json"
QUICKSTART = Path(__file__).parent.parent / "examples" / "quickstart.py"


@pytest.fixture
def ir() -> IR:
    return ir_flows.build().build_ir()


@pytest.fixture
def doc(ir: IR) -> dict:
    return json.loads(ir.to_json())


def _load(tmp_path: Path, text: str) -> IR:
    path = tmp_path / "pipeline.ir.json"
    path.write_text(text, encoding="utf-8")
    return IR.load(path)


# ---------------------------------------------------------------------------------------------
# Golden file
# ---------------------------------------------------------------------------------------------
def _flows_sha256() -> str:
    return hashlib.sha256(Path(ir_flows.__file__).read_bytes()).hexdigest()


def _golden_of_today() -> dict:
    """The golden IR with the sha256 of tests/ir_flows.py as that file is now: the golden pins
    the format, not the bytes of the flows' file (checked against the file itself)."""
    golden = json.loads(GOLDEN.read_text(encoding="utf-8"))
    golden["metadata"]["code_sha256"] = {"tests.ir_flows": _flows_sha256()}
    return golden


def test_ir_json_matches_golden_file(ir: IR):
    text = ir.to_json()
    if os.environ.get("RETRIEVER_UPDATE_GOLDEN") == "1":
        GOLDEN.write_text(text, encoding="utf-8")
    assert GOLDEN.exists(), f"{GOLDEN} is missing; run with RETRIEVER_UPDATE_GOLDEN=1 to create it"
    assert ir.doc["metadata"]["code_sha256"] == {"tests.ir_flows": _flows_sha256()}
    assert text == IR(_golden_of_today()).to_json(), (
        "the IR format changed; if on purpose, regenerate with RETRIEVER_UPDATE_GOLDEN=1 and review the diff")


def test_golden_file_loads_and_rebuilds():
    loaded = IR.load(GOLDEN)
    assert loaded.name == "small"
    assert [n["type"] for n in loaded.nodes] == [
        "tests.ir_flows:Camera", "tests.ir_flows:Planner", "tests.ir_flows:Controller", "tests.ir_flows:Logger"]
    assert Pipeline.from_ir(loaded).build_ir() == IR(_golden_of_today())


def test_to_json_is_stable_with_sorted_keys(ir: IR):
    text = ir.to_json()
    assert text == ir_flows.build().build_ir().to_json()

    def check_sorted(value):
        if isinstance(value, dict):
            assert list(value) == sorted(value)
            for v in value.values():
                check_sorted(v)
        elif isinstance(value, list):
            for v in value:
                check_sorted(v)

    check_sorted(json.loads(text))


def test_ir_shape_follows_the_design(ir: IR):
    doc = ir.doc
    assert doc["version"] == "1.4.0"
    assert doc["metadata"]["name"] == "small"
    assert doc["metadata"]["validated"] is True
    assert doc["metadata"]["optimized"] is False
    planner = ir.node("planner")
    assert planner["type"] == "tests.ir_flows:Planner"
    assert planner["params"] == {"steps": 4, "gains": {"$tuple": [0.5, 0.25]}}  # rebuilt as a tuple
    assert planner["config"]["clock"] == {"Rate": {"hz": 2, "offset": 0.0}}
    assert planner["config"]["latency"] == 0.25
    assert planner["config"]["on_error"] == "skip_tick"
    assert planner["inputs"] == {"recent": "list[float]", "feedback": "float | None"}
    assert planner["outputs"] == {"chunk": "list[float]"}
    feedback = [e for e in ir.edges if e["destination"] == {"node": "planner", "port": "feedback"}]
    assert feedback == [{"source": {"node": "controller", "port": "position"},
                         "destination": {"node": "planner", "port": "feedback"},
                         "adapter": {"latest": {"staleness": 0.5}}, "qsize": 10, "delay": 0.02,
                         "deadline": None}]
    assert (doc["metadata"]["realtime"], doc["metadata"]["deadline"]) == ("soft", 0.1)
    topo = ir.topology
    assert (topo["node_count"], topo["edge_count"], topo["has_cycle"]) == (4, 4, True)
    assert topo["cycles"] == [["planner", "controller"]]


def test_action_chunking_control_hz_defaults_to_the_consumer_rate_in_the_ir(ir: IR):
    (edge,) = [e for e in ir.edges if e["destination"]["node"] == "controller"]
    assert edge["adapter"] == {"action_chunking": {"chunk_steps": 4, "control_hz": 50, "on_exhausted": "hold", "horizon_ms": None}}


def test_node_lookup_names_the_known_nodes(ir: IR):
    with pytest.raises(KeyError, match=r"no node 'ghost' \(nodes: camera, planner, controller, logger\)"):
        ir.node("ghost")


# ---------------------------------------------------------------------------------------------
# Round trip
# ---------------------------------------------------------------------------------------------
def test_round_trip_build_save_load_run_gives_the_identical_trace(tmp_path: Path):
    pipe = ir_flows.build()
    ir = pipe.build_ir()
    path = ir.save(tmp_path / "small.ir.json")
    loaded = IR.load(path)
    assert loaded == ir
    rebuilt = Pipeline.from_ir(loaded)
    assert rebuilt.build_ir().to_json() == ir.to_json()

    original = pipe.run(duration=2.0)
    again = rebuilt.run(duration=2.0)
    assert len(original.events) > 100
    assert {s.node for s in original.steps} == {"camera", "planner", "controller", "logger"}
    assert again == original
    assert again.digest() == original.digest()
    assert again.first_difference(original) is None


def test_round_trip_from_json_string(ir: IR):
    assert IR.from_json(ir.to_json()) == ir


def _same(a, b) -> bool:
    """Equal, of the same types all the way down (arrays: dtype, shape and contents)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and bool((a == b).all())
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    return a == b or (a != a and b != b)  # NaN


ARGUMENTS = [
    (0.5, 0.25),
    [(1, 2), ((3,), [4, {"k": (5,)}])],
    np.arange(6, dtype=np.float32).reshape(2, 3),
    np.int16(-7),
    b"\x00raw",
    float("inf"),
    {1: "int key"},
    {"$tuple": "a user's dict, not a tag"},
    ir_flows.Frame(brightness=0.5, k=3),
    {"plain": [1, 2.5, "x", None, True]},
]


@pytest.mark.parametrize("value", ARGUMENTS, ids=lambda v: type(v).__name__)
def test_a_constructor_argument_comes_back_from_the_ir_as_it_was_given(tmp_path: Path, value):
    """DESIGN §6: a worker rebuilds a flow from msgpack-able arguments, so what JSON would turn
    into something else (a tuple into a list) or cannot hold is tagged in the IR, and a flow
    rebuilt from a saved IR gets the very value, type and all, as in-process."""
    with Pipeline("args") as pipe:
        ir_flows.Tool(value) @ Rate(hz=10)
    node = pipe.build_ir().node("tool")
    assert node["rebuildable"] is True, node
    ir = IR.load(pipe.build_ir().save(tmp_path / "args.ir.json"))
    (flow,) = Pipeline.from_ir(ir).flows
    assert _same(flow.model, value), (flow.model, value)


def test_json_values_stay_readable_in_the_ir_and_tuples_say_so():
    with Pipeline("readable") as pipe:
        ir_flows.Tool({"gains": [0.5, 1], "shape": (64, 48)}) @ Rate(hz=10)
    params = pipe.build_ir().node("tool")["params"]
    assert params == {"model": {"gains": [0.5, 1], "shape": {"$tuple": [64, 48]}}}


@pytest.mark.parametrize("bad, says", [
    ({"$msgpack": "not base64!"}, r"params\.model is a \$msgpack value that does not decode"),
    ({"$msgpack": "kgE="}, r"params\.model is a \$msgpack value that does not decode"),  # cut short
    ({"$tuple": [1], "x": 2}, r"params\.model is an object with reserved key\(s\) \['\$tuple'\]"),
    ({"$set": [1]}, r"params\.model is an object with reserved key\(s\) \['\$set'\]"),
])
def test_a_malformed_tagged_argument_is_refused_naming_node_and_argument(bad, says):
    with Pipeline("tagged") as pipe:
        ir_flows.Tool(1) @ Rate(hz=10)
    doc = json.loads(pipe.build_ir().to_json())
    doc["nodes"][0]["params"]["model"] = bad
    with pytest.raises(IRError, match=r"node 'tool': " + says):
        Pipeline.from_ir(IR(doc))


def test_a_tagged_dataclass_does_not_make_the_rebuild_import_its_module(tmp_path: Path):
    """An IR may not make a worker import code (its allowlist decides what it imports): a
    tagged dataclass that is no registered value type is refused, naming it."""
    import base64

    import msgpack

    from retriever.codec import packb

    with Pipeline("stray") as pipe:
        ir_flows.Tool(1) @ Rate(hz=10)
    doc = json.loads(pipe.build_ir().to_json())
    tagged = base64.b64encode(msgpack.packb(msgpack.ExtType(4, packb(["tests.never_imported_module:Stray", {"x": 1}])))).decode()
    doc["nodes"][0]["params"]["model"] = {"$msgpack": tagged}
    with pytest.raises(IRError, match=r"params\.model is a \$msgpack value that does not decode .*"
                                      r"tests\.never_imported_module"):
        Pipeline.from_ir(IR(doc))


def test_rebuilt_pipeline_is_independent_of_an_enclosing_with_block(ir: IR):
    with Pipeline("outer") as outer:
        rebuilt = Pipeline.from_ir(ir)
    assert outer.flows == []
    assert len(rebuilt.flows) == 4


# ---------------------------------------------------------------------------------------------
# An IR is code: what is checked before anything is imported (issue 17 §3)
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [["/x"], {"a b": "/x"}, {"flows": 3}], ids=repr)
def test_load_bad_module_folders(tmp_path: Path, doc: dict, bad):
    doc["metadata"]["module_folders"] = bad
    with pytest.raises(IRError, match=re.escape(f"metadata.module_folders: expected an object of module name: "
                                                f"folder, got {bad!r}")):
        _load(tmp_path, json.dumps(doc))


@pytest.mark.parametrize("bad", [["tests.ir_flows"], {"a b": "0" * 64}, {"tests.ir_flows": "0" * 63},
                                 {"tests.ir_flows": "A" * 64}, {"tests.ir_flows": 7}], ids=repr)
def test_load_bad_code_hashes(tmp_path: Path, doc: dict, bad):
    doc["metadata"]["code_sha256"] = bad
    with pytest.raises(IRError, match=re.escape("metadata.code_sha256: expected an object of module name: sha256 "
                                                f"(64 lowercase hex digits), got {bad!r}")):
        _load(tmp_path, json.dumps(doc))


def test_an_ir_records_the_sha256_of_each_flow_modules_file(tmp_path: Path):
    from retriever.loading import load_pipeline

    (tmp_path / "hashed_flows.py").write_text(QUICKSTART.read_text(encoding="utf-8") + "# a copy\n", encoding="utf-8")
    try:
        doc = load_pipeline(str(tmp_path / "hashed_flows.py")).build_ir().doc
    finally:
        sys.modules.pop("hashed_flows", None)
    digest = hashlib.sha256((tmp_path / "hashed_flows.py").read_bytes()).hexdigest()
    assert doc["metadata"]["code_sha256"] == {"hashed_flows": digest}


def test_an_ir_of_a_script_records_the_folder_of_its_flows(tmp_path: Path):
    from retriever.loading import load_pipeline

    script = tmp_path / "folder_flows.py"
    script.write_text("from tests.ir_flows import build\npipe = build()\n", encoding="utf-8")
    (tmp_path / "local_flows.py").write_text(
        "from retriever import Flow\nclass Local(Flow):\n    def step(self):\n        return {'x': 1}\n",
        encoding="utf-8")
    assert "module_folders" not in load_pipeline(str(script)).build_ir().doc["metadata"]  # tests.ir_flows: importable
    script.write_text("from retriever import Flow, Pipeline, Rate\n"
                      "class Here(Flow):\n    def step(self):\n        return {'x': 1}\n"
                      "with Pipeline('here') as pipe:\n    Here() @ Rate(hz=1)\n", encoding="utf-8")
    sys.modules.pop("folder_flows", None)
    ir = load_pipeline(str(script)).build_ir()
    assert ir.doc["metadata"]["module_folders"] == {"folder_flows": str(tmp_path)}
    assert IR.from_json(ir.to_json()) == ir


@pytest.mark.parametrize("bad", ["tests.ir_flows", "tests.ir_flows:", ":Camera", "os.system('x'):A", "a b:C",
                                 "tests.ir_flows:Camera()", "tests..ir_flows:Camera", "a:B:C", 3, None], ids=repr)
def test_a_type_must_be_module_colon_dotted_identifiers(tmp_path: Path, doc: dict, bad):
    doc["nodes"][1]["type"] = bad
    with pytest.raises(IRError, match=re.escape(f"node 'planner'.type: expected 'module:Class' (dotted identifiers, "
                                                f"e.g. 'my_robot.flows:Camera'), got {bad!r}")):
        _load(tmp_path, json.dumps(doc))


@pytest.mark.parametrize("port", ["a/b", "a.b", "", "1st", "x y"])
def test_a_port_that_is_no_port_name_is_refused(tmp_path: Path, doc: dict, port):
    """A port is one segment of the log's topic data/<node>/<port> (issue 39)."""
    doc["nodes"][1]["outputs"][port] = "Any"
    with pytest.raises(IRError, match=re.escape(f"node 'planner'.outputs: {port!r} is not a port name")):
        _load(tmp_path, json.dumps(doc))


def _side_effect_module(tmp_path: Path, monkeypatch) -> tuple[str, Path]:
    """A module on the import path whose import, and whose class's construction, leave a mark."""
    name = f"ir_side_effect_{tmp_path.name.replace('-', '_')}"
    marks = tmp_path / "marks"
    (tmp_path / f"{name}.py").write_text(
        "from pathlib import Path\n"
        f"MARKS = Path({str(marks)!r})\n"
        "with MARKS.open('a') as f:\n    f.write('imported\\n')\n"
        "class NotAFlow:\n"
        "    def __init__(self, *args, **kwargs):\n"
        "        with MARKS.open('a') as f:\n            f.write('called\\n')\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)
    return name, marks


def test_no_module_is_imported_while_any_node_has_a_problem(tmp_path: Path, doc: dict, monkeypatch):
    """``this:Camera`` printed the Zen of Python: the first node's module was imported before a
    later node's problem was found."""
    name, marks = _side_effect_module(tmp_path, monkeypatch)
    doc["nodes"][0]["type"] = f"{name}:NotAFlow"
    doc["nodes"][3]["params"] = {"bad": {"$msgpack": "not base64!"}}
    with pytest.raises(IRError, match=r"node 'logger': params\.bad is a \$msgpack value that does not decode"):
        Pipeline.from_ir(IR(doc))
    assert not marks.exists() and name not in sys.modules


def test_a_type_that_is_not_a_flow_is_refused_before_it_is_called(tmp_path: Path, doc: dict, monkeypatch):
    name, marks = _side_effect_module(tmp_path, monkeypatch)
    doc["nodes"][0]["type"] = f"{name}:NotAFlow"
    with pytest.raises(IRError, match=re.escape(f"node 'camera': {name}:NotAFlow is not a Flow class")):
        Pipeline.from_ir(IR(doc))
    assert marks.read_text() == "imported\n"


def test_a_module_not_on_the_import_path_is_named_with_a_hint(doc: dict):
    doc["nodes"][2]["type"] = "no_such_flows_module.sub:Camera"
    with pytest.raises(IRError, match=re.escape(
            "node 'controller': cannot import no_such_flows_module.sub:Camera (No module named "
            "'no_such_flows_module')\n    hint: run from the folder that holds "
            "no_such_flows_module.py (or the no_such_flows_module package), or add that folder to PYTHONPATH")):
        Pipeline.from_ir(IR(doc))


# ---------------------------------------------------------------------------------------------
# Flows that cannot be rebuilt from the IR
# ---------------------------------------------------------------------------------------------
def _tool_pipeline() -> Pipeline:
    with Pipeline("tooled") as pipe:
        ir_flows.Tool(object(), steps=2) @ Rate(hz=10)
    return pipe


def test_unrebuildable_flow_is_marked_in_the_ir_with_the_argument_named():
    pipe = _tool_pipeline()
    node = pipe.build_ir().node("tool")
    assert node["rebuildable"] is False
    assert "'model'" in node["rebuild_problem"]
    assert "object" in node["rebuild_problem"]
    assert node["params"]["steps"] == 2
    assert node["params"]["model"] == {"$unserializable": "builtins.object"}


def test_unrebuildable_flow_still_runs_in_process():
    trace = _tool_pipeline().run(duration=0.25)
    assert trace.values_of("tool", "k") == [2, 2, 2]


def test_from_ir_refuses_an_unrebuildable_flow_naming_node_and_argument():
    ir = _tool_pipeline().build_ir()
    with pytest.raises(IRError, match=r"node 'tool' cannot be rebuilt from the IR: argument 'model'"):
        Pipeline.from_ir(ir)


def test_rebuildable_nodes_are_marked(ir: IR):
    assert all(n["rebuildable"] is True and "rebuild_problem" not in n and "rebuild_needs_main" not in n
               for n in ir.nodes)


def test_a_flow_class_in_main_is_marked_as_needing_only_the_main_script():
    """A worker that imports the main script (the zenoh backend) can rebuild such a flow, so the
    IR says when that is its only problem, and not when its arguments are a problem too."""
    in_main = type("Tool", (ir_flows.Tool,), {"__module__": "__main__", "__qualname__": "Tool"})
    with Pipeline("mains") as pipe:
        in_main(1, steps=2).named("plain") @ Rate(hz=10)
        in_main(object(), steps=2).named("opaque") @ Rate(hz=10)
    ir = pipe.build_ir()
    plain, opaque = ir.node("plain"), ir.node("opaque")
    assert plain["rebuildable"] is False and plain["rebuild_needs_main"] is True
    assert "lives in __main__" in plain["rebuild_problem"]
    # the way out the README gives, in the error `retriever run IR.json` prints
    assert re.search(r"write the IR with `retriever ir \S+\.py --out FILE\.json`", plain["rebuild_problem"])
    assert opaque["rebuildable"] is False and "rebuild_needs_main" not in opaque
    assert "'model'" in opaque["rebuild_problem"]


def test_from_ir_with_an_unimportable_type_names_the_node(doc: dict):
    doc["nodes"][0]["type"] = "tests.no_such_module:Camera"
    with pytest.raises(IRError, match=r"node 'camera': cannot import tests\.no_such_module:Camera"):
        Pipeline.from_ir(IR(doc))


def test_from_ir_with_a_type_that_is_not_a_flow(doc: dict):
    doc["nodes"][0]["type"] = "tests.ir_flows:Frame"
    with pytest.raises(IRError, match=r"node 'camera': tests\.ir_flows:Frame is not a Flow class"):
        Pipeline.from_ir(IR(doc))


def test_from_ir_when_the_constructor_raises_names_the_node(doc: dict):
    doc["nodes"][1]["params"] = {"steps": 4, "gains": 5}
    with pytest.raises(IRError, match=r"node 'planner': tests\.ir_flows:Planner\(\*\*\{.*\}\) raised TypeError"):
        Pipeline.from_ir(IR(doc))


def test_from_ir_refuses_params_the_constructor_does_not_take(doc: dict):
    # A misspelt parameter must not be dropped silently: the flow would run with the default.
    doc["nodes"][2]["params"] = {"gian": 0.9}
    with pytest.raises(IRError, match=r"node 'controller'.*'gian'"):
        Pipeline.from_ir(IR(doc))


# ---------------------------------------------------------------------------------------------
# IR.load: every malformed document is an IRError naming the problem
# ---------------------------------------------------------------------------------------------
def test_load_non_json(tmp_path: Path):
    with pytest.raises(IRError, match=r"invalid IR \(.*pipeline\.ir\.json\):\n"
                                      r"  - not valid JSON: .* at line 1, column 2"):
        _load(tmp_path, "{nodes: []}")


def test_load_json_array(tmp_path: Path):
    with pytest.raises(IRError, match=r"the document must be a JSON object, got list"):
        _load(tmp_path, "[1, 2, 3]")


def test_load_missing_keys_lists_each_one(tmp_path: Path):
    with pytest.raises(IRError) as info:
        _load(tmp_path, json.dumps({"version": "1.0.0", "nodes": []}))
    assert info.value.problems == [
        "'metadata' is missing (expected an object)",
        "'edges' is missing (expected a list)",
        "'topology' is missing (expected an object)",
    ]


def test_load_missing_version(tmp_path: Path, doc: dict):
    del doc["version"]
    with pytest.raises(IRError, match=r"'version' is missing \(expected \"1\.4\.0\"\)"):
        _load(tmp_path, json.dumps(doc))


def test_an_ir_of_version_1_1_still_loads(tmp_path: Path, doc: dict):
    """1.2.0, 1.3.0 and 1.4.0 only added optional keys (metadata.module_folders, metadata.code_sha256,
    a node's config.process)."""
    doc["version"] = "1.1.0"
    del doc["metadata"]["code_sha256"]
    assert Pipeline.from_ir(_load(tmp_path, json.dumps(doc))).build_ir().doc["version"] == "1.4.0"


def test_load_wrong_version(tmp_path: Path, doc: dict):
    doc["version"] = "2.0.0"
    with pytest.raises(IRError, match=r"version '2\.0\.0' is not supported by this Retriever \(it reads 1\.4\.0\)"
                                      r"; rebuild the IR"):
        _load(tmp_path, json.dumps(doc))


def test_load_unknown_adapter(tmp_path: Path, doc: dict):
    doc["edges"][1]["adapter"] = {"freshest": {}}
    with pytest.raises(IRError, match=r"edges\[1\]\.adapter: unknown sync policy 'freshest'; known: action_chunking, "
                                      r"exact, latest, latest_distinct, queue, window"):
        _load(tmp_path, json.dumps(doc))


def test_load_adapter_with_bad_parameters(tmp_path: Path, doc: dict):
    doc["edges"][0]["adapter"] = {"window": {"buffer_size": 3, "size": 4}}
    with pytest.raises(IRError, match=r"edges\[0\]\.adapter: adapter window: bad parameters"):
        _load(tmp_path, json.dumps(doc))


def test_load_unknown_clock_kind(tmp_path: Path, doc: dict):
    doc["nodes"][1]["config"]["clock"] = {"Sometimes": {"hz": 3}}
    with pytest.raises(IRError, match=r"node 'planner'\.config\.clock: unknown clock kind 'Sometimes'; "
                                      r"expected Rate, Trigger or Hybrid"):
        _load(tmp_path, json.dumps(doc))


def test_load_impossible_rate(tmp_path: Path, doc: dict):
    doc["nodes"][0]["config"]["clock"] = {"Rate": {"hz": 0}}
    with pytest.raises(IRError, match=r"node 'camera'\.config\.clock: Rate\(hz=0\): hz must be a finite number > 0"):
        _load(tmp_path, json.dumps(doc))


def test_load_reports_every_number_out_of_range_at_once(tmp_path: Path, doc: dict):
    """NaN and infinite latency or delay, a rate faster than 1 GHz, times past int64 nanoseconds and
    a bad max_microsteps passed validation (or ran into a bare OverflowError, or hung) before."""
    doc["metadata"]["max_microsteps"] = 0
    doc["metadata"]["deadline"] = 1e300
    doc["nodes"][0]["config"]["clock"] = {"Rate": {"hz": 1e300}}
    doc["nodes"][1]["config"]["latency"] = float("nan")
    doc["nodes"][2]["config"]["latency"] = 1e300
    doc["edges"][0]["delay"] = float("inf")
    doc["edges"][1]["delay"] = 1e12
    doc["edges"][2]["deadline"] = float("-inf")
    text = json.dumps(doc)  # JSON readers accept NaN and Infinity, and so does json.loads
    assert "NaN" in text and "Infinity" in text
    with pytest.raises(IRError) as info:
        _load(tmp_path, text)
    too_long = "must be at most 9.223e+09 s (about 292 years: times are int64 nanoseconds)"
    assert info.value.problems == [
        f"metadata.deadline: deadline {too_long}, got 1e+300",
        "metadata.max_microsteps: max_microsteps must be an integer from 1 to 2**63 - 1 (how many microsteps one "
        "instant may run before the run stops with a Zeno-loop error), got 0",
        "node 'camera'.config.clock: Rate(hz=1e+300): hz must be at most 1e+09 (a tick period of at least 1 ns: "
        "ticks are integer nanoseconds), got 1e+300",
        "node 'planner'.config.latency: latency must be a finite number of seconds >= 0, got nan",
        f"node 'controller'.config.latency: latency {too_long}, got 1e+300",
        "edges[0].delay: delay must be a finite number of seconds >= 0, got inf",
        f"edges[1].delay: delay {too_long}, got 1000000000000.0",
        "edges[2].deadline: deadline must be a finite number of seconds >= 0, got -inf",
    ]


@pytest.mark.parametrize("value", ["1000", 1.5, True, -3, None], ids=repr)
def test_load_bad_max_microsteps(tmp_path: Path, doc: dict, value):
    doc["metadata"]["max_microsteps"] = value
    with pytest.raises(IRError, match=r"metadata\.max_microsteps: max_microsteps must be an integer from 1 to "
                                      r"2\*\*63 - 1 .*, got " + re.escape(repr(value))):
        _load(tmp_path, json.dumps(doc))


def test_load_edge_naming_an_unknown_node(tmp_path: Path, doc: dict):
    doc["edges"][0]["source"]["node"] = "ghost"
    with pytest.raises(IRError, match=r"edges\[0\]\.source: unknown node 'ghost'"):
        _load(tmp_path, json.dumps(doc))


def test_load_edge_naming_an_unknown_port(tmp_path: Path, doc: dict):
    doc["edges"][2]["destination"]["port"] = "ghost"
    with pytest.raises(IRError, match=r"edges\[2\]\.destination: node 'planner' has no input port 'ghost'"):
        _load(tmp_path, json.dumps(doc))


def test_load_unknown_on_error(tmp_path: Path, doc: dict):
    doc["nodes"][2]["config"]["on_error"] = "ignore"
    with pytest.raises(IRError, match=r"node 'controller'\.config\.on_error: 'ignore' is not one of "
                                      r"stop, skip_tick, restart"):
        _load(tmp_path, json.dumps(doc))


def test_load_duplicate_node_id(tmp_path: Path, doc: dict):
    doc["nodes"][1]["id"] = "camera"
    with pytest.raises(IRError, match=r"node 'camera': duplicate node id"):
        _load(tmp_path, json.dumps(doc))


def test_load_missing_file(tmp_path: Path):
    with pytest.raises(IRError, match=r"cannot read the file: No such file or directory"):
        IR.load(tmp_path / "absent.json")


def test_load_binary_file(tmp_path: Path):
    path = tmp_path / "binary.json"
    path.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(IRError, match=r"not a text file \(expected UTF-8 JSON\)"):
        IR.load(path)


def test_load_reports_every_problem_at_once(tmp_path: Path, doc: dict):
    doc["nodes"][0]["config"]["clock"] = {"Sometimes": {}}
    doc["nodes"][2]["config"]["latency"] = -1
    doc["edges"][0]["adapter"] = {"freshest": {}}
    doc["edges"][1]["source"]["node"] = "ghost"
    doc["edges"][3]["qsize"] = 0
    with pytest.raises(IRError) as info:
        _load(tmp_path, json.dumps(doc))
    err = info.value
    assert err.source.endswith("pipeline.ir.json")
    assert len(err.problems) == 5
    for expected in ("node 'camera'.config.clock: unknown clock kind 'Sometimes'",
                     "node 'controller'.config.latency: latency must be a finite number of seconds >= 0, got -1",
                     "edges[0].adapter: unknown sync policy 'freshest'",
                     "edges[1].source: unknown node 'ghost'",
                     "edges[3].qsize: expected an integer >= 1, got 0"):
        assert any(p.startswith(expected) for p in err.problems), expected
        assert expected in str(err)
    assert str(err).count("\n  - ") == 5


def test_ir_constructor_validates_too(doc: dict):
    broken = copy.deepcopy(doc)
    broken["version"] = "0.9.0"
    with pytest.raises(IRError, match=r"invalid IR \(<memory>\)"):
        IR(broken)


# ---------------------------------------------------------------------------------------------
# Pictures
# ---------------------------------------------------------------------------------------------
def test_visualize_dot_contains_every_node_and_edge(ir: IR):
    dot = ir.visualize("dot")
    assert dot.startswith('digraph "small" {')
    for n in ir.nodes:
        assert f'"{n["id"]}" [label="{n["id"]}' in dot
    for e in ir.edges:
        assert f'"{e["source"]["node"]}" -> "{e["destination"]["node"]}" [label="{e["source"]["port"]} → ' \
               f'{e["destination"]["port"]}' in dot
    assert "delay 0.02 s" in dot
    assert dot.count(" -> ") == len(ir.edges)


def test_visualize_mermaid_contains_every_node_and_edge(ir: IR):
    mermaid = ir.visualize("mermaid")
    assert mermaid.startswith("flowchart LR\n")
    for n in ir.nodes:
        assert f'  {n["id"]}["{n["id"]}<br/>' in mermaid
    for e in ir.edges:
        assert f'  {e["source"]["node"]} -->|"{e["source"]["port"]} → {e["destination"]["port"]}<br/>' in mermaid
        assert f'| {e["destination"]["node"]}\n' in mermaid
    assert mermaid.count("-->") == len(ir.edges)


def test_visualize_unknown_format(ir: IR):
    with pytest.raises(ValueError, match=r"unknown format 'svg'; expected 'dot' or 'mermaid'"):
        ir.visualize("svg")


# Found by benchmarks/fuzz.py: IRs that passed validation and then made Pipeline.from_ir raise
# ValueError, TypeError or OverflowError, and JSON nested past the recursion limit.
def _broken(change) -> str:
    doc = ir_flows.build().build_ir().doc
    change(doc)
    return json.dumps(doc, allow_nan=True)


def _node(doc: dict, nid: str = "planner") -> dict:
    return next(n for n in doc["nodes"] if n["id"] == nid)


@pytest.mark.parametrize("change, problem", [
    (lambda d: _node(d)["config"].update(latency=float("nan")), r"node 'planner'\.config\.latency: latency must be a finite number of seconds >= 0, got nan"),
    (lambda d: d["edges"][0].update(delay=float("inf")), r"edges\[0\]\.delay: delay must be a finite number of seconds >= 0, got inf"),
    (lambda d: d["metadata"].update(deadline=10**400), r"metadata\.deadline: deadline must be at most 9\.223e\+09 s"),
    (lambda d: d["metadata"].update(max_microsteps=0), r"metadata\.max_microsteps: max_microsteps must be an integer from 1 .*, got 0"),
    (lambda d: d["metadata"].update(name=""), r"metadata\.name: expected the pipeline name \(a non-empty string\)"),
    (lambda d: d["nodes"][0].update(id="../../etc/x"), r"nodes\[0\]\.id: expected a node name of letters, digits"),
    (lambda d: _node(d, "logger")["config"].update(clock={"Trigger": {"ports": True}}), r"node 'logger'\.config\.clock"),
    (lambda d: _node(d, "camera")["config"].update(clock={"Rate": {"hz": 10**400}}), r"node 'camera'\.config\.clock"),
    (lambda d: _node(d, "camera")["config"].update(spin=1.0),
     r"node 'camera'\.config\.spin: expected seconds from 0 to 0\.001, got 1\.0"),
    (lambda d: _node(d, "camera")["config"].update(spin=float("nan")), r"node 'camera'\.config\.spin: .*, got nan"),
    (lambda d: _node(d, "camera")["config"].update(spin="fast"), r"node 'camera'\.config\.spin: .*, got 'fast'"),
    (lambda d: _node(d, "camera")["config"].update(spin=True), r"node 'camera'\.config\.spin: .*, got True"),
    (lambda d: _node(d, "camera")["config"].update(process="a b"),
     r"node 'camera'\.config\.process: expected a name \(letters, digits, _ and -, at most 128\), got 'a b'"),
    (lambda d: _node(d, "camera")["config"].update(process="p" * 129), r"node 'camera'\.config\.process: .*at most 128"),
    (lambda d: d["nodes"][0].update(id="n" * 129), r"nodes\[0\]\.id: expected a node name .*, at most 128 \(it becomes "
                                                   r"a key-space segment and names files\)"),
    (lambda d: _node(d, "camera")["config"].update(process=7), r"node 'camera'\.config\.process: .*, got 7"),
])
def test_an_ir_value_no_pipeline_can_take_is_an_ir_error(change, problem):
    with pytest.raises(IRError, match=problem):
        Pipeline.from_ir(IR.from_json(_broken(change)))


def test_json_nested_past_the_recursion_limit_is_an_ir_error():
    with pytest.raises(IRError, match="nests arrays or objects deeper than Python's recursion limit"):
        IR.from_json('{"nodes": ' + "[" * 100_000 + "]" * 100_000 + "}")


HOSTILE = 'x"; n [shape=none image="/etc/passwd"]; "\\ |]) <b>#amp;`\n'


def _hostile(doc: dict) -> IR:
    """``doc`` with every text a picture shows that an IR file may set made hostile: the pipeline's
    name, a port's name on both ends of its edge and in a Trigger clock, a node id Mermaid reads
    as a statement. A port name like that is refused by the IR's own check (one segment: letters,
    digits, _ and -), so the document skips it here: the picture escapes what it shows all the same."""
    doc["metadata"]["name"] = HOSTILE
    port = "p" + HOSTILE
    controller, logger = (next(n for n in doc["nodes"] if n["id"] == nid) for nid in ("controller", "logger"))
    controller["outputs"] = {port: "float"}
    logger["inputs"] = {port: "Any"}
    logger["config"]["clock"] = {"Trigger": {"ports": [port]}}
    for e in doc["edges"]:
        for end in ("source", "destination"):
            if e[end]["port"] == "position":
                e[end]["port"] = port
            if e[end]["node"] == "logger":
                e[end]["node"] = "end"
    logger["id"] = "end"
    with pytest.raises(IRError, match="is not a port name"):
        IR.from_json(json.dumps(doc))
    ir = object.__new__(IR)
    ir.doc = json.loads(json.dumps(doc))
    return ir


DOT_STRING = r'"(?:[^"\\\n]|\\.)*"'


def test_visualize_dot_escapes_every_text_from_the_ir(doc: dict):
    # issue 40 item 10: a name of `x"; n [image="/etc/passwd"]` made Graphviz read a local file
    dot = _hostile(doc).visualize("dot")
    lines = dot.splitlines()
    assert len(lines) == 3 + 4 + 4 + 1, dot  # header, 4 nodes, 4 edges, closing brace: no line more
    skeleton = [re.sub(DOT_STRING, "S", line) for line in lines]
    assert skeleton[0] == "digraph S {" and skeleton[-1] == "}"
    assert skeleton[3:7] == ["  S [label=S];"] * 4, skeleton
    assert skeleton[7:11] == ["  S -> S [label=S];"] * 4, skeleton
    assert "image=" not in "".join(skeleton)
    # the text is all there, shown as it is
    assert lines[0] == 'digraph "x\\"; n [shape=none image=\\"/etc/passwd\\"]; \\"\\\\ |]) <b>#amp;`\\n" {'
    assert 'p x\\"; n [shape=none' not in dot and 'px\\"; n [shape=none image=\\"/etc/passwd\\"]' in dot


def test_visualize_mermaid_escapes_every_text_from_the_ir(doc: dict):
    mermaid = _hostile(doc).visualize("mermaid")
    lines = mermaid.splitlines()
    assert len(lines) == 1 + 4 + 4, mermaid
    label = r'"[A-Za-z0-9 _\-.,:=+*/@?!\'→#;]*(?:<br/>[A-Za-z0-9 _\-.,:=+*/@?!\'→#;]*)*"'
    for line in lines[1:5]:
        assert re.fullmatch(rf"  [A-Za-z_][A-Za-z0-9_]*\[{label}\]", line), line
    for line in lines[5:]:
        assert re.fullmatch(rf"  [A-Za-z_][A-Za-z0-9_]* -->\|{label}\| [A-Za-z_][A-Za-z0-9_]*", line), line
    # 'end' closes a Mermaid subgraph: that node gets an id of its own, its label still says end
    assert '  node_3["end<br/>Trigger#40;px#34;#59; n ' in mermaid and " end" not in mermaid.replace('"end', "")
    assert "#34;#92; #124;#93;#41; #60;b#62;#35;amp#59;#96;#10;" in mermaid


def test_an_integer_too_long_to_read_is_named_by_node_and_param(doc: dict, tmp_path: Path):
    # issue 40 item 12: json.loads raised 'ValueError: Exceeds the limit (4300 digits) ...'
    limit = sys.get_int_max_str_digits()
    doc["nodes"][0]["params"] = {"gain": 7, "table": [1, {"big": 0}]}
    text = json.dumps(doc).replace('"big": 0', '"big": -' + "9" * (limit + 700))
    text = text.replace('"gain": 7', '"gain": ' + "1" * 5000)
    text = text.replace('"qsize": 10', '"qsize": ' + "2" * 5000, 1)
    problems = (rf"^invalid IR \(.*pipeline\.ir\.json\):\n"
                rf"  - edges\[0\]\.qsize: an integer of 5000 digits; at most {limit} are read\n"
                rf"    hint: write so large a number as a string and convert it in the flow\n"
                rf"  - node 'camera'\.params\.gain: an integer of 5000 digits; at most {limit} are read\n"
                rf"    hint: .*\n"
                rf"  - node 'camera'\.params\.table\[1\]\.big: an integer of {limit + 700} digits; at most "
                rf"{limit} are read\n    hint: .*$")
    with pytest.raises(IRError, match=problems):
        _load(tmp_path, text)


def test_a_flows_process_name_goes_through_the_ir(tmp_path: Path):
    """configure(process=): in the node's config, and back on the flow rebuilt from it."""
    pipe = ir_flows.build()
    node = next(iter(pipe.compile().nodes.values()))
    node.flow.configure(process="perception")
    doc = json.loads(pipe.build_ir().to_json())
    assert [n["id"] for n in doc["nodes"] if n["config"].get("process") == "perception"] == [node.id]
    rebuilt = Pipeline.from_ir(_load(tmp_path, json.dumps(doc))).compile()
    assert {nid: n.settings.process for nid, n in rebuilt.nodes.items() if n.settings.process} == {node.id: "perception"}
    with pytest.raises(ValueError, match=r"configure\(process='a b'\): a process name must be"):
        node.flow.configure(process="a b")
    with pytest.raises(ValueError, match=r"a process name must be .*at most 128"):
        node.flow.configure(process="p" * 129)
    node.flow.configure(process="p" * 128)


def test_a_node_id_made_from_a_long_class_name_is_cut_to_a_valid_one():
    """A node's id names files of a run (``<node>.handover``, at most 255 bytes): a class name past
    NAME_MAX characters gives ids of NAME_MAX, still each its own, that the IR takes."""
    long = type("Long" * 40, (ir_flows.Camera,), {})
    with Pipeline("long_names") as pipe:
        long() @ Rate(hz=1)
        long() @ Rate(hz=1)
    ids = [n["id"] for n in pipe.build_ir().doc["nodes"]]
    assert [len(i) for i in ids] == [NAME_MAX, NAME_MAX] and len(set(ids)) == 2, ids
    assert ids[1].endswith("_2")
