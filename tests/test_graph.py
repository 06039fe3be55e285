"""Compiling a pipeline: port matching, type compatibility, node ids, cycles (retriever/graph.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Sequence

import re
import warnings

import pytest

from retriever import (
    ActionChunking,
    Flow,
    GraphError,
    Latest,
    LogError,
    Pipeline,
    Queue,
    Rate,
    RetrieverWarning,
    Trigger,
    Window,
    io,
)
from retriever.graph import fits
from retriever.log import read_log


@io
class XY:
    x: int
    y: int


@io
class XYZIn:
    x: float
    y: int
    z: Optional[str] = None


@io
class Mixed:
    label: str
    count: int


@io
class Amount:
    amount: float


@io
class Num:
    x: int


@io
class Recent:
    recent: list[float]


@io
class Words:
    words: list[str]


@io
class Row:
    row: float


@io
class Done:
    done: Optional[bool] = None  # sparse: None means no event


@io
class DoneIn:
    done: bool


class XYSource(Flow[None, XY]):
    def step(self, inp):
        return XY(1, 2)


class XYZSink(Flow[XYZIn, None]):
    def step(self, inp):
        return None


class MixedSource(Flow[None, Mixed]):
    def step(self, inp):
        return Mixed("a", 3)


class AmountSink(Flow[Amount, None]):
    def step(self, inp):
        return None


class NumSource(Flow[None, Num]):
    def __init__(self):
        self.n = 0

    def step(self, inp):
        self.n += 1
        return Num(self.n)


class RecentSink(Flow[Recent, None]):
    def step(self, inp):
        return None


class WordsSink(Flow[Words, None]):
    def step(self, inp):
        return None


class RowSink(Flow[Row, None]):
    def step(self, inp):
        return None


class DoneSource(Flow[None, Done]):
    def step(self, inp):
        return Done(True)


class DoneSink(Flow[DoneIn, None]):
    def step(self, inp):
        return None


class UntypedSource(Flow):
    def step(self):
        return {"x": 7}


class UntypedAmountSource(Flow):
    def step(self):
        return {"amount": 7}


class UntypedUnknowable(Flow):  # what it returns cannot be read off its source
    def step(self):
        ports = {"x": 7}
        return ports


class OptionalYSink(Flow):
    def step(self, y=None):
        return None


class UntypedSink(Flow):
    def __init__(self):
        self.got = []

    def step(self, x):
        self.got.append(x)


class CameraFlow(Flow[None, Num]):
    def step(self, inp):
        return Num(0)


class HTTPServerFlow(Flow[None, Num]):
    def step(self, inp):
        return Num(0)


class Relay(Flow):
    def step(self, a=None):
        return {"a": a}


def _edges(pipe: Pipeline) -> list[tuple[str, str, str, str]]:
    return [(e["source"]["node"], e["source"]["port"], e["destination"]["node"], e["destination"]["port"])
            for e in pipe.build_ir().edges]


# ---------------------------------------------------------------------------------------------
# Port matching
# ---------------------------------------------------------------------------------------------
def test_ports_match_by_name():
    with Pipeline("p") as pipe:
        (XYSource() @ Rate(hz=1)).then(XYZSink() @ Rate(hz=1))
    assert _edges(pipe) == [("xy_source", "x", "xyz_sink", "x"), ("xy_source", "y", "xyz_sink", "y")]


def test_a_single_pair_of_generic_types_with_other_names_is_wired_and_warned_of():
    # an image field and an action field are both arrays: wired by type, the image fed the action port
    with Pipeline("p") as pipe:
        (MixedSource() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1))
    with pytest.warns(RetrieverWarning, match=r"edge mixed_source → amount_sink \(.*\): no port names in common, so "
                                              r"mixed_source.count feeds amount_sink.amount because they are the only "
                                              r"pair whose types fit \(int → float\), a type that says little about what "
                                              r"a port means\n    hint: if that is meant, say so: "
                                              r"map=\{'count': 'amount'\}; else name the ports alike"):
        assert _edges(pipe) == [("mixed_source", "count", "amount_sink", "amount")]


@io
@dataclass
class Grasp:
    width: float


@io
@dataclass
class GraspOut:
    grasp: Grasp


@io
@dataclass
class GraspIn:
    command: Optional[Grasp] = None


class GraspSource(Flow[None, GraspOut]):
    def step(self, inp):
        return GraspOut(Grasp(0.1))


class GraspSink(Flow[GraspIn, None]):
    def step(self, inp):
        return None


def test_a_single_pair_of_one_value_type_of_the_programs_own_is_wired_without_a_warning():
    with Pipeline("p") as pipe:
        (GraspSource() @ Rate(hz=1)).then(GraspSink() @ Rate(hz=1))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrieverWarning)
        assert _edges(pipe) == [("grasp_source", "grasp", "grasp_sink", "command")]


def test_a_type_compatible_pair_of_other_names_is_wired_by_map():
    with Pipeline("p") as pipe:
        (MixedSource() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1), map={"count": "amount"})
    assert _edges(pipe) == [("mixed_source", "count", "amount_sink", "amount")]


def test_map_naming_a_key_an_untyped_step_never_returns_is_refused():
    class Camera(Flow):
        def step(self):
            return {"image": 1.0}

    class Policy(Flow):
        def step(self, image):
            return None

    with Pipeline("p") as pipe:
        (Camera() @ Rate(hz=1)).then(Policy() @ Rate(hz=1), map={"imgae": "image"})
    with pytest.raises(GraphError, match=r"map names output port 'imgae', but camera is untyped and its step\(\) "
                                         r"returns 'image', never 'imgae': policy.image would never get an event"):
        pipe.build_ir()


class _ReaderOfLate(Flow):
    def step(self, late):
        return None


class _ReaderOfError(Flow):
    def step(self, error):
        return None


@pytest.mark.parametrize("port, reader", [("late", _ReaderOfLate), ("error", _ReaderOfError)])
def test_an_input_port_named_as_a_step_records_detail_key_is_refused(port, reader):
    """A Queue's drop count is logged in the step record's detail under its input port's name: a
    port named ``late`` that dropped made the run's own log refused as malformed, one named
    ``error`` (or ``flow``, ``missing``, ...) lost the count or the record's own detail (review14)."""
    class Ticker(Flow):
        def step(self):
            return {"out": 1}

    with Pipeline("p") as pipe:
        (Ticker() @ Rate(hz=20)).then(reader() @ Rate(hz=2), sync=Queue(maxsize=2), map={"out": port})
    with pytest.raises(GraphError, match=re.escape(f"input port '{port}' has the name of a step record's detail "
                                                   f"key") + r"[\s\S]*" + re.escape(f"rename it, e.g. '{port}_in'")):
        pipe.build_ir()


