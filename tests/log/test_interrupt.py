"""SIGTERM and Ctrl-C stop a logged run cleanly: the log is finished, marked, and replays."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from retriever.log import read_log
from retriever.replay import replay, resim

REPO = Path(__file__).resolve().parents[2]
RETRIEVER = Path(sys.executable).parent / "retriever"


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_finishes_the_log(tmp_path, sig):
    path = tmp_path / "long.mcap"
    proc = subprocess.Popen([str(RETRIEVER), "run", str(REPO / "examples" / "quickstart.py"), "--duration", "1e6",
                             "--log", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60  # a generous bound, not a speed threshold
        while not (path.exists() and path.stat().st_size > 100_000):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the run never logged 100 kB"
            time.sleep(0.05)
        os.kill(proc.pid, sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + sig, err  # 130 on Ctrl-C, 143 on SIGTERM
    assert "interrupted" in err and str(path) in err
    assert "Traceback" not in err
    log = read_log(path)  # complete: no recovery needed
    assert log.complete and log.end["status"] == "interrupted"
    assert int(log.end["end_ns"]) > 0
    assert replay(log).identical
    assert resim(log).identical


def test_a_signal_while_the_log_is_begun_finishes_it_interrupted(tmp_path, monkeypatch):
    """Ctrl-C that lands as the log's header is written (the file already holds bytes) stops the
    run between ticks like any other: the log is finished and marked, not half begun and then
    removed (a window `retriever run --duration inf` once showed, printing no table)."""
    from retriever.log import writer
    from tests.log.log_flows import build_small

    begin = writer.LogWriter.__init__

    def begin_then_interrupt(self, *args, **kwargs):
        begin(self, *args, **kwargs)
        assert self.path.stat().st_size > 0  # what a watcher of the file sees as "the run started"
        os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(writer.LogWriter, "__init__", begin_then_interrupt)
    path = tmp_path / "begun.mcap"
    pipe = build_small()
    with pytest.raises(KeyboardInterrupt):
        pipe.run(duration=1e6, log=path)  # stops at its first hand-over to the writer
    log = read_log(path)
    assert log.complete and log.end["status"] == "interrupted"
    assert replay(log).identical
    assert pipe.now < 1e6


def test_a_signal_while_the_log_is_ended_does_not_tear_it(tmp_path, monkeypatch):
    """Ctrl-C while the log's end is written (a short run writes most of it there): the end is
    written whole, and the run had finished, so the log says so."""
    from retriever.log import writer
    from tests.log.log_flows import build_small

    close = writer.LogWriter.close

    def interrupt_then_close(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        return close(self, *args, **kwargs)

    monkeypatch.setattr(writer.LogWriter, "close", interrupt_then_close)
    path = tmp_path / "ended.mcap"
    pipe = build_small()
    pipe.run(duration=0.05, log=path)
    log = read_log(path)
    assert log.complete and log.end["status"] == "finished"
    assert replay(log).identical


def test_a_signal_while_a_log_fails_to_begin_interrupts_and_is_not_carried_over(tmp_path, monkeypatch):
    """Ctrl-C while a log that cannot be begun is being begun: the run is interrupted (what was
    asked), the file is gone, and the pipeline runs on as before, not stopped by the old request."""
    from retriever.errors import LogWriteError
    from retriever.log import writer
    from tests.log.log_flows import build_small

    def interrupt_then_fail(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        raise LogWriteError("the disk went away")

    monkeypatch.setattr(writer.LogWriter, "__init__", interrupt_then_fail)
    path = tmp_path / "failed.mcap"
    pipe = build_small()
    pipe.run(duration=0)  # a session exists (a log still records from T0)
    with pytest.raises(KeyboardInterrupt) as caught:
        pipe.run(duration=1, log=path)
    assert isinstance(caught.value.__cause__, LogWriteError)
    assert not path.exists()
    pipe.run(duration=1)
    assert pipe.now == 1


def test_a_second_signal_as_the_log_is_begun_leaves_no_writer_behind(tmp_path, monkeypatch):
    """A second Ctrl-C lands just as the writer is set on the session (the run not begun): the file
    is removed, and the pipeline's next run does not write to that closed file."""
    from retriever.pipeline import RunLog
    from tests.log.log_flows import build_small

    begin = RunLog.begin

    def begun_then_interrupted(self, session):
        begin(self, session)
        raise KeyboardInterrupt  # as the second signal would, before the run begins

    monkeypatch.setattr(RunLog, "begin", begun_then_interrupted)
    path = tmp_path / "twice.mcap"
    pipe = build_small()
    pipe.run(duration=0)  # a session exists: it outlives the refused run
    with pytest.raises(KeyboardInterrupt):
        pipe.run(duration=1, log=path)
    assert not path.exists()
    pipe.run(duration=1)
    assert pipe.now == 1


def test_a_second_signal_while_the_log_is_ended_does_not_tear_it(tmp_path, monkeypatch):
    """Ctrl-C pressed twice: the first stops the run, the second lands as the log's end is written
    (`retriever run --log` then said "the run so far is in" a file that only `log recover` could
    read): it is ignored there, and the log is finished, marked interrupted."""
    from retriever.log import writer
    from tests.log.log_flows import build_small

    close = writer.LogWriter.close

    def interrupted_twice_then_close(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        return close(self, *args, **kwargs)

    monkeypatch.setattr(writer.LogWriter, "close", interrupted_twice_then_close)
    path = tmp_path / "twice.mcap"
    pipe = build_small()
    pipe.run(duration=0.05, log=path)
    log = read_log(path)
    assert log.complete and log.end["status"] == "finished"
    assert replay(log).identical
