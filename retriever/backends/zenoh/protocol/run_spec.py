"""The run's spec: what a worker process needs of its run, as one record.

    coordinator   builds it (coordinator/core.py), and writes it for the processes it starts
                  (``spec.json`` in the run directory: RunSpec.write_file); dora's hosting adds
                  its own part first (DoraPart)
    coordinator → worker daemon   in a prepare request (daemon.PrepareRequest.spec), as msgpack,
                  what holds only on the coordinator's machine left out (RunSpec.for_remote)
    worker daemon   writes it, made for its host (runs.DaemonRuns.local_spec), for its processes
    worker process  reads it (worker.read_spec: RunSpec.read_file) and holds it, typed, from then on

Its decoder is as exact as every other record's: a field of the wrong type, one missing, or one
the record does not take is refused with a WireError naming it. Beyond the fields it checks what
the processes' start rests on: the Zenoh ids of each node's first process (none, or one for
every node of the IR; two nodes share one only as members of one group) and of the hub.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ....errors import WireError
from ..access import write_private
from ..origin import KEY_BYTES
from ..wire import shown
from .schema import (PID_MAX, Bool, Document, HexKey, Int, Kind, ListOf, MapOf, Name, Nested, Nullable, Record, Row,
                     Text, field, port)

#: the largest spec read (it carries the run's IR and plan)
MAX_SPEC_BYTES = 64 << 20
#: a path, an endpoint or an argument of the spec, at most this long
MAX_PATH_CHARS = 4096


class ZenohId(Kind):
    """A Zenoh session's id: 1 to 32 lowercase hex digits, the first not 0 (as Zenoh prints it)."""

    expects = "a Zenoh id (1 to 32 lowercase hex digits, not starting with 0)"

    def read(self, value: Any, where: str) -> str:
        if (type(value) is not str or not 1 <= len(value) <= 32 or value[0] == "0"
                or not all(c in "0123456789abcdef" for c in value)):
            raise self.refuse(value, where)
        return value


class Seconds(Kind):
    """A duration in seconds: an integer or a finite float from ``low`` to ``high``, held as a float."""

    def __init__(self, low: float, high: float):
        self.low, self.high = low, high
        self.expects = f"seconds, a finite number from {low:g} to {high:g}"

    def read(self, value: Any, where: str) -> float:
        if type(value) not in (int, float) or not math.isfinite(value) or not self.low <= value <= self.high:
            raise self.refuse(value, where)
        return float(value)


PATH = Text(MAX_PATH_CHARS)
SECONDS = Seconds(0.0, 1e9)


@dataclass(frozen=True, kw_only=True)
class DoraPart(Record):
    """A dora run's own part of its spec (backends/dora): the dataflow's ids (dataflow.DoraNames),
    and what a dora node's process is not told by being the coordinator's child (dora's daemon
    starts it). Written by dora's hosting (DoraHosting.place), read by dora's node module."""

    #: each node's dora node id (a group's members: the group's one)
    nodes: dict[str, str] = field(MapOf(Name(), Name()))
    #: each node's dora output id, by output port
    outputs: dict[str, dict[str, str]] = field(MapOf(Name(), MapOf(port(), Name())))
    #: each node's dora inputs: the producer and port each brings (the port None: its progress)
    inputs: dict[str, dict[str, tuple[str, str | None]]] = field(MapOf(Name(), MapOf(Name(), Row(
        Name(), Nullable(port()), expects="[a producer node, its port or nil]"))))
    #: the dora output each node's progress goes on, for a node heard in another dora node
    progress: dict[str, str] = field(MapOf(Name(), Name()))
    #: the coordinator's working directory, which a node's process works in, as its child would
    cwd: str = field(PATH)
    #: the coordinator's pid, which a node's process watches in place of its parent (dora's daemon)
    coordinator: int = field(Int(1, PID_MAX))
    #: dora's own directory (its logs), which a node's process removes with the run's once the
    #: coordinator is gone
    dir: str = field(PATH)
    #: the key each node's first process signs its statuses and reports with (origin.py; a
    #: group's members: its process's one)
    keys: dict[str, bytes] = field(MapOf(Name(), HexKey(KEY_BYTES)))


