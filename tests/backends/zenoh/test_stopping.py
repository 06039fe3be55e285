"""zenoh/stopping.py: the stop a daemon, a router or a run's router process waits on, asked for
by a signal wherever the signal lands (a threading.Event's set() in the handler could wait for its
own lock: a run's router process was left running so, its daemon SIGKILLed)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]


def test_a_signal_that_lands_while_the_stop_is_waited_on_ends_the_wait():
    """Signals sent from another thread while the main thread waits in short timed waits (where
    an Event's handler could land with the Event's lock held): every one is taken, the wait ends
    as soon as the first comes, and the process ends (a deadlock would hit the timeout)."""
    script = textwrap.dedent("""
        import os, signal, threading
        from retriever.backends.zenoh.stopping import Stop

        asked = 0
        for _ in range(300):
            stop = Stop(signal.SIGUSR1, signal.SIGUSR2)
            sender = threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGUSR2))
            sender.start()
            while not stop.wait(0.0001):  # timed waits, back to back: a signal lands in any of them
                pass
            sender.join()
            assert stop.is_set() and stop.signal == signal.SIGUSR2
            asked += 1
        stop = Stop(signal.SIGUSR1)
        threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGUSR1)).start()
        assert stop.wait(60)  # returns when the signal comes, not after 60 s
        print(asked)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert (done.returncode, done.stdout.strip()) == (0, "300"), done.stderr


def test_a_stop_is_asked_for_once_by_the_first_signal():
    stop = None
    previous = signal.getsignal(signal.SIGUSR1)
    try:
        from retriever.backends.zenoh.stopping import Stop

        stop = Stop(signal.SIGUSR1)
        assert not stop.is_set() and not stop.wait(0)
        for _ in range(100_000 // 4096 + 2):  # more than the pipe holds: the handler does not block
            os.kill(os.getpid(), signal.SIGUSR1)
        assert stop.is_set() and stop.wait(0) and stop.signal == signal.SIGUSR1
    finally:
        signal.signal(signal.SIGUSR1, previous)
