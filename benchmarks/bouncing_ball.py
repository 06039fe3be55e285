"""Functional determinism under real jitter: path gradients of a hybrid bouncing ball (paper Fig. 7c,
Appendix F-c..i).

The system, exactly as Appendix F-e writes it: each tick ``v ← v − g·dt``, then ``x ← x + v·dt``, then
the impact guard ``x < 0 → x = 0, v = −e·v``; after ``T`` ticks the loss is ``L = (x_T − x_target)²``.
The parameter is the initial velocity ``θ = v_0``; every run reports its *path gradient* ``dL/dθ``:
the derivative of the computation that run actually executed (F-d), carried forward as tangents
``(dx/dθ, dv/dθ)`` next to ``(x, v)`` through every step (forward mode): free flight
``dv' = dv, dx' = dx + dv'·dt``; at an impact ``x ← 0`` gives ``dx ← 0`` and ``v ← −e·v`` gives
``dv ← −e·dv`` (what backpropagation through the executed operations gives, as in the paper; the
impact *time*'s dependence on θ is not differentiated: with a fixed dt the impact ticks are locally
constant in θ, so this is also the derivative of the discrete system, which the script checks with
finite differences). ``dL/dθ = 2·(x_T − x_target)·dx_T/dθ``.

The graph (two flows in a feedback loop, the state and its tangents in the messages)::

    integrator @ Rate(hz), latency P/2 ──flight──▶ guard @ Trigger("flight"), latency P/2
          ▲                                                     │
          └──────────────────── state (Latest) ◀────────────────┘

The integrator's tick at ``t`` reads the guard's newest state (``Latest``; the initial state
``(x0, θ, 0, 1)`` before there is one), integrates and emits at ``t + P/2``; the guard applies the
impact and emits at ``t + P``, which the integrator's next tick, at ``t + P``, sees (tags ≤ τ).
The two latencies make the loop causal and its timing logical. The integrator stops emitting once
its state has ``T`` steps. The trace of a run is the guard's ``(x, v)`` at ticks 1..T.

Executors (``--executors``):

- ``retriever-inproc``: that graph on the in-process backend (virtual time), a fresh pipeline per run.
- ``retriever-zenoh``: the same graph on the Zenoh runtime, one OS process per flow (and each run
  started from a process of its own, see ``run_retriever_zenoh``), in real time
  at ``--hz`` (``dt`` is the logical step; ``hz`` only sets the wall period ``P``); the integrator
  catches up on overruns (``on_overrun="catch_up"``); a tick waits for its input up to ``--deadline``
  (1 s): past it, the tick runs *incomplete* (its step record says so, the counters count it) and
  that run's trace may differ. That is Retriever's contract: event time, unless a deadline passes.
- ``pubsub-mocked``: arrival-time pub/sub in one process, with mocked jitter. The paper says only
  "ROS-like latest-arrived semantics; random jitter yields stale reads that can shift impact
  ticks" with a jitter probability p (F-f, F-g); this is our reading of it. The same two nodes as a
  ROS-like program: the integrator runs on a timer and reads the *most recently arrived* state;
  the guard is a subscriber callback (every flight message, in order) that publishes the state
  back. Each state message arrives in time for the next timer tick with probability 1 − p, and one
  tick late with probability p (FIFO: a late message still arrives before the next one). A late
  message makes that tick read the previous state (a stale read): the ball repeats a step, and
  impacts shift. Each run has its own seed, ``"{--seed}:{config}:{run}"``.
- ``pubsub-zenoh``: the same arrival-time program over real Zenoh, no Retriever, no mock: two OS
  processes of plain zenoh-python (this script with ``--pubsub-integrator`` / ``--pubsub-guard``),
  the integrator on an absolute-deadline timer at ``--hz`` reading the newest state that arrived,
  the guard a subscriber callback. Stale reads come from real scheduling and transport jitter only.
  One pair of processes per configuration runs the K runs one after another.

Reported per configuration and executor: unique traces, unique gradients (exact float equality),
the gradient's standard deviation (numpy's, ddof=0), the trace mismatch rate (runs whose trace
differs from the plain loop of F-e), the mean gradient, sign flips against g*, stale reads per
run (pub/sub), how late the integrator's ticks started (zenoh), the runtime's counters
(retriever-zenoh: deadline misses, incomplete ticks, late events), and the largest |dL/dθ − g*|
where g* is the analytic path gradient of the plain loop's trace: with m impacts, the last at
tick k_m (0-based; none: k_m = −1), ``dx_T/dθ = (−e)^m · dt · (T − 1 − k_m)``, so
``g* = 2·(x_T − x_target)·(−e)^m·dt·(T − 1 − k_m)``.
The paper gives no x0, g or x_target; this script uses x0 = 1 m, g = 9.81 m/s², x_target = 1 m.

    .venv/bin/python benchmarks/bouncing_ball.py                       # both configs, all four executors, ~8 min
    .venv/bin/python benchmarks/bouncing_ball.py --config standard --runs 10 --executors retriever-inproc,pubsub-mocked
    .venv/bin/python benchmarks/bouncing_ball.py --json out.json --csv out.csv --plot out.png

``--json FILE`` writes, per configuration and executor, every parameter of the system (x0, g,
x_target, T, theta, e, dt, p, K) and every run's x_T, loss and dL/dtheta (and its trace's digest),
enough to recompute every number of the table.
"""

