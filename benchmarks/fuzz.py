"""A fuzz campaign over everything Retriever decodes from outside the process (issue 17).

Targets, each fed inputs made by the real encoders and writers and then mutated:

    codec         retriever.codec.unpackb (plain, keep_unregistered=True) and unpackb_out_of_band
    wire-data     wire.decode_events (bursts too)     wire-progress   wire.decode_progress
    wire-report   protocol.Report.decode              wire-status     protocol.STATUS.decode
    wire-control  protocol.RUN_CONTROL.decode
    coordinator   the zenoh coordinator's report handling (its Inbox.handle), after the
                  genuine run's reports: what reaches the trace is checked against the genuine run
    insider       the coordinator's receiving path (signature check, then Inbox.handle) fed statuses and
                  reports an insider holding the secret forges (InsiderTarget)
    seal          a worker process's ControlOpener (protocol/seal.py) fed ctl/run puts an insider
                  makes of the coordinator's sealed ones (SealTarget)
    specs         a worker daemon's prepare (runs.DaemonRuns) fed hostile run specs (SpecTarget)
    spawn-signal  a worker daemon's spawn and signal (runs.DaemonRuns, a run prepared, real
                  worker processes, a sentinel process in no run) fed hostile requests (DaemonOpsTarget)
    ir            IR.from_json, then Pipeline.from_ir (flow types only from a fixed set, plus
                  names of callables that must be refused as no Flow: an IR is code by design)
    log           read_log (strict and salvage), RunLog.trace(), run_info (log info), every
                  value as log cat shows it, replay(log, pipeline), recover
    plan          Plan.from_data, a worker's spec's plan read against its IR (PlanTarget)

Mutations are structure-aware: bit flips, truncations, splices and length headers on the bytes;
in the decoded msgpack (or JSON) tree, type swaps, huge ints, NaN/inf, deep nesting, huge
lengths, and forged extension types 1–6 whose contents are hostile (dataclass paths naming
``os:system``, ``builtins:eval``, ``subprocess:Popen``..., with arguments that would create a
marker file; dtypes ``O``; shapes and buffer indexes out of range).

For every input these things are checked:

- no crash: the entry point returns or raises its documented error (CodecError, WireError,
  IRError, LogError); anything else, or an input that takes longer than HANG_S, is a crash,
  saved under ``benchmarks/fuzz_crashes/`` (``--reproduce FILE`` runs it again);
- no code executed: an audit hook, armed only around the entry point, flags an import of a
  module not yet imported, ``exec``, ``compile``, a process started, a file written or removed,
  a socket, ctypes, pickle or marshal; a marker file that a forged value's command would create
  is checked after every input;
- no forged record accepted (coordinator): nothing the genuine run recorded is changed or
  displaced, and every record a fuzzed report adds is one that the node of the report's key may
  make about itself (its own output ports, an event id and a tick not recorded yet, a value of
  the codec's types): what a run's own process could send anyway. Those are counted apart;
- no process started or signalled unasked (spawn-signal): the guard permits a legitimate
  request's own worker start or signal only; a sentinel process and the run's processes no
  legitimate signal went to must outlive every input (else a crash: Breach). The guard stops
  (Blocked) every signal and process start it does not permit.

    python benchmarks/fuzz.py --seconds 25 --seed 1           # every target, 25 s each
    python benchmarks/fuzz.py --inputs 500 --targets codec,ir  # a fixed number of inputs
    python benchmarks/fuzz.py --insider-run 1000000            # a real run beside an insider (below)

``--insider-run N`` is no fuzzing: a real zenoh run (two flows, 3 s, a log, started as a user
starts one) beside a Zenoh session holding its deployment secret, which puts an ``exit`` and a
``done`` with each node's real pid, then N step records of the source in reports of 100,000
(between its ticks, past its end, at its ticks). It says what the run took of them and how much
the coordinator's memory grew while they came.
"""

from __future__ import annotations

import argparse
import base64
import copy
import functools
import hashlib
import json
import math
import os
import random
import shutil
import signal
import sys
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the test flows (tests.log.log_flows, tests.ir_flows) live there
    sys.path.insert(0, str(ROOT))

import msgpack  # noqa: E402
import numpy as np  # noqa: E402

from retriever import IR, Burst, IRError, LogError, Pipeline, read_log  # noqa: E402
from retriever.backends.base import output_ports  # noqa: E402
from retriever.backends.zenoh.coordinator import Hosting, RunBook, RunControl, assemble  # noqa: E402
from retriever.backends.zenoh.origin import new_key, sign  # noqa: E402
from retriever.backends.zenoh.protocol import (  # noqa: E402
    REQUEST, RUN_CONTROL, STATUS, ControlOpener, ControlSigner, DaemonOp, Done, End, Exit, Failed, Grant, HandedOver,
    Handover, Lost, PrepareRequest, Reached, Ready, Report, Restart, RunSpec, SpawnRequest, Start, State, Stop)
from retriever.backends.zenoh.protocol.seal import COUNTER_BYTES  # noqa: E402
from retriever.backends.zenoh.wire import (  # noqa: E402
    RELIABLE, WIRE_VERSION, KeySpace, WireEncoder, WireError, decode_events, decode_progress)
from retriever.codec import (  # noqa: E402
    EXT_BIGINT, EXT_DATACLASS, EXT_NDARRAY, EXT_NDARRAY_OOB, EXT_NPSCALAR, EXT_TUPLE, CodecError, is_value_type,
    packb, unpackb, unpackb_out_of_band)
from retriever.log.reader import run_info  # noqa: E402
from retriever.log.recover import recover  # noqa: E402
from retriever.replay import replay  # noqa: E402
from retriever.log.mcap_writer import McapWriter  # noqa: E402
from retriever.trace import STEP_STATUSES, StepStatus, Trace  # noqa: E402

CRASH_DIR = Path(__file__).resolve().parent / "fuzz_crashes"
#: an input that takes longer than this is a hang (the slowest genuine input, a log replay, takes ~50 ms)
HANG_S = 10.0
#: the run of the genuine pipeline whose messages, reports and log seed the campaign
RUN_S = 0.5
NAMESPACE = "fuzz"
#: garbage messages a coordinator prints before it only counts them (coordinator/book.py, GARBAGE_SAID)
GARBAGE_PRINTED = 3

#: callables a forged dataclass value names: decoding must never import or call them
HOSTILE_PATHS = ["os:system", "posix:system", "builtins:eval", "builtins:exec", "subprocess:Popen",
                 "subprocess:getoutput", "pathlib:Path.touch", "importlib:import_module", "shutil:rmtree",
                 "tests.log.log_flows:Point.__init__", "retriever.codec:import_type"]
#: value types the test flows register: forged values name them with hostile fields
REGISTERED_PATHS = ["tests.log.log_flows:Point", "tests.log.log_flows:Reading", "tests.ir_flows:Frame"]
#: dtype descriptions a forged array may carry (object dtypes must never be rebuilt)
HOSTILE_DESCRS = ["O", "|O", "<f8", "V1000000000000", "<U999999999", "S0", "i4,O", "(2,)O", "M8[ns]", "m8",
                  [["a", "O"]], [["a", "<f8", [2]]], [["", "|V4"]], [[b"a", "<f8"]], {"descr": "O"}, None, 7, "",
                  "a" * 1000, "<f8\x00"]
#: ints at and past msgpack's edges
EDGE_INTS = [0, -1, 1, 127, 128, 255, 256, 2**31 - 1, 2**31, 2**32, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1,
             -2**31, -2**63]
EDGE_FLOATS = [math.nan, math.inf, -math.inf, -0.0, 5e-324, 1.7976931348623157e308]
#: msgpack heads that announce far more than follows
HUGE_HEADS = [b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff",
              b"\xc9\xff\xff\xff\xff\x04", b"\xc9\x7f\xff\xff\xff\x01", b"\xdc\xff\xff", b"\xc5\xff\xff"]


# ---------------------------------------------------------------------------------------------
# Guard: audit hook, marker file, time limit
# ---------------------------------------------------------------------------------------------
class Hang(BaseException):
    """An input ran past HANG_S (a BaseException, so no `except Exception` under test eats it)."""


class Blocked(BaseException):
    """The guard stopped a signal or a process start an input was not permitted (a spawn-signal
    input that signalled pid -1 would otherwise reach every process of the user)."""


#: audit events that mean code ran or the outside world changed, whatever their arguments
_FORBIDDEN = {"exec", "compile", "os.system", "os.exec", "os.posix_spawn", "os.spawn", "os.fork", "os.forkpty",
              "os.kill", "os.killpg", "subprocess.Popen", "pty.spawn", "os.remove", "os.rename", "os.rmdir",
              "os.mkdir", "os.chmod", "os.chown", "os.truncate", "os.symlink", "os.link", "shutil.rmtree",
              "shutil.copyfile", "shutil.move", "ctypes.dlopen", "ctypes.dlsym", "ctypes.call_function",
              "pickle.find_class", "marshal.loads", "marshal.load", "code.__new__", "function.__new__",
              "builtins.input", "webbrowser.open", "urllib.Request", "socket.connect", "socket.bind",
              "socket.__new__", "socket.getaddrinfo", "import"}
#: of those, the ones the guard also stops (it raises Blocked in the call that would make them)
_BLOCKED = {"os.kill", "os.killpg", "os.system", "subprocess.Popen"}
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND


class Guard:
    """The audit hook (installed once, armed only around a fuzzed call) and the marker file."""

    def __init__(self, marker: Path):
        self.marker = marker
        self.armed = False
        self.may_write: set[str] = set()
        self.may: Callable[[str, tuple], bool] | None = None  # audit events the input may cause
        self.flagged: list[str] = []
        sys.addaudithook(self._hook)
        signal.signal(signal.SIGALRM, self._alarm)

    def _hook(self, event: str, args: tuple) -> None:
        if not self.armed or (self.may is not None and self.may(event, args)):
            return
        if event == "import":
            if args[0] in sys.modules:
                return
        elif event == "open":
            path, mode, flags = args
            writes = (isinstance(mode, str) and any(c in mode for c in "wax+")) or (
                mode is None and isinstance(flags, int) and flags & _WRITE_FLAGS)
            # an int is a descriptor os.open made: its own event named the path, checked then
            if not writes or str(path) in self.may_write or type(path) is int:
                return
        elif event not in _FORBIDDEN and not event.startswith(("os.exec", "os.spawn", "os.posix_spawn")):
            return
        self.armed = False  # nothing below may re-enter the hook
        self.flagged.append(f"{event} {args!r:.200}")
        self.armed = True
        if event in _BLOCKED:
            raise Blocked(f"{event} {args!r:.200}")

    @staticmethod
    def _alarm(signum, frame) -> None:
        raise Hang(f"no answer within {HANG_S} s")

    def call(self, fn: Callable[[], Any], may_write: tuple[str, ...] = (),
             may: Callable[[str, tuple], bool] | None = None) -> tuple[Any, BaseException | None, list[str]]:
        """``fn()`` armed and timed: its result, what it raised, and the audit events it caused
        (but those ``may(event, args)`` permits)."""
        self.flagged, self.may_write, self.may = [], set(may_write), may
        result = error = None
        signal.setitimer(signal.ITIMER_REAL, HANG_S)
        self.armed = True
        try:
            result = fn()
        except KeyboardInterrupt:
            raise
        except BaseException as e:  # noqa: BLE001 - classified by the caller
            error = e
        finally:
            self.armed = False
            signal.setitimer(signal.ITIMER_REAL, 0)
        flagged = self.flagged
        if self.marker.exists():
            flagged.append(f"the marker file {self.marker} was created")
            self.marker.unlink()
        return result, error, flagged


