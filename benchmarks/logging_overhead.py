"""Cost of the MCAP event log: in-process steps/s with logging on vs off, log size, replay speed.

Two workloads, each run by ``pipe.run(duration)`` on the ``inproc`` backend with and without
``log=...`` (a file in a temporary directory), alternating off/on, best of ``--repeats``:

- ``chain``: the trivial chain of ``step_overhead.py`` (1 Rate source + N stages on ``Rate(hz)``,
  ``Latest()`` edges, typed ``@io`` outputs by default). Per-step work is about zero, so this is
  the worst case for the *relative* cost of logging: every step writes one step record and one
  event, and nothing else happens.
- ``quickstart``: ``examples/quickstart.py`` (camera 30 Hz, policy 2 Hz with action chunks,
  controller 200 Hz, numpy payloads) for ``--qs-duration`` virtual seconds.

The session is opened (``pipe.step(0.0)``: compile, wire, reset flows) before the clock starts, on
both sides; the timed logged run includes creating the log (IR, metadata, channels) and finishing
it (last chunk, summary, footer). Ratio = best time with logging / best time without.

Log size: the file's bytes per record (events + step records), split into compressed chunks,
message indexes (16 uncompressed bytes per record, which MCAP's indexed readers need) and the
rest; and a separate estimate per event and per step record: each kind's MCAP messages (as the
log holds them) written on their own by the log's writer, with its zstd compressor and chunk size
cap: the bytes of the compressed chunks. Estimates × counts add up to the file size within a few percent.

Replay: on the recorded quickstart log, ``read_log`` + ``replay`` (re-execute every non-source
step, compare bytes) and ``read_log`` + ``resim`` (re-run the graph from the logged sources), each
timed end to end, best of ``--repeats``; events/s is the log's events over those seconds, and
"× real time" the run's virtual duration over them.

Targets (printed PASS/MISS, never asserted): logging on/off ≤ 1.5× (both workloads) and replay
≥ 50× real time (the quickstart log; resim is shown against the same bar for information).

    .venv/bin/python benchmarks/logging_overhead.py               # defaults, about 25 s
    .venv/bin/python benchmarks/logging_overhead.py --repeats 5 --qs-duration 600
    .venv/bin/python benchmarks/logging_overhead.py --profile     # cProfile of each logged path
"""

from __future__ import annotations

import argparse
import datetime
import gc
import io
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import StreamReader

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without installing
sys.path.insert(0, str(Path(__file__).resolve().parent))  # step_overhead, beside this file

from step_overhead import VARIANTS, Chain, build  # the same chain, the same flow classes

from retriever.loading import load_pipeline
from retriever.log import format as fmt
from retriever.log import read_log
from retriever.replay import replay, resim
from retriever.log.mcap_writer import McapWriter

TARGET_LOG_RATIO = 1.5
TARGET_REPLAY_X = 50.0
QUICKSTART = ROOT / "examples" / "quickstart.py"



# ---------------------------------------------------------------------------------------------
# Workloads
# ---------------------------------------------------------------------------------------------
class Workload:
    """A pipeline that can be run again from T0, off or logged."""

    def __init__(self, name: str, describe: str, duration: float, pipe):
        self.name, self.describe, self.duration, self.pipe = name, describe, duration, pipe

    def run(self, log: Path | None) -> tuple[float, int, int]:
        pipe = self.pipe
        pipe.reset()
        pipe.step(0.0)  # open the session outside the timed region (no tick has t < 0)
        gc.collect()
        t0 = time.perf_counter()
        trace = pipe.run(duration=self.duration, log=log, overwrite=True)  # each repeat logs to the same path
        elapsed = time.perf_counter() - t0
        events, steps = len(trace.raw_events), len(trace.raw_steps)
        pipe.reset()
        return elapsed, events, steps


def chain_workload(args) -> Workload:
    return Workload("chain", f"{args.variant} chain, 1 src + {args.stages} stages @ Rate({args.hz:g})",
                    args.chain_duration, build(Chain(args.variant, "rate", args.stages + 1), args.hz)[0])