from __future__ import annotations

import argparse
import collections
import csv
import datetime
import hashlib
import importlib.metadata
import json
import os
import platform
import random
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # run from a checkout without installing
sys.path.insert(0, str(HERE))

from retriever import Flow, Latest, Pipeline, Rate, Trigger, io
from retriever.errors import BackendError

X0, G, X_TARGET = 1.0, 9.81, 1.0
CONFIGS = {
    "standard": {"T": 200, "theta": 3.0, "e": 0.8, "dt": 0.01, "p": 0.2, "K": 100},
    "high-jitter": {"T": 150, "theta": 4.0, "e": 0.85, "dt": 0.01, "p": 0.4, "K": 50},
}
EXECUTORS = ("retriever-inproc", "retriever-zenoh", "pubsub-mocked", "pubsub-zenoh")
ZENOH_COUNTS = ("incomplete", "late", "overrun", "deadline_miss", "unrun_ticks")


def params_of(config: str, runs: int | None = None) -> dict:
    c = CONFIGS[config]
    return {"x0": X0, "g": G, "x_target": X_TARGET, "T": c["T"], "theta": c["theta"], "e": c["e"],
            "dt": c["dt"], "p": c["p"], "K": runs if runs is not None else c["K"]}


# ---------------------------------------------------------------------------------------------
# The physics, with its tangents: one message type and the two steps, shared by every executor
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Ball:
    k: int  # integration steps taken along this path
    x: float
    v: float
    dx: float  # dx/dθ
    dv: float  # dv/dθ


def initial(prm: dict) -> Ball:
    return Ball(0, prm["x0"], prm["theta"], 0.0, 1.0)


def integrate(s: Ball, g: float, dt: float) -> Ball:
    v = s.v - g * dt
    return Ball(s.k + 1, s.x + v * dt, v, s.dx + s.dv * dt, s.dv)


def impact(s: Ball, e: float) -> Ball:
    if s.x < 0:
        return Ball(s.k, 0.0, -e * s.v, 0.0, -e * s.dv)
    return s


@dataclass
class Run:
    x_T: float
    loss: float
    grad: float
    trace: tuple  # ((x, v) after the guard, ticks 1..T)
    info: dict


class RunFailed(Exception):
    """A real-time run that gave no result: its runtime stopped it, or fewer than T states came."""

    def __init__(self, reason: str, **info):
        super().__init__(reason)
        self.info = {"reason": reason} | info


def finish(states: list[Ball], prm: dict, **info) -> Run:
    """A run's result from the guard's states at ticks 1..T (the last one is x_T's)."""
    last = states[-1]
    err = last.x - prm["x_target"]
    return Run(last.x, err * err, 2.0 * err * last.dx, tuple((s.x, s.v) for s in states), info)


def digest(trace: tuple) -> str:
    return hashlib.sha256(struct.pack(f"<{2 * len(trace)}d", *(f for xv in trace for f in xv))).hexdigest()[:16]


