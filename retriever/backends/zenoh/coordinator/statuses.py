"""The status state machine: what each status a node's process says (status/node/<node>) does.

    status ──▶ decode ──▶ its node's? ──▶ signed by the process that may say it? ──▶ may_say? ──▶ HANDLERS[state]

Each process says where it is in its life (PROCESS_STAGES); the other statuses (``reached``,
``exit``, ``unanswered``) are news of its run. One handler per status, picked from a table: the
machine only dispatches, as dora's daemon loop does.
"""

from __future__ import annotations


from ....errors import RestartLimitError
from ..wire import WireError, decode_status
from .book import RunBook
from .control import RunControl

#: where in its life each state a worker process says of itself puts it: a process says a state
#: only after those below it (`ready` again and again while it waits for the start), and says a
#: last one (done, failed, handed_over) once. Anything else is an insider's replay of a status of
#: the process (its signature holds): a second `done` added its counts and reports again, a `ready`
#: after its `done` moved the node back; refused (may_say)
PROCESS_STAGES = {"ready": 0, "restart": 1, "done": 2, "failed": 2, "handed_over": 2}


def may_say(last: str | None, state: str) -> bool:
    """Whether a process whose last state was ``last`` (None: none yet) may now say ``state``."""
    return last is None or PROCESS_STAGES[state] > PROCESS_STAGES[last] or state == last == "ready"


def is_tag(value: object) -> bool:
    """Whether a decoded value is a tag: ``[time ns, microstep]``."""
    return type(value) is list and len(value) == 2 and all(type(x) is int for x in value)


