"""The coordinator's memory of what it has seen (seen.py) answers as a set would, in bounded memory."""

from hypothesis import given, settings
from hypothesis import strategies as st

from retriever.backends.zenoh.seen import EventIds, RecentTicks


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["cam", "ctl"]), st.integers(0, 40)), max_size=80))
def test_event_ids_answer_as_a_set_would_whatever_the_order(ops):
    ids, reference = EventIds(), set()
    for node, seq in ops:
        ids.add((node, "out", seq))
        reference.add((node, "out", seq))
        for probe in ((n, "out", q) for n in ("cam", "ctl") for q in range(-1, 42)):
            assert (probe in ids) == (probe in reference), probe
        assert ("cam", "other", seq) not in ids
    copy = ids.copy()
    copy.add(("cam", "out", 99))
    assert ("cam", "out", 99) in copy and ("cam", "out", 99) not in ids


def test_a_stream_in_order_is_one_run_and_a_gap_one_more():
    ids = EventIds()
    for seq in range(100_000):
        ids.add(("cam", "image", seq))
    assert ids.runs() == 1
    for seq in range(100_010, 100_020):  # a restarted producer skips seqs
        ids.add(("cam", "image", seq))
    assert ids.runs() == 2 and ("cam", "image", 100_005) not in ids and ("cam", "image", 99_999) in ids


def test_recent_ticks_hold_a_window_per_node_and_count_older_ones_as_seen():
    ticks = RecentTicks(window=4)
    for t in range(10):
        ticks.add(("ctl", (t, 0)))
    assert ("ctl", (9, 0)) in ticks and ("ctl", (10, 0)) not in ticks
    assert ("ctl", (2, 0)) in ticks  # below the floor: refused as a second record
    assert ("cam", (2, 0)) not in ticks
    assert ticks.remembered() == 4
    copy = ticks.copy()
    copy.add(("cam", (1, 0)))
    assert ("cam", (1, 0)) in copy and ("cam", (1, 0)) not in ticks
