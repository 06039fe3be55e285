"""The Zenoh runtime's protocol: every control and status message, as a typed record.

Each message is a frozen dataclass with ``encode()`` (the bytes its sender puts) and an exact ``decode`` (schema.py: every field's type, range and size, none missing,
none more, no extension type; a :class:`WireError` names the field). Op and state names are the
enums below; no other module spells one, but for a spawn's mode, which is the worker's command
line's (``SpawnMode``: command.py reads both). The events and progress of the data plane keep
their own exact decoders in wire.py.

    schema.py          field kinds, the record base, the envelopes
    to_coordinator.py  worker → coordinator: statuses (State), reports
    to_worker.py       coordinator → workers: ctl/run (Op), and answers to a worker's questions
    daemon.py          coordinator ↔ worker daemon: requests, replies, errors, the daemon's events
    deployment.py      `retriever status` / `retriever stop` ↔ a deployment's coordinator
    run_spec.py        the run's spec: coordinator or daemon → each worker process (a dora
                       run's with a part of its own: DoraPart)
    handover.py        restarting worker process → its successor: the hand-over state file
                       (HandoverState, read from the codec's bytes: values may be arrays)
    seal.py            signed control: the coordinator seals, each worker process opens

Every message of the key space (under ``retriever/<namespace>/``). Signed: *process*, with the
MAC of the sending worker process's own key (origin.py); *sealed*, by the coordinator for each
live process (seal.py: ctl/run and its answers); *run*, by a worker daemon with the key it made
for the run and answered in its prepare reply (daemon/runs.py); *request*, by the coordinator
with a key derived from the deployment secret, each nonce taken once (seal.py: every op of
ctl/<name> but ``info``, when the daemon has a secret); *none*, the session's credentials alone (anyone holding the run's or the namespace's password
may send it). The last column: what the receiver checks today beyond the fields (which the
decoders check).

    key / message          from → to       fields (in order; [optional])    signed  the receiver checks too
    ---------------------- --------------- -------------------------------- ------- ---------------------------------
    data/<node>/<port>     worker → its    wire.py: [2, tag, seq, frontier, none    key names producer.port; seq not
                           consumers, put  producer, port, value(, count)]          from the future (EARLY_SEQS_MAX);
                                                                                    frontier not past what it can
                                                                                    promise; each seq once
    progress/<node>        worker → its    wire.py: [2, frontier, producer, none    producer = key; frontier as above
                           consumers, put  {port: last seq}]
                           and reply
    warm/<node>            worker → its    empty (never read): the consumer none    -
                           consumers, put  rehearses an arrival (timing.py)
    ---------------------- --------------- -------------------------------- ------- ---------------------------------
    status/node/<node>     worker →        [2, node, state, {fields, pid}]  process node of the run; signed by its
                           coordinator,                                             current process (done, failed: or
                           put                                                      its retiring one; handed_over:
                                                                                    the retiring one only); a
                                                                                    process's states in order
                                                                                    (may_say)
      ready                                [linked, unlinked, peers]                linked false: the run fails; else
                                                                                    restarted, handover or afresh, by
                                                                                    what the coordinator waits for
      done                                 counts, [reports, started_ns,            stopped true with no stop sent:
                                           ticks, stopped, sent]                    the run fails; sent: output ports
                                                                                    of the node
      failed                               error, [setup], [tag], [counts],         the run fails: SetupError
                                           traceback, [zeno], [raised],             (setup), CausalityError (zeno),
                                           [out_of_restarts]                        RestartLimitError
                                                                                    (out_of_restarts, tag, raised),
                                                                                    StepError (tag)
      restart                              tag, error                               the node's restart budget
      handed_over                          counts, reports                          -
      reached                              until                                    virtual time only; min(until,
                                                                                    grant)
      unanswered                           nodes                                    nodes of the run; before the
                                                                                    start only
      exit                                 tag                                      ends the run only beside the
                                                                                    node's own ok record at that tag,
                                                                                    detail {exit: 0}
    status/report/<node>   worker →        [2, node, [[tag, consumed,       process node of the run; one record per
                           coordinator,    produced, status, detail,                tick, on the node's clock; an
                           put             wall_start_ns, wall_ns], …],             event of its outputs or of an
                                           [[wall_ns, message or file               edge into it, once; a file name
                                           name], …]]                               is the node's own, in the run
                                                                                    directory
    ---------------------- --------------- -------------------------------- ------- ---------------------------------
    ctl/run                coordinator →   [2, op, {fields}]                sealed  (by op)
                           workers, put
      start                                t0, end, values, [grant]                 waited for by a node's first
                                                                                    process
      grant                                until                                    virtual time only; the grant only
                                                                                    grows
      redeclare                            nodes                                    before the start: its node named;
                                                                                    during the run: garbage
      restarted                            node, seqs, values                       the node's fresh process: a seq
                                                                                    >= RESTART_SEQ_GAP per port; a
                                                                                    consumer: node said lost, seqs
                                                                                    near its streams'
      handover                             node                                     the node's process, restarting
      resume                               node                                     the node's new process, waiting
      end                                  at                                       end = min(end, at)
      have                                 streams: [[producer, port, seq],         streams it consumes; have only
                                           …]                                       grows
      lost                                 node                                     its own node: stop, promise
                                                                                    nothing; a producer: its seqs may
                                                                                    jump
      stop                                 -                                        -
    ctl/start              worker query →  start {t0, end, values}          sealed  joins the worker's inbox as
                           coordinator                                              ctl/run's start
                           reply
    status/finished        worker query →  finished {nodes, complete,       sealed  names only
                           coordinator     restarting}
                           reply
    ---------------------- --------------- -------------------------------- ------- ---------------------------------
    ctl/<name>             coordinator     [2, op, {fields}] → [2, op,      request the daemon: size
                           query → daemon  {fields}], or reply_err [2,              (MAX_REQUEST_BYTES), op; the
                           reply           "error", {message}]                      coordinator: replies only from
                                                                                    the session it learned the daemon
                                                                                    by
      info                                 - → protocol, name, labels,              protocol = PROTOCOL_VERSION; the
                                           host, pid, python, packages,             clock's offset; one daemon per
                                           clock_ns, nodes, counts                  name
      prepare                              run, spec, nodes → nodes,                the IR (ir.IR); each class on the
                                           warnings, key                            allowlist, its code's hash; a
                                                                                    coordinator's token up; one run
                                                                                    at a time; the spec's zids,
                                                                                    hub_zid, virtual_time
      spawn                                run, node, mode → pid, key               run and node prepared; no key in
                                                                                    the request; the code's hash
                                                                                    again; at most 2 processes per
                                                                                    node
      signal                               run, pid, signal → -                     a process of the run; USR1, TERM
                                                                                    or KILL
      usage                                run → cpu_s                              the run prepared
      end                                  run → -                                  the run prepared
    workers/<name>/events  daemon →        [2, op, {fields}]                run     its run (a daemon serves one at a
                           coordinator,                                             time); signed with the key its
                                                                                    prepare reply gave
                           put
      output                               run, node, stream, lines                 -
      exit                                 run, node, pid, code                     a process the coordinator started
                                                                                    there
    workers/<name>         daemon          liveliness token                 none    -
    ---------------------- --------------- -------------------------------- ------- ---------------------------------
    deployment             CLI query →     status {} → pipeline, run, t_ns, none    op (anyone holding the
                           coordinator     end_ns, started, nodes; stop {}          namespace's secret may ask, and
                           reply           → pipeline; or reply_err error           stop it: by design)
                                           {message}
    deployment             coordinator     liveliness token                 none    daemons end its run when it goes
"""

