"""The seed paper's spellings of the API (issue 19 §4): its imports, flows with ``run``, its
backend names and ``blocking=``. (Its listing runs on "dora", which is not built yet.)"""

from __future__ import annotations

import pytest

from retriever import BackendError
from tests.paper_flows import build


@pytest.mark.parametrize("backend", ["in-process", "multiprocessing"])
def test_a_flow_whose_method_is_run_steps_on_the_papers_backend_names(backend):
    pipe = build()
    options = {"quiet": True} if backend == "multiprocessing" else {}
    trace = pipe.run(backend=backend, duration=0.5, blocking=True, **options)
    assert [e.value.tolist() for e in trace.events_of("source")][:2] == [[1, 1, 1, 1], [2, 2, 2, 2]]
    assert len(trace.steps_of("sink")) == 10 and all(s.status == "ok" for s in trace.steps_of("sink"))
    assert pipe._session.backend_name == ("inproc" if backend == "in-process" else "zenoh")


def test_the_dora_backend_says_it_is_not_built_yet():
    with pytest.raises(BackendError, match=r"the dora backend is not built yet(.|\n)*hint: run on "
                                           r"backend='multiprocessing'"):
        build().run(backend="dora", duration=0.1)


def test_a_run_in_the_background_returns_a_handle_with_the_same_trace():
    handle = build().run(duration=2.0, blocking=False)
    assert handle.wait(timeout=60) == build().run(duration=2.0)
    assert handle.done


def test_a_background_run_stops_when_its_handle_says_so():
    pipe = build()
    handle = pipe.run(duration=1e6, blocking=False)  # 11 days of virtual time: it would take minutes
    while pipe._session is None or not pipe._session.trace.raw_steps:  # bounded by the run's start
        pass
    handle.stop()
    with pytest.raises(KeyboardInterrupt):
        handle.wait(timeout=60)
    assert handle.done and 0 < len(pipe.trace.steps) < 1e6 * 40
