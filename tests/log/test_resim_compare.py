"""``--resim`` compares the log's events with the re-simulation's by their bytes where that is
exact (an array value the log holds as it was packed), and decoded where it is not: its report is
the first difference of the two whole traces, ``Trace.first_difference``, whatever the values
(arrays of another dtype, shape, order or kind than logged, structured arrays, lists, scalars,
an event left out or added, a step that raised)."""

from __future__ import annotations

import re

import numpy as np
import pytest

import retriever.log.reader as reader
from retriever import Flow, Latest, Pipeline, Rate
from retriever.log import read_log
from retriever.replay import resim, resim_file
from retriever.replay.resimulation import TRACES
from tests.log.helpers import rewrite

_PAIR = np.dtype([("a", "<i4"), ("b", "<f8")])


class Ramp(Flow):
    """A source: an array of four floats a tick."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": np.arange(4.0) + self.k}


class Scale(Flow):
    """Twice its input, as ``kind`` says from its 5th tick on (``same``: as the run did)."""

    def __init__(self, kind: str = "same"):
        self.kind, self.n = kind, 0

    def step(self, x):
        self.n += 1
        y = x * 2
        kind = self.kind if self.n >= 5 else "same"
        if kind == "value":
            y = x * 3
        elif kind == "float32":  # the same numbers, another dtype
            y = y.astype(np.float32)
        elif kind == "reshaped":
            y = y.reshape(1, 4)
        elif kind == "fortran":  # the same array in another memory order: packed the same
            y = np.asfortranarray(np.stack([y, y]))
        elif kind == "c-order":
            y = np.ascontiguousarray(np.stack([y, y]))
        elif kind == "list":
            y = y.tolist()
        elif kind == "scalar":
            y = float(y[0])
        elif kind == "structured":
            y = np.array([(int(x[0]), y[1])], dtype=_PAIR)
        elif kind == "structured-other":
            y = np.array([(int(x[0]) + 1, y[1])], dtype=_PAIR)
        elif kind == "left-out":
            return {}
        elif kind == "added":
            return {"y": y, "z": y}
        elif kind == "raises" and self.n % 3 == 0:  # an error record (skip_tick), its text compared
            raise ValueError(f"no y at {self.n}")
        elif kind == "raises-other" and self.n % 3 == 0:  # the same records but for the error's text
            raise ValueError(f"no y at tick {self.n}")
        return {"y": y}


def _pipe(kind: str) -> Pipeline:
    with Pipeline("ramp") as pipe:
        scale = Scale(kind).named("scale").configure(on_error="skip_tick")
        (Ramp().named("ramp") @ Rate(hz=20)).then(scale @ Rate(hz=10, offset=0.01), sync=Latest())
    return pipe


def _said(difference: str | None) -> str | None:
    # (an event's publish time and a step's wall times are when and how long a run made it)
    return None if difference is None else re.sub(r"(publish_ns|wall_start_ns|wall_ns)=\d+", r"\1=_", difference)


@pytest.mark.parametrize("logged, again", [
    ("same", "same"), ("same", "value"), ("same", "float32"), ("same", "reshaped"), ("same", "list"),
    ("same", "scalar"), ("same", "left-out"), ("same", "added"), ("fortran", "c-order"), ("c-order", "fortran"),
    ("fortran", "reshaped"), ("structured", "structured"), ("structured", "structured-other"),
    ("list", "list"), ("list", "same"), ("scalar", "same"), ("left-out", "same"), ("added", "same"),
    ("same", "raises"), ("raises", "same"), ("raises", "raises"), ("raises", "raises-other"),
])
def test_resim_says_what_the_two_whole_traces_say(tmp_path, logged, again):
    path = tmp_path / "run.mcap"
    _pipe(logged).run(duration=2.0, log=path)
    expected = read_log(path).trace().first_difference(_pipe(again).run(duration=2.0), TRACES)
    assert (expected is None) == (logged == again or {logged, again} == {"fortran", "c-order"}), expected
    for report in (resim(read_log(path), _pipe(again)), resim_file(path, _pipe(again))):
        assert _said(report.difference) == _said(expected)
        assert report.steps_compared == 60


def test_an_identical_resim_decodes_only_what_its_sources_emit(tmp_path, monkeypatch):
    """The log's events whose values are arrays as they were logged are compared by their bytes:
    only the replayed source's values are decoded (to be emitted again), and the first of each
    encoding's length (after which an array of that length decodes surely)."""
    path = tmp_path / "run.mcap"
    _pipe("same").run(duration=2.0, log=path)
    decoded = []
    unpackb = reader.unpackb
    monkeypatch.setattr(reader, "unpackb", lambda data, **kw: decoded.append(data) or unpackb(data, **kw))
    report = resim_file(path, _pipe("same"))
    assert report.identical and report.events_compared == 40 + 20
    assert len(decoded) <= 40 + 1, len(decoded)