@dataclass(frozen=True, kw_only=True)
class RunSpec(Record):
    """A run as its worker processes see it: the fields without a default every spec carries;
    the others only the specs of some hosts (left out: the default), in the order the
    coordinator writes them."""

    #: the run's IR (ir.IR checks it)
    ir: dict = field(Document())
    namespace: str = field(Name())
    #: the hub's endpoint (None for a client of routers)
    hub: str | None = field(Nullable(PATH))
    #: the run's wiring (plan.Plan.from_data checks it against the IR)
    plan: dict = field(Document())
    #: where the flows' modules are imported from, joined to the process's own path
    python_path: tuple[str, ...] = field(ListOf(PATH), default=())
    #: the coordinator's main script, imported as ``__mp_main__`` when it defines flows
    main_file: str | None = field(Nullable(PATH), default=None)
    #: the coordinator's sys.argv, which the flows see as theirs (None: the process's own)
    argv: tuple[str, ...] | None = field(Nullable(ListOf(Text(MAX_PATH_CHARS))), default=None)
    #: where a worker writes the events too big for a report (None: it has no such folder)
    spill_dir: str | None = field(Nullable(PATH), default=None)
    #: the run's credentials (access.RunAccess.to_spec), if any
    access: dict | None = field(Nullable(Document()), default=None)
    #: how long a first process waits for its links and answers before it says ready
    startup_timeout: float = field(SECONDS)
    #: each node's first process's session id (empty: a coordinator that names none), and the hub's
    zids: dict[str, str] = field(MapOf(Name(), ZenohId()))
    hub_zid: str | None = field(Nullable(ZenohId()))
    virtual_time: bool = field(Bool())
    #: the processes that share one (``configure(process=NAME)``): their nodes, by name
    groups: dict[str, tuple[str, ...]] = field(MapOf(Name(), ListOf(Name(), min_items=1)), default_factory=dict)
    #: a daemon's flows joined through routers: those routers (the hub is then None)
    router: tuple[str, ...] = field(ListOf(PATH), default=())
    #: where a process listens for its neighbours (empty: Zenoh's choice)
    listen: tuple[str, ...] = field(ListOf(PATH), default=())
    #: the TLS files of the process's links (access.TlsFiles), if any
    tls: dict | None = field(Nullable(Document()), default=None)
    #: Zenoh's lease of the process's links, and how long a put waits on a blocked one (None: Zenoh's)
    lease: float | None = field(Nullable(SECONDS), default=None)
    blocked_put: float | None = field(Nullable(SECONDS), default=None)
    #: a dora run's own part (backends/dora), read by dora's node module
    dora_part: DoraPart | None = field(Nullable(Nested(DoraPart)), default=None)
    #: whether every edge between two processes of the run goes over a same-host link (node/linked.py:
    #: every node on this host, the coordinator's ``same_host_links``); else all go over Zenoh
    links: bool = field(Bool(), default=False)

    @classmethod
    def from_fields(cls, fields: Any, where: str, **envelope: Any) -> RunSpec:
        spec = super().from_fields(fields, where, **envelope)
        spec._check_ids(where)
        return spec

    def _check_ids(self, where: str) -> None:
        """None, or one id for every node of the IR: a process that knew some would wait for links
        to those only, and say ready with the others unlinked. Nodes share one only in one group; a
        group's members are nodes of the IR, each in one group once (a node runs in one process)."""
        nodes = self.ir.get("nodes")  # (ir.IR checks the IR later: here, only the ids that are names count)
        known = ({n["id"] for n in nodes if isinstance(n, dict) and type(n.get("id")) is str}
                 if isinstance(nodes, list) else set())
        if self.zids and set(self.zids) != known:
            amiss = sorted(set(self.zids) ^ known)
            raise WireError(f"{where}: field 'zids' must name one Zenoh id for each node of its IR, or none "
                            f"(amiss: {', '.join(shown(node, 40) for node in amiss[:5])})")
        group_of = self._group_of(where, known)
        first: dict[str, str] = {}
        for node, zid in self.zids.items():
            other = first.setdefault(zid, node)
            if other != node and (node not in group_of or group_of.get(other) != group_of[node]):
                raise WireError(f"{where}: field 'zids' gives nodes '{other}' and '{node}' one Zenoh id, and they "
                                "are no group's")

    def _group_of(self, where: str, known: set[str]) -> dict[str, str]:
        """Each grouped node's group: a member is a node of the IR, in one group once (a node runs
        in one process; two groups' processes would run it twice)."""
        group_of: dict[str, str] = {}
        for name, members in self.groups.items():
            for i, node in enumerate(members):
                if node not in known:
                    raise WireError(f"{where}: field 'groups' names node {shown(node, 40)} in group "
                                    f"{shown(name, 40)}, which its IR does not have")
                other = group_of.setdefault(node, name)
                if other != name or node in members[:i]:
                    twice = (f"groups {shown(other, 40)} and {shown(name, 40)}" if other != name
                             else f"group {shown(name, 40)} twice")
                    raise WireError(f"{where}: field 'groups' puts node {shown(node, 40)} in {twice}: a node runs "
                                    "in one process")
        return group_of

    @classmethod
    def read_file(cls, path: Path) -> RunSpec:
        """The spec a coordinator or daemon wrote to ``path`` (as JSON); WireError if it is none."""
        data = path.read_bytes()
        if len(data) > MAX_SPEC_BYTES:
            raise WireError(f"the run's spec {path} of {len(data)} bytes, past {MAX_SPEC_BYTES}: refused")
        try:
            doc = json.loads(data)
        except ValueError as e:
            raise WireError(f"the run's spec {path} is not JSON ({e})"[:300]) from None
        return cls.from_fields(doc, f"the run's spec {path}")

    def to_json(self) -> str:
        """The spec as the file a process reads back (:meth:`read_file`): JSON, each field at its
        default left out, as :meth:`write_file` writes it."""
        return json.dumps(self.to_fields())

    def write_file(self, path: Path) -> Path:
        """Write the spec to ``path`` for the processes that read it (:meth:`read_file`), only
        its owner may read: it holds the run's password (``access``). Returns ``path``."""
        return write_private(path, self.to_json())

    def for_remote(self) -> RunSpec:
        """The spec as a coordinator sends it to a worker daemon (a prepare request): what
        holds only on the coordinator's machine left out, each for the daemon to fill in with its
        own (runs.DaemonRuns.local_spec) or to go without:

            access        the coordinator's credentials for its processes, whose dictionary is a
                          file in its run directory: a daemon's processes join with the run's,
                          which the daemon derives from its secret for the run id (access.py)
            python_path   this machine's directories: a daemon's processes import from its own
            spill_dir     the run directory, on this machine: a daemon's processes share no
                          folder with the coordinator, and put every event in their reports
            main_file     a script on this machine, which a daemon's processes cannot import
                          (a daemon refuses a class defined in it: daemon/runs.py)
        """
        return dataclasses.replace(self, access=None, python_path=(), spill_dir=None, main_file=None)