@pytest.mark.parametrize("port", ["a/b", "a.b", "", "1st", "a*", "-a"])
def test_an_untyped_output_port_that_is_no_port_name_is_refused(port):
    """A port is one segment of the log's topic data/<node>/<port>: a '/' in one lost its events
    from read_log and every view and export (issue 39)."""
    class Camera(Flow):
        def step(self):
            return {port: 1.0, "ok": 2.0}

    class Policy(Flow):
        def step(self, image, ok):
            return None

    with Pipeline("p") as pipe:
        (Camera() @ Rate(hz=1)).then(Policy() @ Rate(hz=1), map={port: "image", "ok": "ok"})
    with pytest.raises(GraphError, match=re.escape(f"flow 'camera' (tests.test_graph:") + r".*"
                       + re.escape(f"output port {port!r} is not a port name: letters, digits, _ and -")):
        pipe.build_ir()


def test_a_port_named_by_any_python_identifier_is_taken(tmp_path):
    class Scale(Flow):
        def step(self):
            return {"größe": 1.0}

    class Sink(Flow):
        def step(self, größe):
            return None

    with Pipeline("p") as pipe:
        (Scale() @ Rate(hz=1)).then(Sink() @ Rate(hz=1))
    pipe.run(duration=1.0, log=tmp_path / "run.mcap")
    assert [(e.node, e.port) for e in read_log(tmp_path / "run.mcap").iter_events()] == [("scale", "größe")]


def test_a_returned_key_that_is_no_port_name_is_refused_though_no_edge_reads_it():
    class Camera(Flow):
        def step(self):
            return {"rgb/left": 1.0, "ok": 2.0}

    class Policy(Flow):
        def step(self, ok):
            return None

    with Pipeline("p") as pipe:
        (Camera() @ Rate(hz=1)).then(Policy() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"output port 'rgb/left' is not a port name.*\n.*hint: rename it, e\.g\. "
                                         r"'rgb_left', in its step\(\) and in the edges' map="):
        pipe.build_ir()