# ---------------------------------------------------------------------------------------------
# Mutations
# ---------------------------------------------------------------------------------------------
class Mutator:
    """Structure-aware mutations of msgpack bytes and of the trees they decode to."""

    def __init__(self, rng: random.Random, marker: Path):
        self.rng = rng
        self.marker = marker

    # -- bytes -----------------------------------------------------------------------------
    def bytes(self, data: bytes, others: list[bytes] = ()) -> bytes:
        rng, out = self.rng, bytearray(data)
        for _ in range(rng.choice((1, 1, 2, 3, 8))):
            op = rng.randrange(8)
            pos = rng.randrange(len(out) + 1)
            if op == 0 and out:  # bit flip
                out[min(pos, len(out) - 1)] ^= 1 << rng.randrange(8)
            elif op == 1 and out:  # an interesting byte
                out[min(pos, len(out) - 1)] = rng.choice((0x00, 0xFF, 0x7F, 0x80, 0xC0, 0xC1, 0xC7, 0xC9, 0xD4, 0xD8,
                                                          0xDC, 0xDD, 0xDE, 0xDF, 0x90, 0x9F, 0x80, 0x8F, 0xA0))
            elif op == 2:  # truncate
                del out[pos:]
            elif op == 3:  # insert random bytes
                out[pos:pos] = rng.randbytes(rng.choice((1, 2, 4, 9, 64)))
            elif op == 4:  # a head announcing a huge length, or a deep nest of arrays
                out[pos:pos] = rng.choice(HUGE_HEADS) if rng.random() < 0.7 else b"\x91" * rng.choice((600, 5000))
            elif op == 5 and others:  # splice with another seed
                other = rng.choice(others)
                cut = rng.randrange(len(other) + 1)
                out = out[:pos] + bytearray(other[cut:])
            elif op == 6 and out:  # duplicate a slice
                end = min(len(out), pos + rng.randrange(1, 64))
                out[pos:pos] = out[pos:end]
            elif op == 7 and out:  # delete a slice
                del out[pos:pos + rng.randrange(1, 16)]
        return bytes(out)

    # -- msgpack trees ---------------------------------------------------------------------
    def msgpack(self, data: bytes, others: list[bytes] = ()) -> bytes:
        """Mutate msgpack bytes: in the decoded tree (extension types kept as ExtType), in the
        bytes, or both."""
        choice = self.rng.random()
        if choice < 0.65:
            try:
                tree = msgpack.unpackb(data, raw=False, strict_map_key=False, timestamp=0)
            except Exception:
                return self.bytes(data, others)
            data = pack_tree(self.tree(tree))
            if choice < 0.55:
                return data
        return self.bytes(data, others)

    def tree(self, tree: Any, rounds: int | None = None) -> Any:
        """A msgpack tree (freshly decoded: changed in place), mutated."""
        rng = self.rng
        holder = [tree]
        for _ in range(rounds or rng.choice((1, 1, 1, 2, 3))):
            slots: list[tuple[Any, Any]] = [(holder, 0)]
            _collect(holder[0], slots)
            parent, key = rng.choice(slots)
            value = parent[key]
            op = rng.randrange(10)
            if op < 3:
                parent[key] = self.value(value)
            elif op == 3 and isinstance(value, list) and value:  # delete an item
                del value[rng.randrange(len(value))]
            elif op == 3 and isinstance(value, dict) and value:
                del value[rng.choice(list(value))]
            elif op == 4 and isinstance(value, list):  # insert an item
                value.insert(rng.randrange(len(value) + 1), self.value(None))
            elif op == 4 and isinstance(value, dict):  # a key of another type
                new_key = rng.choice((7, -1, b"k", 1.5, None, True, "", "$msgpack", "__class__", "x" * 300))
                value[new_key] = value.pop(rng.choice(list(value))) if value else self.value(None)
            elif op == 5 and isinstance(value, msgpack.ExtType):  # mutate inside an extension value
                parent[key] = self.ext_inside(value)
            elif op == 6:  # graft another part of the tree here (shared: a cycle is packed cut short)
                other_parent, other_key = rng.choice(slots)
                parent[key] = other_parent[other_key]
            elif op == 7:
                parent[key] = self.forged_ext()
            elif op == 8:  # wrap it: a list, a tuple, a dict
                parent[key] = rng.choice(([value], msgpack.ExtType(EXT_TUPLE, pack_tree([value])), {"v": value}))
            else:
                parent[key] = self.swap_type(value)
        return holder[0]

    def ext_inside(self, ext: msgpack.ExtType) -> msgpack.ExtType:
        rng = self.rng
        if rng.random() < 0.2:
            return msgpack.ExtType(rng.choice((ext.code, 0, 7, 8, 100, 127)), ext.data)
        try:
            inner = msgpack.unpackb(ext.data, raw=False, strict_map_key=False, timestamp=0)
        except Exception:
            return msgpack.ExtType(ext.code, self.bytes(ext.data))
        if rng.random() < 0.7:
            return msgpack.ExtType(ext.code, pack_tree(self.tree(inner)))
        return msgpack.ExtType(ext.code, self.bytes(ext.data))

    def swap_type(self, value: Any) -> Any:
        rng = self.rng
        options = [None, True, 0, -7, 3.5, "s", b"b", [], {}, [value], type(value).__name__, type(value).__name__.encode()]
        return rng.choice(options)

    def value(self, old: Any) -> Any:
        """A hostile value of any kind."""
        rng = self.rng
        kind = rng.randrange(12)
        if kind == 0:
            return rng.choice(EDGE_INTS)
        if kind == 1:
            return rng.choice(EDGE_FLOATS)
        if kind == 2:
            return msgpack.ExtType(EXT_BIGINT, rng.choice((b"9" * rng.choice((20, 5000, 100_000)), b"-0x10", b"1e9",
                                                             b"\xff", b" 12 ", b"", b"1_000", b"-")))
        if kind == 3:  # deep nesting
            value: Any = None
            for _ in range(rng.choice((50, 500, 2000))):
                value = [value] if rng.random() < 0.8 else {"k": value}
            return value
        if kind == 4:  # deep nesting through extension types (each a nested decode)
            return nested_ext(rng.choice((10, 200, 1200)), rng.choice((EXT_TUPLE, EXT_DATACLASS)))
        if kind == 5:  # big containers
            return rng.choice(([0] * 100_000, {str(i): i for i in range(10_000)}, "x" * 1_000_000, b"\0" * 1_000_000))
        if kind in (6, 7):
            return self.forged_ext()
        if kind == 8:
            return rng.choice(("", "\x00", "\udcff".encode("utf-8", "surrogatepass").decode("utf-8", "replace"),
                               "é" * 100, "$tuple", "os:system"))
        if kind == 9:
            return rng.choice((b"", b"\x00" * 9, b"\xc1", packb((1, 2))))
        if kind == 10:
            return msgpack.Timestamp(rng.randrange(2**34), rng.randrange(10**9))
        return self.swap_type(old)

    def forged_ext(self) -> msgpack.ExtType:
        """An extension value 1–6 with hostile contents."""
        rng = self.rng
        code = rng.choice((EXT_NDARRAY, EXT_TUPLE, EXT_BIGINT, EXT_DATACLASS, EXT_DATACLASS, EXT_DATACLASS,
                           EXT_NPSCALAR, EXT_NDARRAY_OOB))
        if code in (EXT_NDARRAY, EXT_NPSCALAR):
            shape = rng.choice(([], [3], [2, 3], [-1], [2**62, 2**62], [0, 2**63], [2**64 - 1], "abc", None, [[1]],
                                [1] * 64, [1.5], 4))
            raw = rng.choice((b"", b"\0" * 8, b"\0" * 24, b"\0" * 7, "text", 5, None))
            parts = [rng.choice(HOSTILE_DESCRS), shape, raw]
            if rng.random() < 0.2:
                parts = rng.choice((parts[:2], parts + [1], "abc", 5, {"descr": "O"}))
            return msgpack.ExtType(code, pack_tree(parts))
        if code == EXT_NDARRAY_OOB:
            parts = [rng.choice(HOSTILE_DESCRS), rng.choice(([2], [0], [2**62], "x", None)),
                     rng.choice((0, 1, -1, 2**64 - 1, "0", None, 0.0))]
            return msgpack.ExtType(code, pack_tree(parts if rng.random() < 0.9 else parts[:1]))
        if code == EXT_TUPLE:
            return msgpack.ExtType(code, rng.choice((b"", b"\xc1", pack_tree(5), pack_tree([self.forged_ext()]))))
        if code == EXT_BIGINT:
            return msgpack.ExtType(code, rng.choice((b"9" * 5000, b"nan", b"inf", b"0" * 100_000, b"\x00")))
        path = rng.choice(HOSTILE_PATHS + REGISTERED_PATHS + ["", ":", "os", "a:b:c", "x" * 1000])
        fields = self.hostile_fields()
        parts: Any = [path, fields]
        if rng.random() < 0.15:
            parts = rng.choice(([path], [path, fields, 1], [path, [1, 2]], [5, fields], path, {path: fields}))
        return msgpack.ExtType(code, pack_tree(parts))

    def hostile_fields(self) -> dict:
        touch = f"touch {self.marker}"
        rng = self.rng
        fields = rng.choice((
            {"command": touch},
            {"args": ["touch", str(self.marker)], "shell": False},
            {"source": f"open({str(self.marker)!r}, 'w')"},
            {"cmd": touch},
            {"self": str(self.marker)},
            {"name": "os"},
            {"x": 1.0, "y": 2.0},
            {"x": 1.0, "y": 2.0, "__class__": "os:system"},
            {"k": 1, "level": 0.5, "pose": None},
            {"brightness": math.nan, "k": 2**64 - 1},
            {"path": str(self.marker)},
            {},
        ))
        if rng.random() < 0.2:
            fields = dict(fields, **{rng.choice(("__init__", "__reduce__", "tags", "extra")): self.forged_ext()})
        return fields


def _collect(tree: Any, slots: list, depth: int = 0) -> None:
    """Every (container, key) of a tree, to pick one from (bounded: big trees stay cheap)."""
    if depth > 40 or len(slots) > 2000:
        return
    if isinstance(tree, list):
        for i, v in enumerate(tree):
            slots.append((tree, i))
            _collect(v, slots, depth + 1)
    elif isinstance(tree, dict):
        for k, v in tree.items():
            slots.append((tree, k))
            _collect(v, slots, depth + 1)


def pack_tree(tree: Any) -> bytes:
    """msgpack bytes of a mutated tree, whatever it holds (too deep, cyclic or shared parts cut)."""
    try:
        return msgpack.packb(tree, use_bin_type=True)
    except (ValueError, OverflowError, TypeError, RecursionError):
        return msgpack.packb(_cut(tree, set(), [20_000]), use_bin_type=True)


