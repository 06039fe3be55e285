"""A partition with a move, N trials (issue 40, item 5): does a consumer moved off a cut-off host get
its producer's events again, how soon, and is a node that stays starved reported?

Each trial runs in a lab of three network namespaces (``deploy/netns-lab.sh`` through
``tests/deploy/lab.py``), with fresh worker daemons: ``arm-pc`` (host 2) runs the camera
(``tests/deploy/deploy_flows.py:watched``: 32 KiB frames at 50 Hz), ``gpu-box`` (host 3) the
viewer (its own 50 Hz clock, ``Latest``), ``spare`` (host 1, beside the coordinator) nothing. Every
daemon and ``retriever deploy`` get ``--lease LEASE``. Once the run's log has step records,
nftables cuts host 3 off (``netns-lab.sh partition``): the camera's link to it fills and holds its
puts, the coordinator counts gpu-box lost and starts the viewer afresh on spare. After the run
the partition is healed and the daemons stopped.

From the log, by event time (the step records' tags): *moved* = a fault record with
``moved_to``; *time to first event* = from the viewer's first tick on spare (its ``restarted``
record) to its first tick that consumed a frame; *recovered* = it consumed one and, from a lease
after that on, consumed at every tick but at most 5 %. A moved viewer that did not recover
stayed starved; it is *unreported* unless the coordinator warned of it while the run went on
("is starved" on stderr), the run's table marked it (the ``starved`` column) and the log holds its
span (``retriever.starved.N``). A move *too late to tell*: the viewer's ticks after its first frame
(after its restart, if none came) span less than a lease before the run ended, so the run says
nothing of recovery or starvation; such a trial counts as neither.

    PYTHONPATH=. .venv/bin/python benchmarks/partition_move.py --trials 5
    PYTHONPATH=. .venv/bin/python benchmarks/partition_move.py --trials 3 --lease 2 --duration 15

Needs root (network namespaces), iproute2 and nftables. Prints one line per trial and the counts,
and writes them to ``--out``/partition_move.json (with each trial's coordinator output). The lab
goes down and every process it started is stopped, whatever happens.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # retriever and tests.deploy from this checkout

from retriever import read_log  # noqa: E402
from tests.deploy.lab import Lab, partitions_unavailable, reap_orphan_labs, unavailable  # noqa: E402
from tests.deploy.test_deploy import FLOWS, HERE, PYTHON, start_worker, wait_going  # noqa: E402

SUBNET = "10.200.93.0/24"
#: how much of the viewer's ticks, from a lease after its first frame on, may go without one
MISSED_AT_MOST = 0.05
#: how long past the run's end a coordinator gets to finish before it is killed
FINISH_S = 60.0


def trial(lab: Lab, folder: Path, lease: float, duration: float, failures: Path,
          deploy_lease: float | None = None) -> dict:
    """One deployment with a partition and a move; what its log and its coordinator said."""
    coordinator, arm, gpu = lab.hosts
    secret = folder / "lab.key"
    secret.write_text(secrets.token_hex(32) + "\n")
    secret.chmod(0o600)
    leased = ["--path", str(HERE), "--lease", f"{lease:g}"]
    start_worker(arm, "arm-pc", secret, *leased)
    start_worker(gpu, "gpu-box", secret, *leased)
    start_worker(coordinator, "spare", secret, *leased)
    placement = folder / "place.toml"
    placement.write_text('[nodes]\ncamera = "arm-pc"\n')  # the viewer goes by load: to gpu-box
    log = folder / "run.mcap"
    connect = [arg for host in (arm, gpu, coordinator) for arg in ("--connect", f"tcp/{host.address}:7447")]
    run = coordinator.popen([PYTHON, "-m", "retriever.cli", "deploy", f"{FLOWS}:watched", *connect, "--secret",
                             str(secret), "--duration", f"{duration:g}", "--placement", str(placement), "--lease",
                             f"{lease if deploy_lease is None else deploy_lease:g}", "--allow-errors", "--log",
                             str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=str(ROOT),
                            env={**os.environ, "NO_COLOR": "1", "TERM": "dumb", "COLUMNS": "200"})
    try:
        wait_going(run, log)
        lab.partition(gpu)
        out, err = run.communicate(timeout=duration + FINISH_S)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
        lab.heal(gpu)
        lab.stop_processes()
    try:
        judged = judge(log, out, err, lease)
    except Exception as e:  # no log, or one cut short: the trial counts as not moved
        judged = {"moved": False, "first_event_s": None, "recovered": False, "too_late": False, "missed_after": None,
                  "warned": False, "table_marked": False, "logged": [], "error": f"{type(e).__name__}: {e}"}
    if run.returncode:  # kept for a look: the log and what the coordinator said
        failures.mkdir(parents=True, exist_ok=True)
        if log.exists():
            shutil.copy(log, failures / f"{folder.name}.mcap")
        (failures / f"{folder.name}.txt").write_text(out + "\n" + err)
    return {"exit": run.returncode, **judged, "stdout": out[-4000:], "stderr": err[-4000:]}


def judge(log: Path, out: str, err: str, lease: float) -> dict:
    """What the trial's log and output say of the viewer after its move (see the module's docstring)."""
    recorded = read_log(log, salvage=True)
    return verdict(recorded.faults, recorded.trace().steps_of("viewer"),
                   [e for e in recorded.starved if e["node"] == "viewer"], out, err, lease)


def verdict(faults: list[dict], steps: list, logged: list[dict], out: str, err: str, lease: float) -> dict:
    """The viewer's verdict from the log's fault records, its step records in tick order (each with
    ``tag``, ``consumed``, ``detail``), its starved spans, and the coordinator's stdout and stderr.

    A move is *too late to tell* when the viewer's ticks after it span less than a lease: past its
    first frame (or, with none, past its restart) no tick came a lease later, so neither recovery
    nor starvation could show before the run ended. Such a trial is neither recovered nor starved."""
    moved = [f for f in faults if f.get("moved_to")]
    restarts = [i for i, s in enumerate(steps) if s.detail and "restarted" in s.detail]
    result = {"moved": bool(moved and restarts), "first_event_s": None, "recovered": False,
              "too_late": False, "missed_after": None, "warned": "node 'viewer' is starved" in err,
              # the table's row of the viewer, its starved column saying "PORT from T s" (to the end)
              "table_marked": any(line.startswith("│ viewer") and " from " in line for line in out.splitlines()),
              "logged": logged}
    if not result["moved"]:
        return result
    after = steps[restarts[0]:]
    first = next((s for s in after if s.consumed), None)
    if first is not None:
        result["first_event_s"] = (first.tag[0] - after[0].tag[0]) / 1e9
    since = (first or after[0]).tag[0]
    settled = [s for s in after if s.tag[0] >= since + lease * 1e9]
    if not settled:
        result["too_late"] = True
        return result
    if first is not None:
        missed = sum(1 for s in settled if not s.consumed)
        result["missed_after"] = missed
        result["recovered"] = missed <= MISSED_AT_MOST * len(settled)
    # (a run that ended in error prints no table: the warning and the log then say it)
    tabled = result["table_marked"] or "│ viewer" not in out
    result["reported"] = result["warned"] and tabled and bool(result["logged"])
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--lease", type=float, default=1.0, help="seconds, every daemon's and the deployment's")
    parser.add_argument("--deploy-lease", type=float, default=None,
                        help="seconds, the deployment's own, if not --lease")
    parser.add_argument("--duration", type=float, default=12.0, help="seconds of each run")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "partition_move_results")
    args = parser.parse_args(argv)
    for reason in (unavailable(), partitions_unavailable()):
        if reason:
            print(f"partition_move: {reason}", file=sys.stderr)
            return 1
    reap_orphan_labs()
    trials = []
    args.out.mkdir(parents=True, exist_ok=True)
    with Lab(3, subnet=SUBNET) as lab, tempfile.TemporaryDirectory(prefix="partition-move-") as tmp:
        for i in range(args.trials):
            folder = Path(tmp) / f"trial{i}"
            folder.mkdir()
            began = time.monotonic()
            result = trial(lab, folder, args.lease, args.duration, args.out / "failures", args.deploy_lease)
            trials.append(result)
            print(f"trial {i + 1}: exit {result['exit']}, moved {result['moved']}, first event after the move "
                  f"{_s(result['first_event_s'])}, recovered {result['recovered']}, "
                  f"too late to tell {result['too_late']}, "
                  f"ticks without a frame after that {result['missed_after']}, starved reported: warned "
                  f"{result['warned']}, table {result['table_marked']}, log {len(result['logged'])} "
                  f"({time.monotonic() - began:.0f} s)", flush=True)
    firsts = [t["first_event_s"] for t in trials if t["first_event_s"] is not None]
    starved = [t for t in trials if t["moved"] and not t["recovered"] and not t["too_late"]]
    summary = {"trials": len(trials), "lease_s": args.lease, "deploy_lease_s": args.deploy_lease or args.lease,
               "duration_s": args.duration,
               "moved": sum(t["moved"] for t in trials),
               "moved_nodes_recovered": sum(t["recovered"] for t in trials),
               "moved_too_late_to_tell": sum(t["too_late"] for t in trials),
               "first_event_after_move_s": {"median": statistics.median(firsts) if firsts else None,
                                            "min": min(firsts, default=None), "max": max(firsts, default=None)},
               "starved_nodes": len(starved),
               "starved_nodes_unreported": sum(not t.get("reported") for t in starved),
               "false_starved_reports": sum(bool(t["warned"] or t["logged"]) for t in trials if t["recovered"]),
               "runs_ended_in_error": sum(bool(t["exit"]) for t in trials),
               "errors": sorted({line for t in trials if t["exit"]
                                 for line in t["stderr"].splitlines() if line.startswith("error: ")})}
    print(json.dumps(summary, indent=2))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "partition_move.json").write_text(json.dumps({"summary": summary, "trials": trials}, indent=1))
    return 0


def _s(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds:.2f} s"


if __name__ == "__main__":
    sys.exit(main())