def test_a_key_only_known_at_run_time_that_is_no_port_name_is_refused_by_the_log(tmp_path):
    class Camera(Flow):
        def step(self):
            return dict([("rgb/left", 1.0), ("ok", 2.0)])

    class Policy(Flow):
        def step(self, ok):
            return None

    with Pipeline("p") as pipe:
        (Camera() @ Rate(hz=1)).then(Policy() @ Rate(hz=1))
    with pytest.raises(LogError, match=r"an event of camera cannot be logged: the output port 'rgb/left' is not a "
                                       r"port name"):
        pipe.run(duration=1.0, log=tmp_path / "run.mcap")


def test_map_routes_ports_explicitly():
    with Pipeline("p") as pipe:
        (XYSource() @ Rate(hz=1)).then(XYZSink() @ Rate(hz=1), map={"y": "x", "x": "y"})
    assert _edges(pipe) == [("xy_source", "y", "xyz_sink", "x"), ("xy_source", "x", "xyz_sink", "y")]


def test_pipe_connect_is_the_same_as_then():
    with Pipeline("p") as pipe:
        src, sink = XYSource() @ Rate(hz=1), XYZSink() @ Rate(hz=1)
        assert pipe.connect(src, sink, map={"x": "y", "y": "x"}) is sink
    assert _edges(pipe) == [("xy_source", "x", "xyz_sink", "y"), ("xy_source", "y", "xyz_sink", "x")]


def test_then_returns_the_destination_so_chains_read_left_to_right():
    with Pipeline("p") as pipe:
        a, b, c = Relay() @ Rate(hz=1), Relay() @ Trigger("a"), Relay() @ Trigger("a")
        assert a.then(b).then(c) is c
    assert _edges(pipe) == [("relay", "a", "relay_2", "a"), ("relay_2", "a", "relay_3", "a")]


def test_untyped_producer_into_a_single_port_consumer():
    with Pipeline("p") as pipe:
        (UntypedSource() @ Rate(hz=10)).then(AmountSink() @ Rate(hz=10), map={"x": "amount"})
        sink = UntypedSink() @ Trigger()
        pipe.connect(pipe.flows[0], sink)
    ir = pipe.build_ir()
    assert _edges(pipe) == [("untyped_source", "x", "amount_sink", "amount"),
                            ("untyped_source", "x", "untyped_sink", "x")]
    # an untyped producer's output ports are the ones its edges name
    assert ir.node("untyped_source")["outputs"] == {"x": "Any"}
    assert ir.node("untyped_sink")["inputs"] == {"x": "Any"}
    pipe.run(duration=0.3)
    assert sink.got == [7, 7, 7]


def test_untyped_producer_into_a_single_typed_port_takes_its_name():
    with Pipeline("p") as pipe:
        (UntypedAmountSource() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1))
    assert _edges(pipe) == [("untyped_amount_source", "amount", "amount_sink", "amount")]
    with Pipeline("q") as pipe:  # its step's returns say nothing: the port's name is taken on trust
        (UntypedUnknowable() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1))
    assert _edges(pipe) == [("untyped_unknowable", "amount", "amount_sink", "amount")]


def test_an_untyped_producer_that_never_returns_the_port_it_feeds_is_refused_or_warned():
    """issue 19 §5: A returns {"x": ...}, B's only input is 'amount': a.then(b) fed b.amount by
    name, nothing ever came, and b skipped every tick, silently. A required port: refused; an
    optional one: a warning. Both name the ports and show map=."""
    with Pipeline("p") as pipe:
        (UntypedSource() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1))
    with pytest.raises(GraphError, match=r"untyped_source is untyped and its step\(\) returns 'x', never 'amount', "
                                         r"the port of amount_sink this edge feeds by name(.|\n)*hint: say which "
                                         r"output feeds it: untyped_source.then\(amount_sink, map=\{'x': 'amount'\}\)"):
        pipe.build_ir()
    with Pipeline("q") as pipe:
        (UntypedSource() @ Rate(hz=1)).then(OptionalYSink() @ Rate(hz=1))
    with pytest.warns(RetrieverWarning, match=r"returns 'x', never 'y'(.|\n)*it is optional(.|\n)*"
                                              r"map=\{'x': 'y'\}"):
        pipe.build_ir()


def test_typed_producer_into_an_untyped_consumer_matches_by_name():
    with Pipeline("p") as pipe:
        (XYSource() @ Rate(hz=1)).then(UntypedSink() @ Rate(hz=1))
    assert _edges(pipe) == [("xy_source", "x", "untyped_sink", "x")]


