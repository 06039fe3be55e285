"""Logs as a training set: ``retriever log export RUN.mcap ... --format lerobot --flow NODE -o DIR``.

One frame per tick of the chosen flow (retriever/log/frames.py says which ticks and which
features); one log is one episode (several with ``gaps="split"``). Two formats:

- ``lerobot``: written with LeRobot's own ``LeRobotDataset.create / add_frame / save_episode /
  finalize`` (the extra ``retriever-robotics[lerobot]``), image features as PNG images (exact
  pixels), loadable offline with ``LeRobotDataset(repo_id, root=DIR)``;
- ``npz``: the same frames and features as plain NumPy arrays, one ``episode_NNNNNN.npz`` per
  episode and ``info.json``, for users without lerobot.

The dataset is written into a folder beside ``DIR`` (``.DIR.PID.partial``) and renamed to it at
the end: an export that fails leaves nothing at ``DIR``. One that was killed (SIGKILL, a power
cut) cannot remove its folder: the next export into the same parent folder does, once no process
of that PID runs.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import time
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ..errors import LogError
from ..time import format_tag
from .frames import TASK, Episode, Feature, FlowFrames, Mapping, Recording, parse_maps
from .reader import RunLog, read_log

FORMATS = ("lerobot", "npz")
NPZ_FORMAT = "retriever-npz/1"
#: the keys each format writes of its own, which no feature can take
RESERVED_KEYS = {"npz": ("timestamp", "frame_index", "tick_ns", TASK),
                 "lerobot": ("timestamp", "frame_index", "episode_index", "index", "task_index", TASK)}
#: threads LeRobot's image writer encodes PNGs in (its own advice: a few per camera)
IMAGE_WRITER_THREADS = max(2, min(4, os.cpu_count() or 1))
#: the folder an export writes before renaming it to its output: ``.NAME.PID.partial``
PARTIAL_FOLDER = re.compile(r"\.(?P<name>.+)\.(?P<pid>[1-9][0-9]*)\.partial")


@dataclass
class ExportSummary:
    """What an export wrote."""

    out: Path
    format: str
    episodes: int
    frames: int
    fps: float
    bytes: int
    seconds: float
    features: list[Feature] = field(default_factory=list)
    left_out: Counter = field(default_factory=Counter)  # ticks, by status or reason
    fields_left_out: list[str] = field(default_factory=list)
    sparse: dict[str, tuple[int, int]] = field(default_factory=dict)  # ports left out: (ticks with a value, ticks)
    non_finite: dict[str, tuple[int, str]] = field(default_factory=dict)  # sources: (frames with NaN/inf, first where)
    reaped: list[str] = field(default_factory=list)  # folders killed exports had left beside out, removed

    def __str__(self) -> str:
        lines = [f"wrote {self.out} ({self.format}): {self.frames} frames in {self.episodes} episode(s) at "
                 f"{self.fps:g} fps, {_size(self.bytes)}, in {self.seconds:.1f} s "
                 f"({self.frames / max(self.seconds, 1e-9):.0f} frames/s)"]
        for f in self.features:
            what = "image" if f.kind == "image" else f"{f.dtype}"
            lines.append(f"  {f.key:<32} {what}{list(f.shape)}  from {f.source}")
        if self.left_out:
            lines.append("  ticks left out: " + ", ".join(f"{n} {why}" for why, n in sorted(self.left_out.items())))
        if self.sparse:
            lines.append("  ports with a value at fewer than half of the ticks, left out (--map one to keep it): "
                         + ", ".join(f"{p} ({n} of {total})" for p, (n, total) in sorted(self.sparse.items())))
        if self.non_finite:
            lines.append("  NaN or infinite values (a dataset's statistics take them in): "
                         + ", ".join(f"{s} in {n} frame(s), first at {first}"
                                     for s, (n, first) in sorted(self.non_finite.items())))
        if self.fields_left_out:
            lines.append("  fields no feature holds (text, None): " + ", ".join(self.fields_left_out))
        if self.reaped:
            lines.append(f"  removed {len(self.reaped)} unfinished folder(s) that killed exports had left in "
                         f"{self.out.parent}: " + ", ".join(self.reaped))
        return "\n".join(lines)


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


def export_dataset(logs: Sequence[str | Path | RunLog | Recording], out: str | Path, *, flow: str,
                   format: str = "lerobot", maps: dict[str, str] | Sequence[str] | None = None,
                   task: str | None = None, exclude: Sequence[str] = (), gaps: str = "refuse",
                   repo_id: str | None = None, overwrite: bool = False,
                   progress: Callable[[int, int, int, int], None] | None = None) -> ExportSummary:
    """Write the ticks of ``flow`` in ``logs`` as a dataset folder ``out`` (one episode per log).

    ``maps`` renames feature sources to keys (``{"joints": "observation.state"}``, or
    ``["joints=observation.state"]``; a text port mapped to ``"task"`` gives each frame's task);
    ``task`` is the task of every frame otherwise (default: the pipeline's name); ``exclude``
    leaves ports (or ``port.field``) out; ``gaps="split"`` ends an episode at a gap between frames
    instead of refusing it. ``progress(log, logs, tick, ticks)`` is called as ticks are read.
    """
    mapping = _checked_mapping(logs, format, maps, task, exclude)
    out = Path(out)
    _check_out(out, logs)
    if out.exists() and not overwrite:
        raise LogError(f"{out} exists", "pass --force (overwrite=True) to replace it")
    writer_class = _LeRobotWriter if format == "lerobot" else _NpzWriter
    writer_class.check_installed()
    started = time.perf_counter()
    reaped = reap_partials(out.parent)
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    written = _Episodes(partial, writer_class, repo_id or f"retriever/{out.name}", flow, format)
    try:
        for n, source in enumerate(logs):
            tick_progress = None if progress is None else (lambda i, total, n=n: progress(n, len(logs), i, total))
            written.add(_recording(source), mapping, gaps, task, tick_progress)
        episodes, count = written.close()
        _put_in_place(partial, out)
    finally:
        written.abandon()
        shutil.rmtree(partial, ignore_errors=True)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    first = written.first
    return ExportSummary(out, format, episodes, count, float(first.fps), size, time.perf_counter() - started,
                         first.features, written.left_out, written.fields_left_out, written.sparse,
                         written.non_finite, reaped)


def _checked_mapping(logs: Sequence[str | Path | RunLog | Recording], format: str,
                     maps: dict[str, str] | Sequence[str] | None, task: str | None,
                     exclude: Sequence[str]) -> Mapping:
    """The export's features mapping (``maps`` and ``exclude``), once the request is one an export
    can meet: a known format, a log at least, one task, keys the format leaves to features."""
    if format not in FORMATS:
        raise LogError(f"unknown dataset format {format!r}", f"use one of: {', '.join(FORMATS)}")
    if not logs:
        raise LogError("no log to export", "give one or more .mcap files")
    mapping = Mapping(parse_maps(list(maps)) if maps is not None and not isinstance(maps, dict) else dict(maps or {}),
                      tuple(exclude))
    if task is not None and TASK in mapping.maps.values():
        raise LogError("the task is given twice: --task and a port mapped to task", "pass one of them")
    _check_keys(mapping, format)
    return mapping


class _Episodes:
    """The episodes of an export's logs, into one writer: made at the first episode (of the first
    log's features and fps, which every later log must have), and what each log left out, totalled."""

    def __init__(self, partial: Path, writer_class: type, repo_id: str, flow: str, format: str):
        self.partial, self.writer_class, self.repo_id, self.flow, self.format = (partial, writer_class, repo_id,
                                                                                 flow, format)
        self.writer = None
        self.first: FlowFrames | None = None  # the frames of the log the writer was made for
        self.left_out: Counter = Counter()
        self.fields_left_out: list[str] = []
        self.sparse: dict[str, tuple[int, int]] = {}
        self.non_finite: dict[str, tuple[int, str]] = {}

    def add(self, recording: Recording, mapping: Mapping, gaps: str, task: str | None,
            progress: Callable[[int, int], None] | None) -> None:
        """Write the episodes of the flow's frames in ``recording``."""
        frames = FlowFrames(recording, self.flow, mapping, gaps)
        self._check_fps(frames, recording)
        for episode in frames.episodes(progress):
            if self.writer is None:
                self.first = frames
                self.writer = self.writer_class(self.partial, frames.features, frames.fps, self.repo_id)
            elif frames.features != self.first.features:
                raise LogError(f"{recording.name}: the frames of '{self.flow}' have other features than those of the "
                               f"logs before ({_describe(frames.features)}, against {_describe(self.first.features)})",
                               "a dataset has one set of features: export those logs apart")
            self.writer.episode(episode, task if task is not None else recording.ir.name, recording.name)
        self._total(frames, recording)

    def _check_fps(self, frames: FlowFrames, recording: Recording) -> None:
        """Refuse a rate LeRobot cannot hold, or one other than the logs' before."""
        if self.format == "lerobot" and frames.fps.denominator != 1:
            raise LogError(f"flow '{self.flow}' ticks at {float(frames.fps):g} Hz: a LeRobot dataset's fps is a whole "
                           "number", "use --format npz, or give the flow a whole-number rate")
        if self.first is not None and frames.fps != self.first.fps:
            raise LogError(f"{recording.name}: flow '{self.flow}' ticks at {float(frames.fps):g} Hz, in the logs "
                           f"before at {float(self.first.fps):g} Hz", "a dataset has one fps: export those logs apart")

    def _total(self, frames: FlowFrames, recording: Recording) -> None:
        """Add what ``frames`` left out (ticks, fields, sparse ports) and its NaN or infinite values."""
        self.left_out.update(frames.left_out)
        for source, (count, tick) in frames.non_finite.items():
            before = self.non_finite.get(source, (0, f"{format_tag(tick)} in {recording.name}"))
            self.non_finite[source] = (before[0] + count, before[1])
        self.fields_left_out += [f for f in frames.fields_left_out if f not in self.fields_left_out]
        for port, (with_value, ticks) in frames.sparse.items():
            before = self.sparse.get(port, (0, 0))
            self.sparse[port] = (before[0] + with_value, before[1] + ticks)

    def close(self) -> tuple[int, int]:
        """Finish the dataset: its episodes and frames. LogError when no log made a frame."""
        if self.writer is None:
            what = ", ".join(f"{n} {why}" for why, n in sorted(self.left_out.items())) or "no step record"
            raise LogError(f"no tick of flow '{self.flow}' makes a frame ({what})",
                           "a frame needs an ok tick with a value on every input and output port; "
                           "--exclude a port that never has one")
        episodes, count = self.writer.close()
        self.writer = None
        return episodes, count

    def abandon(self) -> None:
        """Drop an unfinished writer (an export that failed): a closed one is gone already."""
        if self.writer is not None:
            self.writer.abandon()


def reap_partials(folder: Path) -> list[str]:
    """Remove from ``folder`` the unfinished folders of exports that were killed (SIGKILL gives
    an export no chance to remove its own) and return their names: each named as an export names
    it (:data:`PARTIAL_FOLDER`), a folder (not a link), this user's, and of a PID that no process
    runs. Anything else is left alone: a live export's folder, another user's, other names."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    reaped = []
    for entry in entries:
        match = PARTIAL_FOLDER.fullmatch(entry.name)
        if match is None or not entry.is_dir(follow_symlinks=False):
            continue
        try:
            owner = entry.stat(follow_symlinks=False).st_uid
        except OSError:
            continue
        if owner != os.getuid() or _may_run(int(match["pid"])):
            continue
        shutil.rmtree(entry.path, ignore_errors=True)
        if not os.path.lexists(entry.path):
            reaped.append(entry.name)
    return sorted(reaped)


def _may_run(pid: int) -> bool:
    """Whether a process ``pid`` may be running: this one, or any that signal 0 finds (another
    user's included); False only when no process has that PID."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # (another user's process; a number no PID can be: not an export's of ours)
    return True


def _check_keys(mapping: Mapping, format: str) -> None:
    """Refuse a --map to a key the format writes of its own, or with a '/' (LeRobot's keys are no paths)."""
    for source, key in mapping.maps.items():
        if key == TASK:
            continue
        if key in RESERVED_KEYS[format]:
            raise LogError(f"--map {source}={key}: {key!r} is a key the {format} format writes of its own "
                           f"({', '.join(RESERVED_KEYS[format])})",
                           f"map {source!r} to another key: --map {source}=observation.{source}")
        if "/" in key:
            raise LogError(f"--map {source}={key}: a feature key has no '/' (LeRobot's keys are dotted: "
                           "observation.images.front)", f"--map {source}={key.replace('/', '.')}")


def _check_out(out: Path, logs: Sequence[str | Path | RunLog | Recording]) -> None:
    """Refuse an output that is, holds or lies inside an input log (--force would replace the log),
    or whose folder is a file."""
    target = out.resolve()
    for source in logs:
        path = source.path if isinstance(source, RunLog) else None if isinstance(source, Recording) else Path(source)
        if path is None:
            continue
        log = path.resolve()
        where = ("the log" if target == log else "a folder that holds the log" if target in log.parents
                 else "inside the log" if log in target.parents else None)
        if where is not None:
            raise LogError(f"the output {out} is {where} {path}: writing it would replace the log",
                           "-o a folder apart from the logs")
    for parent in target.parents:
        if parent.exists():
            if not parent.is_dir():
                raise LogError(f"the output {out} lies inside {parent}, which is a file, not a folder",
                               "-o a path whose parent folders are folders")
            break


def _put_in_place(partial: Path, out: Path) -> None:
    """Rename the finished folder to ``out``, replacing what stood there."""
    if not out.exists() and not out.is_symlink():
        os.replace(partial, out)
        return
    old = out.with_name(f".{out.name}.{os.getpid()}.old")
    os.replace(out, old)
    os.replace(partial, out)
    if old.is_dir() and not old.is_symlink():
        shutil.rmtree(old)
    else:
        old.unlink()


def _recording(source: str | Path | RunLog | Recording) -> Recording:
    if isinstance(source, Recording):
        return source
    return Recording.of_log(source if isinstance(source, RunLog) else read_log(source))


def _describe(features: list[Feature]) -> str:
    return ", ".join(f"{f.key} {f.kind} {f.dtype}{list(f.shape)}" for f in features)


class _LeRobotWriter:
    """Frames into LeRobot's own dataset writer (images as PNG: exact pixels)."""

    @staticmethod
    def check_installed() -> None:
        try:
            import lerobot.datasets.lerobot_dataset  # noqa: F401
        except ImportError as e:
            raise LogError(f"the LeRobot export needs the lerobot package, which cannot be imported ({e})",
                           "pip install 'retriever-robotics[lerobot]', or use --format npz") from None

    def __init__(self, root: Path, features: list[Feature], fps, repo_id: str):
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        spec = {f.key: ({"dtype": "image", "shape": f.shape, "names": ["height", "width", "channel"]}
                        if f.kind == "image" else {"dtype": str(f.dtype), "shape": f.shape, "names": list(f.names) or None})
                for f in features}
        # PNG encoding is most of an export's time: LeRobot's writer threads encode in parallel
        threads = IMAGE_WRITER_THREADS if any(f.kind == "image" for f in features) else 0
        logging.disable(logging.WARNING)  # it warns that it would decode video with pyav: there is no video here
        try:
            self.dataset = LeRobotDataset.create(repo_id, fps=int(fps), features=spec, root=root, use_videos=False,
                                                 image_writer_threads=threads)
        finally:
            logging.disable(logging.NOTSET)
        self.episodes = self.frames = 0

    def episode(self, episode: Episode, task: str, source: str) -> None:
        for frame in episode.frames:
            self.dataset.add_frame({**frame.values, "task": frame.task or task})
            # the tick's time from the run's start: add_frame would take a frame's "timestamp" (and
            # else stamps frame_index / fps), but lerobot 0.4.4's frame check refuses the key
            self.dataset.episode_buffer["timestamp"][-1] = frame.timestamp
        with _datasets_progress_bars_off():
            self.dataset.save_episode()
        self.episodes += 1
        self.frames += len(episode.frames)

    def close(self) -> tuple[int, int]:
        self._finish()
        return self.episodes, self.frames

    def abandon(self) -> None:
        """Stop its image writers and close its files (the folder they are in is then removed)."""
        self._finish()

    def _finish(self) -> None:
        self.dataset.stop_image_writer()
        with _datasets_progress_bars_off():
            self.dataset.finalize()


@contextmanager
def _datasets_progress_bars_off() -> Iterator[None]:
    """Hugging Face datasets' own progress bars off while LeRobot saves (a "Map: 100%|…" line
    per episode, beside the export's own progress), through datasets' switch, and set back as
    they were after: the program's other uses of datasets keep their bars. A user who set
    HF_DATASETS_DISABLE_PROGRESS_BARS=0 keeps them (datasets gives that variable the last word)."""
    import datasets

    if datasets.are_progress_bars_disabled() or datasets.config.HF_DATASETS_DISABLE_PROGRESS_BARS is False:
        yield
        return
    datasets.disable_progress_bars()
    try:
        yield
    finally:
        datasets.enable_progress_bars()


class _NpzWriter:
    """Frames as NumPy arrays: ``episode_NNNNNN.npz`` (one array per feature, stacked over the
    episode's frames, plus ``timestamp``, ``frame_index``, ``tick_ns`` and ``task``) and ``info.json``."""

    @staticmethod
    def check_installed() -> None:
        pass

    def __init__(self, root: Path, features: list[Feature], fps, repo_id: str):
        root.mkdir(parents=True)
        self.root, self.fps = root, fps
        self.features = features
        self.index: list[dict[str, Any]] = []
        self.frames = 0

    def episode(self, episode: Episode, task: str, source: str) -> None:
        n = len(self.index)
        arrays = {f.key: np.stack([frame.values[f.key] for frame in episode.frames]) for f in self.features}
        arrays["timestamp"] = np.array([frame.timestamp for frame in episode.frames], dtype=np.float64)
        arrays["frame_index"] = np.arange(len(episode.frames), dtype=np.int64)
        arrays["tick_ns"] = np.array([frame.tick[0] for frame in episode.frames], dtype=np.int64)
        arrays["task"] = np.array([frame.task or task for frame in episode.frames])
        np.savez(self.root / f"episode_{n:06d}.npz", allow_pickle=False, **arrays)
        self.index.append({"episode_index": n, "frames": len(episode.frames), "source": source})
        self.frames += len(episode.frames)

    def close(self) -> tuple[int, int]:
        info = {"format": NPZ_FORMAT, "fps": float(self.fps), "episodes": self.index,
                "features": {f.key: {"kind": f.kind, "dtype": str(f.dtype), "shape": list(f.shape)}
                             for f in self.features}}
        (self.root / "info.json").write_text(json.dumps(info, indent=1) + "\n")
        return len(self.index), self.frames

    def abandon(self) -> None:
        """Nothing is open between two episodes."""
