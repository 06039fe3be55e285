"""Re-execute a logged run and compare it with the log, byte for byte.

``replay`` (the default) isolates every flow: each logged step of a non-source node runs again
on inputs rebuilt from the *logged* events with the edge's policy, so one divergent node cannot
hide or cause divergence elsewhere. Per step it checks the consumed event ids against the log,
then the status, the produced ids and tags, and every output value's msgpack bytes.

What a real-time run did, the replay does: an event that reached a consumer late (after a tick
at or past its tag ran) goes in its buffer right before the consumer's record that names it,
as it did in the run, never earlier; a LET step whose deadline miss dropped its outputs has them
taken back (their seqs used again); a tick the run stopped before stepping is not stepped; and
``incomplete``, ``late`` and ``overrun`` steps compare as ``ok`` (the replay cannot be late).
A flow whose process died and was started afresh (on_error="restart") starts afresh at its first
record after (``restarted``: flow reset, input buffers emptied, events from where the new process
took each stream on); its consumers are withheld the dead process's events they never got
(``restart_gap``); and its steps whose outputs died with it (the log's fault records) are
re-executed but not compared.

Both first compare the sha256 of each flow module's file, as the run's IR recorded it, with the
file the replay loaded (retriever/code.py): a module edited since the run is warned of before any
value is compared, and named again in the report (``code_changes``), so that a divergence it
causes is not taken for nondeterminism.

**Memory: a log larger than RAM replays.** ``replay_file(path)`` (what ``retriever replay``
runs) reads the file twice and keeps neither:

1. ``log.reader.scan_log`` checks it whole, as ``read_log`` does (the same errors for a log torn
   or damaged, before anything runs), handing each message to a :class:`LogSurvey`: what the
   replay must know of the whole log before its first step, in memory that grows with what was
   unusual in the run, not with its length (the nodes, the step count, the event ids as ranges
   of seqs per port, the ``late`` / ``had_below`` / ``restart_gap`` details), and where the chunks
   are. A step record without detail (nearly all) is only read for its node there (where the
   chunk is read as arrays, every one at once: whether it has the plain shape Retriever writes,
   ``survey._plain_steps``): the second pass checks it, whole where the survey did not find it
   plain (``LogSurvey.unchecked``), else its status alone, which is all the shape leaves to
   check; a log with one that is not one is refused there, with the same error and no report;
2. ``ScannedLog.in_order`` reads the messages again in log-time order (ties in file
   order: what sorting the file's messages by log time gives), chunk by chunk, holding only the
   chunks whose times overlap (as numpy arrays; handed on in batches of columns, no tuple a
   message). The replay takes them an instant (a log time) at a time: the instant's events go
   to their consumers' deliveries (decoded once, on a heap by arrival; a value only ``Latest``
   inputs take, once a tick takes it, when it decodes surely), then
   its step records run in ``(tag, node)`` order, as when every record was sorted up front. An
   event waits until the record that produced it has run (the same instant, for a log a run
   wrote); a step's outputs are compared once they are read (a LET step's come later in the
   log than its tick), the comparisons reported in step order. An id that the survey says the
   log lacks is known to be missing at once (the log is cut short, or it is a divergence). A
   source is not re-executed, so its records are checked against the log's events: one naming
   an event the log lacks, or one an earlier record named, and an event no record of its source
   named, refuse the log (a LogError; not in a log cut short or whose process died).

``replay(log)`` of a log read whole (``read_log``) takes the same two steps over its message
list. Only a changed log can tell them apart: a record that names as late an event from its own
future puts it in at once rather than at that record, and a second record naming an event the
first already took compares as if the log lacked it. ``keep_trace`` holds the whole replayed run,
so only ``replay`` has it.

``resim`` re-runs the whole graph in virtual time, with the sources emitting their logged events,
and compares the full trace: it proves the log is one consistent run of this graph.
``resim_file(path)`` (what ``retriever replay --resim`` runs) reads the file twice and keeps
neither, as ``replay_file`` does: a check of the whole, then its records in log-time order as the
re-simulation advances, a second of virtual time at a time (resimulation.py says how).

Replay runs the pipeline and the in-process backend, so it sits above them, not in ``log/``.
This ``__init__`` holds the two ways in, ``replay`` and ``replay_file``, and re-exports the public
names of the modules that do the work, one job each:

    survey.py        the first pass: LogSurvey, what the replay must know of the whole log
                     before its first step
    prepare.py       what runs: the pipeline (given, or rebuilt from the IR), its flows set up,
                     the code loaded compared with the run's
    steps.py         the second pass: StepReplay, an instant at a time (the deliveries, the
                     ticks re-executed, the checks reported in step order)
    compare.py       one step against the log: its tick on the clock, its record, its outputs'
                     tags and bytes
    report.py        what a replay finds: ReplayReport, each Divergence, where two values differ
    resimulation.py  resim: the whole graph re-run from its sources, its trace compared
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Iterator

from ..backends.inproc import InprocSession
from ..log.reader import LogHead, RunLog, read_log
from ..pipeline import Pipeline
from .compare import TickCheck
from .prepare import MAX_SAID, code_changes, from_the_log, pipeline_for, ran_other_code, set_up_flows, surveyed
from .report import MAX_DIVERGENCES_KEPT, Divergence, NodeReplay, ReplayReport, explain_difference
from .resimulation import ResimReport, ResimSurvey, resim, resim_file
from .steps import PROGRESS_EVERY, StepReplay
from .survey import LogSurvey

__all__ = sorted([
    "MAX_DIVERGENCES_KEPT", "MAX_SAID", "PROGRESS_EVERY", "Divergence", "LogSurvey", "NodeReplay", "ReplayReport",
    "ResimReport", "ResimSurvey", "TickCheck", "code_changes", "explain_difference", "from_the_log", "pipeline_for",
    "ran_other_code", "replay", "replay_file", "resim", "resim_file",
])


def replay(log: RunLog, pipeline: Pipeline | None = None,
           progress: Callable[[int, int], None] | None = None, keep_trace: bool = False) -> ReplayReport:
    """Re-execute every non-source step of ``log``; see the module docstring. The flows are set
    up before the first step and torn down at the end, as in a run. ``keep_trace=True`` keeps
    the replayed run in ``report.trace`` (what an export of the replay reads: docs/learning.md)."""
    survey = LogSurvey(log.path)
    # as message tuples (log/reader.py), positioned by their index: sorted, in log-time order, ties in file order
    messages = [(m.log_time, i, m.channel_id, m.sequence, m.publish_time, m.data) for i, m in enumerate(log.messages)]
    survey.take(log.channels, messages)

    def ordered() -> Iterator[tuple[list, ...]]:  # one batch of columns, as ScannedLog.in_order hands them
        if not messages:
            return iter(())
        log_times, _, channel_ids, sequences, publish_times, data = map(list, zip(*sorted(messages)))
        return iter([(log_times, channel_ids, sequences, publish_times, data)])

    return _replay_surveyed(log, survey, ordered, pipeline, progress, keep_trace)


def replay_file(path: str | os.PathLike, pipeline: Pipeline | Callable[[], Pipeline] | None = None,
                progress: Callable[[str, int, int], None] | None = None) -> ReplayReport:
    """:func:`replay` of the log at ``path`` that holds no more than a few of its chunks in memory
    at a time, however long the log (the module docstring says how). ``pipeline``: as for
    :func:`replay`, or a function that makes it, called once the log has been read (so a log
    that cannot be read is said first). ``progress(what, done, total)``: ``"reading"`` with bytes
    as the file is checked, then ``"replaying"`` with steps. A log with messages outside its chunks
    (MCAP allows them; Retriever's writer makes none) is replayed by :func:`replay`, read whole."""
    survey = LogSurvey(Path(path))
    log, pipeline, steps = surveyed(path, survey, pipeline, progress)
    if log.loose:
        return replay(read_log(path), pipeline, steps)
    return _replay_surveyed(log, survey, log.in_order, pipeline, steps, False)


def _replay_surveyed(log: LogHead, survey: LogSurvey, messages: Callable[[], Iterator], pipeline: Pipeline | None,
                     progress: Callable[[int, int], None] | None, keep_trace: bool) -> ReplayReport:
    pipeline = pipeline_for(log, pipeline, survey.logged_nodes)
    graph = pipeline.compile()
    survey.check_details(graph)
    changes = code_changes(log, graph)
    session = InprocSession(graph)
    logged = from_the_log(graph)
    set_up_flows(session, logged)
    try:
        report = StepReplay(log, survey, graph, session, logged, keep_trace).play(messages, progress)
    finally:
        session.close()
    report.code_changes = changes
    return report
