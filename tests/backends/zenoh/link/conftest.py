"""The link's tests' fixtures: a private folder for a link's socket (checked empty after the
test, and nothing of a link's left in /dev/shm), and peers in processes of their own."""

from __future__ import annotations

import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import pytest

PEERS = Path(__file__).with_name("link_peers.py")
ROOT = Path(__file__).resolve().parents[4]
#: how long a test waits for a peer's line: only a bound on a hang, never a wait for something to happen
LINE_TIMEOUT = 60.0


@pytest.fixture
def folder():
    """A new folder only this user may enter, short enough for a socket's path; after the test it
    must hold nothing but what the test allowed (``folder.left``), and /dev/shm nothing new of a link."""
    shm = set(os.listdir("/dev/shm"))
    path = Path(tempfile.mkdtemp(prefix="link-"))
    yield path
    left = sorted(os.listdir(path))
    shutil.rmtree(path)
    assert left == [], f"left in the link's folder: {left}"
    assert [name for name in set(os.listdir("/dev/shm")) - shm if "link" in name] == []


class Peer:
    """link_peers.py in a process of its own: its lines read one at a time, its stdin closed to end it."""

    def __init__(self, *args: object):
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        self.process = subprocess.Popen([sys.executable, str(PEERS), *map(str, args)], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, text=True, env=env)
        self._lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self._lines.put(line)
        self._lines.put("")

    def line(self) -> object:
        try:
            line = self._lines.get(timeout=LINE_TIMEOUT)
        except queue.Empty:
            raise AssertionError("a peer printed nothing in time") from None
        assert line, f"a peer ended (exit {self.process.wait()})"
        return json.loads(line) if line.startswith("{") else line.strip()

    def lines(self, count: int) -> list:
        return [self.line() for _ in range(count)]

    def kill(self) -> None:
        self.process.kill()
        self.process.wait()
        self._reader.join()
        self.process.stdout.close()
        self.process.stdin.close()

    def end(self) -> int:
        self.process.stdin.close()
        code = self.process.wait(LINE_TIMEOUT)
        self._reader.join()
        self.process.stdout.close()
        return code


@pytest.fixture
def peers():
    """Starts Peers; any still running at the end are killed."""
    started: list[Peer] = []

    def start(*args: object) -> Peer:
        started.append(Peer(*args))
        return started[-1]

    yield start
    for peer in started:
        if peer.process.poll() is None:
            peer.kill()
