"""Placement (issue 18): the placement file's format, where ``place`` puts each node, and the
problems that refuse a placement before anything starts — every one of them at once."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import retriever
from retriever import PlacementError, RetrieverError
from retriever.errors import Problem
from retriever.placement import Constraint, LiveDaemon, Placement, load_placement, parse_placement, place

EXAMPLE = Path(__file__).resolve().parents[1] / "deploy" / "placement.example.toml"
SETTINGS = settings(max_examples=300, deadline=None)


def worker(name: str, *labels: str, nodes: int = 0, host: str | None = None) -> LiveDaemon:
    return LiveDaemon(name, frozenset(labels), nodes, host)


def rules(**nodes) -> Placement:
    """A placement from keyword arguments: a string pins, a set asks for labels, a tuple is (worker, labels)."""
    def constraint(value):
        if isinstance(value, str):
            return Constraint(worker=value)
        if isinstance(value, tuple):
            return Constraint(value[0], frozenset(value[1]))
        return Constraint(labels=frozenset(value))
    return Placement({node: constraint(value) for node, value in nodes.items()}, "placement.toml")


def write(tmp_path: Path, text: str | bytes) -> Path:
    path = tmp_path / "placement.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def problems_of(excinfo) -> list[str]:
    return [str(p) for p in excinfo.value.problems]


# ---------------------------------------------------------------------------------------------
# Where nodes go
# ---------------------------------------------------------------------------------------------
def test_the_example_file_loads_and_places():
    placement = load_placement(EXAMPLE)
    assert placement.source == str(EXAMPLE)
    assert placement.nodes == {"camera": Constraint(worker="arm-pc"), "policy": Constraint(labels=frozenset({"gpu"})),
                               "planner": Constraint("gpu-box", frozenset({"gpu", "cuda"}))}
    assert placement.processes == {"viz": "viewers"}
    workers = [worker("arm-pc", "camera"), worker("gpu-box", "gpu", "cuda"), worker("spare")]
    assert place(["camera", "policy", "planner", "arm", "viz", "logger"], placement, workers) == {
        "camera": "arm-pc", "policy": "gpu-box", "planner": "gpu-box", "arm": "spare", "viz": "spare",
        "logger": "arm-pc"}


def test_a_pinned_node_goes_to_its_worker_whatever_its_load():
    workers = [worker("busy", nodes=50), worker("idle")]
    assert place(["camera"], rules(camera="busy"), workers) == {"camera": "busy"}


def test_a_node_with_labels_goes_to_the_least_loaded_worker_that_has_them_all():
    workers = [worker("a", "gpu", nodes=3), worker("b", "gpu", "cuda", nodes=2), worker("c", "gpu", "cuda", nodes=1),
               worker("d", "cuda")]
    assert place(["policy"], rules(policy={"gpu", "cuda"}), workers) == {"policy": "c"}


def test_a_pin_with_labels_goes_to_its_worker_when_it_has_them():
    workers = [worker("gpu-box", "gpu", "cuda", nodes=9), worker("other", "gpu", "cuda")]
    assert place(["planner"], rules(planner=("gpu-box", {"gpu"})), workers) == {"planner": "gpu-box"}


def test_without_a_placement_nodes_spread_by_load_counting_what_workers_already_run():
    workers = [worker("a", nodes=2), worker("b"), worker("c", nodes=1)]
    assert place(["n1", "n2", "n3", "n4", "n5"], None, workers) == {
        "n1": "b", "n2": "b", "n3": "c", "n4": "a", "n5": "b"}


def test_with_equal_loads_unlisted_nodes_differ_by_at_most_one_per_worker():
    result = place([f"n{i}" for i in range(10)], None, [worker("x"), worker("y"), worker("z")])
    assert sorted(list(result.values()).count(w) for w in "xyz") == [3, 3, 4]


def test_ties_go_to_the_first_worker_name():
    assert place(["only"], None, [worker("zed"), worker("alpha"), worker("mid")]) == {"only": "alpha"}


def test_pins_are_placed_first():
    # 'aa' (labels) would take 'a' on the name tie; the pin of 'zz' to 'a' counts first, so 'aa' goes to 'c'
    workers = [worker("a", "gpu"), worker("c", "gpu")]
    assert place(["aa", "zz"], rules(aa={"gpu"}, zz="a"), workers) == {"aa": "c", "zz": "a"}


def test_the_most_constrained_nodes_are_placed_before_the_others():
    # 'x2' can only go to 'a'; placed first, it leaves 'b' the least loaded for 'x1', then 'free' takes 'c'
    workers = [worker("a", "gpu", "cuda"), worker("b", "gpu"), worker("c")]
    assert place(["free", "x1", "x2"], rules(x1={"gpu"}, x2={"gpu", "cuda"}), workers) == {
        "free": "c", "x1": "b", "x2": "a"}


def test_the_result_follows_the_order_of_the_node_ids_and_nothing_else_depends_on_order():
    nodes = ["planner", "camera", "arm", "viz", "policy"]
    placement = rules(camera="arm-pc", policy={"gpu"})
    workers = [worker("arm-pc", "camera", nodes=1), worker("gpu-box", "gpu"), worker("spare"), worker("gpu2", "gpu")]
    first = place(nodes, placement, workers)
    assert list(first) == nodes
    again = place(list(reversed(nodes)), placement, list(reversed(workers)))
    assert list(again) == list(reversed(nodes))
    assert again == first


def test_place_is_pure():
    placement = rules(camera="a")
    workers = [worker("a", nodes=1), worker("b")]
    before = (dict(placement.nodes), list(workers))
    assert place(["camera", "x"], placement, workers) == place(["camera", "x"], placement, workers)
    assert (dict(placement.nodes), workers) == before


def test_nothing_to_place_needs_no_worker():
    assert place([], None, []) == {}


# ---------------------------------------------------------------------------------------------
# A placement that cannot be met: every problem, with what to change
# ---------------------------------------------------------------------------------------------
def test_a_node_the_ir_does_not_have_is_named_with_the_nodes_it_has_and_the_closest():
    with pytest.raises(PlacementError, match=re.escape(
            "placement placement.toml has 1 problem:\n"
            "  - [nodes] 'camra': the IR has no such node (its nodes: 'camera', 'policy')\n"
            "    hint: did you mean 'camera'?")):
        place(["camera", "policy"], rules(camra="a"), [worker("a")])


def test_a_node_far_from_every_name_gets_a_plain_hint():
    with pytest.raises(PlacementError, match=r"'zzzz': the IR has no such node .*\n    hint: use the IR's node ids"):
        place(["camera"], rules(zzzz="a"), [worker("a")])


def test_a_pin_to_a_worker_that_is_not_up_lists_the_workers_up():
    with pytest.raises(PlacementError, match=re.escape(
            "[nodes] 'camera' is pinned to worker 'arm-pc', which is not up (workers up: 'arm-pc2', 'gpu-box')\n"
            "    hint: did you mean 'arm-pc2'? Start it (retriever-worker --name arm-pc), or pin 'camera' to a "
            "worker that is up")):
        place(["camera"], rules(camera="arm-pc"), [worker("gpu-box"), worker("arm-pc2")])


def test_labels_no_worker_has_say_which_worker_has_which_labels():
    with pytest.raises(PlacementError, match=re.escape(
            "[nodes] 'policy' needs the label(s) 'cuda', 'gpu', and no worker up has all of them "
            "('a' has 'gpu'; 'b' has 'cuda'; 'c' has no labels)\n"
            "    hint: start a worker with them (retriever-worker --name NAME --labels cuda,gpu), "
            "or change the labels of 'policy' in placement.toml")):
        place(["policy"], rules(policy={"gpu", "cuda"}), [worker("b", "cuda"), worker("a", "gpu"), worker("c")])


def test_a_pinned_worker_without_the_labels_asked_for_is_refused():
    with pytest.raises(PlacementError, match=re.escape(
            "[nodes] 'planner' is pinned to worker 'gpu-box', which lacks the label(s) 'cuda' that 'planner' needs "
            "(it has 'gpu')\n"
            "    hint: start 'gpu-box' with --labels cuda,gpu, or drop worker or labels from the entry of "
            "'planner'")):
        place(["planner"], rules(planner=("gpu-box", {"gpu", "cuda"})), [worker("gpu-box", "gpu")])


def test_no_worker_at_all_says_how_to_start_one():
    with pytest.raises(PlacementError, match=re.escape(
            "automatic placement (no --placement file) has 1 problem:\n  - no worker is up\n"
            "    hint: start one on each machine that should run nodes: retriever-worker --name NAME")):
        place(["camera"], None, [])


def test_two_workers_of_one_name_are_refused():
    with pytest.raises(PlacementError, match=re.escape(
            "2 workers are up under the name 'arm-pc' (hosts: 'lab-1', unknown)\n"
            "    hint: give each worker its own --name")):
        place(["camera"], None, [worker("arm-pc", host="lab-1"), worker("arm-pc"), worker("spare")])


def test_every_problem_is_reported_at_once():
    placement = rules(camra="arm-pc", policy={"gpu"}, planner="gpu-box", viz=("spare", {"screen"}))
    with pytest.raises(PlacementError, match=r"^placement placement.toml has 6 problems:\n  - ") as excinfo:
        place(["camera", "policy", "planner", "viz"], placement, [worker("spare"), worker("spare")])
    found = problems_of(excinfo)
    assert [line.split(",")[0].split(" (")[0] for line in found] == [
        "[nodes] 'camra': the IR has no such node", "2 workers are up under the name 'spare'",
        "[nodes] 'camra' is pinned to worker 'arm-pc'", "[nodes] 'policy' needs the label(s) 'gpu'",
        "[nodes] 'planner' is pinned to worker 'gpu-box'", "[nodes] 'viz' is pinned to worker 'spare'"]
    assert all("\n    hint: " in line for line in found)


def test_no_worker_is_one_problem_not_one_per_pin():
    with pytest.raises(PlacementError) as excinfo:
        place(["camera", "policy"], rules(camera="arm-pc", policy={"gpu"}, ghost="x"), [])
    assert [p.message for p in excinfo.value.problems] == [
        "[nodes] 'ghost': the IR has no such node (its nodes: 'camera', 'policy')", "no worker is up"]


def test_placement_error_is_a_retriever_error_with_its_problems_and_source():
    with pytest.raises(RetrieverError) as excinfo:
        place(["a"], rules(a="gone"), [worker("here")])
    error = excinfo.value
    assert isinstance(error, PlacementError) and retriever.PlacementError is PlacementError
    assert error.source == "placement.toml"
    assert len(error.problems) == 1 and isinstance(error.problems[0], Problem)
    assert str(error) == "placement placement.toml has 1 problem:\n  - " + str(error.problems[0])


# ---------------------------------------------------------------------------------------------
# The file
# ---------------------------------------------------------------------------------------------
def test_a_file_of_pins_labels_and_both(tmp_path):
    path = write(tmp_path, """
