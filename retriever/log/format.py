"""What a Retriever log holds and how each record is encoded (docs/log.md).

One MCAP file per run, ``profile="retriever"``:

=====================  =========================================================================
channel ``data/N/P``   one per output port ``N.P``; a message per event: ``log_time`` = tag time
                       (ns since T0), ``publish_time`` = wall clock (Unix ns), ``sequence`` = seq,
                       data = msgpack ``[microstep, value]`` (value in :mod:`retriever.codec`)
channel ``steps``      a message per step: ``log_time`` = tick time, ``publish_time`` = wall start,
                       ``sequence`` = step index, data = msgpack ``[node, microstep, consumed,
                       produced, status, detail, wall_ns]`` with ``consumed`` = ``{port: [[node,
                       port, seq], ...]}`` and ``produced`` = ``[[node, port, seq], ...]``
attachment             ``pipeline.ir.json``: the IR the run executed
metadata               ``retriever.run`` (written first) and ``retriever.end`` (written last,
                       its status a :class:`RunEnd`; absent when the writer was killed), plus
                       ``retriever.recovered``, and ``retriever.fault.N`` (N = 1, 2, ...) when a
                       run's process was lost: node, at_ns, exit, restarted, seqs (JSON: the new
                       process's first seq per port) and lost_events (JSON: ids its step records
                       produced that were never logged)
=====================  =========================================================================
"""

from __future__ import annotations

import functools
import getpass
import json
import os
import platform
import re
import socket
import subprocess
import sys
from enum import StrEnum
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import msgpack

from ..trace import STEP_STATUSES, StepStatus

PROFILE = "retriever"
FORMAT_VERSION = "1"
MESSAGE_ENCODING = "msgpack"
STEPS_TOPIC = "steps"
IR_ATTACHMENT = "pipeline.ir.json"
RUN_METADATA = "retriever.run"
END_METADATA = "retriever.end"
RECOVERED_METADATA = "retriever.recovered"
FAULT_METADATA = "retriever.fault."
STARVED_METADATA = "retriever.starved."
#: what pip installs Retriever as (it imports as ``retriever``; "retriever" on PyPI is another project)
DISTRIBUTION = "retriever-robotics"
#: the distributions whose versions a run records, by the name a log's and a worker's versions give
#: each: Retriever's own by its import name, so that the key does not change with the distribution's
PACKAGES = {"retriever": DISTRIBUTION, "eclipse-zenoh": "eclipse-zenoh", "msgpack": "msgpack", "numpy": "numpy",
            "mcap": "mcap", "mujoco": "mujoco"}


class RunEnd(StrEnum):
    """How a run ended: the ``status`` of its log's ``retriever.end`` record (docs/log.md). A
    ``str``: the log holds its value (``"finished"``), and a status read back compares equal to its
    member. A log whose writer was killed has no end record, so no status (``RunLog.end`` is None)."""

    #: ran to its end, or a flow ended it (``sys.exit()``)
    FINISHED = "finished"
    #: stopped between two ticks by Ctrl-C, SIGTERM or ``RunHandle.stop()``
    INTERRUPTED = "interrupted"
    #: stopped by an exception; the record's ``error`` names it
    ERROR = "error"


#: a data channel's topic: a node and a port, one segment each (a run's names are ir.NODE_ID and
#: ir.PORT_NAME; a reader takes any segment, so that a log's odd names reach the exports, which make
#: them names of their own, but never a port of two segments)
_DATA_TOPIC = re.compile(r"data/([^/]+)/([^/]+)")


def data_topic(node: str, port: str) -> str:
    return f"data/{node}/{port}"


def parse_data_topic(topic: str) -> tuple[str, str] | None:
    """``data/<node>/<port>`` → ``(node, port)``; None for any other topic, one under ``data/`` of
    other than two segments too (a port holding '/'): :func:`data_topic_problem` says so."""
    match = _DATA_TOPIC.fullmatch(topic)
    return (match[1], match[2]) if match else None


