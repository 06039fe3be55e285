"""``pipe.session`` and ``pipe.open()``: the public handle on the run going on (issue 37), the
one that the CLI, the benchmarks and the tests watch a run through."""

from __future__ import annotations

import pytest

from retriever import BackendError, Flow, Pipeline, Rate
from retriever.backends import Session


class Count(Flow):
    def __init__(self):
        self.n = 0

    def step(self) -> dict:
        self.n += 1
        return {"n": self.n}


def _pipe() -> Pipeline:
    with Pipeline("watched") as pipe:
        Count() @ Rate(hz=10)
    return pipe


def test_the_session_is_the_run_from_its_first_step_to_a_reset():
    pipe = _pipe()
    assert pipe.session is None
    pipe.step(0.5)
    session = pipe.session
    assert isinstance(session, Session) and session.backend_name == "inproc"
    assert session.trace is pipe.trace and session.stats() == pipe.stats()
    pipe.run(duration=0.5)
    assert pipe.session is session and session.now_ns == 1_000_000_000  # the run goes on
    pipe.reset()
    assert pipe.session is None


def test_open_opens_the_session_that_the_next_run_goes_on_with():
    pipe = _pipe()
    session = pipe.open("inproc", keep="records")
    assert pipe.session is session and session.keep == "records" and session.now_ns == 0
    assert pipe.open() is session
    pipe.run(duration=0.3)
    assert pipe.session is session and len(session.trace.steps_of("count")) == 3
    with pytest.raises(BackendError, match=r"backend options \['keep'\] can only be given on the first run/step"):
        pipe.open(keep="trace")