def test_fan_in_with_one_policy_is_allowed():
    with Pipeline("p") as pipe:
        sink = RecentSink() @ Rate(hz=1)
        (NumSource() @ Rate(hz=2)).then(sink, sync=Window(buffer_size=4), map={"x": "recent"})
        (NumSource() @ Rate(hz=2)).then(sink, sync=Window(buffer_size=4), map={"x": "recent"})
    assert len(_edges(pipe)) == 2


# ---------------------------------------------------------------------------------------------
# Type compatibility
# ---------------------------------------------------------------------------------------------
class Base:
    pass


class Derived(Base):
    pass


@pytest.mark.parametrize("out_t, in_t", [
    (int, int),
    (int, float),  # PEP 484 numeric tower
    (int, complex),
    (float, complex),
    (bool, int),
    (Derived, Base),
    (int, Optional[float]),
    (int, float | None),
    (list[int], list[float]),
    (dict[str, int], dict[str, float]),
    (Any, int),
    (int, Any),
    ("SomeForwardRef", int),
    (list[int], list),
    (list, list[int]),
])
def test_types_that_fit(out_t, in_t):
    assert fits(out_t, in_t)


@pytest.mark.parametrize("out_t, in_t", [
    (float, int),
    (str, float),
    (Base, Derived),
    (list[str], list[int]),
    (Optional[str], int),
    (int | str, int),
    (dict[str, str], dict[str, int]),
])
def test_types_that_do_not_fit(out_t, in_t):
    assert not fits(out_t, in_t)


def test_sparse_optional_output_fits_a_required_input_of_its_type():
    # DESIGN §4: a None in an output field means "no event on that port", so an Optional[bool]
    # output only ever delivers bools.
    with Pipeline("p") as pipe:
        (DoneSource() @ Rate(hz=1)).then(DoneSink() @ Rate(hz=1))
    assert _edges(pipe) == [("done_source", "done", "done_sink", "done")]


def test_int_output_into_float_input_builds():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(AmountSink() @ Rate(hz=1), map={"x": "amount"})
    assert _edges(pipe) == [("num_source", "x", "amount_sink", "amount")]


def test_int_output_into_optional_input_builds():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(XYZSink() @ Rate(hz=1), map={"x": "x"})
        (MixedSource() @ Rate(hz=1)).then(pipe.flows[1], map={"label": "z", "count": "y"})
    assert len(_edges(pipe)) == 3


@pytest.mark.parametrize("sync", [Window(buffer_size=3), Queue(maxsize=3)])
def test_window_and_queue_deliver_lists(sync):
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RecentSink() @ Rate(hz=1), sync=sync, map={"x": "recent"})
    assert _edges(pipe) == [("num_source", "x", "recent_sink", "recent")]


@pytest.mark.parametrize("sync", [Window(buffer_size=3), Queue(maxsize=3)])
def test_window_and_queue_check_the_element_type(sync):
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(WordsSink() @ Rate(hz=1), sync=sync, map={"x": "words"})
    with pytest.raises(GraphError, match=r"type mismatch on num_source\.x → words_sink\.words: the input expects "
                                         r"list\[str\], the edge delivers list of int"):
        pipe.build_ir()


def test_list_input_fed_by_latest_is_a_mismatch():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RecentSink() @ Rate(hz=1), sync=Latest(), map={"x": "recent"})
    with pytest.raises(GraphError, match=r"the input expects list\[float\], the edge delivers int"):
        pipe.build_ir()


def test_type_mismatch_through_name_matching():
    with Pipeline("p") as pipe:
        (MixedSource() @ Rate(hz=1)).then(WordsSink() @ Rate(hz=1), map={"count": "words"})
    with pytest.raises(GraphError, match=r"the input expects list\[str\], the edge delivers int"):
        pipe.build_ir()


def test_action_chunking_delivers_rows_whatever_the_annotation():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(RowSink() @ Rate(hz=10), sync=ActionChunking(chunk_steps=4),
                                        map={"x": "row"})
    assert _edges(pipe) == [("num_source", "x", "row_sink", "row")]


def test_window_into_an_unannotated_port_is_fine():
    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(UntypedSink() @ Rate(hz=1), sync=Window(buffer_size=2))
    assert _edges(pipe) == [("num_source", "x", "untyped_sink", "x")]