def data_topic_problem(topic: str) -> str | None:
    """Why a topic under ``data/`` is not ``data/<node>/<port>``, or None: a reader that skipped
    such a channel would lose its events without a word."""
    if not topic.startswith("data/") or _DATA_TOPIC.fullmatch(topic):
        return None
    return (f"its channel topic {topic!r:.80} is under data/ but is not data/<node>/<port>, a node and a port of "
            "one non-empty segment each (a port name holds no '/')")


def split_event(data: bytes) -> tuple[int, bytes]:
    """``[microstep, value]`` → microstep and the value's own msgpack bytes, undecoded."""
    if len(data) < 3 or data[0] != 0x92:
        raise ValueError("an event message must be a msgpack array of 2: [microstep, value]")
    if data[1] < 0x80:  # positive fixint: the common case
        return data[1], data[2:]
    unpacker = msgpack.Unpacker()
    unpacker.feed(data[1:])
    try:
        microstep = unpacker.unpack()
    except Exception as e:  # msgpack's OutOfData, FormatError...: a damaged record
        raise ValueError(f"its microstep is not valid msgpack ({type(e).__name__})") from None
    if not isinstance(microstep, int) or microstep < 0:
        raise ValueError(f"an event's microstep must be an integer >= 0, got {microstep!r}")
    return microstep, data[1 + unpacker.tell():]


#: the statuses a step record has detail with
_DETAILED_STATUSES = frozenset({StepStatus.LATE, StepStatus.ERROR})
#: the statuses of a step record without detail
PLAIN_STEP_STATUSES = frozenset(STEP_STATUSES) - _DETAILED_STATUSES
#: the keys of a step record's detail that name streams into its node's input ports: ``{port:
#: [[producer, producer's port, ...], ...]}``
STREAM_DETAIL_KEYS = ("late", "had_below", "restart_gap")


_NOT_A_STEP = "it is not [node, microstep, consumed, produced, status, detail, wall_ns] of a step"
_NOT_IDS = "its event ids are not [node, port, seq] triples"


def decode_step(data: bytes) -> tuple:
    """A steps message → ``(node, microstep, consumed, produced, status, detail, wall_ns)``,
    event ids as tuples like the in-memory trace has them."""
    # most records have no detail: their arrays are read as the tuples they are kept as, checked
    # in place (a replay reads every step record of the log, twice)
    try:
        step = msgpack.unpackb(data, use_list=False)
    except Exception as e:  # msgpack's FormatError (a byte it never uses) says nothing of itself
        if str(e):
            raise
        raise ValueError(f"it is not valid msgpack ({type(e).__name__})") from None
    node, microstep, consumed, produced, status, detail, wall_ns = step
    if detail is None:
        # checked in the order of the reading below (an unhashable status raises TypeError, after the ports);
        # the ids as event_ids checks them, inline (a call per port costs more than its checks)
        if type(node) is not str or type(microstep) is not int or microstep < 0 or type(consumed) is not dict:
            raise ValueError(_NOT_A_STEP)
        for port in consumed:  # (a loop, not all(): its generator costs more than the check)
            if type(port) is not str:
                raise ValueError(_NOT_A_STEP)
        if status not in PLAIN_STEP_STATUSES or type(wall_ns) is not int:
            raise ValueError(_NOT_A_STEP)
        if consumed:
            for ids in consumed.values():
                if type(ids) is not tuple:
                    raise ValueError(_NOT_IDS)
                for i in ids:
                    if type(i) is not tuple or len(i) != 3:
                        raise ValueError(_NOT_IDS)
                    id_node, id_port, seq = i
                    if type(id_node) is not str or type(id_port) is not str or type(seq) is not int or seq < 0:
                        raise ValueError(_NOT_IDS)
        if type(produced) is not tuple:
            raise ValueError(_NOT_IDS)
        for i in produced:
            if type(i) is not tuple or len(i) != 3:
                raise ValueError(_NOT_IDS)
            id_node, id_port, seq = i
            if type(id_node) is not str or type(id_port) is not str or type(seq) is not int or seq < 0:
                raise ValueError(_NOT_IDS)
        return step
    node, microstep, consumed, produced, status, detail, wall_ns = msgpack.unpackb(data, raw=False)
    # what readers (log info, replay) rely on; a damaged or forged record is a ValueError here
    if (type(node) is not str or type(microstep) is not int or microstep < 0 or type(consumed) is not dict
            or not all(type(p) is str for p in consumed) or status not in STEP_STATUSES or type(wall_ns) is not int
            or not (detail is None or (type(detail) is dict and all(type(k) is str for k in detail)))
            or (detail is None and status in _DETAILED_STATUSES)):
        raise ValueError(_NOT_A_STEP)
    if detail is not None:  # (most records have none)
        late = detail.get("late", {})
        if type(late) is not dict:
            raise ValueError("its late events are not {port: [event id, ...]}")
        for ids in late.values():
            event_ids(ids)
        had_below = detail.get("had_below", {})
        if type(had_below) is not dict:
            raise ValueError("what its incomplete inputs had is not {port: [[node, port, next seq], ...]}")
        for streams in had_below.values():
            event_ids(streams)
        _check_restart_detail(detail)
    if consumed:
        consumed = {port: event_ids(ids) for port, ids in consumed.items()}
    return node, microstep, consumed, event_ids(produced), status, detail, wall_ns