def test_the_resim_survey_of_a_chunk_as_arrays_is_its_survey_as_message_tuples(tmp_path):
    """``ResimSurvey.take_chunk`` (a chunk as numpy read it: what ``resim_file`` takes) finds what
    ``take`` finds of the same messages as tuples (what ``resim`` of a log read whole takes): on
    the log as written, and on a chunk of it whose step records or events are not ones (the
    first of each kept), or whose event is there twice."""
    import msgpack
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    from retriever.log.reader import scan_log
    from retriever.replay.resimulation import ResimSurvey
    from tests.log.test_replay_stream import chunk_read_both_ways

    path = tmp_path / "run.mcap"
    _pipe("raises").run(duration=2.0, log=path)

    def state(survey):
        return (survey.nodes, survey.steps, survey.last_ns, str(survey.step_error), str(survey.events.event_error),
                str(survey.events.twice), {k: (v.lo, v.hi) for k, v in survey.events.seqs.items()})

    by_arrays, by_tuples, chunks = ResimSurvey(path), ResimSurvey(path), []
    scan_log(path, by_arrays.take, take_chunk=lambda c, m: chunks.append(m) or by_arrays.take_chunk(c, m))
    scan_log(path, by_tuples.take)
    assert chunks and state(by_arrays) == state(by_tuples) and by_arrays.steps == 60

    channels = scan_log(path, lambda c, m: None).channels
    chunk = next(r for r in StreamReader(open(path, "rb"), emit_chunks=True).records if type(r) is Chunk)
    plain = breakup_chunk(chunk)
    steps = [i for i, m in enumerate(plain) if channels[m.channel_id].topic == "steps"]
    events = [i for i, m in enumerate(plain) if channels[m.channel_id].topic.startswith("data/scale/")]

    def changed(records, i, **fields):
        m = records[i]
        return [*records[:i], Message(**{**{k: getattr(m, k) for k in ("channel_id", "sequence", "log_time",
                                                                          "publish_time", "data")}, **fields}),
                *records[i + 1:]]

    def record(i, **changes):
        fields = msgpack.unpackb(plain[i].data)
        for at, value in changes.items():
            fields["node microstep consumed produced status detail wall_ns".split().index(at)] = value
        return msgpack.packb(fields)

    one, two, last = steps[len(steps) // 2], steps[-1], events[-1]

    def bytes_at(i, at, new):
        data = plain[i].data
        return data[:at] + new + data[at + len(new):] if at != -len(new) else data[:at] + new

    microstep = 2 + plain[one].data[1] - 0xA0  # (after the record's head and its node's fixstr)
    seq = plain[one].data.index(b"\xce")  # the first seq's head (the writer packs a seq as a uint32)
    variants = [plain, changed(plain, one, data=b"\xc1"), changed(plain, one, data=record(one, status="nonsense")),
                changed(plain, one, data=record(one, node="nobody")), changed(plain, one, data=record(one, microstep=-1)),
                changed(plain, one, data=record(one, detail={"late": {"x": [["ramp", "x", 3]]}}, status="late")),
                # a status that a record without detail does not have; another that it has; a valid
                # record that is not of the shape parsed with numpy (a node not ASCII)
                changed(plain, one, data=record(one, status="late")),
                changed(plain, one, data=record(one, status="error")),
                changed(plain, one, data=record(one, status="skipped")),
                changed(plain, one, data=record(one, node="nöde")),
                changed(changed(plain, one, data=b""), two, data=record(two, status="nonsense")),
                changed(plain, last, data=b"\x92"), changed(plain, last, data=b"\x92\xc1"),
                changed(plain, last, sequence=plain[events[0]].sequence),
                changed(changed(plain, last, data=b"\x92"), two, data=b"\xc1"),
                # as long as the others of its node (told by their bytes, survey._shapes), but another
                # node, a node not ASCII, a microstep no fixint (its high bit), a wall time a negative
                # fixint, another seq's width, or detail
                *(changed(plain, one, data=bytes_at(one, at, new)) for at, new in (
                    (2, b"Z"), (2, b"\xff"), (microstep, b"\x80"), (microstep, b"\xff"), (-9, b"\xd3"), (-9, b"\xcb"),
                    (seq, b"\xcf"), (-10, b"\x90"))),
                # the first of its length (the shape taken) a node not ASCII (UTF-8: it reads)
                changed(plain, steps[0], data=bytes_at(steps[0], 2, "é".encode()))]
    for n, records in enumerate(variants):
        arrays, tuples = chunk_read_both_ways(records, channels)
        assert type(tuples) is list and type(arrays) is not list
        a, b = ResimSurvey(path), ResimSurvey(path)
        for _ in range(2):  # a chunk, then another after it
            a.take_chunk(channels, arrays)
            b.take(channels, tuples)
            assert state(a) == state(b), n


def test_a_damaged_source_value_no_tick_takes_refuses_the_resim(tmp_path):
    """A replayed source's logged value is decoded when its tick takes it, and one that no tick
    takes (here, the last tick's of a run that did not finish: it is not compared, and the
    re-simulation stops before it) when the comparison reads past it: a damaged one refuses the
    log, as ``RunLog.value`` says it, read whole and streamed."""
    from retriever.errors import LogError

    path = tmp_path / "run.mcap"
    _pipe("same").run(duration=2.0, log=path)

    def interrupted(name, values) -> None:
        if name == "retriever.end":
            values["status"] = "interrupted"

    def damaged(topic, message) -> bool:
        if topic == "data/ramp/x" and message.sequence == 39:  # the last, at 1.95 s
            message.data = message.data[:2] + b"\xc1"
        return True

    whole = rewrite(path, tmp_path / "interrupted.mcap", metadata=interrupted)
    for report in (resim(read_log(whole), _pipe("same")), resim_file(whole, _pipe("same"))):
        assert report.identical and report.horizon_ns == 1_950_000_000
    log = rewrite(path, tmp_path / "damaged.mcap", metadata=interrupted, keep=damaged)
    for again in (lambda: resim(read_log(log), _pipe("same")), lambda: resim_file(log, _pipe("same"))):
        with pytest.raises(LogError, match="event ramp.x #39 is not valid msgpack"):
            again()



class Twice(Flow):
    """Twice its input (three times when it ``differs``); a ``sink`` returns nothing, and raises
    from its 5th tick on when it differs; with ``more_at``, another event at that tick."""

    def __init__(self, differs: bool = False, sink: bool = False, more_at: int = 0):
        self.differs, self.sink, self.more_at, self.n = differs, sink, more_at, 0

    def step(self, x):
        self.n += 1
        if self.sink:
            if self.differs and self.n >= 5:
                raise ValueError(f"no sink at {self.n}")
            return {}
        if self.n == self.more_at:
            return {"y": x * 2, "z": x}
        return {"y": x * (3 if self.differs else 2)}


def _two(differ: str = "", sinks: bool = False, offset: float = 0.01, more_at: int = 0) -> Pipeline:
    """Two chains that tick at the same instants; those whose names start with a letter of
    ``differ`` differ from the run's (``Twice``, at 10 Hz from ``offset``; ``zeta2`` with another
    event at its ``more_at``th tick)."""
    with Pipeline("two") as pipe:
        for name in ("zeta", "alpha"):
            twice = Twice(name[0] in differ, sinks, more_at if name == "zeta" else 0).named(f"{name}2")
            twice = twice.configure(on_error="skip_tick")
            (Ramp().named(name) @ Rate(hz=20)).then(twice @ Rate(hz=10, offset=offset), sync=Latest())
    return pipe


def _each_instant_reversed(messages: list) -> list:
    """A log's messages (in log-time order) with those of each log time in the reverse order:
    ``zeta``'s records of an instant before ``alpha``'s, as a log of another backend may hold them
    (in the order they arrived), which a trace sorts after."""
    by_time: dict[int, list] = {}
    for m in messages:
        by_time.setdefault(m[2].log_time, []).append(m)
    return [m for t in sorted(by_time) for m in reversed(by_time[t])]


@pytest.mark.parametrize("sinks", [False, True])
@pytest.mark.parametrize("differ", ["", "z", "a", "za"])
@pytest.mark.parametrize("reversed_", [False, True])
def test_records_read_in_another_order_than_a_trace_sorts_them(tmp_path, differ, sinks, reversed_):
    """A second's records of both sides are first paired in the order they came (the log's in
    log-time order, ties in file order; the session's events sorted, its step records as it
    recorded them): that order pairs them only when each pair is the same. Otherwise, as when the
    log holds an instant's records in another order (``reversed_``: ``zeta``'s first), they are
    sorted and compared as two whole traces are: identical if only the order differs, and the first
    difference is the one ``Trace.first_difference`` finds (``alpha``'s where both differ)."""
    path = tmp_path / "run.mcap"
    _two(sinks=sinks).run(duration=3.0, log=path)
    if reversed_:
        path = rewrite(path, tmp_path / "reversed.mcap", order=_each_instant_reversed)
    expected = read_log(path).trace().first_difference(_two(differ, sinks).run(duration=3.0), TRACES)
    assert (expected is None) == (differ == "")
    if "a" in differ:
        assert "alpha2" in expected
    for report in (resim(read_log(path), _two(differ, sinks)), resim_file(path, _two(differ, sinks))):
        assert _said(report.difference) == _said(expected)
        assert report.steps_compared == 2 * (60 + 30)


@pytest.mark.parametrize("sinks", [False, True])
def test_a_record_the_log_lacks_at_the_end_of_a_second(tmp_path, sinks):
    """The log lacks the last record of the first second (``zeta2``'s event, or its step record:
    the last of the second as a trace sorts them), and the next seconds are the same: the
    session's record left over is compared with the log's next one, as in the two whole traces,
    not put aside while the next second pairs on its own."""
    path = tmp_path / "run.mcap"
    _two(sinks=sinks, offset=0.099).run(duration=3.0, log=path)
    lacked = "steps" if sinks else "data/zeta2/y"

    def kept(topic, message) -> bool:
        return not (topic == lacked and message.log_time == 999_000_000
                    and (topic != "steps" or message.data.startswith(b"\x97\xa5zeta2")))

    path = rewrite(path, tmp_path / "lacking.mcap", keep=kept)
    expected = read_log(path).trace().first_difference(_two(sinks=sinks, offset=0.099).run(duration=3.0), TRACES)
    assert expected is not None and expected.startswith("record "), expected
    for report in (resim(read_log(path), _two(sinks=sinks, offset=0.099)),
                   resim_file(path, _two(sinks=sinks, offset=0.099))):
        assert _said(report.difference) == _said(expected)


@pytest.mark.parametrize("more_in", ["session", "log"])
def test_one_more_event_at_the_end_of_a_log_of_instants_reversed(tmp_path, more_in):
    """One side has one event more than the other, the last of all (its other records the same),
    and the log holds each instant's records in another order than a trace sorts them: the first
    difference is that event, named, and which side has it (not the other side's first step
    record, with which the canonical records pair it)."""
    path = tmp_path / "run.mcap"
    _two(offset=0.099, more_at=30 if more_in == "log" else 0).run(duration=3.0, log=path)
    path = rewrite(path, tmp_path / "reversed.mcap", order=_each_instant_reversed)
    again = _two(offset=0.099, more_at=30 if more_in == "session" else 0)
    expected = read_log(path).trace().first_difference(again.run(duration=3.0), TRACES)
    has, lacks = ("the re-simulation", "the log") if more_in == "session" else ("the log", "the re-simulation")
    assert expected.startswith(f"record 180: event zeta2.z #0 at t=2.999000000s m=1 is in {has}, not in {lacks}: "
                               "Event(tag=(2999000000, 1), node='zeta2', port='z', seq=0, value=array("), expected
    for report in (resim(read_log(path), _two(offset=0.099, more_at=30 if more_in == "session" else 0)),
                   resim_file(path, _two(offset=0.099, more_at=30 if more_in == "session" else 0))):
        assert _said(report.difference) == _said(expected)


@pytest.mark.parametrize("again, said", [
    ("left-out", "record 13: event scale.y #4 at t=0.410000000s m=1 is in the log, not in the re-simulation: "),
    ("added", "record 14: event scale.z #0 at t=0.410000000s m=1 is in the re-simulation, not in the log: "),
])
def test_an_event_one_side_lacks_is_named(tmp_path, again, said):
    """An event the re-simulation did not produce, or produced in addition, is named by its id,
    read whole and streamed."""
    path = tmp_path / "run.mcap"
    _pipe("same").run(duration=2.0, log=path)
    for report in (resim(read_log(path), _pipe(again)), resim_file(path, _pipe(again))):
        assert report.difference.startswith(said), report.difference


def _let(differ: str = "") -> Pipeline:
    """LET outputs of two nodes at the same tags: ``zeta2``'s (0.1 s after its step) recorded
    before ``alpha2``'s (0.05 s after its step, 0.05 s later), which a trace sorts first."""
    with Pipeline("let") as pipe:
        for name, offset, latency in (("zeta", 0.0, 0.1), ("alpha", 0.05, 0.05)):
            twice = Twice(name[0] in differ).named(f"{name}2").configure(latency=latency, on_error="skip_tick")
            (Ramp().named(name) @ Rate(hz=20)).then(twice @ Rate(hz=10, offset=offset), sync=Latest())
    return pipe


@pytest.mark.parametrize("differ", ["", "z", "a", "za"])
def test_let_outputs_recorded_in_another_order_than_a_trace_sorts_them(tmp_path, differ):
    """The session's events of a tag are in the order it recorded them (``zeta2``'s first), and so
    are the log's: paired as they came when each pair is the same; otherwise both sorted, and the
    first difference is the one ``Trace.first_difference`` finds."""
    path = tmp_path / "run.mcap"
    _let().run(duration=3.0, log=path)
    expected = read_log(path).trace().first_difference(_let(differ).run(duration=3.0), TRACES)
    assert (expected is None) == (differ == "")
    for report in (resim(read_log(path), _let(differ)), resim_file(path, _let(differ))):
        assert _said(report.difference) == _said(expected)
        assert report.steps_compared == 2 * (60 + 30)


@pytest.mark.parametrize("damage", [b"\xc1", b"\xd4\x7f\x00", b"\x93\x01", "dtype"])
def test_a_damaged_source_value_a_tick_takes_refuses_the_resim(tmp_path, damage):
    """A replayed source's logged value is decoded when its tick takes it: one that is not valid
    msgpack, not a value the codec makes, cut short, or as long as the others but with another
    head (a dtype no array has: not decoded as the others, by their head) refuses the log with
    ``RunLog.value``'s error, read whole and streamed."""
    from retriever.errors import LogError

    path = tmp_path / "run.mcap"
    _pipe("same").run(duration=2.0, log=path)

    def damaged(topic, message) -> bool:
        if topic == "data/ramp/x" and message.sequence == 10:
            message.data = message.data.replace(b"<f8", b"<z8") if damage == "dtype" else message.data[:2] + damage
        return True

    log = rewrite(path, tmp_path / "damaged.mcap", keep=damaged)
    whole = read_log(log)
    event = next(e for e in whole.iter_events() if e.node == "ramp" and e.seq == 10)
    with pytest.raises(LogError) as said:
        whole.value(event)
    for again in (lambda: resim(read_log(log), _pipe("same")), lambda: resim_file(log, _pipe("same"))):
        with pytest.raises(LogError, match=re.escape(str(said.value))):
            again()


@pytest.mark.parametrize("how", ["msgpack", "wall", "seq", "time"])
def test_step_records_compared_by_their_bytes_where_they_tell_it(tmp_path, how):
    """A step record not of a replayed source is compared by its data as the log writer packs the
    session's (its seqs and wall time in fixed widths: the quickstart's controller's), but for its
    wall time, where that tells it: records packed otherwise (``msgpack``: the smallest ints) or
    with other wall times are the same records (read and compared field by field, where the bytes
    differ); one that names another seq, or at another time (its log time: its tag's), is the first
    difference of the two whole traces, read whole and streamed."""
    import msgpack

    from retriever.loading import load_pipeline

    def quickstart():
        pipe = load_pipeline("examples/quickstart.py")
        pipe.reset()
        return pipe

    path = tmp_path / "run.mcap"
    quickstart().run(duration=2.0, log=path)
    changed = []

    def keep(topic, message) -> bool:
        data = message.data
        if topic == "steps" and data.startswith(b"\x97\xaacontroller") and data[-9] == 0xCF:  # (the writer's)
            if how == "msgpack":
                data = msgpack.packb(msgpack.unpackb(data))
            elif how == "wall":
                data = data[:-8] + (int.from_bytes(data[-8:], "big") + 1_000_003).to_bytes(8, "big")
            elif changed:
                return True
            elif how == "time":
                message.log_time += 1
                changed.append(data)
                return True
            else:  # the seq of the event consumed (a uint32), one more
                at = data.index(b"\xa6policy\xa5chunk\xce") + 14
                data = data[:at] + (int.from_bytes(data[at:at + 4], "big") + 1).to_bytes(4, "big") + data[at + 4:]
            assert data != message.data
            changed.append(data)
            message.data = data
        return True

    log = rewrite(path, tmp_path / "changed.mcap", keep=keep)
    assert len(changed) == (1 if how in ("seq", "time") else 240)
    expected = read_log(log).trace().first_difference(quickstart().run(duration=2.0), TRACES)
    assert (expected is None) == (how in ("msgpack", "wall")), expected
    for report in (resim(read_log(log), quickstart()), resim_file(log, quickstart())):
        assert _said(report.difference) == _said(expected)