# ---------------------------------------------------------------------------------------------
# The reference: the plain loop of F-e, and the analytic path gradient of its trace
# ---------------------------------------------------------------------------------------------
def plain_loop(prm: dict, theta: float | None = None) -> tuple[tuple, list[int]]:
    """F-e as written, plain floats, no tangents: the trace and the impact ticks."""
    x, v, g, dt, e = prm["x0"], prm["theta"] if theta is None else theta, prm["g"], prm["dt"], prm["e"]
    trace, impacts = [], []
    for t in range(prm["T"]):
        v = v - g * dt
        x = x + v * dt
        if x < 0:
            x, v = 0.0, -e * v
            impacts.append(t)
        trace.append((x, v))
    return tuple(trace), impacts


def analytic(prm: dict) -> dict:
    trace, impacts = plain_loop(prm)
    x_T, m = trace[-1][0], len(impacts)
    last = impacts[-1] if impacts else -1
    dx_T = (-prm["e"]) ** m * prm["dt"] * (prm["T"] - 1 - last)
    grad = 2.0 * (x_T - prm["x_target"]) * dx_T
    h = 1e-6  # small enough that no impact moves a tick: L is affine in θ there
    lo, hi = (plain_loop(prm, prm["theta"] + s)[0][-1][0] for s in (-h, h))
    fd = ((hi - prm["x_target"]) ** 2 - (lo - prm["x_target"]) ** 2) / (2 * h)
    return {"trace": trace, "digest": digest(trace), "impact_ticks": impacts, "x_T": x_T,
            "loss": (x_T - prm["x_target"]) ** 2, "dx_T/dtheta": dx_T, "dL/dtheta": grad,
            "finite_difference": fd}


# ---------------------------------------------------------------------------------------------
# Retriever: two flows in a feedback loop
# ---------------------------------------------------------------------------------------------
@io
@dataclass
class Fed:
    state: Ball | None = None  # the guard's newest state; None before the first


@io
@dataclass
class Flight:
    flight: Ball | None = None  # None: no event (the run has its T steps)


@io
@dataclass
class Landed:
    state: Ball


class Integrator(Flow[Fed, Flight]):
    """Free flight: ``v ← v − g·dt, x ← x + v·dt`` with the tangents, from the fed-back state."""

    def __init__(self, x0: float, theta: float, g: float, dt: float, T: int):
        self.x0, self.theta, self.g, self.dt, self.T = x0, theta, g, dt, T

    def step(self, inp: Fed) -> Flight:
        s = inp.state or initial({"x0": self.x0, "theta": self.theta})
        return Flight(integrate(s, self.g, self.dt) if s.k < self.T else None)


class Guard(Flow[Flight, Landed]):
    """The impact guard: ``x < 0 → x = 0, v = −e·v`` (tangents ``dx = 0, dv = −e·dv``)."""

    def __init__(self, e: float):
        self.e = e

    def step(self, inp: Flight) -> Landed:
        return Landed(impact(inp.flight, self.e))


def build(prm: dict, hz: float, deadline: float = 1.0) -> tuple[Pipeline, int]:
    period = round(1e9 / hz)
    half = period // 2
    with Pipeline("bouncing_ball", deadline=deadline) as pipe:
        integrator = Integrator(prm["x0"], prm["theta"], prm["g"], prm["dt"], prm["T"]).configure(
            name="integrator", latency=half / 1e9, on_overrun="catch_up") @ Rate(hz=hz)
        guard = Guard(prm["e"]).configure(name="guard", latency=(period - half) / 1e9) @ Trigger("flight")
        integrator.then(guard, sync=Latest())
        guard.then(integrator, sync=Latest())
    return pipe, period