def decode_plain_step(data: bytes) -> tuple:
    """:func:`decode_step` of a record whose bytes were found to be a step record without detail
    as Retriever writes nearly every one (replay/survey.py, ``_plain_steps``: a node, ports and ids
    of ASCII fixstrs, a microstep and seqs of msgpack's unsigned integers, a fixstr status, nil,
    an integer), which leaves only its status to check; another status is decode_step's error."""
    step = msgpack.unpackb(data, use_list=False)
    if step[4] not in PLAIN_STEP_STATUSES:
        return decode_step(data)
    return step


def _check_restart_detail(detail: dict) -> None:
    """What replay reads of a restart (zenoh/node/handover.py), or ValueError:
    ``restart_gap`` {port: [[node, port, first seq given up, first seq taken], ...]} on a consumer's
    record, ``restarted`` {seqs: {port: seq}, inputs: {port: [[node, port, first seq], ...]}} on the
    first record of a flow started afresh."""
    gaps = detail.get("restart_gap", {})
    if type(gaps) is not dict or not all(type(g) is list and all(_is_range(r) for r in g) for g in gaps.values()):
        raise ValueError("its restart gaps are not {port: [[node, port, from seq, to seq], ...]}")
    restarted = detail.get("restarted")
    if restarted is None:
        return
    seqs, inputs = (restarted.get("seqs"), restarted.get("inputs")) if type(restarted) is dict else (None, None)
    if (type(seqs) is not dict or not all(type(p) is str and type(n) is int and n >= 0 for p, n in seqs.items())
            or type(inputs) is not dict or not all(type(p) is str for p in inputs)):
        raise ValueError("its restart is not {seqs: {port: seq}, inputs: {port: [event id, ...]}}")
    for ids in inputs.values():
        event_ids(ids)


def _is_range(item: Any) -> bool:
    return (type(item) is list and len(item) == 4 and type(item[0]) is str and type(item[1]) is str
            and all(type(n) is int and n >= 0 for n in item[2:]))


def event_ids(ids: Any) -> tuple:
    """``[[node, port, seq], ...]`` → a tuple of event ids, or ValueError."""
    if type(ids) is list:
        out = []
        for i in ids:  # (a loop, not all(): two or three ids a record, read for every record of a log)
            if type(i) is not list or len(i) != 3:
                break
            node, port, seq = i
            if type(node) is not str or type(port) is not str or type(seq) is not int or seq < 0:
                break
            out.append((node, port, seq))
        else:
            return tuple(out)
    raise ValueError(_NOT_IDS)