class StatusMachine:
    """Takes the statuses of the run's processes. ``supervisor``: starts a node's processes
    (processes.Supervisor); ``virtual_time``: the run is in lockstep; ``startup_timeout``: for
    the error of a worker that never linked to its neighbours."""

    def __init__(self, book: RunBook, control: RunControl, supervisor, *, virtual_time: bool = False,
                 startup_timeout: float = 60.0):
        self.book, self.control, self.supervisor = book, control, supervisor
        self.virtual_time, self.startup_timeout = virtual_time, startup_timeout
        self.handlers = {"reached": self._reached, "exit": self._exit, "unanswered": self._unanswered,
                         "ready": self._ready, "restart": self._restart, "failed": self._failed,
                         "handed_over": self._handed_over, "done": self._done}

    def take(self, key: str, data: bytes, sender: object) -> None:
        """A status on ``key``, signed by ``sender`` (a process of its node: origin.py)."""
        book = self.book
        try:
            node, state, info = decode_status(data)
        except WireError as e:
            book.garbage(key, e)
            return
        if node not in book.state:
            book.garbage(key, WireError(f"status of an unknown node '{node}'"))
            return
        # Only the node's own process speaks for it: its running one (a restart spawns a process,
        # so only it may ask for one), or, while it restarts, the old one (which alone says it
        # handed over). A status signed by another of its processes (one that already handed
        # over or was replaced) is garbage; an insider's (a `failed` stopped the run, a `done`
        # added its counts, an `exit` ended it) is signed by none and never got here.
        current, retiring = book.workers.get(node), book.retiring.get(node)
        sayers = {"handed_over": (retiring,), "done": (current, retiring), "failed": (current, retiring)}
        if sender is None or not any(sender is p for p in sayers.get(state, (current,))):
            book.garbage(key, WireError(f"a '{state}' status of {node} from pid {info.get('pid')!r:.20}, "
                                        f"which is not the process of {node} that could say it"))
            return
        if state in PROCESS_STAGES:
            if not may_say(book.said.get(sender), state):
                book.garbage(key, WireError(f"a '{state}' status of {node} after its process said "
                                            f"'{book.said[sender]}' (a replay)"))
                return
            book.said[sender] = state
            self._count(key, node, state, info)
        self.handlers[state](key, node, info, sender)

    def _count(self, key: str, node: str, state: str, info: dict) -> None:
        """What every stage of a process says besides: its counters, and the reports it sent."""
        book = self.book
        counts = info.get("counts", {})
        if type(counts) is not dict or not all(type(k) is str and type(v) is int for k, v in counts.items()):
            book.garbage(key, WireError(f"status of {node} with counts that are not names and integers"))
            counts = {}
        node_counts = book.stats[node].counts
        for name, n in counts.items():
            node_counts[name] = node_counts.get(name, 0) + n
        if state in ("done", "handed_over") and type(info.get("reports")) is int:
            book.reports_sent[node] += info["reports"]
        if state != "ready":
            book.restarted.pop(node, None)

    # ---------------------------------------------------------------------------------------
    # News of a process's run
    # ---------------------------------------------------------------------------------------
    def _reached(self, key: str, node: str, info: dict, sender: object) -> None:
        """Virtual time: the node ran every tick below ``until``."""
        book, until = self.book, info.get("until")
        if not self.virtual_time or type(until) is not int:
            book.garbage(key, WireError(f"a 'reached' status of {node} with until {until!r:.30}"
                                        f"{'' if self.virtual_time else ' in a run not in virtual time'}"))
            return
        # past the grant (one it was told by someone else): it reached this one on the way
        book.reached[node] = max(book.reached.get(node, -1), min(until, book.granted))

    def _exit(self, key: str, node: str, info: dict, sender: object) -> None:
        """Its step called sys.exit(0): the run ends there, once its record is in."""
        tag = info.get("tag")
        if not is_tag(tag):
            self.book.garbage(key, WireError(f"an 'exit' status of {node} with tag {tag!r:.30}"))
            return
        self.book.exit_said[node] = (tuple(tag), sender)
        self.end_by_exit(node)

    def end_by_exit(self, node: str) -> None:
        """End the run as a step of ``node`` asked (sys.exit(0)), once its process both said so
        (status ``exit``) and recorded that step (status ok, detail ``{"exit": 0}``) at that tag."""
        book = self.book
        said = book.exit_said.get(node)
        if said is None or book.exit_recorded.get(node) != said or book.t0 is None or book.stop_sent:
            return
        book.stop_sent = True
        book.ended_by = node
        # as if the run ended now: no tick at or past the exit, but every event sent before
        # it (each stamped before now, the exit's tag may be earlier on a late node) still
        # reaches the ticks it triggers, within their deadline, as at any run's end
        self.control.put("end", {"at": max(said[0][0], book.run_time())})

    def _unanswered(self, key: str, node: str, info: dict, sender: object) -> None:
        """Before the start: its neighbours declare themselves again."""
        book, nodes = self.book, info.get("nodes")
        if type(nodes) is not list or not nodes or not all(type(n) is str and n in book.state for n in nodes):
            book.garbage(key, WireError(f"an 'unanswered' status of {node} that names no nodes of the run"))
        elif book.t0 is not None:  # no worker asks once the run started
            book.garbage(key, WireError(f"an 'unanswered' status of {node} after the run's start"))
        else:
            self.control.put("redeclare", {"nodes": sorted(set(nodes))})

    # ---------------------------------------------------------------------------------------
    # The stages of a process's life (PROCESS_STAGES)
    # ---------------------------------------------------------------------------------------
    def _ready(self, key: str, node: str, info: dict, sender: object) -> None:
        book = self.book
        if info.get("linked") is False and book.failure is None:
            # peers do not route for each other: a worker without a link to another would never
            # get that one's events, nor it this one's
            unlinked = info.get("unlinked")
            unlinked = (", ".join(f"'{n:.60}'" for n in unlinked[:8] if type(n) is str)
                        if type(unlinked) is list else "some of its neighbours")
            book.failure = (node, {"error": (
                f"the worker of '{node}' has no direct link to {unlinked} after {self.startup_timeout:g} s\n"
                f"    hint: on a loaded machine, give it longer: pipe.run(..., startup_timeout=seconds); across "
                f"machines, each must reach the others at the address it listens on (retriever-worker --listen)")})
            return
        if node in book.fresh:
            self.supervisor.restart_afresh(node)
        elif node in book.restarted:
            # said again: it has not seen `restarted` yet (worker.START_ASK_S), nor, maybe, its consumers
            self.control.put("restarted", {"node": node, "seqs": book.restarted[node], "values": book.values})
        elif node in book.retiring:
            if book.state[node] == "done":  # the run ended while it restarted: stopped at close
                return
            self.control.put("handover", {"node": node})
        book.state[node] = "ready"

    def _restart(self, key: str, node: str, info: dict, sender: object) -> None:
        """Its flow asks for a restart in a new process: the old one keeps listening until the
        new one takes over."""
        book = self.book
        tag = info.get("tag")
        budget = book.restarts[node]
        tag = tuple(tag) if is_tag(tag) else (book.run_time(), 0)
        if not budget.take(tag[0]):
            book.limit = RestartLimitError(node, tag, str(info.get("error", "")), budget.max_restarts,
                                           budget.window_s)
            book.failure = (node, {"error": str(book.limit)})
            return
        node_counts = book.stats[node].counts
        node_counts["restarts"] = node_counts.get("restarts", 0) + 1
        book.retiring[node] = book.workers[node]
        self.supervisor.spawn(node, join=(book.t0, book.end_ns))

    def _failed(self, key: str, node: str, info: dict, sender: object) -> None:
        self.book.failure = (node, info)
        self.book.state[node] = "failed"

    def _handed_over(self, key: str, node: str, info: dict, sender: object) -> None:
        """The old process of a restarting node gave its state to the new one, which resumes."""
        book = self.book
        book.retired.append(book.retiring.pop(node))
        self.control.put("resume", {"node": node})
        book.joining.discard(node)

    def _done(self, key: str, node: str, info: dict, sender: object) -> None:
        book = self.book
        if (info.get("stopped") is True and not book.stop_sent and book.t0 is not None and book.failure is None
                and node not in book.exit_said):  # (an exit's record may come after its `done`)
            # it ended before the run's end on a stop this coordinator never sent: a run cut
            # short must not look finished (a SIGTERM to it: a `stop` on ctl/run it takes only sealed)
            book.failure = (node, {"error": (
                f"{node} stopped before the run's end: told to stop, and not by this coordinator (someone sent "
                "its worker SIGTERM)")})
        book.done_info[node] = {k: info[k] for k in ("started_ns", "ticks") if type(info.get(k)) is int}
        sent = info.get("sent")  # {port: last seq put}: which events its reports held (diagnostics.unfinished)
        if type(sent) is dict and all(type(p) is str and p in book.graph.nodes[node].outputs and type(q) is int
                                      for p, q in sent.items()):
            book.done_info[node]["sent"] = sent
        old = book.retiring.pop(node, None)
        if old is not None:
            book.retired.append(old)
        book.state[node] = "done"
