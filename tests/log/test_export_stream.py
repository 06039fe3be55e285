"""``retriever log export --format ros2 | rerun | foxglove`` streams the log as ``retriever replay``
does (issue 39): read once to check it and see what it holds, then again a few chunks at a time,
so its memory stays flat however long the log (before, every message was held, read_log)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.log.helpers import RETRIEVER, cli_env
from tests.log.test_replay_stream import _PEAK, _frames_log


@pytest.fixture(scope="module")
def frames_logs(tmp_path_factory) -> tuple[Path, Path]:
    """The frames log (64 KiB of noise a frame at 30 Hz), 2 s and 16 s of it: 4 MB and 32 MB."""
    folder = tmp_path_factory.mktemp("frames")
    short, long = _frames_log(folder / "short.mcap", 2.0), _frames_log(folder / "long.mcap", 16.0)
    assert long.stat().st_size > 7.5 * short.stat().st_size > 7.5 * 3e6
    return short, long


def _export_peak_rss_kib(log: Path, format: str, out: Path) -> int:
    """The peak RSS of ``retriever log export LOG --format FORMAT -o OUT``, in KiB, measured by a
    process of its own whose only child is the export."""
    done = subprocess.run([sys.executable, "-c", _PEAK, str(RETRIEVER), "log", "export", str(log), "--format", format,
                           "-o", str(out), "--force"], capture_output=True, text=True, env=cli_env(), timeout=120)
    peak, _, output = done.stdout.partition("\n")
    assert done.returncode == 0 and f"wrote {out}" in output, output
    return int(peak)


#: how much more a log 8 times as long (28 MB more of frames) may take to export, in KiB. Read
#: whole, each export took 29 to 35 MB more. ros2 and foxglove: flat (under 2 MB more, measured).
#: rerun: Rerun's SDK (0.26) keeps about 0.3 MB per MB of log however often it is flushed (9.0
#: to 13.7 MB more here, 2026-12-05, on the code of that morning too; a 126 MB log's export peaked
#: 30 MB above a 3 MB log's): not flat, an open finding (issue 42), bounded here below reading
#: the log whole
_MORE_KIB = {"ros2": 12 * 1024, "foxglove": 12 * 1024, "rerun": 20 * 1024}


@pytest.mark.parametrize("format", ["ros2", "rerun", "foxglove"])
def test_export_memory_is_flat_however_long_the_log(frames_logs, tmp_path, format):
    """A log 8 times as long (28 MB more of frames) exports in the same memory, within a few MB
    (_MORE_KIB: rerun's SDK grows a little); read whole, each export took 29 to 35 MB more."""
    short, long = frames_logs
    out = tmp_path / f"view.{format}"
    one, eight = _export_peak_rss_kib(short, format, out), _export_peak_rss_kib(long, format, out)
    assert eight - one < _MORE_KIB[format], f"peak RSS {one} KiB for the 1x log, {eight} KiB for the 8x log"
