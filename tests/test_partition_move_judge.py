"""benchmarks/partition_move.py's verdict on a trial, on synthetic step records: recovered, starved
(reported or not), and a move too late in the run to tell either."""

from __future__ import annotations

from benchmarks.partition_move import verdict
from retriever import StepRecord

MS = 1_000_000
LEASE_S = 1.0
MOVED = [{"node": "viewer", "moved_to": "spare"}]
TABLE_MARKED = "│ viewer   │ 50.0 Hz │ frame from 4.20 s\n"
WARNED = "warning: node 'viewer' is starved of camera.frame\n"


def viewer(restart_s: float, end_s: float, frames_from_s: float | None, gap: tuple[float, float] = (0, 0)) -> list:
    """The viewer's ticks at 50 Hz from its restart to the run's end; from ``frames_from_s`` on
    each consumed a frame, but those inside ``gap``."""
    steps, t = [], round(restart_s * 1000) * MS
    first = True
    while t < end_s * 1e9:
        fed = frames_from_s is not None and t >= frames_from_s * 1e9 and not gap[0] * 1e9 <= t < gap[1] * 1e9
        steps.append(StepRecord("viewer", (t, 0), {"frame": (("camera", "frame", t),)} if fed else {}, (),
                                "ok" if fed else "skipped", {"restarted": True} if first else None))
        first, t = False, t + 20 * MS
    return steps


def test_a_viewer_fed_again_soon_after_its_move_recovered():
    got = verdict(MOVED, viewer(5.0, 12.0, 5.04), [], "", "", LEASE_S)
    assert got["moved"] and got["recovered"] and not got["too_late"]
    assert abs(got["first_event_s"] - 0.04) < 1e-9 and got["missed_after"] == 0


def test_a_viewer_that_lost_its_frames_again_did_not_recover():
    got = verdict(MOVED, viewer(5.0, 12.0, 5.0, gap=(7.0, 12.0)), [], "", "", LEASE_S)
    assert got["moved"] and not got["recovered"] and not got["too_late"] and not got["reported"]


def test_a_starved_viewer_is_reported_only_when_warned_marked_and_logged():
    steps, span = viewer(5.0, 12.0, None), [{"node": "viewer", "port": "frame", "from_ns": 6 * 10**9}]
    assert verdict(MOVED, steps, span, TABLE_MARKED, WARNED, LEASE_S)["reported"]
    unreported = verdict(MOVED, steps, [], TABLE_MARKED, WARNED, LEASE_S)
    assert not unreported["recovered"] and not unreported["too_late"] and not unreported["reported"]
    assert unreported["first_event_s"] is None


def test_a_first_frame_less_than_a_lease_before_the_end_is_too_late_to_tell():
    got = verdict(MOVED, viewer(11.0, 12.0, 11.2), [], "", "", LEASE_S)
    assert got["moved"] and got["too_late"] and not got["recovered"]
    assert abs(got["first_event_s"] - 0.2) < 1e-9


def test_a_restart_less_than_a_lease_before_the_end_with_no_frame_is_too_late_to_tell():
    got = verdict(MOVED, viewer(11.5, 12.0, None), [], "", "", LEASE_S)
    assert got["moved"] and got["too_late"] and not got["recovered"]


def test_no_move_recorded_is_not_moved():
    got = verdict([], viewer(5.0, 12.0, 5.0), [], "", "", LEASE_S)
    assert not got["moved"] and not got["too_late"] and not got["recovered"]