[nodes]
camera = "arm-pc"
policy = { labels = ["gpu", "gpu"] }
planner = { worker = "gpu-box", labels = ["gpu"] }
logger = { worker = "spare" }

[nodes.viz]
labels = ["screen"]
""")
    assert load_placement(path) == Placement({
        "camera": Constraint("arm-pc"), "policy": Constraint(labels=frozenset({"gpu"})),
        "planner": Constraint("gpu-box", frozenset({"gpu"})), "logger": Constraint("spare"),
        "viz": Constraint(labels=frozenset({"screen"}))}, str(path))


def test_an_empty_file_places_every_node_automatically(tmp_path):
    assert load_placement(write(tmp_path, "# nothing pinned\n")).nodes == {}
    assert load_placement(write(tmp_path, "[nodes]\n")).nodes == {}


def test_a_toml_syntax_error_names_the_file_and_the_line(tmp_path):
    path = write(tmp_path, "[nodes]\ncamera = arm-pc\n")
    with pytest.raises(PlacementError, match=re.escape(
            f"placement {path} has 1 problem:\n  - not valid TOML: Invalid value (at line 2, column 10)\n"
            "    hint: a placement is a [nodes] table")) as excinfo:
        load_placement(path)
    assert excinfo.value.__cause__ is None and excinfo.value.__suppress_context__


def test_a_file_that_cannot_be_read_is_a_placement_error(tmp_path):
    with pytest.raises(PlacementError, match=r"missing.toml has 1 problem:\n  - cannot read the file: No such file"):
        load_placement(tmp_path / "missing.toml")
    with pytest.raises(PlacementError, match=r"cannot read the file: Is a directory"):
        load_placement(tmp_path)
    with pytest.raises(PlacementError, match=r"not a text file \(expected UTF-8 TOML\)"):
        load_placement(write(tmp_path, b"[nodes]\ncamera = \"\xff\xfe\"\n"))


def test_toml_nested_past_the_recursion_limit_is_a_placement_error(tmp_path):
    path = write(tmp_path, "x = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(PlacementError, match="nests arrays or tables deeper than Python's recursion limit"):
        load_placement(path)


@pytest.mark.parametrize("text, expected", [
    ('[workers]\na = "b"\n', r"unknown top-level key 'workers'\n    hint: a placement has only a \[nodes\] table"),
    ("nodes = 5\n", r"\[nodes\]: expected a table of node = worker, got an integer"),
    ("nodes = [1]\n", r"\[nodes\]: expected a table of node = worker, got an array"),
    ("[nodes]\ncamera = 5\n", r"\[nodes\] 'camera': expected a worker name \(\"arm-pc\"\) or a table .* an integer"),
    ('[nodes]\ncamera = ["arm-pc"]\n', r"\[nodes\] 'camera': expected a worker name .* got an array"),
    ("[nodes]\ncamera = true\n", r"got a boolean"),
    ("[nodes]\ncamera = 1.5\n", r"got a float"),
    ("[nodes]\ncamera = 1979-05-27\n", r"got a value of type date"),
    ('[nodes]\ncamera = ""\n', r"\[nodes\] 'camera': the worker name is empty"),
    ("[nodes]\ncamera = {}\n", r"'camera': says none of worker, labels and process"),
    ('[nodes]\ncamera = { worker = "" }\n', r"'camera': worker: expected a worker name \(a non-empty string\), got ''"),
    ("[nodes]\ncamera = { worker = 3 }\n", r"worker: expected a worker name .*, got an integer"),
    ('[nodes]\npolicy = { labels = "gpu" }\n',
     r"'policy': labels: expected a list, got the string 'gpu'\n    hint: write labels = \['gpu'\]"),
    ("[nodes]\npolicy = { labels = [] }\n", r"'policy': labels: expected a non-empty list of labels, got an array"),
    ("[nodes]\npolicy = { labels = { gpu = true } }\n", r"expected a non-empty list of labels, got a table"),
    ('[nodes]\npolicy = { labels = ["gpu", 7] }\n', r"'policy': labels\[1\]: expected a label .*, got an integer"),
    ('[nodes]\npolicy = { labels = ["gpu", ""] }\n', r"labels\[1\]: expected a label \(a non-empty string\), got ''"),
    ('[nodes]\ncamera = { process = "" }\n', r"'camera': process: expected a process name \(letters, digits, _ and -, "
                                              r"not starting with a digit or -\), got ''\n    hint: write process = "),
    ('[nodes]\ncamera = { process = "a b" }\n', r"'camera': process: expected a process name .*, got 'a b'"),
    ('[nodes]\ncamera = { process = "9lives" }\n', r"'camera': process: expected a process name .*, got '9lives'"),
    ('[nodes]\ncamera = { process = "-x" }\n', r"'camera': process: expected a process name .*, got '-x'"),
    ("[nodes]\ncamera = { process = 3 }\n", r"'camera': process: expected a process name .*, got an integer"),
    ('[nodes]\ncamera = { process = ["a"] }\n', r"'camera': process: expected a process name .*, got an array"),
    ('[nodes]\ncamera = { process = "caméra" }\n', r"'camera': process: expected a process name .*, got 'caméra'"),
    ('[nodes]\ncamera = { process = "ｆront" }\n', r"'camera': process: expected a process name .*, got 'ｆront'"),
    ('[nodes]\ncamera = { process = "a\\u001b[2Jb" }\n', r"'camera': process: expected a process name .*, got 'a\\x1b\[2Jb'"),
    ("[nodes]\ncamera = { process = {} }\n", r"'camera': process: expected a process name .*, got a table"),
])
def test_a_malformed_placement_says_what_is_wrong(tmp_path, text, expected):
    with pytest.raises(PlacementError, match=expected):
        load_placement(write(tmp_path, text))


def test_an_unknown_key_in_a_node_table_is_a_problem_and_a_typo_leaves_the_entry_empty(tmp_path):
    with pytest.raises(PlacementError) as excinfo:
        load_placement(write(tmp_path, '[nodes]\npolicy = { label = ["gpu"] }\n'))
    assert problems_of(excinfo) == [
        ("[nodes] 'policy': unknown key 'label'\n"
         '    hint: a node\'s table has only worker = "NAME", labels = ["LABEL", ...] and process = "NAME"'),
        ("[nodes] 'policy': says none of worker, labels and process\n"
         '    hint: write a worker name ("arm-pc") or a table ({ labels = ["gpu"] } or { process = "NAME" }, '
         'optionally with worker = "NAME")')]


def test_every_problem_of_a_file_is_reported_at_once(tmp_path):
    path = write(tmp_path, """
