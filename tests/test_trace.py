"""The trace's tape (records kept compact until read) and the GC hold the records need."""

from __future__ import annotations

import gc
import threading

import msgpack

from retriever import Flow, Pipeline, Rate, Trigger
from retriever.trace import STEP_STATUSES, StepStatus, Trace, holding_full_collections


def test_the_tape_expands_in_recording_order_on_first_read():
    def pair(tape, i, add_event, add_step):
        """A compact record [pair, tag, node, seq]: one event and the step that made it."""
        _, tag, node, seq = tape[i:i + 4]
        add_event(((tag[0], tag[1] + 1), node, "out", seq, seq * 10, 0))
        add_step((node, tag, {}, ((node, "out", seq),), StepStatus.OK, None, 0, 0))
        return i + 4

    trace = Trace()
    trace.tape += [pair, (0, 0), "a", 0]
    trace.tape.append(((0, 1), "b", "out", 0, "x", 0))  # plain records, in between
    trace.tape.append(("b", (0, 0), {}, (("b", "out", 0),), StepStatus.OK, None, 0, 0))
    trace.tape += [pair, (1, 0), "a", 1]
    assert [e[1:4] for e in trace.raw_events] == [("a", "out", 0), ("b", "out", 0), ("a", "out", 1)]
    assert [(s.node, s.tag) for s in trace.steps] == [("a", (0, 0)), ("b", (0, 0)), ("a", (1, 0))]
    assert trace.tape == []
    trace.tape += [pair, (2, 0), "a", 2]  # appended after a read: read on the next one
    assert len(trace) == 4 and trace.events[-1].value == 20


def test_full_collections_are_held_while_any_holder_is_open():
    before = gc.get_threshold()
    opened, release = threading.Event(), threading.Event()

    def other():
        with holding_full_collections():
            opened.set()
            release.wait()

    thread = threading.Thread(target=other)
    with holding_full_collections():
        thread.start()
        opened.wait()
        assert gc.get_threshold()[2] == 1 << 30
    assert gc.get_threshold()[2] == 1 << 30  # the other thread still holds them
    release.set()
    thread.join()
    assert gc.get_threshold() == before


def test_a_trace_expanded_from_within_its_own_expansion_returns_at_once():
    """A signal handler that reads the trace (pipe.stats()) while its thread is expanding the
    tape: the inner expansion does nothing (no hang on the trace's lock, no record twice)."""
    trace = Trace()
    step = ("n", (0, 0), {}, (), StepStatus.OK, None, 0, 0)

    def compact(tape, i, add_event, add_step):
        trace.expand()  # as the handler would, in the middle of this expansion
        add_step(step)
        return i + 1

    trace.tape.extend([compact, step])
    assert trace.raw_steps == [step, step] and not trace.tape


def test_expanding_without_waiting_leaves_a_tape_whose_lock_is_held():
    """Counts read from a signal handler (pipe.stats() in the run's thread) expand the tape
    without waiting: if its lock is held (the handler came while this thread was taking it), they
    leave it as it is, rather than wait for themselves."""
    trace = Trace()
    step = ("n", (0, 0), {}, (), StepStatus.OK, None, 0, 0)
    holding, done = threading.Event(), threading.Event()

    def hold() -> None:  # as the thread the handler interrupted: expanding, the lock held
        holding.set()
        done.wait(10)

    holder = threading.Thread(target=trace.expand, kwargs={"then": hold})
    holder.start()
    holding.wait(10)
    trace.tape.append(step)
    trace.expand(wait=False)
    assert trace.tape == [step]
    done.set()
    holder.join()
    assert trace.raw_steps == [step] and not trace.tape


def test_latest_is_the_newest_event_of_a_port_after_every_step():
    class Source(Flow):
        def __init__(self, base):
            self.base, self.k = base, 0

        def step(self):
            self.k += 1
            return {"v": self.base + self.k}

    class Sink(Flow):
        def step(self, v):
            return {"seen": v}

    with Pipeline("p") as pipe:
        sink = Sink() @ Trigger("v")
        (Source(100).configure(name="fast") @ Rate(hz=30)).then(sink)
        (Source(200).configure(name="slow") @ Rate(hz=7, offset=0.01)).then(sink)
    assert pipe.trace.latest("sink", "seen") is None
    for _ in range(40):
        trace = pipe.step(0.05)
        for node, port in (("fast", "v"), ("slow", "v"), ("sink", "seen")):
            events = trace.events_of(node, port)
            assert trace.latest(node, port) == (events[-1] if events else None)
    assert trace.latest("sink", "seen").value == 160  # fast ticked 60 times in 2 s