from __future__ import annotations

from ..command import SpawnMode
from .daemon import (DAEMON_EVENT, ERROR, ERROR_REPLY, MAX_REQUEST_BYTES, PROTOCOL_VERSION, REPLY, REQUEST,
                     SEALED_OPS, DaemonEvent, DaemonOp, EndReply, EndRequest, ErrorReply, InfoReply, InfoRequest,
                     OtherProtocolReply, PrepareReply, PrepareRequest, ProcessExit, ProcessOutput, SignalReply,
                     SignalRequest, SpawnReply, SpawnRequest, Stream, UsageReply, UsageRequest, decode_reply,
                     error_message)
from .deployment import (DEPLOYMENT_QUERY, DEPLOYMENT_REPLY, DeploymentOp, NodeState, NodeStatus, StatusQuery,
                         StatusReply, StopQuery, StopReply)
from .handover import HANDOVER_EVENTS_MAX, HandoverState, decode_handover_state
from .run_spec import DoraPart, RunSpec
from .schema import ABSENT, Record
from .seal import ControlOpener, ControlSigner, RequestOpener, RequestSealer, new_nonce
from .to_coordinator import (EXIT_ABANDONED, EXIT_FAILED, EXIT_HANDED_OVER, STATUS, Done, Exit, Failed, HandedOver, Reached, Ready, Report, ReportedEvent,
                             ReportedStep, Restart, State, Status, Unanswered)
from .to_worker import (FINISHED_REPLY, RESTART_SEQ_GAP, RUN_CONTROL, End, Finished, Grant, Handover, Have, Lost, Op, Redeclare,
                        Restarted, Resume, Start, Stop)

__all__ = sorted([
    "ABSENT", "ControlOpener", "ControlSigner", "DAEMON_EVENT", "DEPLOYMENT_QUERY", "DEPLOYMENT_REPLY", "DaemonEvent",
    "DaemonOp", "DeploymentOp", "Done", "DoraPart", "ERROR", "ERROR_REPLY", "EXIT_ABANDONED", "EXIT_FAILED",
    "EXIT_HANDED_OVER", "End", "EndReply", "EndRequest", "ErrorReply", "Exit", "FINISHED_REPLY", "Failed", "Finished",
    "Grant", "HANDOVER_EVENTS_MAX", "HandedOver", "Handover", "HandoverState", "Have", "InfoReply", "InfoRequest",
    "Lost", "MAX_REQUEST_BYTES", "NodeState", "NodeStatus", "Op", "OtherProtocolReply", "PROTOCOL_VERSION",
    "PrepareReply", "PrepareRequest", "ProcessExit", "ProcessOutput", "REPLY", "REQUEST", "RESTART_SEQ_GAP",
    "RUN_CONTROL", "Reached", "Ready", "Record", "Redeclare", "Report", "ReportedEvent", "ReportedStep",
    "RequestOpener", "RequestSealer", "Restart", "Restarted", "Resume", "RunSpec", "SEALED_OPS", "STATUS",
    "SignalReply", "SignalRequest", "SpawnMode", "SpawnReply", "SpawnRequest", "Start", "State", "Status",
    "StatusQuery", "StatusReply", "Stop", "StopQuery", "StopReply", "Stream", "Unanswered", "UsageReply",
    "UsageRequest", "decode_handover_state", "decode_reply", "error_message", "new_nonce",
])