def run_retriever(prm: dict, backend: str, hz: float, deadline: float = 1.0) -> Run:
    pipe, period = build(prm, hz, deadline)
    if backend == "inproc":
        trace = pipe.run(duration=(prm["T"] + 2) * period / 1e9)
    else:
        try:
            trace = pipe.run(duration=(prm["T"] + 2) * period / 1e9, backend=backend, quiet=True)
        except BackendError as e:  # e.g. a worker that did not finish in time on an overloaded machine
            raise RunFailed(str(e).splitlines()[0]) from None
    # the guard's states of ticks 1..T, tagged P..T·P (in an incomplete tick, from another path)
    states = [e.value for e in sorted(trace.events_of("guard", "state"), key=lambda e: e.tag)
              if e.tag <= (prm["T"] * period, 0)]
    if backend == "inproc":
        return finish(states, prm)
    counts = {k: v for k, v in dict(pipe.counts()).items() if v}
    if len(states) != prm["T"]:
        statuses = {node: dict(collections.Counter(rec.status for rec in trace.steps_of(node)))
                    for node in ("integrator", "guard")}
        raise RunFailed(f"{len(states)} of T = {prm['T']} states", counts=counts, statuses=statuses)
    ticks = trace.steps_of("integrator")  # how late each tick started, against the first one
    late = max((s.wall_start_ns - ticks[0].wall_start_ns) - (s.tag[0] - ticks[0].tag[0]) for s in ticks)
    return finish(states, prm, counts={k: v for k, v in counts.items() if k in ZENOH_COUNTS},
                  max_tick_lateness_ms=late / 1e6)


def run_retriever_zenoh(prm: dict, hz: float, deadline: float) -> Run:
    """One zenoh run in a process of its own (this script with ``--retriever-zenoh-run``): a
    process keeps the shared-memory pools of every run it started mapped until it exits (Zenoh's
    receiver side never unmaps a segment, eclipse-zenoh/zenoh#2787), ~258 MB of /dev/shm a run here."""
    me = [sys.executable, str(Path(__file__).resolve()), "--retriever-zenoh-run", json.dumps(prm), str(hz),
          str(deadline)]
    done = subprocess.run(me, stdout=subprocess.PIPE, text=True, timeout=120 + 3 * prm["T"] / hz, check=False)
    lines = done.stdout.strip().splitlines()
    if done.returncode or not lines:
        raise RunFailed(f"the run's process exited with {done.returncode}")
    out = json.loads(lines[-1])
    if "failed" in out:
        raise RunFailed(out["failed"], **out["info"])
    return Run(out["x_T"], out["loss"], out["grad"], tuple(map(tuple, out["trace"])), out["info"])