@functools.cache
def package_versions() -> dict[str, str]:
    """Installed versions of Retriever and the packages a run depends on (read once per process)."""
    versions = {}
    for name, distribution in PACKAGES.items():
        try:
            versions[name] = importlib_metadata.version(distribution)
        except importlib_metadata.PackageNotFoundError:
            pass
    return versions


@functools.cache
def _git_revision(folders: tuple[str, ...], files: tuple[str, ...] = ()) -> tuple[str, str]:
    """``(HEAD, "")`` of the first of ``folders`` inside a git work tree, ``-dirty`` appended when
    tracked files changed or one of ``files`` (the flow modules') in it is not tracked (HEAD does
    not hold the code that ran); else ``("", why)``: what git said of the first folder it refused
    for another reason than not being a repository (a checkout another user owns: git's
    ``safe.directory``), or "" when none is in one (or git is not installed).

    Every folder is tried, not only the first: the flows of one run may come from a checkout and
    from an installed package (``agents``), and the working directory is the last resort.

    Asked once per process for the same folders and files: git takes two or three processes,
    tens of ms, which every logged run would pay again; and a process runs the code it imported,
    whatever is edited in the checkout afterwards."""
    refused = ""
    for folder in folders:
        try:
            done = subprocess.run(["git", "rev-parse", "--show-toplevel", "HEAD"], capture_output=True, text=True,
                                  timeout=5, cwd=folder)
            if done.returncode != 0:
                said = done.stderr.strip().splitlines()[:1]
                if said and "not a git repository" not in said[0] and not refused:
                    refused = said[0].removeprefix("fatal: ")
                continue
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                   text=True, timeout=5, cwd=folder).stdout.strip()
            top, _, head = done.stdout.strip().partition("\n")
            inside = [f for f in files if os.path.realpath(f).startswith(os.path.realpath(top) + os.sep)]
            if inside and not dirty:
                listed = subprocess.run(["git", "ls-files", "--others", "--exclude-standard", "--", *inside],
                                        capture_output=True, text=True, timeout=5, cwd=folder)
                dirty = listed.stdout.strip() if listed.returncode == 0 else ""
        except (OSError, subprocess.SubprocessError):
            continue
        return head + ("-dirty" if dirty else ""), ""
    return "", refused


def import_roots(modules: list[str]) -> list[str]:
    """The ``sys.path`` folders these modules were imported from, so a replay on the same
    machine can import the flow classes again from any working directory."""
    roots: list[str] = []
    for name in modules:
        file = getattr(sys.modules.get(name), "__file__", None)
        if not file:
            continue
        path = Path(file).resolve()
        depth = name.count(".") + (1 if path.name == "__init__.py" else 0)
        root = str(path.parents[depth])
        if root not in roots:
            roots.append(root)
    return roots


def run_metadata(pipeline: str, backend: str, seeds: dict[str, Any], started_unix_ns: int,
                 flow_modules: list[str]) -> dict[str, str]:
    """The ``retriever.run`` record: enough to know what ran, where, and how to run it again."""
    roots = import_roots(flow_modules)
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = ""
    files = [f for name in flow_modules if isinstance(f := getattr(sys.modules.get(name), "__file__", None), str)]
    revision, git_refused = _git_revision((*roots, os.getcwd()), tuple(files))
    return {
        "format": FORMAT_VERSION,
        "pipeline": pipeline,
        "backend": backend,
        "seeds": json.dumps(seeds, sort_keys=True),
        "started_unix_ns": str(started_unix_ns),
        "packages": json.dumps(package_versions(), sort_keys=True),
        "python": platform.python_version(),
        "git_revision": revision,
        "python_path": json.dumps(roots),
        "host": socket.gethostname(),
        "user": user,
        "pid": str(os.getpid()),
        "cwd": os.getcwd(),
        "command_line": json.dumps(sys.argv),
        **({"git_error": git_refused} if git_refused else {}),
    }
