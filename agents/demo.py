"""``retriever demo``: one episode of Retriever-0 on the drawer (or bag) task, shown as it goes and
explained after (skill trace, task progress, rates, pictures, a log that replays)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from .episode import Episode, summarize


class DemoError(RuntimeError):
    """Something the user can fix: the message says what."""


def check_rendering() -> None:
    """Offscreen rendering works here, or DemoError saying what to install or set. Checked in a
    child process: a missing EGL library can abort the interpreter, not just raise."""
    probe = ("import os; os.environ.setdefault('MUJOCO_GL', 'egl'); import mujoco; "
             "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\".1\"/></worldbody></mujoco>'); "
             "r = mujoco.Renderer(m, 8, 8); r.update_scene(mujoco.MjData(m)); r.render(); r.close()")
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        backend = env["MUJOCO_GL"]
        raise DemoError(
            f"MuJoCo cannot render offscreen with MUJOCO_GL={backend}: {last}\n"
            "    hint: the cameras render on the CPU without a display; install the EGL and Mesa libraries "
            "(Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri), or try MUJOCO_GL=osmesa "
            "(apt-get install libosmesa6)")


def run_episode(config, backend: str = "zenoh", duration: float = 120.0, log: str | None = "run.mcap",
                quiet: bool = True, pipe=None, overwrite: bool = False):
    """Run one episode (``pipe``: the graph ``build(config)`` made, for a caller that keeps it, as
    ``retriever demo`` does to tell a SIGTERM from a Ctrl-C; ``overwrite``: replace an existing
    ``log``, which is refused otherwise); returns (trace, episode, wall seconds)."""
    from .retriever0 import build
    pipe = build(config) if pipe is None else pipe
    options = {"quiet": quiet} if backend == "zenoh" else {}
    started = time.perf_counter()
    trace = pipe.run(duration=duration, backend=backend, log=log, overwrite=overwrite, **options)
    wall = time.perf_counter() - started
    return trace, summarize(trace, pipe.build_ir()), wall


def ending(episode: Episode) -> str:
    if episode.gave_up:
        return f"gave up ({episode.gave_up})"
    if episode.finished:
        return "finished" if episode.score >= 1.0 else "the plan ended with the task not done"
    return "not finished (out of time)"


def report(episode: Episode, wall: float, backend: str) -> list[str]:
    """The lines ``retriever demo`` prints after an episode, before its rates (rate_rows)."""
    return [f"skill trace: {episode.skill_trace or '(none)'}",
             f"task progress: {episode.score:.0%} ("
             + ", ".join(f"{k.replace('_', ' ')} {'✓' if v else '✗'}" for k, v in episode.milestones.items())
             + f"), best reached at t={episode.best_at:.1f} s",
             f"{ending(episode)} after {episode.duration:.1f} s of world time "
             f"in {wall:.1f} s wall on {backend}; {episode.replans} replans, {episode.failures} failed skills"
             + "".join(f", {n} {what}" for what, n in (
                 ("stale progress reports ignored", episode.ignored.get("stale_feedback", 0)),
                 ("superseded plans dropped", episode.ignored.get("stale_plans", 0)),
                 ("bad plans refused", episode.ignored.get("bad_plans", 0))) if n)]


#: the columns of rate_table: how each flow on a Rate kept its clock; in real time also how late its
#: ticks started and how many of its steps missed (their LET deadline, an overrun, an incomplete input)
RATE_COLUMNS = ("flow", "clock\nHz", "ran\nHz")
LATENESS_COLUMNS = ("start late\np99 ms", "ticks >1\nperiod late", "steps missed\n(deadline, overrun,\nincomplete)")


def rate_table(episode: Episode) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    """The columns and rows of the rates table: a row per flow on a Rate (the lateness columns
    only in real time: virtual time is never late)."""
    rated = [r for r in episode.rates if r.hz]
    real_time = any(r.late_p99_ms is not None for r in rated)
    rows = [(r.node, f"{r.hz:g}", f"{r.achieved_hz:.1f}")
            + ((_ms(r.late_p99_ms), str(r.behind), str(r.missed)) if real_time else ()) for r in rated]
    return RATE_COLUMNS + (LATENESS_COLUMNS if real_time else ()), rows


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"  # None: no tick of it stepped (an episode that ended early)


def rate_notes(episode: Episode, backend: str) -> list[str]:
    """What the rates table means in real time: what "late" is, and whether the machine kept up."""
    rated = [r for r in episode.rates if r.hz]
    if backend == "inproc" or not rated:
        return []
    lines = ["late: a tick started after its time (T0 + its tag) on the wall clock; every flow declares its "
             "latency (LET) and catches up, so a late tick still consumes and emits what it would have on time and "
             "the trace is the virtual-time one (retriever replay checks the log)"]
    if any(r.behind or r.achieved_hz < 0.95 * r.hz for r in rated):
        lines.append("some flows fell behind their clocks: this machine is busy or slow for these rates "
                     "(--backend inproc runs the same agent in virtual time)")
    return lines
