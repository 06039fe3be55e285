"""The Zenoh runtime's protocol: every control and status message, as a typed record (issue 37).

Each message is a frozen dataclass with ``encode()`` (the bytes today's senders put, byte for
byte) and an exact ``decode`` (schema.py: every field's type, range and size, none missing,
none more, no extension type; a :class:`WireError` names the field). Op and state names are the
enums below; no other module spells one. The events and progress of the data plane keep their
own exact decoders in wire.py.

    schema.py          field kinds, the record base, the envelopes
    to_coordinator.py  worker → coordinator: statuses (State), reports
    to_worker.py       coordinator → workers: ctl/run (Op), and answers to a worker's questions
    daemon.py          coordinator ↔ worker daemon: requests, replies, errors, the daemon's events
    deployment.py      `retriever status` / `retriever stop` ↔ a deployment's coordinator
    seal.py            signed control: the coordinator seals, each worker process opens

Every message of the key space (under ``retriever/<namespace>/``). Signed: *process*, with the
MAC of the sending worker process's own key (origin.py); *sealed*, by the coordinator for each
live process (seal.py; ctl/run and its answers, once wired); *none*, the session's credentials
alone (anyone holding the run's or the namespace's password may send it). Checks: what the
receiver checks today beyond the fields' types.

    key / message              direction, how          fields                                  signed   receiver checks
    -------------------------  ----------------------  --------------------------------------  -------  ---------------------------------------------
    data/<node>/<port>         worker → consumers put  wire.py: [2, tag, seq, frontier,        none     key names producer.port; seq not from the
                                                       producer, port, value(, count)]                  future (EARLY_SEQS_MAX); frontier not past
                                                                                                        what it can promise; a seq once (loop.py)
    progress/<node>            worker → consumers put  wire.py: [2, frontier, producer,        none     producer = key; frontier as above
                               and queryable reply     {port: last seq}]
    warm/<node>                worker put              empty; no one subscribes                none     -
    status/node/<node>         worker → coordinator    [2, node, state, {fields…, pid}]        process  node of the run; signed by its current
                               put                                                                      process (done, failed: or its retiring
                                                                                                        one; handed_over: the retiring one only);
                                                                                                        states in a process's order (may_say)
      ready                                            [linked, unlinked, peers]                        linked false: the run fails (no link);
                                                                                                        else restarted / handover / afresh, by
                                                                                                        what the coordinator waits for
      done                                             counts, [reports, started_ns, ticks,             stopped true and no stop sent: the run
                                                       stopped, sent]                                   fails; sent: output ports of the node
      failed                                           error, [setup], [tag], [counts],                 the run fails: SetupError (setup),
                                                       traceback, [zeno]                                CausalityError (zeno), StepError (tag)
      restart                                          tag, error                                       the node's restart budget
      handed_over                                      counts, reports                                  -
      reached                                          until                                            virtual time only; min(until, grant)
      unanswered                                       nodes                                            nodes of the run; before the start only
      exit                                             tag                                              ends the run only beside the node's own
                                                                                                        ok record, detail {exit: 0}, at that tag
    status/report/<node>       worker → coordinator    [2, node, [[tag, consumed, produced,    process  node of the run; one record per tick, on
                               put                     status, detail, wall_start_ns,                   the node's clock; an event of its outputs
                                                       wall_ns], …], [[wall_ns, message or              or of an edge into it, once; a file name
                                                       file name], …]]                                  is the node's own, in the run directory
    ctl/run                    coordinator → workers   [2, op, {fields}]                       sealed   (see each op)
                               put
      start                                            t0, end, values, [grant]                         waited for by a first process
      grant                                            until                                            virtual time only; granted only grows
      redeclare                                        nodes                                            before the start: its node named;
                                                                                                        during the run: garbage
      restarted                                        node, seqs, values                               the node's fresh process: a seq >=
                                                                                                        RESTART_SEQ_GAP per port; a consumer:
                                                                                                        node said lost, seqs near its streams
      handover                                         node                                             the node's process, restarting
      resume                                           node                                             the node's new process, waiting
      end                                              at                                               end = min(end, at)
      have                                             streams: [[producer, port, seq], …]              streams it consumes; have only grows
      lost                                             node                                             its own: stop, promise nothing; a
                                                                                                        producer's: its seqs may jump
      stop                                             -                                                -
    ctl/start                  worker query →          reply: start {t0, end, values}          sealed   joins the worker's inbox as ctl/run's
                               coordinator reply
    status/finished            worker query →          reply: finished {nodes, complete,       sealed   names only
                               coordinator reply       restarting}
    ctl/<name>                 coordinator query →     [2, op, {fields}] → [2, op, {fields}]   none     the daemon: size (MAX_REQUEST_BYTES), op;
                               daemon reply            or reply_err [2, "error", {message}]             the coordinator: replies only from the
                                                                                                        session it learned the daemon by
      info                                             - → protocol, name, labels, host, pid,           protocol = PROTOCOL_VERSION; the clock's
                                                       python, packages, clock_ns, nodes,               offset; one daemon per name
                                                       counts
      prepare                                          run, spec, nodes → nodes, warnings               the IR (ir.IR); each class on the
                                                                                                        allowlist, its code's hash; a
                                                                                                        coordinator's token up; one run at a time;
                                                                                                        spec's zids, hub_zid, virtual_time
      spawn                                            run, node, mode → pid, key                       run and node prepared; no key in the
                                                                                                        request; the code's hash again; at most 2
                                                                                                        processes per node
      signal                                           run, pid, signal → -                             a process of the run; USR1, TERM or KILL
      usage                                            run → cpu_s                                      the run prepared
      end                                              run → -                                          the run prepared
    workers/<name>/events      daemon → coordinator    [2, op, {fields}]                       none     its run (the daemon serves one at a time)
                               put
      output                                           run, node, stream, lines                         -
      exit                                             run, node, pid, code                             a process the coordinator started there
    workers/<name>             daemon                  liveliness token                        none     -
    deployment                 CLI query → the         status {} → pipeline, run, t_ns,        none     op (anyone holding the namespace's
                               deployment's reply      end_ns, started, nodes; stop {} →                secret may ask, and stop it: by design)
                                                       pipeline; or reply_err error {message}
    deployment                 coordinator             liveliness token                        none     daemons end its run when it goes
"""