def test_sequence_annotation_accepts_a_window():
    @io
    class SeqIn:
        values: Sequence[int]

    class SeqSink(Flow[SeqIn, None]):
        def step(self, inp):
            return None

    with Pipeline("p") as pipe:
        (NumSource() @ Rate(hz=1)).then(SeqSink() @ Rate(hz=1), sync=Window(buffer_size=2), map={"x": "values"})
    assert len(_edges(pipe)) == 1


# ---------------------------------------------------------------------------------------------
# Node ids
# ---------------------------------------------------------------------------------------------
def test_default_node_ids_come_from_the_class_name():
    with Pipeline("p") as pipe:
        CameraFlow() @ Rate(hz=1)
        HTTPServerFlow() @ Rate(hz=1)
        XYSource() @ Rate(hz=1)
    assert [n["id"] for n in pipe.build_ir().nodes] == ["camera", "http_server", "xy_source"]


def test_default_node_ids_are_deduplicated():
    with Pipeline("p") as pipe:
        for _ in range(3):
            CameraFlow() @ Rate(hz=1)
    assert [n["id"] for n in pipe.build_ir().nodes] == ["camera", "camera_2", "camera_3"]


def test_explicit_names_are_kept_and_defaults_avoid_them():
    with Pipeline("p") as pipe:
        CameraFlow() @ Rate(hz=1)
        CameraFlow().named("camera") @ Rate(hz=1)
        CameraFlow().configure(name="wrist-cam") @ Rate(hz=1)
        CameraFlow() @ Rate(hz=1)
    assert [n["id"] for n in pipe.build_ir().nodes] == ["camera_2", "camera", "wrist-cam", "camera_3"]


def test_pipe_add_with_a_name():
    pipe = Pipeline("p")
    pipe.add(CameraFlow() @ Rate(hz=1), name="head")
    assert [n["id"] for n in pipe.build_ir().nodes] == ["head"]


def test_node_ids_are_the_trace_names():
    with Pipeline("p") as pipe:
        CameraFlow() @ Rate(hz=1)
        CameraFlow().named("wrist") @ Rate(hz=1)
    trace = pipe.run(duration=1)
    assert sorted({e.node for e in trace.events}) == ["camera", "wrist"]
    assert sorted(pipe.stats()) == ["camera", "wrist"]


def test_flows_are_added_once_however_often_they_are_wired():
    with Pipeline("p") as pipe:
        src = NumSource() @ Rate(hz=1)
        src.then(UntypedSink() @ Rate(hz=1))
        src.then(UntypedSink() @ Rate(hz=1))
        pipe.add(src)
    assert [n["id"] for n in pipe.build_ir().nodes] == ["num_source", "untyped_sink", "untyped_sink_2"]


# ---------------------------------------------------------------------------------------------
# Topology and cycles
# ---------------------------------------------------------------------------------------------
def test_dag_has_no_cycle():
    with Pipeline("p") as pipe:
        (XYSource() @ Rate(hz=1)).then(XYZSink() @ Rate(hz=1))
    topo = pipe.build_ir().topology
    assert topo == {"node_count": 2, "edge_count": 2, "has_cycle": False, "cycles": [],
                    "instantaneous_cycles": []}


def test_cycles_are_listed_in_topology():
    with Pipeline("p") as pipe:
        a, b, c = Relay() @ Rate(hz=10), Relay() @ Rate(hz=10), Relay() @ Rate(hz=10)
        a.then(b).then(c).then(a)
        b.then(a)
    ir = pipe.build_ir()
    assert ir.topology["has_cycle"] is True
    assert sorted(ir.topology["cycles"]) == [["relay", "relay_2"], ["relay", "relay_2", "relay_3"]]
    assert ir.topology["instantaneous_cycles"] == []  # every link goes into a Rate flow


def test_instantaneous_cycles_are_listed_and_warned():
    with Pipeline("p") as pipe:
        a, b = Relay() @ Trigger("a"), Relay() @ Trigger("a")
        a.then(b).then(a)
        (Relay() @ Rate(hz=1)).then(a)
    with pytest.warns(RetrieverWarning, match=r"instantaneous cycle relay → relay_2 → relay"):
        ir = pipe.build_ir()
    assert ir.topology["cycles"] == [["relay", "relay_2"]]
    assert ir.topology["instantaneous_cycles"] == [["relay", "relay_2"]]
    assert any("instantaneous cycle relay → relay_2 → relay" in w for w in ir.warnings)