def test_latest_and_values_of_refuse_a_port_the_run_does_not_have():
    import pytest

    class Camera(Flow):
        def step(self):
            return {"image": 1.0}

    class Viewer(Flow):
        def step(self, image):
            return None

    with Pipeline("p") as pipe:
        (Camera() @ Rate(hz=10, offset=0.05)).then(Viewer() @ Rate(hz=10))
    trace = pipe.step(0.01)
    assert trace.latest("camera", "image") is None and trace.values_of("camera", "image") == []  # none yet
    with pytest.raises(ValueError, match=r"trace.latest\(\): the run has no node 'camra' \(nodes: camera, viewer\)\n"
                                         r"    hint: did you mean 'camera'\?"):
        trace.latest("camra", "image")
    with pytest.raises(ValueError, match=r"trace.values_of\(\): 'camera' has no output port 'imgae' \(outputs: image\)"
                                         r"\n    hint: did you mean 'image'\?"):
        trace.values_of("camera", "imgae")


def test_latest_knows_the_ports_of_an_untyped_flow_that_no_edge_reads():
    import pytest

    class Camera(Flow):
        def step(self):
            return {"image": 1.0}

    class Controller(Flow):  # a sink whose port is only looked at, never wired
        def step(self, image):
            return {"command": image}

    class Opaque(Flow):  # keys unknown before the run: any port name may be one of its
        def step(self, image):
            out = {"command": image}
            return out

    with Pipeline("p") as pipe:
        camera = Camera() @ Rate(hz=10, offset=0.05)
        camera.then(Controller() @ Rate(hz=10))
        camera.then(Opaque() @ Rate(hz=10))
    trace = pipe.step(0.01)
    assert trace.latest("controller", "command") is None and trace.latest("opaque", "anything") is None
    with pytest.raises(ValueError, match=r"'controller' has no output port 'comand' \(outputs: command\)\n"
                                         r"    hint: did you mean 'command'\?"):
        trace.latest("controller", "comand")


# -- step statuses: one spelling, trace.StepStatus (tests/test_enum_literals.py checks it) -------
def test_a_step_status_is_its_value_in_a_log_and_on_the_wire():
    assert [str(s) for s in STEP_STATUSES] == ["ok", "skipped", "incomplete", "late", "overrun", "error"]
    for status in StepStatus:
        assert msgpack.packb(status, use_bin_type=True) == msgpack.packb(status.value, use_bin_type=True)
        assert status == status.value and hash(status) == hash(status.value) and f"{status}" == status.value
    trace = Trace(steps=[("a", (0, 0), {}, (), StepStatus.LATE, None, 0, 0)])
    same = Trace(steps=[("a", (0, 0), {}, (), "ok", None, 0, 0)])  # as a log reads one back
    assert trace == same and trace.digest() == same.digest()


def test_first_difference_names_an_event_one_trace_has_and_the_other_has_not():
    """Where one trace has an event the other has not, the first difference names it (by its
    id and tag) and says which trace has it: at the end of the events too, where the two whole
    traces' canonical records pair it with the other's first step record; the same event with
    another value or at another tag is the two events, as they are."""
    def trace(*events):
        step = ("a", (0, 0), {}, (), StepStatus.OK, None, 0, 0)
        return Trace([(tag, "a", port, seq, value, 0) for tag, port, seq, value in events], [step])

    one, two, three = ((0, 1), "x", 0, 1.0), ((0, 1), "y", 0, 2.0), ((5, 0), "x", 1, 3.0)
    last = "record 2: event a.x #1 at t=0.000000005s m=0 is in {}, not in {}: Event(tag=(5, 0), node='a'"
    first, second = "the first trace", "the second"
    assert trace(one, two, three).first_difference(trace(one, two)).startswith(last.format(first, second))
    assert trace(one, two).first_difference(trace(one, two, three)).startswith(last.format(second, first))
    assert trace(one, two).first_difference(trace(one, two, three), ("the log", "the re-run")).startswith(
        last.format("the re-run", "the log"))
    middle = "record 1: event a.y #0 at t=0.000000000s m=1 is in {}, not in {}: "
    assert trace(one, two, three).first_difference(trace(one, three)).startswith(middle.format(first, second))
    assert trace(one, three).first_difference(trace(one, two, three)).startswith(middle.format(second, first))
    assert trace(one, two).first_difference(trace(one, ((0, 1), "y", 0, 2.5))) == (
        "record 1: Event(tag=(0, 1), node='a', port='y', seq=0, value=2.0, publish_ns=0) != "
        "Event(tag=(0, 1), node='a', port='y', seq=0, value=2.5, publish_ns=0)")
    assert trace(one, two).first_difference(trace(one, ((0, 2), "y", 0, 2.0))).startswith(
        "record 1: Event(tag=(0, 1), node='a', port='y', seq=0, value=2.0, publish_ns=0) != Event(tag=(0, 2)")
    assert trace(one, two).first_difference(trace(one, two)) is None
    assert trace(one).first_difference(Trace([(one[0], "a", "x", 0, 1.0, 0)], [])) == "lengths differ: 2 records vs 1"