from __future__ import annotations

from .daemon import (DAEMON_EVENT, ERROR, ERROR_REPLY, MAX_REQUEST_BYTES, PROTOCOL_VERSION, REPLY, REQUEST, DaemonEvent, DaemonOp,
                     EndReply, EndRequest, ErrorReply, InfoReply, InfoRequest, PrepareReply, PrepareRequest,
                     ProcessExit, ProcessOutput, SignalReply, SignalRequest, SpawnMode, SpawnReply, SpawnRequest, Stream,
                     UsageReply, UsageRequest, decode_reply, error_message)
from .deployment import (DEPLOYMENT_QUERY, DEPLOYMENT_REPLY, DeploymentOp, NodeStatus, StatusQuery, StatusReply,
                         StopQuery, StopReply)
from .schema import ABSENT, Record
from .seal import ControlOpener, ControlSigner, new_nonce
from .to_coordinator import (STATUS, Done, Exit, Failed, HandedOver, Reached, Ready, Report, ReportedEvent,
                             ReportedStep, Restart, State, Status, Unanswered)
from .to_worker import (FINISHED_REPLY, RUN_CONTROL, End, Finished, Grant, Handover, Have, Lost, Op, Redeclare,
                        Restarted, Resume, Start, Stop)

__all__ = sorted([
    "ABSENT", "DAEMON_EVENT", "DEPLOYMENT_QUERY", "DEPLOYMENT_REPLY", "ERROR", "ERROR_REPLY", "FINISHED_REPLY",
    "MAX_REQUEST_BYTES", "PROTOCOL_VERSION", "REPLY", "REQUEST", "RUN_CONTROL", "STATUS", "ControlOpener", "ControlSigner", "DaemonEvent",
    "DaemonOp", "DeploymentOp", "Done", "End", "EndReply", "EndRequest", "ErrorReply", "Exit", "Failed", "Finished",
    "Grant", "HandedOver", "Handover", "Have", "InfoReply", "InfoRequest", "Lost", "NodeStatus", "Op", "PrepareReply",
    "PrepareRequest", "ProcessExit", "ProcessOutput", "Reached", "Ready", "Record", "Redeclare", "Report",
    "ReportedEvent", "ReportedStep", "Restart", "Restarted", "Resume", "SignalReply", "SignalRequest", "SpawnMode",
    "SpawnReply", "SpawnRequest", "Start", "State", "Status", "StatusQuery", "StatusReply", "Stop", "StopQuery",
    "StopReply", "Stream", "Unanswered", "UsageReply", "UsageRequest", "decode_reply", "error_message", "new_nonce",
])
