"""`retriever log export --format ros2|rerun` and the exports behind it: the command writes what
the library writes, says what it wrote, refuses to overwrite without --force, and takes one log
only."""

from __future__ import annotations

import os
import re
import signal
import stat
import subprocess
import sys
import time

import pytest

from retriever import LogError, read_log
from retriever.log.rerun import export_rerun
from retriever.log.ros2 import export_ros2
from tests.log.export_flows import camera_log, long_log, shadowed_steps_log
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


@pytest.mark.parametrize("fmt, said", [("ros2", "names that make one ROS name kept apart: "),
                                       ("rerun", "entities kept apart: ")])
def test_the_command_says_which_names_were_kept_apart(tmp_path, fmt, said):
    out = tmp_path / f"view.{'mcap' if fmt == 'ros2' else 'rrd'}"
    done = _export(shadowed_steps_log(tmp_path), out, fmt, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert f"{said}retriever.steps.cam on /retriever/steps/cam_2" in " ".join(done.stdout.split()), done.stdout


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
    for out in (tmp_path, "", "newbag/"):  # a trailing / names a folder, even one not there (it wrote a file 'newbag')
        done = _export(log_path, out, fmt, "--force", cwd=tmp_path)
        assert done.returncode == 1 and "is a folder, not a file" in done.stderr, done.stderr
        assert "Traceback" not in done.stderr and "IsADirectoryError" not in done.stderr, done.stderr
    assert not (tmp_path / "newbag").exists()


@pytest.mark.parametrize("fmt", ["foxglove", "ros2", "rerun"])
def test_a_device_or_fifo_as_the_output_is_refused_even_with_force(tmp_path, fmt):
    """With --force, an export was renamed over a FIFO or a device node (as root, -o /dev/null
    would have made the machine's /dev/null a file)."""
    log_path = camera_log(tmp_path)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    done = _export(log_path, fifo, fmt, "--force", cwd=tmp_path)
    assert done.returncode == 1 and "is no regular file" in done.stderr, done.stderr
    assert stat.S_ISFIFO(fifo.lstat().st_mode)


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


@pytest.fixture(scope="module")
def long_log_path(tmp_path_factory):
    return long_log(tmp_path_factory.mktemp("long") / "long.mcap")


#: how long the export may take to start writing (its interpreter, imports, reading the log), at most
START_BOUND_S = 120.0


@pytest.mark.parametrize("fmt, extra, signum", [
    ("ros2", (), signal.SIGTERM), ("rerun", (), signal.SIGTERM), ("foxglove", (), signal.SIGTERM),
    ("npz", ("--flow", "count"), signal.SIGTERM),  # a dataset's partial folder too
    ("ros2", (), signal.SIGINT),  # Ctrl-C: the same path
])
def test_an_export_stopped_by_a_signal_leaves_no_file_and_says_so_in_one_line(tmp_path, long_log_path, fmt, extra,
                                                                                signum):
    """SIGTERM (what a supervisor or `timeout` sends) or Ctrl-C's SIGINT while the export writes
    its ``.partial``: the partial file is removed, nothing is at ``-o``, the command says so in one
    line and exits 128 + the signal, as an interrupted `retriever run` does. (SIGTERM used to kill
    it where it stood, the partial file left behind.)"""
    views = tmp_path / "views"
    views.mkdir()
    out = views / ("out" if fmt == "npz" else "out.mcap")
    export = subprocess.Popen([sys.executable, "-m", "retriever.cli", "log", "export", str(long_log_path),
                               "--format", fmt, "-o", str(out), *extra], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=cli_env())
    try:
        deadline = time.monotonic() + START_BOUND_S
        while not list(views.glob(".out*.partial")) and export.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)  # polling a real process's file, bounded: what the test waits for is its work
        assert export.poll() is None, f"the export ended before it was signalled: {export.communicate()}"
        assert list(views.glob(".out*.partial")), f"no .partial in {START_BOUND_S} s"
        export.send_signal(signum)
        stdout, stderr = export.communicate(timeout=120)
    finally:
        if export.poll() is None:
            export.kill()
            export.communicate()
    name = signal.Signals(signum).name
    assert export.returncode == 128 + signum, (export.returncode, stdout, stderr)
    assert stderr.splitlines() == [f"interrupted by {name}: {out} was not written"], stderr
    assert list(views.iterdir()) == [], "a file was left behind"


