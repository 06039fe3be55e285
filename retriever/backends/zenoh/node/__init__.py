"""One node's real-time loop, inside its worker process (docs/semantics.md, docs/realtime.md).

    transport thread ──(DATA: key, bytes)──▶ inbox ──┐   (or, the main thread waiting and the
    control, progress ──(CONTROL, PROGRESS)────────▶ │    node's steps short: handled right
    a producer of this process ──(EVENTS)──────────▶ │    there, NodeLoop.receive, then NUDGE)
    NodeLoop.run ◀───────────────────────────────────┘
      ┌─▶ drain the inbox ── handle ─┬─ DATA ─────▶ frontiers.Streams: in seq order, frontiers,
      │                              │               deliver to buffers, schedule trigger ticks
      │                              ├─ EVENTS ───▶ the same, values by reference, nothing decoded
      │                              ├─ PROGRESS ─▶ frontiers.Streams: frontiers
      │                              ├─ CONTROL ──▶ control.obey: stop, end, grant, have, lost, …
      │                              ├─ NUDGE ────▶ nothing to take: look again at the time to wake
      │                              └─ FAILED ───▶ raised: the transport's receiving thread died
      │   outputs.release: held LET outputs whose time came
      │   try_tick: τ = the schedule's next Rate tick or pending trigger tag
      │     waiting: inputs complete up to τ (producers' frontiers > τ), or past deadline? else
      │              ask producers, wake later           (virtual time: the coordinator's grant)
      │     steps.tick: select inputs, step(), outcome ─▶ outputs: stamp, publish or hold (LET)
      │                                                 └▶ reports.record (flushed in batches)
      └── sleep until the next wake (timing.Pacer: warm up before it) or the next message

Tags are ``(ns since T0, microstep)``. A *frontier* is a producer's promise: every later event of
it has a tag ``≥`` the frontier (frontiers.py). ASAP outputs are stamped at completion, LET ones
``τ + latency`` and released then (outputs.py).

Virtual time (``virtual=True``, ``retriever deploy --virtual-time``): the same loop with logical
time only, so that the run's trace is the in-process backend's. A tick runs once its inputs are
complete, however long that takes (no deadline), outputs are stamped as in-process ((t, m + 1),
or (t + latency, 0) published at once), nothing overruns, and the wall clock only paces waiting
and asking; the coordinator advances all nodes in lockstep (waiting.py).

The modules, one job each:

    loop.py       NodeLoop: wiring, the inbox, the run loop (dispatch only)
    inbox.py      what the inbox holds
    transport.py  how events and progress travel (the seam; Zenoh's; dora's: retriever/backends/dora/link.py)
    linked.py     the same over same-host links (backends/zenoh/link/) where both ends are on this host
    clock.py      T0, the end, the wall and HLC clocks read from T0
    schedule.py   Rate ticks and pending trigger ticks
    frontiers.py  input streams: seq order, frontiers, claims refused, delivery to the edges
    waiting.py    whether a due tick may run; asking producers; the virtual-time lockstep
    steps.py      a tick: inputs, step(), and its outcome (overrun, LET deadline, on_error)
    source.py     the short way for a plain Rate source
    outputs.py    stamping, LET holding, publishing, the node's own frontier
    reports.py    step records and published events to the coordinator
    reporter.py   sending those reports, from a thread of its own
    notes.py      counts, and what the next step record must tell
    timing.py     warming up before a predictable moment; the loop's sleep to its next wake
    handover.py   restarts: the hand-over to a new process (its state file, which the protocol reads
                  exactly), a fresh start after a lost one
    in_place.py   a restart where the flow runs (a group's member): a fresh flow in the same loop
    control.py    the run's control messages
    ending.py     how a loop ends before the run's end, and which of two endings wins
    plane.py      the control plane on the run's session: control heard, progress queries answered
    group.py      several nodes in one process: their passes on one thread, events by reference
"""

from .ending import Ending
from .frontiers import CLOCK_AHEAD_MAX_NS, EARLY_SEQS_MAX, NEVER, WAITING_MAX, InEdge
from .inbox import CONTROL, DATA, FAILED, NUDGE, PROGRESS
from .loop import INLINE_STEP_NS, RESTART_POLL_NS, NodeLoop
from .reports import (FLUSH_AFTER_NS, FLUSH_MAX, FLUSH_MAX_BYTES, FLUSH_MAX_SEQS, HOLD_RECORDS_NS,
                      RECORDS_FLUSH_AFTER_NS, SPILL_BYTES)
from .timing import WARM_AFTER_IDLE_NS, WARM_AHEAD_NS
from .transport import Transport, ZenohTransport
from .waiting import ASK_EVERY_NS, PROBE_AFTER_NS, VIRTUAL_IDLE_NS

__all__ = [
    "ASK_EVERY_NS", "CLOCK_AHEAD_MAX_NS", "CONTROL", "DATA", "EARLY_SEQS_MAX", "Ending", "FAILED", "FLUSH_AFTER_NS",
    "FLUSH_MAX", "FLUSH_MAX_BYTES", "FLUSH_MAX_SEQS", "HOLD_RECORDS_NS", "INLINE_STEP_NS", "NEVER", "NUDGE",
    "PROBE_AFTER_NS", "PROGRESS", "RECORDS_FLUSH_AFTER_NS", "RESTART_POLL_NS", "SPILL_BYTES",
    "VIRTUAL_IDLE_NS", "WAITING_MAX", "WARM_AFTER_IDLE_NS", "WARM_AHEAD_NS", "InEdge", "NodeLoop", "Transport",
    "ZenohTransport",
]
