"""node/ending.py: a node loop ends one way, the gravest of those it was told, whatever their
order (NodeLoop.ending): a real NodeLoop given the run's control messages by hand."""

from __future__ import annotations

import itertools

import pytest

from retriever import Pipeline, Queue, Rate, Trigger
from retriever.backends.zenoh.node import CONTROL, Ending
from retriever.backends.zenoh.protocol import Handover, Lost, Stop
from retriever.backends.zenoh.worker.build import build_loop

from .semantics_flows import Ticker, WhereRun
from .specs import run_spec

#: each control message that ends the loop of ``where``, and how it ends it
TOLD = {"stop": (Stop(), Ending.TOLD_TO_STOP), "handover": (Handover(node="where"), Ending.HANDING_OVER),
        "lost": (Lost(node="where"), Ending.ABANDONED)}
#: every order of every non-empty set of them
ORDERS = [order for n in range(1, len(TOLD) + 1) for told in itertools.combinations(TOLD, n)
          for order in itertools.permutations(told)]


@pytest.fixture
def loop(session):
    """The loop of ``where`` (on_error="restart"), declared, not started."""
    with Pipeline("ending_by_hand") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where", on_error="restart") @ Trigger("x"), sync=Queue(maxsize=10),
                 map={"value": "x"})
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "ending-test"), "where", session)
    loop.declare()
    yield loop
    loop.undeclare()


def test_a_loop_told_nothing_has_no_ending(loop):
    assert (loop.ending, loop.stopping) == (None, False)


@pytest.mark.parametrize("order", ORDERS, ids="-".join)
def test_the_gravest_ending_wins_whatever_the_order(loop, order):
    loop.restarting = True  # (a handover is for a restarting loop only)
    for name in order:
        loop.handle((CONTROL, None, TOLD[name][0]))
    assert loop.stopping
    assert loop.ending is max(TOLD[name][1] for name in order)


def test_a_handover_to_a_loop_that_is_not_restarting_ends_nothing(loop):
    loop.handle((CONTROL, None, Handover(node="where")))
    assert (loop.ending, loop.stopping) == (None, False)