extra = 1
[nodes]
camera = 5
policy = { labels = "gpu", gpus = 2 }
planner = { worker = "", labels = [] }
fine = "arm-pc"
""")
    with pytest.raises(PlacementError, match=r"has 6 problems:\n") as excinfo:
        load_placement(path)
    assert [p.message.split(":")[0] for p in excinfo.value.problems] == [
        "unknown top-level key 'extra'", "[nodes] 'camera'", "[nodes] 'policy'", "[nodes] 'policy'",
        "[nodes] 'planner'", "[nodes] 'planner'"]


# ---------------------------------------------------------------------------------------------
# Hostile input: no traceback, bounded messages, no control character reaches a terminal
# ---------------------------------------------------------------------------------------------
def test_a_document_that_is_no_table_is_refused():
    with pytest.raises(PlacementError, match=r"<memory> has 1 problem:\n  - expected a document with a \[nodes\] "
                                             r"table, got an array"):
        parse_placement([["nodes"]])


def test_keys_that_are_not_strings_are_problems():
    with pytest.raises(PlacementError) as excinfo:
        parse_placement({1: "x", "nodes": {5: "a", ("x",): "b", None: {"labels": ["gpu"]}}}, "api")
    assert [p.message for p in excinfo.value.problems] == [
        "unknown top-level key an integer",
        "[nodes] has a key that is an integer; a node name is a string",
        "[nodes] has a key that is a value of type tuple; a node name is a string",
        "[nodes] has a key that is a value of type NoneType; a node name is a string"]


def test_huge_label_lists_are_read_and_their_problems_are_one_line():
    labels = [f"l{i}" for i in range(100_000)]
    assert parse_placement({"nodes": {"policy": {"labels": labels}}}).nodes["policy"].labels == frozenset(labels)
    with pytest.raises(PlacementError) as excinfo:
        parse_placement({"nodes": {"policy": {"labels": [*labels, 0, 1, 2]}}})
    assert problems_of(excinfo) == [
        "[nodes] 'policy': labels[100000]: expected a label (a non-empty string), got an integer"]


def test_long_listings_are_cut_and_long_names_are_shortened():
    nodes = [f"node{i}" for i in range(100)]
    workers = [worker(f"w{i}", *(f"l{j}" for j in range(50))) for i in range(100)]
    placement = Placement({"x" * 10_000: Constraint("y" * 10_000), "p": Constraint(labels=frozenset({"gpu"}))})
    with pytest.raises(PlacementError) as excinfo:
        place([*nodes, "p"], placement, workers)
    lines = str(excinfo.value).split("\n")
    assert len(lines) == 7
    assert max(len(line) for line in lines) < 4000
    assert "'xxxxxxxxxx" in lines[1] and "…" in lines[1] and "… (81 more)" in lines[1]
    assert "'p' needs the label(s) 'gpu'" in lines[5] and lines[5].endswith("; … (80 more))")


def test_control_characters_in_names_are_escaped():
    evil = "cam\x1b[31m\nera"
    with pytest.raises(PlacementError) as excinfo:
        place(["camera"], Placement({evil: Constraint(worker=evil)}), [worker("w\x07", "l\r")])
    text = str(excinfo.value)
    assert "\x1b" not in text and "\x07" not in text and "\r" not in text
    assert text.count("\n") == 2 * len(excinfo.value.problems)
    assert r"'cam\x1b[31m\nera'" in text and r"'w\x07'" in text


def test_thousands_of_unknown_nodes_are_each_reported():
    placement = Placement({f"ghost{i}": Constraint() for i in range(5000)})
    with pytest.raises(PlacementError, match="has 5000 problems") as excinfo:
        place(["camera"], placement, [worker("a")])
    assert all(p.message.endswith("(its nodes: 'camera')") for p in excinfo.value.problems)


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8) | st.integers(), inner,
                                                                 max_size=4),
    max_leaves=20)


@SETTINGS
@given(doc=JSONISH | st.fixed_dictionaries({"nodes": st.dictionaries(st.text(max_size=8), JSONISH, max_size=5)}))
def test_any_document_is_a_placement_or_a_placement_error(doc):
    try:
        placement = parse_placement(doc)
    except PlacementError as e:
        assert e.problems and all(isinstance(p, Problem) for p in e.problems)
        return
    for constraint in placement.nodes.values():
        assert constraint.worker or constraint.labels
        assert all(isinstance(label, str) and label for label in constraint.labels)


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------
LABELS = ["gpu", "cuda", "cam", "arm"]
WORKER_NAMES = [f"w{i}" for i in range(6)]
NODE_NAMES = [f"n{i}" for i in range(12)]


def any_workers():
    """One to six workers of distinct names, each with some labels and a load."""
    names = st.lists(st.sampled_from(WORKER_NAMES), min_size=1, max_size=6, unique=True)
    return names.flatmap(lambda names: st.tuples(*(
        st.builds(LiveDaemon, st.just(name), st.frozensets(st.sampled_from(LABELS)), st.integers(0, 3))
        for name in names))).map(list)


@st.composite
def satisfiable(draw):
    """Workers, nodes and a placement every constraint of which some worker up meets."""
    workers = draw(any_workers())
    nodes = draw(st.lists(st.sampled_from(NODE_NAMES), min_size=1, unique=True))
    placement = {}
    for node in nodes:
        host = draw(st.sampled_from(workers))
        labels = draw(st.frozensets(st.sampled_from(sorted(host.labels)))) if host.labels else frozenset()
        kind = draw(st.sampled_from(["unlisted", "pin", "labels"] if labels else ["unlisted", "pin"]))
        if kind != "unlisted":
            placement[node] = Constraint(host.name if kind == "pin" else None, labels)
    return nodes, Placement(placement), workers


def _meets(w: LiveDaemon, c: Constraint) -> bool:
    return c.worker in (None, w.name) and c.labels <= w.labels


@SETTINGS
@given(case=satisfiable(), data=st.data())
def test_every_node_goes_to_a_worker_that_meets_its_constraint_and_load_is_spread(case, data):
    nodes, placement, workers = case
    result = place(nodes, placement, workers)
    assert list(result) == nodes
    by_name = {w.name: w for w in workers}
    assert all(_meets(by_name[result[n]], placement.nodes.get(n, Constraint())) for n in nodes)
    load = {w.name: w.nodes + list(result.values()).count(w.name) for w in workers}
    # a node every worker may run is placed after the nodes with fewer choices, on a least-loaded worker:
    # so that worker ends at most one node above the lightest
    free = [n for n in nodes if all(_meets(w, placement.nodes.get(n, Constraint())) for w in workers)]
    assert all(load[result[n]] <= min(load.values()) + 1 for n in free)
    shuffled = data.draw(st.permutations(nodes)), data.draw(st.permutations(workers))
    assert place(shuffled[0], placement, shuffled[1]) == result


@SETTINGS
@given(workers=any_workers(), nodes=st.lists(st.sampled_from(NODE_NAMES), unique=True),
       entries=st.dictionaries(st.sampled_from(NODE_NAMES + ["ghost"]),
                               st.builds(Constraint, st.none() | st.sampled_from(WORKER_NAMES),
                                         st.frozensets(st.sampled_from(LABELS))), max_size=6))
def test_a_placement_is_refused_exactly_when_a_constraint_cannot_be_met_with_one_problem_each(workers, nodes, entries):
    entries = {node: c for node, c in entries.items() if c.worker or c.labels}
    unmet = [n for n in entries if n not in nodes] + [n for n, c in entries.items() if
                                                      not any(_meets(w, c) for w in workers)]
    if not unmet:
        result = place(nodes, Placement(entries), workers)
        assert all(_meets(next(w for w in workers if w.name == result[n]), entries.get(n, Constraint()))
                   for n in nodes)
        return
    with pytest.raises(PlacementError) as excinfo:
        place(nodes, Placement(entries), workers)
    assert len(excinfo.value.problems) == len(unmet)


# ---------------------------------------------------------------------------------------------
# Moves after a worker loss: the rule of the first placement
# ---------------------------------------------------------------------------------------------
def test_a_move_goes_to_the_least_loaded_worker_still_up_that_the_placement_allows():
    from retriever.placement import move

    rules = Placement({"policy": Constraint(labels=frozenset({"gpu"})), "camera": Constraint(worker="arm")})
    up = [LiveDaemon("a", frozenset({"gpu"}), nodes=3), LiveDaemon("b", frozenset({"gpu"}), nodes=1),
          LiveDaemon("c", nodes=0)]
    assert move(["policy", "other", "more"], rules, up) == {"policy": "b", "other": "c", "more": "c"}
    assert move(["camera"], rules, up) is None  # pinned to a worker that is gone: nowhere to go
    assert move(["policy"], rules, [LiveDaemon("c")]) is None  # no worker up with its labels


@settings(max_examples=50, deadline=None)
@given(st.lists(st.sampled_from("abcde"), min_size=1, max_size=5, unique=True), st.integers(0, 3))
def test_a_move_and_a_first_placement_decide_alike(names, load):
    from retriever.placement import move

    workers = [LiveDaemon(name, frozenset({"gpu"}) if i % 2 else frozenset(), nodes=load * i)
               for i, name in enumerate(names)]
    rules = Placement({"n1": Constraint(labels=frozenset({"gpu"}))}) if len(names) > 1 else None
    nodes = ["n0", "n1", "n2", "n3"]
    assert move(nodes, rules, workers) == place(nodes, rules, workers)


def test_the_shared_check_refuses_an_assignment_its_rule_could_not_make():
    from retriever.placement import check_assignment

    with pytest.raises(PlacementError, match="node 'n' was assigned to worker 'gone', which is not up"):
        check_assignment({"n": "gone"}, {}, [LiveDaemon("up")])


# ---------------------------------------------------------------------------------------------
# Flows that share a process: placed as one unit, on one worker
# ---------------------------------------------------------------------------------------------
def test_a_process_name_in_the_file_is_read_beside_the_constraints(tmp_path):
    placement = load_placement(write(tmp_path, '[nodes]\ncamera = { worker = "arm-pc", process = "perception" }\n'
                                               'detector = { process = "perception" }\nplanner = "gpu-box"\n'))
    assert placement.nodes == {"camera": Constraint(worker="arm-pc"), "planner": Constraint(worker="gpu-box")}
    assert placement.processes == {"camera": "perception", "detector": "perception"}


def test_a_process_name_for_a_node_the_ir_does_not_have_is_a_problem():
    placement = Placement({}, "placement.toml", {"ghost": "front"})
    with pytest.raises(PlacementError, match=r"\[nodes\] 'ghost': the IR has no such node"):
        place(["camera"], placement, [worker("a")])


def test_a_group_goes_to_one_worker_by_its_members_load_and_follows_a_members_pin():
    workers = [worker("a"), worker("b"), worker("c", "gpu")]
    assert place(["cam", "det", "viz", "log"], None, workers, {"front": ["cam", "det", "viz"]}) == {
        "cam": "a", "det": "a", "viz": "a", "log": "b"}
    assert place(["cam", "det", "log"], rules(det="b"), workers, {"front": ["cam", "det"]}) == {
        "cam": "b", "det": "b", "log": "a"}
    assert place(["cam", "det"], rules(cam={"gpu"}), workers, {"front": ["cam", "det"]}) == {"cam": "c", "det": "c"}


def test_a_group_pinned_to_different_workers_is_refused_naming_the_process_its_flows_their_workers_and_the_fix():
    with pytest.raises(PlacementError) as excinfo:
        place(["cam", "det", "log"], rules(cam="a", det="b"), [worker("a"), worker("b")], {"front": ["cam", "det"]})
    assert problems_of(excinfo) == [
        "process 'front': its flows 'cam', 'det' share one process, on one worker, and are pinned to different "
        "workers ('cam' on 'a', 'det' on 'b')\n"
        "    hint: a group's flows run in one process, on one worker: pin them to one worker (or none), or give the "
        "ones that must run elsewhere another process name (configure(process=), or process = \"NAME\" in "
        "[nodes]); a flow with no process name runs in a process of its own"]


def test_a_group_whose_members_no_one_worker_meets_together_is_refused():
    with pytest.raises(PlacementError) as excinfo:
        place(["cam", "det"], rules(cam={"camera"}, det="b"), [worker("a", "camera"), worker("b")],
              {"front": ["cam", "det"]})
    assert problems_of(excinfo)[0].startswith(
        "process 'front': its flows 'cam', 'det' share one process, on one worker, and no worker up meets all "
        "their constraints together ('cam' wants label(s) 'camera'; 'det' wants worker 'b')")


def test_a_lost_workers_group_moves_together():
    from retriever.placement import move

    up = [LiveDaemon("a", nodes=1), LiveDaemon("b", nodes=0)]
    assert move(["cam", "det", "log"], None, up, {"front": ["cam", "det"]}) == {"cam": "b", "det": "b", "log": "a"}
    assert move(["cam", "det"], rules(cam={"gpu"}), up, {"front": ["cam", "det"]}) is None  # nowhere for both


def test_the_shared_check_refuses_a_group_split_across_workers():
    from retriever.placement import check_assignment

    with pytest.raises(PlacementError, match=r"the nodes 'cam', 'det', which share a process, were assigned to "
                                             r"workers 'a', 'b'\n    hint: this is a bug"):
        check_assignment({"cam": "a", "det": "b"}, {}, [LiveDaemon("a"), LiveDaemon("b")], None, {"f": ["cam", "det"]})


@SETTINGS
@given(case=satisfiable(), data=st.data())
def test_every_group_lands_on_one_worker_whenever_a_placement_takes_it(case, data):
    nodes, placement, workers = case
    members = data.draw(st.lists(st.sampled_from(nodes), unique=True, max_size=4))
    groups = {"g": members} if len(members) > 1 else {}
    try:
        result = place(nodes, placement, workers, groups)
    except PlacementError as e:
        assert any("process 'g'" in p.message for p in e.problems), e
        return
    assert len({result[n] for n in members}) <= 1
    by_name = {w.name: w for w in workers}
    assert all(_meets(by_name[result[n]], placement.nodes.get(n, Constraint())) for n in nodes)