def _cut(tree: Any, path: set[int], budget: list[int], depth: int = 0) -> Any:
    """``tree`` with what lies deeper than 100 levels, on a cycle or past ``budget`` nodes
    replaced by an unknown extension value."""
    budget[0] -= 1
    if depth > 100 or id(tree) in path or budget[0] < 0:
        return msgpack.ExtType(0x7F, b"")
    if isinstance(tree, (list, dict)):
        path.add(id(tree))
        if isinstance(tree, list):
            out: Any = [_cut(v, path, budget, depth + 1) for v in tree]
        else:
            out = {k: _cut(v, path, budget, depth + 1) for k, v in tree.items()}
        path.discard(id(tree))
        return out
    if isinstance(tree, int) and not -2**63 <= tree < 2**64:
        return msgpack.ExtType(EXT_BIGINT, str(tree).encode())
    return tree


@functools.cache
def nested_ext(depth: int, code: int) -> msgpack.ExtType:
    """An extension value nested ``depth`` deep: a tuple in a tuple..., or a dataclass in a
    dataclass's field; each level is a nested decode."""
    inner = msgpack.packb(None)
    for _ in range(depth):
        if code == EXT_TUPLE:
            payload = b"\x91" + inner
        else:
            payload = (b"\x92" + msgpack.packb("tests.log.log_flows:Point") + b"\x83" + msgpack.packb("x")
                       + msgpack.packb(0.0) + msgpack.packb("y") + msgpack.packb(0.0) + msgpack.packb("tags") + inner)
        inner = msgpack.packb(msgpack.ExtType(code, payload))
    return msgpack.ExtType(code, payload)


# ---------------------------------------------------------------------------------------------
# The genuine run every target starts from
# ---------------------------------------------------------------------------------------------
@dataclass
class Genuine:
    """A real run of the log tests' small pipeline (in-process), its trace and its log file."""

    trace: Trace
    log: Path
    pipeline: Pipeline  # rebuilt for replays of fuzzed logs (given, so nothing is imported by name)


def genuine_run(workdir: Path) -> Genuine:
    from tests.log.log_flows import build_small

    path = workdir / "genuine.mcap"
    pipe = build_small()
    trace = pipe.run(duration=RUN_S, log=path)
    return Genuine(trace, path, build_small())


def _ids(ids) -> list:
    return [list(i) for i in ids]