def quickstart_workload(args) -> Workload:
    return Workload("quickstart", "examples/quickstart.py", args.qs_duration, load_pipeline(str(QUICKSTART)))


# ---------------------------------------------------------------------------------------------
# Measurements
# ---------------------------------------------------------------------------------------------
def measure_logging(w: Workload, tmp: Path, repeats: int) -> dict:
    """Alternate off / on runs; keep the last log for the size figures (and replay)."""
    off, on = [], []
    path = tmp / f"{w.name}.mcap"
    counts = None
    for _ in range(repeats):
        t, *c_off = w.run(None)
        off.append(t)
        t, *c_on = w.run(path)
        on.append(t)
        if c_off != c_on:
            raise SystemExit(f"{w.name}: the logged run differs from the unlogged one: {c_off} vs {c_on}")
        counts = c_on
    events, steps = counts
    return {"workload": w, "events": events, "steps": steps, "off": min(off), "on": min(on),
            "ratio": min(on) / min(off), "path": path, **log_size(path, events, steps)}


def log_size(path: Path, events: int, steps: int) -> dict:
    """File bytes per record and where they go; a per-kind estimate (see the module docstring)."""
    size = path.stat().st_size
    log = read_log(path)
    if log.end is None or int(log.end["events"]) != events or int(log.end["steps"]) != steps:
        raise SystemExit(f"{path}: the log does not hold the run's {events} events and {steps} steps ({log.end})")
    # Where the file's bytes are: compressed chunks, the (uncompressed) message indexes, the rest.
    chunks = indexes = 0
    with open(path, "rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            if isinstance(record, Chunk):
                chunks += len(record.data)
            elif isinstance(record, MessageIndex):
                indexes += 1 + 8 + 2 + 4 + 16 * len(record.records)  # opcode, length, channel, array length
    # Each kind on its own: its MCAP message records, exactly as in the chunks, written alone.
    step_channels = {c.id for c in log.channels.values() if c.topic == fmt.STEPS_TOPIC}
    kinds = {"event": [], "step": []}
    payload = {"event": 0, "step": 0}
    for m in log.messages:
        kind = "step" if m.channel_id in step_channels else "event"
        kinds[kind].append(m)
        payload[kind] += len(m.data)
    out = {"size": size, "per_record": size / (events + steps), "chunks": chunks, "indexes": indexes,
           "other": size - chunks - indexes}
    for kind, messages in kinds.items():
        n = events if kind == "event" else steps
        compressed, record_bytes = written_alone(messages, log.channels)
        out["est_" + kind] = compressed / n if n else 0.0
        out["raw_" + kind] = payload[kind] / n if n else 0.0
        out["raw_record_" + kind] = record_bytes / n if n else 0.0
    return out


def written_alone(messages: list, channels: dict) -> tuple[int, int]:
    """``messages`` (a log's, of one kind) written on their own by the log's writer, with its
    compressor and chunk size cap, on the channels they had: the bytes of its compressed chunks,
    and of the MCAP message records in them before compression (header and payload)."""
    buffer = io.BytesIO()
    writer = McapWriter(buffer)
    ids = {c.id: writer.add_channel(c.topic, c.message_encoding, c.metadata) for c in channels.values()}
    for m in messages:
        writer.add_message(ids[m.channel_id], m.log_time, m.publish_time, m.sequence, m.data)
    writer.finish()
    compressed = records = 0
    for record in StreamReader(io.BytesIO(buffer.getvalue()), emit_chunks=True).records:
        if isinstance(record, Chunk):
            compressed += len(record.data)
            records += record.uncompressed_size
    return compressed, records


def measure_replay(path: Path, virtual_s: float, repeats: int) -> list[dict]:
    rows = []
    for name, fn in (("replay", replay), ("resim", resim)):
        best = None
        for _ in range(repeats):
            gc.collect()
            t0 = time.perf_counter()
            log = read_log(path)
            t1 = time.perf_counter()
            report = fn(log)
            t2 = time.perf_counter()
            if not report.identical:
                raise SystemExit(f"{name} of {path} is not identical: {report}")
            if best is None or t2 - t0 < best[0]:
                best = (t2 - t0, t1 - t0, t2 - t1)
            events = int(log.end["events"])
            steps = report.steps_replayed if name == "replay" else report.steps_compared
        total, read_s, run_s = best
        rows.append({"what": name, "total": total, "read": read_s, "run": run_s, "events": events,
                     "steps": steps, "events_per_s": events / total, "x_real": virtual_s / total})
    return rows


# ---------------------------------------------------------------------------------------------
# Profile
# ---------------------------------------------------------------------------------------------
def profile(workloads: list[Workload], tmp: Path, top: int) -> None:
    import cProfile
    import pstats

    def show(title: str, fn, *a, **kw) -> None:
        prof = cProfile.Profile()
        prof.runcall(fn, *a, **kw)
        print(f"--- {title} (under cProfile: times inflated) ---")
        pstats.Stats(prof).sort_stats("tottime").print_stats(top)

    for w in workloads:
        for log in (None, tmp / f"{w.name}.mcap"):
            w.pipe.reset()
            w.pipe.step(0.0)
            show(f"{w.name}, {w.duration:g} s virtual, logging {'on' if log else 'off'}",
                 w.pipe.run, duration=w.duration, log=log, overwrite=True)
            w.pipe.reset()
    path = tmp / "quickstart.mcap"
    show("read_log + replay of the quickstart log", lambda: replay(read_log(path)))
    show("read_log + resim of the quickstart log", lambda: resim(read_log(path)))


def revision() -> str:
    """The checkout's commit, "-dirty" if the work tree has changes (the numbers are for that code)."""
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], check=False,
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown (not a git checkout)"


