"""The coordinator of a real-time run on Zenoh: the embedded default (docs/realtime.md).

    pipe.run(duration=10, backend="zenoh")
        │ open the hub (tcp/127.0.0.1:PORT, a free port), write SPEC.json (IR + python path)
        │ start one worker process per node ──▶ each says `ready` on status/node/<node>
        │ put `start` {T0 = HLC now + margin, end} on ctl/run
        │ collect status/report/* (the events each worker published, its step records) into the
        │ trace and the log: the coordinator is not on the events' path
        ▼ every worker says `done` (or one fails: `stop` the rest) → processes reaped, sessions closed

What it listens to, and what it decides::

    status/node/<node> ─┐                   ┌─▶ StatusMachine: one handler per status
    status/report/<node>┴─▶ signed? ─▶ Inbox┤     (ready, restart, done, failed, handed_over,
       (Zenoh's thread: origin.Senders)     │      reached, exit, unanswered)
                                            └─▶ ReportIngest: step records, events ─▶ trace
    Waits (the coordinator's thread)             │ both write one RunBook
      ├─ until every node is ready, then `start` ▼
      ├─ every LOG_HANDOVER_S: session.write_log() ─▶ LogWriter: what is new in the trace ─▶ the log
      ├─ Supervisor.check: a dead process ─▶ restart afresh, or fail the run
      ├─ a failure ─▶ the run's error (diagnostics) ─▶ stop, reap
      └─ every node done, every report in ─▶ end checks (forged, exit recorded, every flow ticked)
    ctl/run ◀─ RunControl: redeclare, start, grant, have, lost, restarted, handover, resume, end, stop

    core.py         Coordinator: opens the hub, wires the parts below, runs, closes
    hosting.py      where the processes run (Hosting; LocalHosting: this machine)
    book.py         RunBook: what the coordinator knows of the run, a part per concern and writer
    inbox.py        the signed messages, dispatched to their handler
    statuses.py     the status state machine (PROCESS_STAGES, may_say)
    reports.py      report and event ingest
    processes.py    spawn, check, lost, restart afresh, stop, reap
    waiting.py      the waits for the start and the finish, lockstep virtual time
    exits.py        virtual time: records held until no step's sys.exit(0) cuts them off
    diagnostics.py  stacks, what a node left unfinished, the run's error
    faults.py       Fault, RunFailure: what went wrong, as typed records
    endchecks.py    what is checked and said once the run is over
    control.py      RunControl: the puts on ctl/run
    spec.py         the run's directory, the flows' import path

Tags in the trace and the log are ns since ``T0``, so a run's trace compares with the in-process
backend's directly. Workers are started and stopped by PID; none outlives the run (each also asks
the kernel for SIGTERM when its parent dies).
"""

from __future__ import annotations

from .book import BookView, RunBook
from .control import RunControl
from .core import Coordinator, Parts, assemble
from .diagnostics import STACKS_WAIT_S
from .endchecks import ticks_due
from .hosting import Hosting, LocalHosting
from .processes import STOP_GRACE_S
from .spec import run_dir
from .statuses import PROCESS_STAGES, may_say

__all__ = ["PROCESS_STAGES", "STACKS_WAIT_S", "STOP_GRACE_S", "BookView", "Coordinator", "Hosting", "LocalHosting",
           "Parts", "RunBook", "RunControl", "assemble", "may_say", "run_dir", "ticks_due"]
