"""Pictures of an episode: a contact sheet of the head camera with the running skill written on
each frame, and a timeline of skills, progress, replans, the task-progress score and, in real
time, how late each flow's ticks started (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from retriever import NOT_KEPT

from .episode import Episode, lateness


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def skill_at(episode: Episode, t: float) -> str:
    """The skill the monitor was running at world time ``t``."""
    current = ""
    for when, status in episode.statuses:
        if when > t:
            break
        current = status.skill or (f"({status.waiting})" if status.waiting else current)
    return current


def contact_sheet(trace, episode: Episode, path: Path, frames: int = 12, camera: str = "head_camera") -> Path | None:
    """``frames`` head-camera images spread over the episode, each titled with time and skill."""
    shots = [e.value for e in trace.events_of(camera, "frame") if e.value is not NOT_KEPT]
    if not shots:
        return None
    picks = [shots[i] for i in np.linspace(0, len(shots) - 1, min(frames, len(shots))).round().astype(int)]
    plt = _pyplot()
    cols = 4
    rows = -(-len(picks) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 2.6, rows * 2.3), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, frame in zip(axes.flat, picks):
        ax.imshow(frame.rgb, interpolation="nearest")
        ax.set_title(f"t={frame.t:.1f}s\n{skill_at(episode, frame.t)}", fontsize=7)
    fig.suptitle(f"Retriever-0, head camera: {episode.score:.0%} task progress", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def timeline(trace, episode: Episode, path: Path) -> Path:
    """Skills as bars, the skill policy's progress, plan requests and answers, the score, and in
    real time each flow's tick lateness (a virtual-time trace has none)."""
    plt = _pyplot()
    late = lateness(trace)
    ratios = [2, 1.2, 1] + ([1.2] if late else [])
    fig, axes = plt.subplots(len(ratios), 1, figsize=(10, 5.5 + 1.5 * bool(late)), sharex=True,
                             gridspec_kw={"height_ratios": ratios})
    ax_skill, ax_p, ax_score = axes[:3]
    spans, start, name = [], None, ""
    for t, status in episode.statuses:
        if status.skill != name:
            if name:
                spans.append((name, start, t))
            name, start = status.skill, t
    if name:
        spans.append((name, start, episode.duration))
    labels = list(dict.fromkeys(s[0] for s in spans))
    colours = plt.get_cmap("tab10")
    for skill, t0, t1 in spans:
        row = labels.index(skill)
        ax_skill.barh(row, t1 - t0, left=t0, color=colours(row % 10), height=0.7)
    ax_skill.set_yticks(range(len(labels)), labels, fontsize=7)
    ax_skill.invert_yaxis()
    ax_skill.set_title("Retriever-0: skills, progress, replans, task progress"
                       + (", how late ticks started (wall clock)" if late else ""), fontsize=9)
    progress = [e.value for e in trace.events_of("skill", "progress") if e.value is not NOT_KEPT]
    ax_p.plot([p.t for p in progress], [p.p for p in progress], ".", markersize=3, color="tab:blue")
    ax_p.axhline(0.9, color="grey", linewidth=0.6, linestyle="--")
    ax_p.set_ylabel("skill p", fontsize=8)
    ax_p.set_ylim(-0.05, 1.05)
    for e in trace.events_of("monitor", "request"):
        if e.value is not NOT_KEPT:
            ax_p.axvline(e.value.t, color="tab:red", linewidth=0.8, alpha=0.7)
    ax_p.plot([], [], color="tab:red", label="plan request")
    ax_p.legend(fontsize=7, loc="lower right")
    ax_score.step([t for t, _ in episode.statuses], [s.score for _, s in episode.statuses], where="post",
                  color="tab:green")
    ax_score.set_ylabel("task", fontsize=8)
    ax_score.set_ylim(-0.05, 1.05)
    if late:
        _lateness(axes[3], late)
    axes[-1].set_xlabel("world time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _lateness(ax, late: dict[str, tuple[list[float], list[float]]]) -> None:
    """How late each flow's ticks started on the wall clock (ms, on a log scale: under 0.1 ms
    drawn at 0.1), which catching up absorbs: the trace stays the virtual-time one."""
    for node, (times, ms) in sorted(late.items()):
        ax.plot(times, [max(m, 0.1) for m in ms], ".", markersize=1.5, label=node)
    ax.set_yscale("log")
    ax.set_ylabel("tick late (ms)", fontsize=8)
    ax.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.0, 1.05), markerscale=4, frameon=False)