# ---------------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3, help="timed runs per measurement, best kept (default 3)")
    p.add_argument("--stages", type=int, default=4, help="chain: stages after the source (default 4)")
    p.add_argument("--hz", type=float, default=1000.0, help="chain: rate of every flow (default 1000)")
    p.add_argument("--variant", default="typed", choices=sorted(VARIANTS), help="chain: flow variant (default typed)")
    p.add_argument("--chain-duration", type=float, default=10.0, metavar="S",
                   help="chain: virtual seconds per run (default 10: 50k steps with 4 stages at 1 kHz)")
    p.add_argument("--qs-duration", type=float, default=200.0, metavar="S",
                   help="quickstart: virtual seconds per run, also the recorded run replayed (default 200)")
    p.add_argument("--profile", action="store_true",
                   help="diagnostic: instead of timing, run each path once under cProfile and print the top functions")
    p.add_argument("--top", type=int, default=15, help="--profile: functions shown per profile (default 15)")
    args = p.parse_args(argv)
    if args.repeats < 1 or args.stages < 1 or min(args.hz, args.chain_duration, args.qs_duration) <= 0:
        p.error("--repeats and --stages must be >= 1; --hz and the durations > 0")

    print("retriever logging overhead: inproc steps/s with pipe.run(log=...) vs without; log size; replay speed")
    print(f"python {platform.python_version()} ({platform.python_implementation()}), {platform.machine()}, "
          f"{platform.system()}, {os.cpu_count()} cpus; {datetime.date.today().isoformat()}; "
          f"best of {args.repeats} runs per figure; code {revision()}")
    workloads = [chain_workload(args), quickstart_workload(args)]
    for w in workloads:
        print(f"  {w.name:<10} {w.describe}, {w.duration:g} s virtual per run")
    print()

    with tempfile.TemporaryDirectory(prefix="retriever-logbench-") as tmp_name:
        tmp = Path(tmp_name)
        if args.profile:
            profile(workloads, tmp, args.top)
            return 0
        rows = [measure_logging(w, tmp, args.repeats) for w in workloads]
        qs = rows[-1]
        replays = measure_replay(qs["path"], qs["workload"].duration, args.repeats)

    head = (f"{'workload':<10} {'virtual':>7} {'events':>7} {'steps':>7} │ {'steps/s, best':>19} │ "
            f"{'µs/step':>15} │ {'on/off':>6} │ ≤{TARGET_LOG_RATIO:g}×")
    print(head)
    print(f"{'':<10} {'':>7} {'':>7} {'':>7} │ {'log off':>9} {'log on':>9} │ {'off':>7} {'+log':>7} │ {'':>6} │")
    print("─" * len(head))
    for r in rows:
        r["ok"] = r["ratio"] <= TARGET_LOG_RATIO
        print(f"{r['workload'].name:<10} {r['workload'].duration:>6g}s {r['events']:>7,} {r['steps']:>7,} │ "
              f"{r['steps'] / r['off']:>9,.0f} {r['steps'] / r['on']:>9,.0f} │ "
              f"{r['off'] / r['steps'] * 1e6:>7.2f} {(r['on'] - r['off']) / r['steps'] * 1e6:>7.2f} │ "
              f"{r['ratio']:>5.2f}× │ {'PASS' if r['ok'] else 'MISS'}")
    print()
    print("on/off = best logged run time / best unlogged run time; +log = the extra µs per step with logging.")
    print()

    head = (f"{'log size':<10} {'file':>7} │ {'B/record':>8} │ {'chunks':>6} {'index':>6} {'other':>6} │ "
            f"{'est. B/':>13} │ {'payload B/':>11} │ {'record B/':>11}")
    print(head)
    print(f"{'':<10} {'MB':>7} │ {'(file)':>8} │ {'B/record (file)':>20} │ {'event':>6} {'step':>6} │ "
          f"{'event':>5} {'step':>5} │ {'event':>5} {'step':>5}")
    print("─" * len(head))
    for r in rows:
        n = r["events"] + r["steps"]
        print(f"{r['workload'].name:<10} {r['size'] / 1e6:>7.2f} │ {r['per_record']:>8.1f} │ "
              f"{r['chunks'] / n:>6.1f} {r['indexes'] / n:>6.1f} {r['other'] / n:>6.1f} │ "
              f"{r['est_event']:>6.1f} {r['est_step']:>6.1f} │ {r['raw_event']:>5.0f} {r['raw_step']:>5.0f} │ "
              f"{r['raw_record_event']:>5.0f} {r['raw_record_step']:>5.0f}")
    print()
    print("B/record = file size / (events + step records), split into the zstd chunks, the message indexes")
    print("(uncompressed: 16 B per record, for MCAP's indexed readers) and the rest (IR, metadata, channels, summary).")
    print("est. = one kind's MCAP message records written on their own by the log's writer (its zstd chunks),")
    print("per record; payload = mean msgpack bytes per record; record = payload + the 31 B")
    print("MCAP message header (channel, sequence, log time, publish time), before compression.")
    print()

    head = (f"{'quickstart log':<15} {'events':>7} {'steps':>7} │ {'read_log':>8} {'re-run':>8} {'total':>8} │ "
            f"{'events/s':>9} {'× real time':>11} │ ≥{TARGET_REPLAY_X:g}×")
    print(head)
    print(f"{'(' + format(qs['workload'].duration, 'g') + ' s virtual)':<15} {'':>7} {'':>7} │ "
          f"{'s':>8} {'s':>8} {'s':>8} │ {'':>9} {'':>11} │")
    print("─" * len(head))
    for r in replays:
        ok = r["x_real"] >= TARGET_REPLAY_X
        r["ok"] = ok
        label = "PASS" if ok else "MISS"
        if r["what"] == "resim":
            label += " (info)"
        print(f"{r['what']:<15} {r['events']:>7,} {r['steps']:>7,} │ {r['read']:>8.3f} {r['run']:>8.3f} "
              f"{r['total']:>8.3f} │ {r['events_per_s']:>9,.0f} {r['x_real']:>10.1f}× │ {label}")
    print()
    print("steps = steps re-executed (replay: non-source steps) or compared (resim).")
    print()
    print("targets (measured, not asserted):")
    for r in rows:
        print(f"  logging on/off <= {TARGET_LOG_RATIO:g}x, {r['workload'].name:<10}: {r['ratio']:.2f}x  "
              f"{'PASS' if r['ok'] else 'MISS'}")
    rp = replays[0]
    print(f"  replay >= {TARGET_REPLAY_X:g}x real time (quickstart): {rp['x_real']:.1f}x  {'PASS' if rp['ok'] else 'MISS'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