@pytest.mark.parametrize("breaker", ["delay", "latency", "rate"])
def test_a_delay_latency_or_rate_makes_a_cycle_non_instantaneous(breaker, recwarn):
    with Pipeline("p") as pipe:
        a = Relay() @ (Rate(hz=10) if breaker == "rate" else Trigger("a"))
        b = Relay() @ Trigger("a")
        if breaker == "latency":
            b.configure(latency=0.01)
        a.then(b)
        b.then(a, delay=0.01 if breaker == "delay" else 0.0)
        (Relay() @ Rate(hz=1)).then(a)
    ir = pipe.build_ir()
    assert ir.topology["cycles"] == [["relay", "relay_2"]]
    assert ir.topology["instantaneous_cycles"] == []
    assert not [w for w in recwarn if issubclass(w.category, RetrieverWarning)]


def test_compile_is_cached_until_the_pipeline_changes():
    with Pipeline("p") as pipe:
        src = NumSource() @ Rate(hz=1)
    first = pipe.compile()
    assert pipe.compile() is first
    with pipe:
        src.then(UntypedSink() @ Rate(hz=1))
    assert pipe.compile() is not first
    assert len(pipe.compile().edges) == 1


# ---------------------------------------------------------------------------------------------
# ActionChunking: a chunk that starts at a consumer tick, a microstep too late for it
# ---------------------------------------------------------------------------------------------
class ChunkPolicy(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"chunk": [self.k * 100 + i for i in range(10)]}


class ChunkController(Flow):
    def step(self, chunk):
        return {"command": chunk}


def _chunked(latency: float = 0.0, offset: float = 0.0) -> Pipeline:
    with Pipeline("p") as pipe:
        policy = ChunkPolicy().configure(latency=latency) @ Rate(hz=20, offset=offset)
        policy.then(ChunkController() @ Rate(hz=200), sync=ActionChunking())
    return pipe


def test_a_zero_latency_chunk_producer_on_the_consumers_ticks_is_warned_of_and_its_row_0_is_never_run():
    pipe = _chunked()
    with pytest.warns(RetrieverWarning, match=r"edge chunk_policy.chunk → chunk_controller.chunk: chunk_policy has no "
                                              r"latency and ticks when chunk_controller ticks \(first at 0 s\): .*row 0 "
                                              r"of those chunks is never executed\n    hint: give chunk_policy a latency of "
                                              r"one control period or more"):
        trace = pipe.run(duration=0.1)
    assert trace.values_of("chunk_controller", "command")[:12] == [101, 102, 103, 104, 105, 106, 107, 108, 109, 109,
                                                                   201, 202]


@pytest.mark.parametrize("latency, offset", [(0.005, 0.0), (0.0, 0.0025)])
def test_a_chunk_producer_off_the_consumers_ticks_has_every_row_run_once_and_no_warning(latency, offset):
    pipe = _chunked(latency, offset)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrieverWarning)
        trace = pipe.run(duration=0.1)
    assert trace.values_of("chunk_controller", "command")[:12] == [100, 101, 102, 103, 104, 105, 106, 107, 108, 109,
                                                                   200, 201]


def _adds_extra(step):
    def wrapper(self):  # a source's step
        out = dict(step(self))
        out["extra"] = 1
        return out
    return wrapper


def test_the_keys_of_a_decorated_step_are_not_guessed_from_its_source():
    import functools

    def with_extra(step):
        return functools.wraps(step)(_adds_extra(step))

    class Wrapped(Flow):  # functools.wraps: getsource reads the inner step, which never returns "extra"
        @with_extra
        def step(self):
            return {"image": 1.0}

    class Decorated(Flow):  # a decorator without wraps: the source read is the decorated def
        @_adds_extra
        def step(self):
            return {"image": 1.0}

    class Sink(Flow):
        def step(self, x):
            return None

    for source in (Wrapped, Decorated):
        with Pipeline("p") as pipe:
            (source() @ Rate(hz=1)).then(Sink() @ Rate(hz=1), map={"extra": "x"})
        assert [e["source"]["port"] for e in pipe.build_ir().edges] == ["extra"]


def test_no_chunk_warning_where_the_next_tick_takes_row_0():
    # control_hz=100 on a 200 Hz consumer: the tick 5 ms after a chunk's start takes its row 0
    with Pipeline("p") as pipe:
        (ChunkPolicy() @ Rate(hz=20)).then(ChunkController() @ Rate(hz=200), sync=ActionChunking(control_hz=100))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RetrieverWarning)
        trace = pipe.run(duration=0.1)
    assert trace.values_of("chunk_controller", "command")[:4] == [100, 101, 101, 102]