def retriever_zenoh_child(prm_json: str, hz: float, deadline: float) -> int:
    try:
        r = run_retriever(json.loads(prm_json), "zenoh", hz, deadline)
    except RunFailed as f:
        print(json.dumps({"failed": str(f), "info": {k: v for k, v in f.info.items() if k != "reason"}}), flush=True)
        return 0
    print(json.dumps({"x_T": r.x_T, "loss": r.loss, "grad": r.grad, "trace": r.trace, "info": r.info}), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# Arrival-time pub/sub with the mocked jitter, in one process
# ---------------------------------------------------------------------------------------------
def run_pubsub_mocked(prm: dict, seed: str) -> Run:
    rng = random.Random(seed)
    newest = None  # the newest state that has arrived at the integrator
    in_flight: list[tuple[int, Ball]] = []  # (tick by which it has arrived, state), FIFO
    states, stale = [], 0
    for t in range(prm["T"]):
        while in_flight and in_flight[0][0] <= t:  # deliver, in order: the newest arrived wins
            newest = in_flight.pop(0)[1]
        stale += t > 0 and (newest is None or newest is not states[-1])
        flight = integrate(newest or initial(prm), prm["g"], prm["dt"])  # the timer tick
        landed = impact(flight, prm["e"])  # the guard's callback, on every message
        states.append(landed)
        late = rng.random() < prm["p"]
        in_flight.append((t + 1 + late, landed))
    return finish(states, prm, seed=seed, stale_reads=stale)


# ---------------------------------------------------------------------------------------------
# Arrival-time pub/sub over real Zenoh: two processes of plain zenoh-python
# ---------------------------------------------------------------------------------------------
WIRE = struct.Struct("<iiidddd")  # run, integrator tick, k, x, v, dx, dv


def pack(run: int, tick: int, s: Ball) -> bytes:
    return WIRE.pack(run, tick, s.k, s.x, s.v, s.dx, s.dv)


def unpack(data: bytes) -> tuple[int, int, Ball]:
    run, tick, k, x, v, dx, dv = WIRE.unpack(data)
    return run, tick, Ball(k, x, v, dx, dv)


def _wait_matching(pub, what: str) -> None:
    give_up = time.monotonic() + 20
    while not pub.matching_status.matching:
        if time.monotonic() > give_up:
            raise SystemExit(f"{what}: no subscriber matched in 20 s")
        time.sleep(0.01)


def pubsub_guard(connect: str, key: str, e: float) -> int:
    """The guard process: a subscriber callback that applies the impact and publishes the state."""
    import zenoh
    from latency import _config

    with zenoh.open(_config(connect=connect)) as session:
        pub = session.declare_publisher(f"{key}/state", congestion_control=zenoh.CongestionControl.BLOCK)

        def on_flight(sample) -> None:
            run, tick, s = unpack(sample.payload.to_bytes())
            pub.put(pack(run, tick, impact(s, e)))

        session.declare_subscriber(f"{key}/flight", on_flight)
        _wait_matching(pub, "guard")
        print("READY", flush=True)
        sys.stdin.readline()  # until the integrator's side is done
    return 0


def pubsub_integrator(listen: str, key: str, prm_json: str, hz: float) -> int:
    """The integrator process: a timer at hz reading the newest state that arrived. Per line
    ``run N`` on stdin, one run of T ticks; prints its states as JSON."""
    import zenoh
    from latency import _config

    prm = json.loads(prm_json)
    period = 1.0 / hz
    current = {"run": -1, "newest": None, "states": {}}
    lock = threading.Lock()

    def on_state(sample) -> None:
        run, tick, s = unpack(sample.payload.to_bytes())
        with lock:
            if run == current["run"]:
                current["newest"] = (tick, s)
                current["states"][tick] = s

    with zenoh.open(_config(listen=listen)) as session:
        pub = session.declare_publisher(f"{key}/flight", congestion_control=zenoh.CongestionControl.BLOCK)
        session.declare_subscriber(f"{key}/state", on_state)
        _wait_matching(pub, "integrator")
        print("READY", flush=True)
        for line in sys.stdin:
            run = int(line.split()[1])
            with lock:
                current.update(run=run, newest=None, states={})
            stale, late, start = [], 0.0, time.monotonic() + 0.02
            for t in range(prm["T"]):
                delay = start + t * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                late = max(late, time.monotonic() - start - t * period)
                newest = current["newest"]  # whatever arrived most recently
                if t > 0 and (newest is None or newest[0] != t - 1):
                    stale.append(t)
                pub.put(pack(run, t, integrate(newest[1] if newest else initial(prm), prm["g"], prm["dt"])))
            give_up = time.monotonic() + 5
            while len(current["states"]) < prm["T"] and time.monotonic() < give_up:
                time.sleep(0.005)
            with lock:
                states = [current["states"].get(t) for t in range(prm["T"])]
            print(json.dumps({"run": run, "stale_ticks": stale, "max_tick_lateness_ms": late * 1e3,
                              "missing": sum(s is None for s in states),
                              "states": [[s.k, s.x, s.v, s.dx, s.dv] if s else None for s in states]}), flush=True)
    return 0


class PubSubZenoh:
    """The two processes of one configuration, for its K runs."""

    def __init__(self, prm: dict, hz: float):
        from latency import free_port

        endpoint, key = f"tcp/127.0.0.1:{free_port()}", f"bench/bouncing_ball/{os.getpid()}"
        me = [sys.executable, str(Path(__file__).resolve())]
        self.integrator = subprocess.Popen(
            me + ["--pubsub-integrator", endpoint, key, json.dumps(prm), str(hz)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.guard = subprocess.Popen(me + ["--pubsub-guard", endpoint, key, str(prm["e"])],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        for proc in (self.integrator, self.guard):
            if proc.stdout.readline().strip() != "READY":
                self.close()
                raise SystemExit("a pub/sub process did not start")

    def run(self, prm: dict, run: int) -> Run:
        self.integrator.stdin.write(f"run {run}\n")
        self.integrator.stdin.flush()
        out = json.loads(self.integrator.stdout.readline())
        if out["missing"]:
            raise RunFailed(f"{out['missing']} of T = {prm['T']} states never came back (5 s)")
        states = [Ball(*s) for s in out["states"]]
        return finish(states, prm, stale_reads=len(out["stale_ticks"]), stale_ticks=out["stale_ticks"],
                      max_tick_lateness_ms=out["max_tick_lateness_ms"])

    def close(self) -> None:
        for proc in (self.integrator, self.guard):
            if proc.stdin and not proc.stdin.closed:
                proc.stdin.close()
        for proc in (self.integrator, self.guard):
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


# ---------------------------------------------------------------------------------------------
# Running an executor K times, and the numbers
# ---------------------------------------------------------------------------------------------
def run_executor(name: str, config: str, prm: dict, hz: float, seed: int, deadline: float = 1.0,
                 failures: list | None = None) -> list[Run]:
    """K runs. A real-time run that fails (``RunFailed``) is noted in ``failures`` and made again,
    up to K more times."""
    runs, pair, attempt = [], PubSubZenoh(prm, hz) if name == "pubsub-zenoh" else None, 0
    try:
        while len(runs) < prm["K"]:
            i, attempt = attempt, attempt + 1
            try:
                if name == "retriever-inproc":
                    runs.append(run_retriever(prm, "inproc", hz))
                elif name == "retriever-zenoh":
                    runs.append(run_retriever_zenoh(prm, hz, deadline))
                elif name == "pubsub-mocked":
                    runs.append(run_pubsub_mocked(prm, f"{seed}:{config}:{i}"))
                else:
                    runs.append(pair.run(prm, i))
            except RunFailed as f:
                print(f"    {name} attempt {i} failed: {f}; load average {os.getloadavg()[0]:.1f}", flush=True)
                if failures is not None:
                    failures.append({"attempt": i, "load_average": os.getloadavg()[0]} | f.info)
                if attempt >= 2 * prm["K"]:
                    raise SystemExit(f"{name}: {attempt - len(runs)} of {attempt} runs failed; giving up") from None
    finally:
        if pair:
            pair.close()
    return runs


def summarize(runs: list[Run], ref: dict) -> dict:
    import numpy as np

    grads = [r.grad for r in runs]
    out = {"runs": len(runs), "unique_traces": len({r.trace for r in runs}), "unique_gradients": len(set(grads)),
           "gradient_std": float(np.std(grads)), "trace_mismatch_rate": sum(r.trace != ref["trace"] for r in runs)
           / len(runs), "gradient_mean": float(np.mean(grads)),
           "max_abs_error_vs_analytic": max(abs(g - ref["dL/dtheta"]) for g in grads),
           "sign_flips": sum((g > 0) != (ref["dL/dtheta"] > 0) for g in grads)}
    if any("stale_reads" in r.info for r in runs):
        out["stale_reads_mean"] = float(np.mean([r.info["stale_reads"] for r in runs]))
    if any("max_tick_lateness_ms" in r.info for r in runs):
        late = [r.info["max_tick_lateness_ms"] for r in runs]
        out["max_tick_lateness_ms"] = {"median": float(np.median(late)), "max": float(np.max(late))}
    if any("counts" in r.info for r in runs):
        out["counts"] = {k: sum(r.info["counts"].get(k, 0) for r in runs) for k in ZENOH_COUNTS}
        out["counts"]["runs_with_incomplete_ticks"] = sum(bool(r.info["counts"].get("incomplete")) for r in runs)
        # a run that differs with every tick complete would break the contract (none expected)
        out["counts"]["mismatches_with_every_tick_complete"] = sum(
            r.trace != ref["trace"] and not r.info["counts"].get("incomplete") for r in runs)
    return out


def print_table(results: dict) -> None:
    cols = [("config", 11), ("executor", 16), ("K", 4), ("traces", 6), ("grads", 5), ("grad std", 9), ("mismatch", 8),
            ("mean dL/dθ", 10), ("max|g-g*|", 9), ("flips", 5), ("stale/run", 9), ("late ms med/max", 15)]
    head = " ".join(f"{name:<{w}}" if i < 2 else f"{name:>{w}}" for i, (name, w) in enumerate(cols)) + "  counts"
    print(head)
    print("─" * len(head))
    for config, res in results.items():
        for name, ex in res["executors"].items():
            s = ex["summary"]
            stale = f"{s['stale_reads_mean']:.1f}" if "stale_reads_mean" in s else "-"
            late = s.get("max_tick_lateness_ms")
            late = f"{late['median']:.1f}/{late['max']:.1f}" if late else "-"
            counts = [f"{k} {v}" for k, v in s.get("counts", {}).items() if v]
            counts = ", ".join(counts + ([f"failed runs {s['failed_runs']} (made again)"] if s["failed_runs"] else []))
            cells = [config, name, s["runs"], s["unique_traces"], s["unique_gradients"], f"{s['gradient_std']:.3g}",
                     f"{s['trace_mismatch_rate']:.0%}", f"{s['gradient_mean']:.4f}",
                     f"{s['max_abs_error_vs_analytic']:.3g}", s["sign_flips"], stale, late]
            print(" ".join(f"{c:<{w}}" if i < 2 else f"{c:>{w}}" for i, (c, (_, w)) in enumerate(zip(cells, cols)))
                  + f"  {counts}")


def write_csv(path: str, results: dict) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["config", "executor", "run", "x_T", "loss", "dL_dtheta", "trace_digest", "trace_matches_reference",
                    "stale_reads"])
        for config, res in results.items():
            for name, ex in res["executors"].items():
                for i, r in enumerate(ex["runs"]):
                    w.writerow([config, name, i, repr(r["x_T"]), repr(r["loss"]), repr(r["dL_dtheta"]),
                                r["trace_digest"], r["trace_digest"] == res["analytic"]["trace_digest"],
                                r.get("stale_reads", "")])


def plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def plot(path: str, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    configs = list(results)
    names = list(next(iter(results.values()))["executors"])
    fig, axes = plt.subplots(len(configs), len(names), figsize=(3.3 * len(names), 2.9 * len(configs)),
                             squeeze=False, sharey="row")
    for row, config in enumerate(configs):
        res = results[config]
        star = res["analytic"]["dL/dtheta"]
        every = [r["dL_dtheta"] for ex in res["executors"].values() for r in ex["runs"]] + [star]
        lo, hi = min(every), max(every)
        pad = 0.05 * (hi - lo) or 0.05 * abs(star) or 0.01
        bins = np.linspace(lo - pad, hi + pad, 61)
        for col, name in enumerate(names):
            ax, ex = axes[row][col], res["executors"][name]
            grads = [r["dL_dtheta"] for r in ex["runs"]]
            color = "tab:blue" if name.startswith("retriever") else "tab:red"
            ax.hist(grads, bins=bins, color=color, alpha=0.8)
            ax.axvline(star, color="black", linestyle="--", linewidth=1, label="analytic g*")
            s = ex["summary"]
            hz = f" at {ex['params']['hz']:g} Hz" if "hz" in ex["params"] else ""
            ax.set_title(f"{name}{hz}, {s['runs']} runs\n{plural(s['unique_traces'], 'trace')}, "
                         f"{plural(s['unique_gradients'], 'gradient')}, σ = {s['gradient_std']:.2g}", fontsize=9)
            ax.set_xlabel("path gradient dL/dθ", fontsize=8)
            ax.tick_params(labelsize=7)
            if col == 0:
                p = res["params"]
                ax.set_ylabel(f"{config} (T={p['T']}, θ={p['theta']}, e={p['e']}, p={p['p']})\nruns", fontsize=8)
                ax.legend(fontsize=7)
    fig.suptitle("Path gradients of the bouncing ball across runs: event time (Retriever) vs arrival time (pub/sub)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=130)


def machine() -> dict:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False,
                                cwd=HERE).stdout.strip()
    except OSError:
        commit = ""
    try:
        zenoh_version = importlib.metadata.version("eclipse-zenoh")
    except importlib.metadata.PackageNotFoundError:
        zenoh_version = ""
    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "zenoh": zenoh_version, "commit": commit, "date": datetime.datetime.now().isoformat(timespec="seconds")}


def run_all(args, names: list[str], configs: list[str]) -> dict:
    results = {}
    for config in configs:
        prm = params_of(config, args.runs)
        ref = analytic(prm)
        print(f"\n{config}: {prm}\n  plain loop: x_T = {ref['x_T']!r}, impacts at ticks {ref['impact_ticks']}, "
              f"loss {ref['loss']:.6g}; analytic path gradient g* = {ref['dL/dtheta']!r} "
              f"(finite difference of the plain loop: {ref['finite_difference']!r})", flush=True)
        res = {"params": prm, "analytic": {k: v for k, v in ref.items() if k not in ("trace", "digest")}
               | {"trace_digest": ref["digest"]}, "executors": {}}
        for name in names:
            t0 = time.monotonic()
            failures: list[dict] = []
            runs = run_executor(name, config, prm, args.hz, args.seed, args.deadline, failures)
            summary = summarize(runs, ref) | {"failed_runs": len(failures)}
            res["executors"][name] = {
                "params": prm | ({"hz": args.hz, "burn": args.burn} if "zenoh" in name else {})
                | ({"deadline": args.deadline} if name == "retriever-zenoh" else {})
                | ({"seed": args.seed} if name == "pubsub-mocked" else {}),
                "summary": summary,
                "runs": [{"x_T": r.x_T, "loss": r.loss, "dL_dtheta": r.grad, "trace_digest": digest(r.trace)} | r.info
                         for r in runs],
                "failed_runs": failures}
            print(f"  {name}: {len(runs)} runs in {time.monotonic() - t0:.1f} s; {summary['unique_traces']} unique "
                  f"traces, {summary['unique_gradients']} unique gradients", flush=True)
        results[config] = res
    return results


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--pubsub-integrator":
        return pubsub_integrator(argv[1], argv[2], argv[3], float(argv[4]))
    if argv and argv[0] == "--retriever-zenoh-run":
        return retriever_zenoh_child(argv[1], float(argv[2]), float(argv[3]))
    if argv and argv[0] == "--pubsub-guard":
        return pubsub_guard(argv[1], argv[2], float(argv[3]))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", choices=[*CONFIGS, "all"], default="all")
    ap.add_argument("--runs", type=int, default=None, metavar="K", help="runs per executor (default: the config's K)")
    ap.add_argument("--executors", default=",".join(EXECUTORS), help="comma-separated, of " + ", ".join(EXECUTORS))
    ap.add_argument("--hz", type=float, default=200.0, help="wall tick rate of the zenoh executors (default 200)")
    ap.add_argument("--deadline", type=float, default=1.0,
                    help="retriever-zenoh: how long a tick waits for its input before it runs incomplete (s)")
    ap.add_argument("--burn", type=int, default=0, metavar="N",
                    help="start N processes that burn a core each for the whole script: contention, real jitter")
    ap.add_argument("--seed", type=int, default=0, help="seed of the mocked jitter")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--csv", metavar="FILE")
    ap.add_argument("--plot", metavar="FILE")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.executors.split(",") if n.strip()]
    if unknown := [n for n in names if n not in EXECUTORS]:
        ap.error(f"unknown executors {unknown}; choose from {', '.join(EXECUTORS)}")
    configs = list(CONFIGS) if args.config == "all" else [args.config]

    info = machine()
    print(f"bouncing ball path gradients; python {info['python']}, {info['platform']}, {info['cpus']} cpus, "
          f"zenoh {info['zenoh']}, code {info['commit']}; zenoh executors at {args.hz:g} Hz; "
          f"{args.burn} core burners; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    info["load_average_start"] = os.getloadavg()
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.burn)]
    try:
        results = run_all(args, names, configs)
    finally:
        for proc in burners:
            proc.kill()
            proc.wait()
    info["load_average_end"] = os.getloadavg()
    print(f"\nload average at end {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print_table(results)
    if args.json:
        command = " ".join(["benchmarks/bouncing_ball.py", *argv])
        record = {"machine": info, "command": command, "configs": results}
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n")
    if args.csv:
        write_csv(args.csv, results)
    if args.plot:
        plot(args.plot, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