def genuine_reports(genuine: Genuine, batches: int = 2) -> list[tuple[str, bytes]]:
    """The run's records as a zenoh worker reports them: ``(key, report)`` per node and batch,
    made by the real encoders (data messages with their frontier at their own tag)."""
    encoder, keys = WireEncoder(), KeySpace(NAMESPACE)
    reports = []
    nodes = sorted({s[0] for s in genuine.trace.raw_steps})
    for node in nodes:
        events = [[wall, encoder.data(tag, seq, tag, n, port, value)]
                  for tag, n, port, seq, value, wall in genuine.trace.raw_events if n == node]
        records = [[list(tag), {p: _ids(ids) for p, ids in consumed.items()}, _ids(produced), status, detail, start,
                    wall] for n, tag, consumed, produced, status, detail, start, wall in genuine.trace.raw_steps
                   if n == node]
        for b in range(batches):
            part = slice(b * len(records) // batches, (b + 1) * len(records) // batches)
            epart = slice(b * len(events) // batches, (b + 1) * len(events) // batches)
            reports.append((keys.report(node), Report(node=node, records=tuple(records[part]),
                                                      events=tuple(events[epart])).encode()))
    return reports


# ---------------------------------------------------------------------------------------------
# Targets
# ---------------------------------------------------------------------------------------------
class Target:
    """One entry point: how to make a fuzzed input, and how to feed it.

    ``make`` returns the input as bytes (what is saved on a crash); ``prepare`` turns it into
    what ``feed`` takes, unarmed (e.g. a log file on disk); ``feed`` is the armed call, which may
    raise only ``allowed``, and returns how many forged records it saw accepted (0 but for the
    coordinator)."""

    name = ""
    allowed: tuple[type[BaseException], ...] = ()
    may_write: tuple[str, ...] = ()

    def __init__(self, mutator: Mutator, genuine: Genuine, workdir: Path):
        self.m, self.genuine, self.workdir = mutator, genuine, workdir

    def make(self) -> bytes:
        raise NotImplementedError

    def prepare(self, data: bytes) -> Any:
        return data

    def feed(self, prepared: Any) -> int:
        raise NotImplementedError

    def seeds(self) -> list[bytes]:
        """The genuine inputs (fed once, unarmed, before fuzzing: what they import is imported)."""
        raise NotImplementedError

    def tolerated(self, error: BaseException) -> bool:
        return isinstance(error, self.allowed)

    def permits(self, prepared: Any) -> Callable[[str, tuple], bool] | None:
        """Which audit events (name, arguments) feeding ``prepared`` may cause: None, none."""
        return None

    def close(self) -> None:
        """Give back what the target holds (a Zenoh session, processes)."""


def _values(genuine: Genuine) -> list[Any]:
    """Values of every kind the codec carries: the run's own (nested @io dataclasses, arrays)
    and a few more."""
    from tests.log.log_flows import Point

    own = [e[4] for e in genuine.trace.raw_events]
    return own[:6] + [1, -2**70, 2.5, "s", b"b", None, (1, (2, "x")), {"a": [1, 2], 3: None},
                      np.arange(6, dtype=np.float32).reshape(2, 3), np.int16(7), np.zeros((2, 2), dtype=[("a", "<f8")]),
                      Point(1.0, 2.0, ("t", 1)), [np.ones(3), np.ones((0, 4))]]


class CodecTarget(Target):
    name = "codec"

    def __init__(self, *args):
        super().__init__(*args)
        self._seeds = [packb(v) for v in _values(self.genuine)]

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        return self.m.msgpack(self.m.rng.choice(self._seeds), self._seeds)

    def feed(self, data: bytes) -> int:
        unpackb(data, keep_unregistered=True)
        unpackb_out_of_band(data, [bytes(16), memoryview(bytes(24))])
        unpackb(data)
        return 0

    def tolerated(self, error: BaseException) -> bool:
        # CodecError is the codec's own; a ValueError raised by msgpack itself on malformed
        # bytes (ExtraData, FormatError, StackError, bad UTF-8) is msgpack's documented one
        return isinstance(error, CodecError) or (isinstance(error, (ValueError, TypeError)) and _raised_by_msgpack(error))


def _raised_by_msgpack(error: BaseException) -> bool:
    """Whether msgpack's unpacker raised it on the bytes (not numpy, nor the codec's own code,
    called back from it): the innermost frame is msgpack's Cython unpacker. msgpack raises
    ValueError on malformed bytes, TypeError on a map key that cannot be one (a list)."""
    tb = error.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    return tb.tb_frame.f_code.co_filename.endswith("_unpacker.pyx")


class WireTarget(Target):
    """A wire decoder fed mutations of real messages."""

    allowed = (WireError,)

    def __init__(self, name: str, decode: Callable[[bytes], Any], seeds: list[bytes], *args):
        super().__init__(*args)
        self.name, self.decode, self._seeds = name, decode, seeds

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        return self.m.msgpack(self.m.rng.choice(self._seeds), self._seeds)

    def feed(self, data: bytes) -> int:
        self.decode(data)
        return 0


class SealTarget(Target):
    """A worker process's side of signed control: ControlOpener.control fed what an insider (a
    session with the run's secret, not a process's key) makes of the coordinator's sealed
    ``ctl/run`` puts: altered payloads or seals, seals of its own key, replays. An input is
    msgpack ``[payload, seal]``. Anything that opens but a genuine put's payload and counter,
    the first time, is a forged message accepted (the MACs for other processes may be altered:
    they are not this process's to check)."""

    name = "seal"
    allowed = (WireError,)

    def __init__(self, *args):
        super().__init__(*args)
        self.key, self.key_expr = new_key(), KeySpace("fuzz").run_control()
        signer, self.forger = ControlSigner(), ControlSigner()
        signer.add(self, self.key)
        signer.add(signer, new_key())  # another process of the run: its MAC rides along
        self.forger.add(self.forger, new_key())
        payloads = [Stop().encode(), Lost(node="acc").encode(), End(at=10**9).encode(), Grant(until=5).encode()]
        self.genuine_puts = [(payload, signer.seal(self.key_expr, payload)) for payload in payloads]
        self.sealed = {(payload, seal[:COUNTER_BYTES]) for payload, seal in self.genuine_puts}
        self._seeds = [msgpack.packb(list(put), use_bin_type=True) for put in self.genuine_puts]

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        rng = self.m.rng
        payload, seal = rng.choice(self.genuine_puts)
        roll = rng.random()
        if roll < 0.4:
            payload = self.m.msgpack(payload, [p for p, _ in self.genuine_puts])
        elif roll < 0.75:
            seal = self.m.bytes(seal, [s for _, s in self.genuine_puts])
        elif roll < 0.9:
            payload = self.m.msgpack(payload, [p for p, _ in self.genuine_puts])
            seal = self.forger.seal(self.key_expr, payload)
        return msgpack.packb([payload, seal], use_bin_type=True)

    def feed(self, data: bytes) -> int:
        payload, seal = msgpack.unpackb(data, raw=False)
        opener = ControlOpener(self.key)
        opener.control(self.key_expr, payload, seal)  # WireError: refused
        try:
            opener.open(self.key_expr, payload, seal)
        except WireError:  # a replay: refused
            return 0 if (payload, seal[:COUNTER_BYTES]) in self.sealed else 1
        return 1


class DataTarget(WireTarget):
    """Data messages: a msgpack array of bins (envelope, then the arrays' bytes)."""

    def make(self) -> bytes:
        rng, seed = self.m.rng, self.m.rng.choice(self._seeds)
        if rng.random() < 0.3:
            return self.m.bytes(seed, self._seeds)
        bins = msgpack.unpackb(seed)
        which = rng.randrange(len(bins) + 1)
        if which == len(bins):  # the bins themselves: drop, add, reorder
            op = rng.randrange(3)
            if op == 0 and len(bins) > 1:
                del bins[rng.randrange(len(bins))]
            elif op == 1:
                bins.append(rng.choice((b"", b"\0" * 7, b"\0" * 4096, bins[0])))
            else:
                rng.shuffle(bins)
        elif which == 0:
            bins[0] = self.m.msgpack(bins[0], [msgpack.unpackb(s)[0] for s in self._seeds])
        else:
            bins[which] = self.m.bytes(bins[which])
        packed = msgpack.packb(bins, use_bin_type=True)
        return self.m.bytes(packed) if rng.random() < 0.1 else packed

    def feed(self, data: bytes) -> int:
        decode_events(data)
        decode_events(data, ("counter", "out"))
        decode_events(data, ("counter", "out"), blank_ok=True)  # as the coordinator takes a report's
        return 0


class CoordinatorTarget(Target):
    """Fuzzed reports fed to the coordinator's message handler after the genuine run's reports.

    The handler is the coordinator's own (``Inbox.handle``), assembled over a record of the run
    (``RunBook``: the streams, the seen ids and ticks) and a trace, with no Zenoh session or
    process (:class:`_Offline`). Before fuzzing, the genuine reports go through it and
    the trace it builds must equal the in-process run's."""

    name = "coordinator"
    allowed = ()  # set below: the handler raises nothing, it counts garbage and drops it

    def __init__(self, *args):
        super().__init__(*args)
        self.reports = genuine_reports(self.genuine)
        self.graph = self.genuine.pipeline.compile()
        self.spill = self.workdir / "spill"
        self.spill.mkdir()
        self.base = self._session()
        for key, data in self.reports:
            self.base.inbox.handle((key, data, self.base.book.processes.workers[key.rsplit("/", 1)[1]]))
        if self.base.trace != self.genuine.trace or self.base.counts["garbage"]:
            raise SystemExit("the coordinator harness does not rebuild the genuine run's trace from its reports: "
                             "the coordinator's handlers changed; update CoordinatorTarget._session")
        self.nodes = sorted(self.graph.nodes)
        self.insider_claims = 0

    def _session(self) -> _Offline:
        s = _Offline(self.graph, self.spill)
        # each node's process, as the coordinator knows it: what signed its messages (origin.py)
        s.book.processes.workers = {nid: _Process(40_000 + i) for i, nid in enumerate(sorted(self.graph.nodes))}
        s.book.processes.state = {nid: "ready" for nid in self.graph.nodes}
        return s

    def seeds(self) -> list[bytes]:
        return [_key_and(key, data) for key, data in self.reports]

    def make(self) -> bytes:
        rng = self.m.rng
        key, data = rng.choice(self.reports)
        if rng.random() < 0.5:  # mutate the data messages inside the report's events
            tree = msgpack.unpackb(data, raw=False, strict_map_key=False)
            if tree[3]:
                event = rng.choice(tree[3])
                if rng.random() < 0.85:
                    event[1] = self.m.msgpack(event[1], [e[1] for e in tree[3]])
                else:
                    event[1] = rng.choice((f"{tree[1]}.1.msg", "../../etc/passwd", f"{tree[1]}.x.msg/..", ""))
            data = pack_tree(tree)
            if rng.random() < 0.3:
                data = self.m.msgpack(data)
        elif rng.random() < 0.9:
            data = self.m.msgpack(data, [r for _, r in self.reports])
        # replayed as is otherwise: a genuine report sent again
        if rng.random() < 0.2:  # on another node's key, or one of no node
            key = KeySpace(NAMESPACE).report(rng.choice(self.nodes + ["intruder", "counter.out", ""]))
        return _key_and(key, data)

    def prepare(self, data: bytes) -> tuple:
        key, _, report = data.partition(b"\n")
        s = self._session()
        base = self.base
        s.trace.raw_events[:], s.trace.raw_steps[:] = base.trace.raw_events, base.trace.raw_steps
        s.book.intake.event_ids, s.book.intake.ticks = base.book.intake.event_ids.copy(), base.book.intake.ticks.copy()
        s.counts["garbage"] = GARBAGE_PRINTED  # past the few it prints: it prints none
        return s, (key.decode(), report)

    def feed(self, prepared: tuple) -> int:
        """As the node's own process sent it (signed with its key): what any process of the run may send."""
        s, (key, report) = prepared
        s.inbox.handle((key, report, s.book.processes.workers.get(key.rsplit("/", 1)[1])))
        forged = self._forged(s, key)
        refused = s.counts["garbage"] - GARBAGE_PRINTED + s.book.processes.senders.refused
        if not forged and refused:
            raise Dropped(refused)
        return forged

    def _forged(self, s: _Offline, key: str) -> int:
        """How many records that the report's node could not make reached the trace; counts the
        ones it could (an insider's claims about its own outputs) in ``insider_claims``."""
        base, node = self.base.trace, key.rsplit("/", 1)[1]
        events, steps = s.trace.raw_events, s.trace.raw_steps
        if (len(events) < len(base.raw_events) or len(steps) < len(base.raw_steps)
                or any(a is not b for a, b in zip(events, base.raw_events))
                or any(a is not b for a, b in zip(steps, base.raw_steps))):
            return 1  # a genuine record was changed or displaced
        forged, seen_ids, seen_ticks = 0, self.base.book.intake.event_ids.copy(), self.base.book.intake.ticks.copy()
        new_events, new_steps = events[len(base.raw_events):], steps[len(base.raw_steps):]
        for tag, producer, port, seq, value, _ in new_events:
            own = (producer, port) in s.book.intake.streams or producer in s.book.intake.open_outputs
            if producer != node or not own or (producer, port, seq) in seen_ids or not _inert(value) \
                    or not _is_tag(tag):
                forged += 1
            seen_ids.add((producer, port, seq))
        for n, tag, consumed, produced, status, detail, start, wall in new_steps:
            if (n != node or (n, tag) in seen_ticks or status not in STEP_STATUSES or not _is_tag(tag)
                    or not all(isinstance(p, str) for p in consumed) or type(start) is not int):
                forged += 1
            seen_ticks.add((n, tag))
        if not forged:
            self.insider_claims += len(new_events) + len(new_steps)
        return forged


class Dropped(Exception):
    """The coordinator counted (part of) a report as garbage: its way of refusing it."""


CoordinatorTarget.allowed = (Dropped,)


class _Process:
    """A worker process as the coordinator sees one (host.WorkerProcess), never started."""

    def __init__(self, pid: int):
        self.pid = pid


class InsiderTarget(CoordinatorTarget):
    """What an insider (a session holding the run's secret, not a process the coordinator
    started) puts on a node's status and report keys, through the coordinator's receiving path:
    the signature check (origin.Senders, on Zenoh's thread), then ``Inbox.handle``.

    Forged statuses carry the node's own pid (``exit`` at one of its ticks, ``done`` stopped,
    ``failed``, ``restart``, ``handed_over``, ``ready``, mutated), forged reports step records
    between the node's ticks, past the run's end and at its ticks, an ``exit`` record among them.
    Each comes with no MAC, random bytes, the MAC of the insider's own key, the node's MAC of
    another message (a replay on another key, or of another payload), or a cut one. A fifth are
    signed with the node's own key (its process, compromised): then only records at its ticks,
    and an `exit` backed by its record, may count. Anything else that reaches the trace, the
    node's state, its counts, a failure or the run's end is a forgery accepted."""

    name = "insider"

    def __init__(self, mutator: Mutator, genuine: Genuine, workdir: Path):
        self.keys = {nid: new_key() for nid in genuine.pipeline.compile().nodes}
        self.own_key = new_key()  # the insider's: it may derive the run's passwords, not a process's key
        self.end_ns = round(RUN_S * 1e9)
        super().__init__(mutator, genuine, workdir)

    def _session(self) -> _Offline:
        s = super()._session()
        s.book.t0, s.book.end_ns = 0, round(RUN_S * 1e9)
        procs = s.book.processes
        procs.hosts = {nid: _Host() for nid in procs.workers}  # where a signed `restart` starts a process
        for nid, proc in procs.workers.items():
            procs.senders.add(nid, self.keys[nid], proc)
        return s

    def seeds(self) -> list[bytes]:
        return []

    def make(self) -> bytes:
        rng, keys = self.m.rng, KeySpace(NAMESPACE)
        node = rng.choice(self.nodes)
        clock = self.graph.nodes[node].clock
        tick = rng.choice([(clock.tick_time(rng.randrange(8)), 0) if clock.hz else (5, 0),
                           (rng.randrange(1, 10**8), 0), (self.end_ns + rng.randrange(10**9), 0),
                           (clock.tick_time(1) if clock.hz else 5, rng.randrange(1, 4))])
        if rng.random() < 0.55:
            said = {"node": node, "pid": self.base.book.processes.workers[node].pid}
            status = rng.choice([
                Exit(**said, tag=tick), Exit(**said, tag=tick), Done(**said, counts={"late": 1000}, reports=1,
                                                                     stopped=True),
                Failed(**said, error="forged", tag=tick, traceback=None), Restart(**said, tag=tick, error="forged"),
                HandedOver(**said, counts={"late": 1000}, reports=1), Ready(**said), Reached(**said, until=10**12)])
            key, payload = keys.node_status(node), status.encode()
        else:
            records = tuple((tick, {}, (), StepStatus.OK, rng.choice([None, {"exit": 0}]), 0, 0)
                            for tick in {tick, (tick[0] + 1, 0), (self.end_ns + 10**8, 0)})
            key, payload = keys.report(node), Report(node=node, records=records, events=()).encode()
        if rng.random() < 0.3:
            payload = self.m.msgpack(payload)
        mac = rng.choice([None, os.urandom(16), sign(self.own_key, key, payload),
                          sign(self.keys[node], keys.report(node) if "node/" in key else keys.node_status(node),
                               payload), sign(self.keys[node], key, payload + b"\0"),
                          sign(self.keys[node], key, payload)[:8], "own"])
        if mac == "own":  # its own process, compromised: signed
            mac = sign(self.keys[node], key, payload)
        return msgpack.packb([key, mac, payload])

    def prepare(self, data: bytes) -> tuple:
        key, mac, payload = msgpack.unpackb(data)
        return self._session(), (key, payload, mac)

    def feed(self, prepared: tuple) -> int:
        s, (key, payload, mac) = prepared
        node = key.rsplit("/", 1)[1]
        signed = node in self.keys and mac == sign(self.keys[node], key, payload)  # by its process, in truth
        sender = s.book.processes.senders.sender(node, key, payload, mac)
        if sender is None:  # refused before anything was decoded or held
            return self._changed(s, signed)
        s.inbox.handle((key, payload, sender))
        return self._changed(s, signed) + (not signed)

    def _changed(self, s: _Offline, signed: bool) -> int:
        """What a forgery changed: records off their node's clock, or anything at all when it
        was not signed; an end of the run without the node's exit record."""
        steps = s.trace.raw_steps
        book = s.book
        ending, intake = book.ending, book.intake
        changed = sum(1 for n, tag, *_ in steps
                      if not signed or not self.graph.nodes[n].clock.may_tick_at(tag, book.end_ns))
        changed += len(s.trace.raw_events) if not signed else 0
        if ending.ended_by is not None and not any(n == ending.ended_by and (d or {}).get("exit") == 0
                                                   for n, _, _, _, _, d, *_ in steps):
            changed += 1
        if not signed and (ending.failure is not None or ending.stop_sent or ending.exit_said
                           or any(state != State.READY for state in book.processes.state.values())
                           or any(st.counts for st in intake.stats.values()) or any(intake.reports_sent.values())):
            changed += 1
        if not changed and not signed:
            raise Dropped(book.processes.senders.refused)
        return changed


class _Offline:
    """The coordinator's message handling with no Zenoh and no process: its record of the run
    (``book``), a trace, and the inbox that hands a signed message to its handler; its control
    puts go to a stand-in hub (an accepted exit puts `end`)."""

    def __init__(self, graph, spill: Path):
        self.trace, self.counts = Trace(keep="trace"), Counter()
        self.trace.ports = output_ports(graph)  # as a session's trace has them
        self.book = RunBook(graph, self.counts)
        self.hub = _Hub()
        self.inbox = assemble(self.book, self.trace, spill, RunControl(self.hub, KeySpace(NAMESPACE)), Hosting()).inbox


class _Host:
    """A host whose processes are never started (what a signed ``restart`` asks for)."""

    def spawn(self, node: str, mode, key) -> tuple[_Process, bytes]:
        return _Process(50_000), key


class _Hub:
    """The hub session's put, for a coordinator with no Zenoh: what it was asked to put."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes, **_) -> None:
        self.puts.append((key, payload))


def _key_and(key: str, data: bytes) -> bytes:
    return key.encode() + b"\n" + data


def _is_tag(tag: Any) -> bool:
    return type(tag) is tuple and len(tag) == 2 and all(type(x) is int and x >= 0 for x in tag)


def _inert(value: Any, depth: int = 0) -> bool:
    """Whether a decoded value holds only the codec's types (no object of any other class)."""
    if value is None or type(value) in (bool, int, float, str, bytes, np.ndarray) or isinstance(value, np.generic):
        return type(value) is not np.ndarray or not value.dtype.hasobject
    if type(value) in (list, tuple):
        return all(_inert(v, depth + 1) for v in value)
    if type(value) is dict:
        return all(_inert(k, depth + 1) and _inert(v, depth + 1) for k, v in value.items())
    if is_value_type(type(value)):
        return all(_inert(v, depth + 1) for v in vars(value).values())
    return False


#: the flow types a fuzzed IR may name: the test flows (an IR is code by design: it names the
#: classes a run imports), and callables that are no Flow, which must be refused, never called
IR_TYPES = ["tests.ir_flows:Camera", "tests.ir_flows:Planner", "tests.ir_flows:Controller", "tests.ir_flows:Logger",
            "tests.ir_flows:Tool", "tests.log.log_flows:Counter", "tests.log.log_flows:Accumulate",
            "tests.log.log_flows:Tally", "tests.log.log_flows:Point", "os:system", "builtins:eval", "builtins:exec",
            "subprocess:Popen", "posix:system", "retriever.codec:import_type", "tests.ir_flows:Camera.__init__"]
DEEP = "__deep__"  # a string the IR mutator puts where the JSON text gets a deep nest


class SpecTarget(Target):
    """What an insider asks a worker daemon to prepare (runs.DaemonRuns.prepare, then the spec the
    daemon would write for its processes, runs.DaemonRuns.local_spec): the run's spec, hostile.

    Node types name what a daemon must never import (``venv.__main__``, ``test.__main__``: the
    standard library's command lines; ``os:system``; dunder parts) beside the genuine flows; the
    spec carries an ``argv`` (which a worker must never take from the network), zids, timing.
    The daemon's ``--path`` is a folder holding the test flows and, as a project folder may,
    ``venv/`` and ``test/`` folders without ``__init__.py``. It sees no coordinator's token, so a
    prepare that passes every check stops there, before it writes anything: the spec it would
    write is then made too. Its only error is WireError; nothing may be imported or run."""

    name = "specs"
    allowed = (WireError,)
    HOSTILE_TYPES = ["venv.__main__:EnvBuilder", "test.__main__:main", "venv:main", "test.regrtest:main",
                     "os:system", "builtins:eval", "subprocess:Popen", "tests.__main__:X", "__main__:X",
                     "tests..log:X", ".tests:X", "tests.log.log_flows.__init__:Counter", "agents.planner:Planner"]

    def __init__(self, *args):
        super().__init__(*args)
        from retriever.backends.zenoh import daemon
        from retriever.backends.zenoh.daemon import DaemonRuns

        folder = self.workdir / "project"
        for name in ("venv", "test", "tests"):
            (folder / name).mkdir(parents=True)  # namespace packages: never admitted
        paths = [str(ROOT), str(folder)]
        self.session = _daemon_session()  # no coordinator's liveliness token on it
        self.runs = DaemonRuns(self.session, "fuzz", NAMESPACE, listen=(), secret=None,
                               allowed=lambda module: daemon.module_allowed(module, [], paths),
                               refusal=lambda module: daemon.refusal(module, [], paths), paths=())
        ir = self.genuine.pipeline.build_ir().doc
        self.base = {"ir": ir, "namespace": NAMESPACE, "hub": "tcp/127.0.0.1:7447", "plan": _plan_of(ir),
                     "startup_timeout": 60.0,
                     "argv": ["retriever-fuzz", "--clear", str(self.workdir)], "python_path": [str(ROOT)],
                     "zids": {n["id"]: f"{i + 1:x}" * 4 for i, n in enumerate(ir["nodes"])}, "hub_zid": "abc",
                     "virtual_time": False, "main_file": None}
        self._seeds = [msgpack.packb({"run": "r1", "spec": self.base, "nodes": [n["id"] for n in ir["nodes"]]})]

    def close(self) -> None:
        self.runs.close()
        self.session.close()

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        rng = self.m.rng
        args = copy.deepcopy(msgpack.unpackb(self._seeds[0]))
        nodes = args["spec"]["ir"]["nodes"]
        for node in rng.sample(nodes, rng.randrange(1, len(nodes) + 1)):
            node["type"] = rng.choice(self.HOSTILE_TYPES)
        if rng.random() < 0.3:
            args["spec"]["argv"] = ["-m", "venv", "--clear", str(self.workdir)]
        data = msgpack.packb(args)
        return self.m.msgpack(data, self._seeds) if rng.random() < 0.4 else data

    def prepare(self, data: bytes) -> Any:
        try:
            return msgpack.unpackb(data, raw=False, strict_map_key=False)
        except Exception:  # noqa: BLE001 - bytes a daemon's control decoder refuses before prepare
            return None

    def feed(self, args: Any) -> int:
        request = PrepareRequest.from_fields(args, "a prepare request")  # the daemon's decoder (protocol.REQUEST)
        try:
            self.runs.prepare(request)
        except WireError as e:
            if "liveliness token" not in str(e):
                raise
        spec = self.runs.local_spec(request.spec, self.workdir, request.run)  # every check passed: what it would write
        if spec.argv is not None:
            return 1  # the network's argv reached a worker's spec
        return 0


class Breach(Exception):
    """What a daemon op did to the world that it must not: a process outside the run signalled,
    one of the run's processes gone without a legitimate signal, a process not asked for."""


def _plan_of(ir_doc: dict) -> dict:
    """The plan a coordinator ships with ``ir_doc`` (its IR's own: retriever.plan)."""
    from retriever.plan import plan_ir

    return plan_ir(IR(ir_doc)).to_data()


def _daemon_session(listen: tuple[str, ...] = ()):
    """A real Zenoh session, local only (no scouting, no shared memory: nothing left in /dev/shm)."""
    import zenoh

    from retriever.backends.zenoh.hub import peer_config

    return zenoh.open(peer_config(listen=list(listen), shared_memory=False))


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: legitimate spawns and signals the spawn-signal target sends among its hostile ones (each may
#: start a real worker process)
LEGITIMATE_REQUESTS = 12


class DaemonOpsTarget(Target):
    """What an insider (a session holding the secret) asks a worker daemon to ``spawn`` and
    ``signal`` (runs.DaemonRuns, made by its constructor on a real Zenoh session): the control
    message's bytes through the daemon's decoder (protocol.REQUEST), then the op.

    The daemon has prepared run ``r1`` (a coordinator's liveliness token is up on the same session)
    with one node of the genuine pipeline, and runs one real worker process of it (spawned once,
    unarmed, as a coordinator does). Beside it runs a sentinel process the target started (Python,
    sleeping until this process ends), in no run. Requests are made from the genuine ones with one
    to three fields hostile: other runs' ids, nodes not prepared or not strings, modes with
    non-ASCII digits or flags of Python's own, signing keys of the wrong length (whitespace that
    ``bytes.fromhex`` skips), pids of the daemon itself, of pid 1, 0, -1 (every process), of the
    sentinel and of process groups, huge and negative numbers, signals outside SIGUSR1, SIGTERM and
    SIGKILL (0, SIGSTOP, floats, names), extra ``env``, ``path`` and ``argv`` entries, then often
    mutated further (deep nests, forged extension values, bytes). Among them go LEGITIMATE_REQUESTS
    legitimate ones with such extra entries (each may start a real worker).

    Allowed: WireError. The guard permits, for a request that is legitimate by the protocol (the
    run's id; a prepared node with fewer than two live processes; ``[]`` or ``--join``/``--fresh``
    with ASCII digits; a key of 32 bytes as 64 hex digits), only the start of that node's worker
    with exactly that argv and an environment of no more than the flow environment and that key;
    for a legitimate signal only ``os.kill`` of that pid with that signal. Anything else the
    guard flags (a process started, a process signalled, code run). After every input the
    sentinel must live, and so must every process of the run no legitimate signal was sent to."""

    name = "spawn-signal"
    allowed = (WireError,)
    RUN = "r1"

    def __init__(self, *args):
        super().__init__(*args)
        import subprocess

        from retriever.backends.zenoh import daemon
        from retriever.backends.zenoh.command import WORKER_MODULE
        from retriever.backends.zenoh.daemon import runs
        from retriever.backends.zenoh.origin import KEY_BYTES, KEY_FD_ENV

        self.worker_module, self.key_fd_env, self.key_bytes = WORKER_MODULE, KEY_FD_ENV, KEY_BYTES
        self.signals, self.flow_env = runs.SIGNALS, runs.flow_environment
        self.max_per_node = runs.MAX_PROCESSES_PER_NODE
        namespace = f"{NAMESPACE}-runs-{os.getpid()}"
        hub = f"tcp/127.0.0.1:{_free_port()}"  # the run's workers link to this session, and wait there
        self.session = _daemon_session((hub,))
        # in no run and no session of the daemon's; it ends when this process does, even SIGKILLed
        sleep = f"import os, time\nwhile os.getppid() == {os.getpid()}: time.sleep(0.2)"
        self.sentinel = subprocess.Popen([sys.executable, "-I", "-S", "-c", sleep], start_new_session=True,
                                         stdin=subprocess.DEVNULL)
        paths = [str(ROOT)]
        self.runs = runs.DaemonRuns(self.session, "fuzz", namespace, listen=(), secret=None,
                                    allowed=lambda module: daemon.module_allowed(module, [], paths),
                                    refusal=lambda module: daemon.refusal(module, [], paths), paths=(), lease=None)
        # the coordinator's liveliness token, without which the daemon prepares nothing
        self.token = self.session.liveliness().declare_token(KeySpace(namespace).deployment())
        ir = self.genuine.pipeline.build_ir().doc
        self.ir_nodes = [n["id"] for n in ir["nodes"]]
        self.node = self.ir_nodes[0]
        spec = RunSpec(ir=ir, namespace=namespace, hub=hub, plan=_plan_of(ir), startup_timeout=86400.0, zids={},
                       hub_zid=None, virtual_time=False)
        for _ in range(100):  # the token's own subscriber sees it on a Zenoh thread
            try:
                self.runs.prepare(PrepareRequest(run=self.RUN, spec=spec, nodes=(self.node,)))
                break
            except WireError as e:
                if "liveliness token" not in str(e):
                    raise
                time.sleep(0.05)
        else:
            raise SystemExit("the daemon never saw the coordinator's liveliness token")
        self.key = new_key().hex()
        self._seeds = [SpawnRequest(run=self.RUN, node=self.node, mode=()).encode()]
        self.signalled: set[int] = set()  # the run's processes a legitimate request signalled
        self.legitimate_left = LEGITIMATE_REQUESTS

    def close(self) -> None:
        self.runs.close()  # ends the run: its processes get SIGTERM, then SIGKILL
        self.token.undeclare()
        self.session.close()
        self.sentinel.kill()
        self.sentinel.wait()

    def seeds(self) -> list[bytes]:
        return self._seeds

    # -- inputs ---------------------------------------------------------------------------------
    def _pids(self) -> list[int]:
        run = self.runs.run
        return sorted(run.processes) if run else []

    def _hostile(self, field: str) -> Any:
        rng, pids = self.m.rng, self._pids() or [2**22]
        pid = rng.choice(pids)
        marker = str(self.m.marker)
        hostile = {
            "run": ["r0", "r2", "", None, 1, ["r1"], {"run": "r1"}, "r1\x00", "R1", "r1 ", b"r1", "*", "r1/../r0"],
            "node": [*(n for n in self.ir_nodes if n != self.node), "", None, 7, [self.node], {self.node: 1},
                     f"{self.node}\x00", "../../../bin/sh", "os:system", "-c", "--help", self.node.upper(),
                     "x" * 100_000, b"counter"],
            "mode": [["--join"], ["--fresh", "-1", "5"], ["--fresh", "1e9", "2"], ["--join", "²", "3"],
                     ["--join", "١٢٣", "4"], ["--fresh", "𝟙", "1"], ["--fresh", "9" * 20, "1"], ["--join", 1, 2],
                     ["--inspect", "1", "2"], ["-c", f"open({marker!r}, 'w')", "x"], "--join 1 2", None,
                     {"0": "--join"}, ["--join", "1", "2", "--extra"], ["--join", " 1", "2"],
                     ["--fresh", "0x10", "1"], ["-m", "venv", "--clear"], ["--join", "1\n", "2"], [[]]],
            "key": [self.key, self.key.upper(), "ab" * (self.key_bytes - 1), "ab" * (self.key_bytes + 1), "zz" * self.key_bytes,
                    "ab" * (self.key_bytes - 1) + "  ", " " + "ab" * (self.key_bytes - 1) + " ",
                    "ab " * (2 * self.key_bytes // 3) + "ab"[: 2 * self.key_bytes % 3],
                    bytes(self.key_bytes), bytes(2 * self.key_bytes), None, 0, 2**256 % 2**64, "", "é" * 64,
                    self.key[:-1] + "\n", ["ab"] * self.key_bytes, {"hex": self.key}],
            "pid": [os.getpid(), 1, 0, -1, self.sentinel.pid, -self.sentinel.pid, -pid, os.getppid(), 2**31,
                    2**31 - 1, 2**63 - 1, 2**64 - 1, -2**63, float(pid), True, str(pid), [pid], {"pid": pid},
                    pid + 1, None],
            "signal": [0, 2, 19, 17, 18, 64, 65, -9, 9.0, 15.0, "SIGKILL", "9", True, None, 2**63, [9], 10**30 % 2**64],
        }
        return rng.choice(hostile[field])

    def make(self) -> bytes:
        rng = self.m.rng
        if rng.random() < 0.5:
            op = DaemonOp.SPAWN
            args: dict = {"run": self.RUN, "node": self.node,
                          "mode": rng.choice(([], ["--join", "12", "34"], ["--fresh", "0", "9" * 19]))}
            fields = ["run", "node", "mode", "key"]
        else:
            op = DaemonOp.SIGNAL
            args = {"run": self.RUN, "pid": rng.choice(self._pids() or [0]), "signal": int(rng.choice(self.signals))}
            fields = ["run", "pid", "signal"]
        legitimate = self.legitimate_left > 0 and rng.random() < 0.05
        if legitimate:  # a request the daemon grants, with entries it must ignore (a real process each: few)
            self.legitimate_left -= 1
        else:
            for field in rng.sample(fields, rng.choice((1, 1, 1, 2, 3))):
                args[field] = self._hostile(field)
        if legitimate or rng.random() < 0.2:  # what a daemon must ignore, not use
            extra = rng.choice((("env", {"LD_PRELOAD": str(self.m.marker), "PYTHONSTARTUP": str(self.m.marker)}),
                                ("path", str(self.m.marker)), ("argv", ["-c", "import os"]), ("executable", "/bin/sh"),
                                ("cwd", "/"), ("python_path", [str(self.workdir)]), ("spec", "/etc/passwd")))
            args[extra[0]] = extra[1]
        if legitimate:
            return pack_tree([WIRE_VERSION, op, args])
        if op == DaemonOp.SPAWN and rng.random() < 0.1:
            args.pop(rng.choice(fields), None)
        if rng.random() < 0.3:
            args = self.m.tree(args)
        data = pack_tree([WIRE_VERSION, op, args])
        return self.m.bytes(data) if rng.random() < 0.1 else data

    def prepare(self, data: bytes) -> Any:
        try:
            request = REQUEST.decode(data)
        except WireError:
            return data, None, None
        return data, request, request.to_fields()

    # -- what a request may do ----------------------------------------------------------------------
    def _legitimate_spawn(self, args: dict) -> list[str] | None:
        """The argv of the worker a legitimate spawn starts; None for any other request."""
        run, node, mode = self.runs.run, args.get("node"), args.get("mode")
        if run is None or args.get("run") != self.RUN \
                or type(node) is not str or node not in run.nodes:
            return None
        if not (mode == [] or (type(mode) is list and len(mode) == 3 and mode[0] in ("--join", "--fresh")
                               and all(type(x) is str and x.isascii() and x.isdigit() and len(x) <= 19
                                       for x in mode[1:]))):
            return None
        if "key" in args:  # the daemon makes its process's key: a request's is refused
            return None
        if sum(1 for n, p in run.processes.values() if n == node and p.poll() is None) >= self.max_per_node:
            return None
        return [sys.executable, "-m", self.worker_module, str(run.folder / "spec.json"), node, *mode]

    def _legitimate_signal(self, args: dict) -> tuple[int, int] | None:
        run, pid, sig = self.runs.run, args.get("pid"), args.get("signal")
        if run is None or args.get("run") != self.RUN:
            return None
        if type(pid) is int and pid in run.processes and type(sig) is int and sig in self.signals:
            return pid, sig
        return None

    def permits(self, prepared: Any) -> Callable[[str, tuple], bool] | None:
        _, request, args = prepared
        op = request.NAME if request is not None else None
        if op == DaemonOp.SPAWN:
            argv = self._legitimate_spawn(args)
            if argv is None:
                return None
            env = self.flow_env(os.environ)

            def with_key_pipe(given: dict) -> bool:  # the flows' environment, and the number of the key's pipe
                fd = given.get(self.key_fd_env, "")
                return fd.isascii() and fd.isdigit() and {k: v for k, v in given.items() if k != self.key_fd_env} == env
            return lambda event, a: ((event == "subprocess.Popen" and a[1] == argv and with_key_pipe(a[3]))
                                     or (event == "open" and a[0] == os.devnull))  # its stdin
        if op == DaemonOp.SIGNAL:
            legitimate = self._legitimate_signal(args)
            return None if legitimate is None else lambda event, a: event == "os.kill" and tuple(a) == legitimate
        return None

    def feed(self, prepared: Any) -> int:
        data, request, args = prepared
        if request is None:
            REQUEST.decode(data)  # raises what the daemon's decoder raises
        op = request.NAME
        live = {pid: proc for pid, (_, proc) in self.runs.run.processes.items() if proc.poll() is None}
        before = set(self.runs.run.processes)
        legitimate = self.permits(prepared) is not None
        try:
            handler = self.runs.ops.get(op) if op in (DaemonOp.SPAWN, DaemonOp.SIGNAL) else None
            if handler is None:
                raise WireError(f"the fuzzed op {op!r:.20} is not spawn or signal")
            handler(request)
        finally:
            problems = self._breaches(op, args, legitimate, live, before)
            if problems:
                raise Breach("; ".join(problems))
        return 0

    def _breaches(self, op: str, args: dict, legitimate: bool, live: dict, before: set) -> list[str]:
        problems = []
        if self.sentinel.poll() is not None:
            problems.append(f"the sentinel process (pid {self.sentinel.pid}, in no run) ended "
                            f"({self.sentinel.returncode})")
        if op == DaemonOp.SIGNAL and legitimate:
            self.signalled.add(args["pid"])  # it may end now, or later (its signal is on its way)
        for pid, proc in live.items():
            if pid not in self.signalled and proc.poll() is not None:
                problems.append(f"the run's process {pid} ended without a legitimate signal to it")
        started = set(self.runs.run.processes) - before
        if started and not (op == DaemonOp.SPAWN and legitimate and len(started) == 1):
            problems.append(f"processes started by a request that was not a legitimate spawn: {sorted(started)}")
        return problems


class IRTarget(Target):
    """IR JSON text: IR.from_json, then Pipeline.from_ir."""

    name = "ir"
    allowed = (IRError,)

    def __init__(self, *args):
        super().__init__(*args)
        from tests import ir_flows

        self.docs = [ir_flows.build().build_ir().doc, self.genuine.pipeline.build_ir().doc]
        self._seeds = [json.dumps(d).encode() for d in self.docs]

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        rng = self.m.rng
        doc = copy.deepcopy(rng.choice(self.docs))
        for _ in range(rng.choice((1, 1, 2, 4))):
            self._mutate(doc)
        text = json.dumps(doc, allow_nan=True)
        if DEEP in text:
            depth = rng.choice((100, 1000, 100_000))
            text = text.replace(json.dumps(DEEP), "[" * depth + "]" * depth, 1)
        data = text.encode()
        return self.m.bytes(data, self._seeds) if rng.random() < 0.1 else data

    def _mutate(self, doc: dict) -> None:
        slots: list = []
        _collect(doc, slots)
        parent, key = self.m.rng.choice(slots)
        try:
            self._mutate_part(doc)
        except (TypeError, KeyError, AttributeError, ValueError, IndexError):  # an earlier mutation broke that part
            parent[key] = self._json(parent[key])

    def _mutate_part(self, doc: dict) -> None:
        rng = self.m.rng
        slots: list = []
        _collect(doc, slots)
        parent, key = rng.choice(slots)
        op = rng.randrange(10)
        node = rng.choice(doc["nodes"]) if doc["nodes"] else None
        if op == 0 and node is not None:
            node["type"] = rng.choice(IR_TYPES)
        elif op in (1, 2) and node is not None:  # a constructor argument
            name = rng.choice(list(node["params"]) + ["period", "scale", "gain", "evil"])
            node["params"][name] = self._param()
        elif op == 3 and node is not None:  # a clock
            node["config"]["clock"] = rng.choice((
                {"Rate": {"hz": self._number()}}, {"Rate": {"hz": 10, "offset": self._number()}},
                {"Trigger": {"ports": self._json(None)}}, {"Hybrid": {"hz": self._number(), "trigger": ["x"]}},
                {"Rate": {"hz": 10}, "Trigger": {}}, {"Rate": None}, {}, []))
        elif op == 4 and doc["edges"]:  # a sync policy or edge values
            edge = rng.choice(doc["edges"])
            (policy, params), = edge["adapter"].items() if len(edge["adapter"]) == 1 else (("Latest", {}),)
            choice = rng.randrange(3)
            if choice == 0:
                edge["adapter"] = {rng.choice(("Latest", "Queue", "Window", "ActionChunking", "Evil", "__class__")):
                                   {rng.choice(("maxsize", "buffer_size", "chunk_steps", "staleness", "x")):
                                    self._number()}}
            elif choice == 1:
                edge[rng.choice(("delay", "qsize", "deadline"))] = self._number()
            else:
                edge[rng.choice(("source", "destination"))] = self._json(None)
        elif op == 5 and node is not None:  # config values
            node["config"][rng.choice(("latency", "on_error", "on_overrun", "on_deadline_miss"))] = self._json(None)
        elif op == 6:
            doc["metadata"][rng.choice(("max_microsteps", "realtime", "deadline", "name", "warnings"))] = \
                self._json(None)
        else:
            parent[key] = self._json(parent[key])

    def _number(self) -> Any:
        return self.m.rng.choice((0, -1, 1e-300, 10**400, math.nan, math.inf, -math.inf, 2**63, 1e308, 0.5, True,
                                  "10", None, [1], -0.0))

    def _param(self) -> Any:
        rng = self.m.rng
        kind = rng.randrange(4)
        if kind == 0:  # a codec value, forged or mutated
            value = pack_tree(self.m.forged_ext()) if rng.random() < 0.5 else \
                self.m.msgpack(packb(rng.choice(_values(self.genuine))))
            return {"$msgpack": base64.b64encode(value).decode()}
        if kind == 1:
            return {"$tuple": self._json(None)} if rng.random() < 0.5 else {"$tuple": [self._param()]}
        if kind == 2:
            return rng.choice(({"$msgpack": "!!not base64"}, {"$msgpack": 5}, {"$msgpack": "", "$tuple": []},
                               {"$evil": 1}, {"$msgpack": base64.b64encode(b"\xc1").decode()}))
        return self._json(None)

    def _json(self, old: Any) -> Any:
        rng = self.m.rng
        return rng.choice((None, True, 0, -1, 10**400, 2**64, math.nan, math.inf, -math.inf, 1e308, "", "x" * 10_000,
                           "os:system", [], {}, [old], {"k": old}, DEEP, self._number(), str(old)[:40]))

    def feed(self, data: bytes) -> int:
        Pipeline.from_ir(IR.from_json(data.decode("utf-8", "surrogateescape")))
        return 0


class LogTarget(Target):
    """A log file: its bytes mutated, or its records (event values, step records, channels,
    metadata, the IR attachment, times and sequences) mutated and written with the real MCAP
    writer; then everything that reads a log."""

    name = "log"
    allowed = (LogError,)

    def __init__(self, *args):
        super().__init__(*args)
        self.path, self.out = self.workdir / "fuzzed.mcap", self.workdir / "fuzzed.recovered.mcap"
        self.may_write = (str(self.out),)
        self.source = read_log(self.genuine.log)
        self.raw = self.genuine.log.read_bytes()
        self.ir = IRTarget(self.m, self.genuine, self.workdir)

    def seeds(self) -> list[bytes]:
        return [self.raw]

    def make(self) -> bytes:
        rng = self.m.rng
        if rng.random() < 0.3:
            return self.m.bytes(self.raw)
        log = self.source
        channels = {c.id: (c.topic, c.message_encoding, dict(c.metadata)) for c in log.channels.values()}
        attachments = {a.name: [a.media_type, bytes(a.data), a.log_time, a.create_time]
                       for a in log.attachments.values()}
        metadata = {name: dict(data) for name, data in log.metadata.items()}
        messages = [[m.channel_id, m.log_time, m.publish_time, m.sequence, bytes(m.data)] for m in log.messages]
        for _ in range(rng.choice((1, 1, 2, 4))):
            op = rng.randrange(12)
            if op < 6 and messages:  # a record's msgpack: an event [microstep, value] or a step record
                m = rng.choice(messages)
                m[4] = self.m.msgpack(m[4], [x[4] for x in messages])
            elif op == 6 and messages:  # times and sequence
                m = rng.choice(messages)
                m[rng.choice((1, 2, 3))] = rng.choice((0, 2**32 - 1, 2**63, 2**64 - 1, m[1] + 1))
                m[3] &= 0xFFFFFFFF
            elif op == 7 and messages:  # a message on another channel, twice, or dropped
                i = rng.randrange(len(messages))
                choice = rng.randrange(3)
                if choice == 0:
                    messages[i][0] = rng.choice(list(channels))
                elif choice == 1:
                    messages.insert(rng.randrange(len(messages)), list(messages[i]))
                else:
                    del messages[i]
            elif op == 8:  # a channel's topic
                cid = rng.choice(list(channels))
                channels[cid] = (rng.choice(("data/x", "data/a/b/c", "data//", "steps", "data/counter/out",
                                             "data/tally/count", "data/\udcff/p".encode("utf-8", "replace").decode())),
                                 *channels[cid][1:])
            elif op == 9:  # the IR attachment
                attachment = attachments.get("pipeline.ir.json")
                if attachment is not None:
                    attachment[1] = self.ir.make()
            elif op == 10 and metadata:  # the run and end records
                record = metadata[rng.choice(list(metadata))]
                record[rng.choice(list(record) + ["end_ns", "status", "backend", "python_path"])] = rng.choice(
                    ("", "x", "-1", "1e400", "nan", "[]", '["/"]', "finished", "zenoh", str(2**64), "{"))
            else:
                messages.sort(key=lambda _: rng.random())
        return _write_mcap(channels, attachments, metadata, messages)

    def prepare(self, data: bytes) -> Path:
        self.path.write_bytes(data)
        self.out.unlink(missing_ok=True)
        return self.path

    def feed(self, path: Path) -> int:
        refused = None
        for step in (lambda: read_log(path), lambda: self._read_all(path), lambda: recover(path, self.out)):
            try:
                step()
            except LogError as e:
                refused = e
        if refused is not None:
            raise refused
        return 0

    def _read_all(self, path: Path) -> None:
        log = read_log(path, salvage=True)
        for step in (log.trace, lambda: run_info(log),
                     lambda: [repr(log.value(e, keep_unregistered=True)) for e in log.iter_events()],
                     lambda: replay(log, self.genuine.pipeline)):
            try:
                step()
            except LogError:
                pass


def _write_mcap(channels: dict, attachments: dict, metadata: dict, messages: list) -> bytes:
    """An MCAP file of these records, by the writer Retriever's logs are written with."""
    import io

    buffer = io.BytesIO()
    writer = McapWriter(buffer, profile="retriever", library="fuzz")
    ids = {cid: writer.add_channel(*spec) for cid, spec in channels.items()}
    for name, (media_type, data, log_time, create_time) in attachments.items():
        writer.add_attachment(name, media_type, data, log_time, create_time)
    for name, data in metadata.items():
        writer.add_metadata(name, data)
    for cid, log_time, publish_time, sequence, data in messages:
        writer.add_message(ids.get(cid, 0), log_time, publish_time, sequence, data)
    writer.finish()
    return buffer.getvalue()


class PlanTarget(Target):
    """The plan a coordinator ships in a worker's spec (retriever.plan): decoded from msgpack as a
    daemon's control message is, then Plan.from_data against the IR it came with. An input is one
    byte choosing the IR, then the plan. Beside the tree's mutations, names, numbers and booleans
    are swapped for others of the same plan: pieces of the right type in the wrong places, which
    get past the type checks to the checks against the IR and between nodes."""

    name = "plan"
    allowed = (IRError,)

    def __init__(self, *args):
        super().__init__(*args)
        import warnings

        from retriever.plan import Plan, plan_ir
        from tests import ir_flows
        from tests.backends.test_conformance import _cycle_pipeline

        self.read = Plan.from_data
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.irs = [pipe.build_ir() for pipe in (ir_flows.build(), self.genuine.pipeline, _cycle_pipeline(5))]
        self.plans = [plan_ir(ir).to_data() for ir in self.irs]
        self._seeds = [bytes([i]) + msgpack.packb(plan) for i, plan in enumerate(self.plans)]

    def seeds(self) -> list[bytes]:
        return self._seeds

    def make(self) -> bytes:
        rng = self.m.rng
        i = rng.randrange(len(self.plans))
        if rng.random() < 0.5:
            return bytes([i]) + self.m.msgpack(self._seeds[i][1:], [s[1:] for s in self._seeds])
        plan = copy.deepcopy(self.plans[i])
        slots: list = []
        _collect(plan, slots)
        pieces = [parent[key] for parent, key in slots if isinstance(parent[key], (str, int))]
        for _ in range(rng.choice((1, 1, 2, 3))):
            parent, key = rng.choice(slots)
            if isinstance(parent[key], (str, int)):
                parent[key] = rng.choice([p for p in pieces if type(p) is type(parent[key])])
        return bytes([i]) + msgpack.packb(plan)

    def prepare(self, data: bytes) -> Any:
        try:
            plan = msgpack.unpackb(data[1:], raw=False, strict_map_key=False)
        except Exception:  # noqa: BLE001 - bytes a daemon's control decoder refuses before any plan
            plan = None
        return self.irs[data[0] % len(self.irs) if data else 0], plan

    def feed(self, prepared: Any) -> int:
        ir, plan = prepared
        self.read(plan, ir)
        return 0


# ---------------------------------------------------------------------------------------------
# The campaign
# ---------------------------------------------------------------------------------------------
TARGET_NAMES = ["codec", "wire-data", "wire-progress", "wire-report", "wire-status", "wire-control", "coordinator",
                "insider", "seal", "specs", "spawn-signal", "ir", "log", "plan"]


def build_target(name: str, mutator: Mutator, genuine: Genuine, workdir: Path) -> Target:
    args = (mutator, genuine, workdir)
    if name == "codec":
        return CodecTarget(*args)
    if name == "coordinator":
        return CoordinatorTarget(*args)
    if name == "insider":
        return InsiderTarget(*args)
    if name == "seal":
        return SealTarget(*args)
    if name == "specs":
        return SpecTarget(*args)
    if name == "spawn-signal":
        return DaemonOpsTarget(*args)
    if name == "ir":
        return IRTarget(*args)
    if name == "log":
        return LogTarget(*args)
    if name == "plan":
        return PlanTarget(*args)
    enc, trace = WireEncoder(), genuine.trace
    if name == "wire-data":
        values = [e[4] for e in trace.raw_events] + _values(genuine)
        seeds = [enc.data((i, 0), i, (i, 1), "counter", "out", v) for i, v in enumerate(values)]
        bursts = [Burst(values[:5]), Burst(np.arange(12, dtype=np.float32).reshape(4, 3)), Burst(np.arange(9)),
                  Burst([np.zeros(2), "x", (1, 2)]), Burst.unchecked((None,) * 3)]
        seeds += [enc.data((7, 0), 7, (7, 1), "counter", "out", b) for b in bursts]
        return DataTarget(name, decode_events, seeds, *args)
    reports = [data for _, data in genuine_reports(genuine)]
    seeds = {
        "wire-progress": [enc.progress((5, 0), "counter", {"out": 3}), enc.progress((0, 0), "tally", {}),
                          enc.progress((2**63, 7), "acc", {"out": -1, "x": 2**40})],
        "wire-report": reports,
        "wire-status": [status.encode() for status in (
            Ready(node="counter", pid=7, linked=True, unlinked=(), peers=2),
            Done(node="counter", pid=7, counts={"late": 1}),
            Failed(node="counter", pid=7, error="e", tag=(1, 0), counts={"late": 1}, traceback=None),
            Restart(node="counter", pid=7, tag=(1, 0), error="e"),
            HandedOver(node="counter", pid=7, counts={"late": 1}, reports=3))],
        "wire-control": [record.encode() for record in (
            Start(t0=2**62, end=10**9, values=True), Stop(), Handover(node="acc"), Grant(until=10**9))],
    }[name]
    decode = {"wire-progress": decode_progress, "wire-report": Report.decode, "wire-status": STATUS.decode,
              "wire-control": RUN_CONTROL.decode}[name]
    return WireTarget(name, decode, seeds, *args)


@dataclass
class Outcome:
    target: str
    inputs: int = 0
    accepted: int = 0  # returned
    refused: int = 0  # raised the documented error
    crashes: int = 0
    code_executed: int = 0
    forged_accepted: int = 0
    insider_claims: int = 0
    seconds: float = 0.0
    slowest_s: float = 0.0
    #: one per kind of problem (exception type and where it was raised): the file its first input is in
    findings: dict[str, str] = field(default_factory=dict)

    @property
    def clean(self) -> bool:
        return not (self.crashes or self.code_executed or self.forged_accepted)


def fuzz_target(target: Target, guard: Guard, *, seconds: float | None = None, inputs: int | None = None,
                save: bool = True) -> Outcome:
    """Feed the genuine inputs once unarmed, then fuzzed ones until ``seconds`` or ``inputs``."""
    for seed in target.seeds():  # unarmed: what decoding imports on first use is imported now
        try:
            target.feed(target.prepare(seed))
        except target.allowed:  # the coordinator drops a genuine report it already has
            pass
    outcome = Outcome(target.name)
    start = time.perf_counter()
    while (inputs is None or outcome.inputs < inputs) and (seconds is None or time.perf_counter() - start < seconds):
        data = target.make()
        prepared = target.prepare(data)
        began = time.perf_counter()
        forged, error, flagged = guard.call(lambda: target.feed(prepared), target.may_write, target.permits(prepared))
        took = time.perf_counter() - began
        outcome.inputs += 1
        outcome.slowest_s = max(outcome.slowest_s, took)
        problems = []  # (signature, details)
        if error is None:
            outcome.accepted += 1
        elif target.tolerated(error) and took < HANG_S:
            outcome.refused += 1
        else:
            outcome.crashes += 1
            problems.append((f"crash: {_signature(error)}: {str(error)[:100]}",
                             "".join(traceback.format_exception(error))))
        if flagged:
            outcome.code_executed += 1
            problems.append((f"code executed: {flagged[0][:120]}", "\n".join(flagged)))
        if forged:
            outcome.forged_accepted += forged
            problems.append((f"forged record accepted ({forged})", ""))
        for signature, details in problems:
            kind = signature.split(": ")[1] if signature.startswith("crash") else signature
            if kind not in outcome.findings:
                outcome.findings[kind] = _save(target.name, data, signature, details) if save else ""
    outcome.seconds = time.perf_counter() - start
    if type(target) is CoordinatorTarget:
        outcome.insider_claims = target.insider_claims
    return outcome


def _signature(error: BaseException) -> str:
    """The kind of a crash: its type and the innermost place it was raised."""
    tb = error.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    where = f" at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno}" if tb is not None else ""
    return f"{type(error).__name__}{where}"


def _save(target: str, data: bytes, signature: str, details: str) -> str:
    """Keep an input that found a problem, for ``--reproduce``; returns its file."""
    digest = hashlib.sha256(data).hexdigest()[:12]
    CRASH_DIR.mkdir(exist_ok=True)
    path = CRASH_DIR / f"{target}-{digest}.bin"
    path.write_bytes(data)
    (CRASH_DIR / f"{target}-{digest}.txt").write_text(f"{signature}\n\n{details}\n")
    return str(path.relative_to(ROOT))


class Campaign:
    """The genuine run, the guard and one target per name, in a scratch directory."""

    def __init__(self, seed: int):
        self.seed = seed
        self.workdir = Path(tempfile.mkdtemp(prefix="retriever-fuzz-", dir=_scratch()))
        self.marker = self.workdir / "pwned"
        self.genuine = genuine_run(self.workdir)
        self.guard = Guard(self.marker)
        self.targets: list[Target] = []

    def target(self, name: str) -> Target:
        mutator = Mutator(random.Random(f"{self.seed}:{name}"), self.marker)
        workdir = self.workdir / name
        workdir.mkdir(exist_ok=True)
        self.targets.append(build_target(name, mutator, self.genuine, workdir))
        return self.targets[-1]

    def close(self) -> None:
        for target in self.targets:
            target.close()
        shutil.rmtree(self.workdir, ignore_errors=True)


def _scratch() -> str | None:
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def reproduce(path: Path) -> int:
    """Run one saved input again, unguarded, and show what it raises."""
    name = next(n for n in sorted(TARGET_NAMES, key=len, reverse=True) if path.name.startswith(n + "-"))
    campaign = Campaign(0)
    try:
        target = campaign.target(name)
        target.feed(target.prepare(path.read_bytes()))
        print(f"{path.name}: {name} returned")
    except BaseException:  # noqa: BLE001 - shown whole: that is the point
        traceback.print_exc()
        return 1
    finally:
        campaign.close()
    return 0


def insider_run(records: int) -> dict[str, int]:
    """See the module docstring (``--insider-run``)."""
    import subprocess

    from tests.backends.zenoh.test_access import Run, _insider, _secret_file
    from tests.backends.zenoh.test_origin import _rss, _worker_pid

    workdir = Path(tempfile.mkdtemp(prefix="retriever-insider-", dir=_scratch()))
    namespace = f"insider-{os.getpid()}"
    per, ticks = 100_000, 100_000_000  # records a report; the source's period (10 Hz)
    payloads = [msgpack.packb([2, "counter", [[[t, 0], {}, [], "ok", None, 0, 0] for t in
                                              (range(1 + i, 1 + i + n) if k % 3 == 0 else
                                               range((40 + i) * ticks, (40 + i + n) * ticks, ticks) if k % 3 == 1 else
                                               [j % 30 * ticks for j in range(n)])], []])
                for k, i in enumerate(range(0, records, per)) for n in [min(per, records - i)]]
    secret = _secret_file(workdir)
    run = Run(workdir, namespace, secret)
    statuses = grown = 0
    try:
        with _insider(run, namespace, secret, workdir) as (insider, keys):
            before = _rss(run.proc.pid)
            for node, tag in (("counter", (500_000_000, 0)), ("total", (400_000_000, 0))):
                pid = _worker_pid(run.proc.pid, node)
                for status in (Exit(node=node, pid=pid, tag=tag), Done(node=node, pid=pid, counts={}, stopped=True)):
                    insider.put(keys.node_status(node), status.encode(), congestion_control=RELIABLE)
                    statuses += 1
            for payload in payloads:
                insider.put(keys.report("counter"), payload, congestion_control=RELIABLE)  # all of it arrives
            while True:
                try:
                    grown = max(grown, _rss(run.proc.pid) - before)
                    run.proc.wait(timeout=0.05)
                    break
                except subprocess.TimeoutExpired:
                    continue
                except OSError:
                    break
        result = run.result()
        steps = list(read_log(run.log).iter_steps())
    finally:
        run.kill()
        shutil.rmtree(workdir, ignore_errors=True)
    genuine = {"counter": 30, "total": 15}
    return {"statuses put": statuses, "records put": records, "reports put": len(payloads),
            "refused as forged": result["counts"].get("forged", 0),
            "records accepted past the run's own": sum(max(0, result["stats"][n][0] - k) for n, k in genuine.items()),
            "ticks the run missed (ended early)": sum(max(0, k - result["stats"][n][0]) for n, k in genuine.items()),
            "step records in the log": len(steps), "coordinator MiB before": before >> 20,
            "coordinator MiB grown (peak)": grown >> 20}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, help="seconds per target")
    parser.add_argument("--inputs", type=int, help="inputs per target")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--targets", default=",".join(TARGET_NAMES), help="comma-separated: " + ", ".join(TARGET_NAMES))
    parser.add_argument("--reproduce", type=Path, help="run a saved input of benchmarks/fuzz_crashes/ again")
    parser.add_argument("--insider-run", type=int, metavar="RECORDS",
                        help="a real run beside an insider putting RECORDS forged step records (no fuzzing)")
    args = parser.parse_args(argv)
    if args.reproduce:
        return reproduce(args.reproduce)
    if args.insider_run is not None:
        measured = insider_run(args.insider_run)
        print("| what | count |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in measured.items()))
        ok = not measured["records accepted past the run's own"] and not measured["ticks the run missed (ended early)"]
        return 0 if ok else 1
    if args.seconds is None and args.inputs is None:
        args.seconds = 10.0
    names = [n.strip() for n in args.targets.split(",") if n.strip()]
    unknown = sorted(set(names) - set(TARGET_NAMES))
    if unknown:
        parser.error(f"unknown target(s) {', '.join(unknown)}; the targets are {', '.join(TARGET_NAMES)}")
    campaign = Campaign(args.seed)
    outcomes = []
    try:
        for name in names:
            outcome = fuzz_target(campaign.target(name), campaign.guard, seconds=args.seconds, inputs=args.inputs)
            outcomes.append(outcome)
            print(f"{name}: {outcome.inputs} inputs in {outcome.seconds:.1f} s", file=sys.stderr, flush=True)
            for signature, path in outcome.findings.items():
                print(f"    {signature}\n        {path}", file=sys.stderr)
    finally:
        campaign.close()
    print(table(outcomes))
    return 0 if all(o.clean for o in outcomes) else 1


def table(outcomes: list[Outcome]) -> str:
    head = ("| target | inputs | accepted | refused | crashes | code executed | forged records accepted "
            "| insider claims | slowest input |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for o in outcomes:
        lines.append(f"| {o.target} | {o.inputs} | {o.accepted} | {o.refused} | {o.crashes} | {o.code_executed} "
                     f"| {o.forged_accepted} | {o.insider_claims if o.target == 'coordinator' else '–'} "
                     f"| {o.slowest_s * 1e3:.0f} ms |")
    total = sum(o.inputs for o in outcomes)
    lines.append(f"| **total** | **{total}** | | | **{sum(o.crashes for o in outcomes)}** "
                 f"| **{sum(o.code_executed for o in outcomes)}** | **{sum(o.forged_accepted for o in outcomes)}** | | |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
