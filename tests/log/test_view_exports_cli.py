"""`retriever log export --format ros2|rerun` and the exports behind it: the command writes what
the library writes, says what it wrote, refuses to overwrite without --force, and takes one log
only."""

from __future__ import annotations

import subprocess
import sys

import pytest

from retriever import LogError, read_log
from retriever.log.rerun import export_rerun
from retriever.log.ros2 import export_ros2
from tests.log.export_flows import camera_log
from tests.log.helpers import cli_env


def _export(log_path, out, fmt: str, *flags: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "retriever.cli", "log", "export", str(log_path), "--format", fmt,
                           "-o", str(out), *flags], capture_output=True, text=True, timeout=180, cwd=cwd,
                          env=cli_env())


@pytest.mark.parametrize("fmt, said", [("ros2", "(ROS 2 MCAP)"), ("rerun", "open it with: rerun ")])
def test_the_command_writes_the_view_and_refuses_to_overwrite(tmp_path, fmt, said):
    log_path = camera_log(tmp_path)
    out = tmp_path / f"view.{'mcap' if fmt == 'ros2' else 'rrd'}"
    done = _export(log_path, out, fmt, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"wrote {out}: ") and said in done.stdout and out.stat().st_size > 0, done.stdout
    again = _export(log_path, out, fmt, cwd=tmp_path)
    assert again.returncode == 1 and "exists" in again.stderr and "--force" in again.stderr, again.stderr
    assert _export(log_path, out, fmt, "--force", cwd=tmp_path).returncode == 0
    assert read_log(log_path).path == log_path  # the log itself is untouched and still reads


def test_a_view_takes_one_log_and_an_unknown_format_is_named(tmp_path):
    log_path = camera_log(tmp_path)
    two = subprocess.run([sys.executable, "-m", "retriever.cli", "log", "export", str(log_path), str(log_path),
                          "--format", "rerun", "-o", str(tmp_path / "v.rrd")], capture_output=True, text=True,
                         timeout=180, cwd=tmp_path, env=cli_env())
    assert two.returncode == 1 and "--format rerun exports one log, got 2" in two.stderr, two.stderr
    unknown = _export(log_path, tmp_path / "v", "rosbag", cwd=tmp_path)
    assert unknown.returncode == 1 and "unknown export format 'rosbag'" in unknown.stderr
    assert "foxglove, ros2, rerun, lerobot or npz" in unknown.stderr, unknown.stderr


@pytest.mark.parametrize("fmt", ["foxglove", "ros2", "rerun"])
def test_a_folder_or_no_name_as_the_output_is_said_even_with_force(tmp_path, fmt):
    log_path = camera_log(tmp_path)
    for out in (tmp_path, ""):
        done = _export(log_path, out, fmt, "--force", cwd=tmp_path)
        assert done.returncode == 1 and "is a folder, not a file" in done.stderr, done.stderr
        assert "Traceback" not in done.stderr and "IsADirectoryError" not in done.stderr, done.stderr


@pytest.mark.parametrize("export, name", [(export_ros2, "out.mcap"), (export_rerun, "run.rrd")])
def test_it_refuses_to_overwrite_and_to_write_over_the_log(tmp_path, export, name):
    log_path = camera_log(tmp_path)
    out = tmp_path / name
    export(read_log(log_path), out)
    with pytest.raises(LogError, match="exists(.|\n)*--force"):
        export(read_log(log_path), out)
    export(read_log(log_path), out, overwrite=True)
    with pytest.raises(LogError, match="is the log being exported"):
        export(read_log(log_path), log_path, overwrite=True)