# ---------------------------------------------------------------------------------------------
# -o -: standard output, where the format is written front to back (issue 39)
# ---------------------------------------------------------------------------------------------
def _piped(log_path, fmt: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "retriever.cli", "log", "export", str(log_path), "--format", fmt,
                           "-o", "-"], capture_output=True, timeout=180, cwd=cwd, env=cli_env())


def test_ros2_to_standard_output_is_the_file_it_writes(tmp_path):
    """Before, ``-o -`` wrote a file named '-' in the working folder."""
    log_path = camera_log(tmp_path)
    piped = _piped(log_path, "ros2", tmp_path)
    assert piped.returncode == 0, piped.stderr
    assert piped.stderr.decode().startswith("wrote standard output: ") and not (tmp_path / "-").exists()
    export_ros2(log_path, tmp_path / "view.mcap")
    assert piped.stdout == (tmp_path / "view.mcap").read_bytes()


def test_rerun_to_standard_output_loads_as_the_file_it_writes(tmp_path):
    import rerun as rr

    log_path = camera_log(tmp_path)
    piped = _piped(log_path, "rerun", tmp_path)
    assert piped.returncode == 0, piped.stderr
    assert "a viewer reads it from a pipe: | rerun -" in piped.stderr.decode() and not (tmp_path / "-").exists()
    (tmp_path / "piped.rrd").write_bytes(piped.stdout)
    written = export_rerun(log_path, tmp_path / "view.rrd").written
    for path in (tmp_path / "piped.rrd", tmp_path / "view.rrd"):
        recording = rr.dataframe.load_recording(path)
        for entity, rows in written.items():
            assert recording.view(index="event_time", contents=entity).select().read_all().num_rows <= rows
            assert recording.view(index="seq", contents=entity).select().read_all().num_rows == rows, (path, entity)


@pytest.mark.parametrize("fmt, why", [("foxglove", "Foxglove's SDK writes its MCAP only to a file it opens by name"),
                                      ("npz", "a dataset is a folder of files")])
def test_a_format_not_written_front_to_back_refuses_standard_output_saying_why(tmp_path, fmt, why):
    log_path = camera_log(tmp_path)
    done = _piped(log_path, fmt, tmp_path)
    assert done.returncode == 1 and not done.stdout and not (tmp_path / "-").exists()
    assert done.stderr.decode().startswith(f"error: --format {fmt} cannot be written to standard output (-o -): "
                                           f"{why}\nhint: give it a path: -o FILE"), done.stderr


def test_standard_output_on_a_terminal_is_refused(tmp_path):
    import pty

    log_path = camera_log(tmp_path)
    pid, fd = pty.fork()
    if pid == 0:  # the child: the export, its standard output a terminal
        os.chdir(tmp_path)
        os.execve(sys.executable, [sys.executable, "-m", "retriever.cli", "log", "export", str(log_path), "--format",
                                   "ros2", "-o", "-"], cli_env())
    said = b""
    while True:
        try:
            chunk = os.read(fd, 4096)
        except OSError:
            break
        if not chunk:
            break
        said += chunk
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 1
    assert b"-o - writes the ros2 export to standard output, which is a terminal" in said, said
    assert not (tmp_path / "-").exists()


# ---------------------------------------------------------------------------------------------
# -o - when standard output cannot take the export: one designed line each (issue 39)
# ---------------------------------------------------------------------------------------------
def _export_argv(log_path, fmt: str = "ros2") -> list[str]:
    return [sys.executable, "-m", "retriever.cli", "log", "export", str(log_path), "--format", fmt, "-o", "-"]


@pytest.mark.parametrize("fmt", ["ros2", "rerun"])
def test_a_closed_standard_output_is_said_in_one_line(tmp_path, fmt):
    """`>&-` was AttributeError: 'NoneType' object has no attribute 'isatty'."""
    log_path = camera_log(tmp_path)
    done = subprocess.run(_export_argv(log_path, fmt), stderr=subprocess.PIPE, text=True, timeout=180, cwd=tmp_path,
                          env=cli_env(), preexec_fn=lambda: os.close(1))  # the child's `>&-`
    assert done.returncode == 1, done.stderr
    piped = "| mcap info /dev/stdin" if fmt == "ros2" else "| rerun -"
    assert done.stderr.splitlines() == ["error: standard output is closed", f"hint: pipe it into a program ({piped}), "
                                        "redirect it (> FILE) or give a path: -o FILE"], done.stderr


