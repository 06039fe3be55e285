"""Speed and size of ``retriever log export --format lerobot | npz`` (issue 36, section 1).

Two logs, each exported in both formats, timed end to end (``export_dataset``: reading the log,
building each frame from the step records, writing, renaming), best of ``--repeats``:

- ``camera``: a camera pipeline recorded in virtual time for ``--duration`` s: ``camera @ Rate(hz)``
  sends an RGB image (``--size`` H×W: a gradient with a moving square and a sensor's noise of
  ±2 levels, which PNG compresses about as it does a real camera's) and 7 joint angles;
  ``policy @ Rate(hz)`` consumes both (Latest) and sends a 7-element action. One frame per policy tick.
- ``retriever0`` (with ``--retriever0 LOG``): a Retriever-0 demo log (``retriever demo --backend
  inproc --log LOG``), the ``skill`` flow (2 Hz; the head camera's 96×128 frame, the observation,
  the skill command; the action chunk and progress). Its sparse ``inspection`` port is left out
  by the export's rule.

Printed per log and format: frames, seconds, frames/s, output size and bytes per frame, and the
log's size for comparison.

    .venv/bin/python benchmarks/dataset_export.py                       # defaults: 60 s at 30 Hz, 96×128
    .venv/bin/python benchmarks/dataset_export.py --retriever0 r0.mcap  # and a Retriever-0 log
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from retriever import Flow, Latest, Pipeline, Rate, io  # noqa: E402
from retriever.log.dataset import export_dataset  # noqa: E402


@io
class Shot:
    image: np.ndarray
    joints: np.ndarray


@io
class Act:
    action: np.ndarray


class Camera(Flow[None, Shot]):
    def __init__(self, height: int = 96, width: int = 128):
        self.height, self.width = height, width
        self.k = 0

    def step(self, inp: None) -> Shot:
        self.k += 1
        h, w = self.height, self.width
        image = np.zeros((h, w, 3), dtype=np.uint8)
        image[..., 0] = np.linspace(40, 200, w, dtype=np.uint8)[None, :]
        image[..., 1] = np.linspace(60, 160, h, dtype=np.uint8)[:, None]
        image[..., 2] = 90
        x, y = (self.k * 3) % (w - 12), (self.k * 2) % (h - 12)
        image[y:y + 12, x:x + 12] = (230, 40, 40)
        noise = np.random.default_rng(self.k).integers(0, 5, (h, w, 3), dtype=np.uint8)  # a sensor's, ±2 levels
        image = image - 2 + noise
        joints = np.sin(np.arange(7) + self.k * 0.05).astype(np.float32)
        return Shot(image=image, joints=joints)


class Policy(Flow[Shot, Act]):
    def step(self, inp: Shot) -> Act:
        return Act(action=(inp.joints * 0.5 + inp.image[0, 0, 0] / 255).astype(np.float32))


def camera_log(path: Path, duration: float, hz: int, height: int, width: int) -> Path:
    with Pipeline("camera benchmark") as pipe:
        camera = Camera(height, width).named("camera") @ Rate(hz)
        policy = Policy().named("policy") @ Rate(hz)
        camera.then(policy, sync=Latest())
    pipe.run(duration=duration, log=str(path))
    return path


def folder_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def measure(name: str, log: Path, flow: str, formats: list[str], repeats: int, scratch: Path) -> None:
    print(f"\n{name}: {log.name}, {log.stat().st_size / 1e6:.2f} MB, flow {flow}")
    print(f"{'format':<8} {'frames':>7} {'best s':>8} {'frames/s':>9} {'size MB':>8} {'kB/frame':>9}")
    for format in formats:
        times, summary = [], None
        for _ in range(repeats):
            out = scratch / f"{name}-{format}"
            shutil.rmtree(out, ignore_errors=True)
            started = time.perf_counter()
            summary = export_dataset([log], out, flow=flow, format=format)
            times.append(time.perf_counter() - started)
        size = folder_size(out)
        best = min(times)
        print(f"{format:<8} {summary.frames:>7} {best:>8.2f} {summary.frames / best:>9.0f} {size / 1e6:>8.2f} "
              f"{size / summary.frames / 1e3:>9.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="virtual seconds of the camera run")
    parser.add_argument("--hz", type=int, default=30)
    parser.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--formats", nargs="+", default=["npz", "lerobot"])
    parser.add_argument("--retriever0", type=Path, metavar="LOG", help="a Retriever-0 demo log (its skill flow)")
    args = parser.parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        import datasets
        datasets.disable_progress_bars()
    except ImportError:
        pass
    revision = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent).stdout.strip()
    print(f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, code {revision}, "
          f"{platform.node()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        log = camera_log(scratch / "camera.mcap", args.duration, args.hz, *args.size)
        measure(f"camera {args.size[0]}x{args.size[1]} at {args.hz} Hz, {args.duration:g} s", log, "policy",
                args.formats, args.repeats, scratch)
        if args.retriever0 is not None:
            measure("retriever0", args.retriever0, "skill", args.formats, args.repeats, scratch)


if __name__ == "__main__":
    main()