def test_a_full_standard_output_is_said_in_one_line(tmp_path):
    """`> /dev/full` was a raw OSError: [Errno 28] No space left on device."""
    log_path = camera_log(tmp_path)
    with open("/dev/full", "wb") as full:
        done = subprocess.run(_export_argv(log_path), stdout=full, stderr=subprocess.PIPE, text=True, timeout=180,
                              cwd=tmp_path, env=cli_env())
    assert done.returncode == 1, done.stderr
    assert done.stderr.splitlines() == [
        "error: standard output is full: No space left on device (0 bytes were written before; not a whole export)",
        "hint: write the export to a file with room: -o FILE"], done.stderr


def test_a_reader_that_went_away_ends_the_export_quietly_with_141(tmp_path):
    """`| head -c 10` was BrokenPipeError and exit 1; Unix tools end quietly, 128 + SIGPIPE."""
    log_path = camera_log(tmp_path)
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the first write: EPIPE for certain, not a race with head
    try:
        done = subprocess.run(_export_argv(log_path), stdout=write, stderr=subprocess.PIPE, text=True, timeout=180,
                              cwd=tmp_path, env=cli_env())
    finally:
        os.close(write)
    assert (done.returncode, done.stderr) == (128 + signal.SIGPIPE, "")


def test_a_reader_that_went_away_ends_the_rerun_export_with_141(tmp_path):
    """Rerun's SDK writes standard output from a thread of its own, and its flush then raised
    RuntimeError("File-writer thread shut down prematurely"): `| head -c 100000` ended with
    exit 1 and "error: RuntimeError: ...". (The SDK's own log lines about it remain.)"""
    log_path = camera_log(tmp_path)
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run(_export_argv(log_path, "rerun"), stdout=write, stderr=subprocess.PIPE, text=True,
                              timeout=180, cwd=tmp_path, env=cli_env())
    finally:
        os.close(write)
    assert done.returncode == 128 + signal.SIGPIPE, done.stderr
    assert "error:" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_ctrl_c_while_writing_standard_output_says_how_much_was_written(tmp_path, long_log_path):
    """It said '- was not written' although the export had written to the pipe."""
    export = subprocess.Popen(_export_argv(long_log_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0,
                              cwd=tmp_path, env=cli_env())
    try:
        first = export.stdout.read(1)  # blocks until the export writes: it is under way
        assert first, export.communicate()
        export.send_signal(signal.SIGINT)
        rest, stderr = export.communicate(timeout=120)
    finally:
        if export.poll() is None:
            export.kill()
            export.communicate()
    received = len(first) + len(rest)
    assert export.returncode == 128 + signal.SIGINT, (export.returncode, stderr)
    said = stderr.decode().splitlines()
    amount = re.fullmatch(r"interrupted by SIGINT: (\d+)(?: to (\d+))? bytes of the ros2 export were written to "
                          r"standard output \(not a whole one\)", said[0]) if len(said) == 1 else None
    assert amount, said
    # a range only when the signal came during a write, which may have gone out in part
    least, most = int(amount[1]), int(amount[2] or amount[1])
    assert least <= received <= most and received > 0, (said, received)


@pytest.mark.parametrize("fmt", ["foxglove", "ros2"])
def test_an_interrupt_right_as_the_partial_file_is_created_leaves_no_file(tmp_path, monkeypatch, fmt):
    """The window the signal test above found under load (a foxglove ``.partial`` left behind):
    the interrupt raised the moment the SDK's ``open_mcap`` (or ``open``) returned, before the
    cleanup's ``try``. The real opener runs (the file is made); then KeyboardInterrupt, as a
    signal handler raises it there. Nothing may remain beside the output."""
    from retriever.log import foxglove as foxglove_module
    from retriever.log import ros2 as ros2_module

    log_path = camera_log(tmp_path)
    out = tmp_path / "views" / "out.mcap"
    out.parent.mkdir()

    def interrupted(opener):
        def open_then_interrupt(*args, **kwargs):
            opened = opener(*args, **kwargs)
            interrupted.opened = opened
            raise KeyboardInterrupt
        return open_then_interrupt

    if fmt == "foxglove":
        sdk = pytest.importorskip("foxglove")  # the module export_foxglove opens its file with
        monkeypatch.setattr(sdk, "open_mcap", interrupted(sdk.open_mcap))
        export = foxglove_module.export_foxglove
    else:
        monkeypatch.setattr(ros2_module, "open", interrupted(open), raising=False)
        export = export_ros2
    with pytest.raises(KeyboardInterrupt):
        export(log_path, out)
    closer = getattr(interrupted.opened, "close", None)
    if closer is not None:
        closer()
    assert list(out.parent.iterdir()) == [], "a file was left behind"
