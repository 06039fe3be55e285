"""What a worker daemon does for a run's processes (runs.py) that the deploy tests cannot show
at will: how a process's output reaches the coordinator. A real child process prints; the
daemon's forwarder reads its pipe; what it would send is collected in place of the Zenoh put."""

from __future__ import annotations

import subprocess
import sys
import threading
from types import SimpleNamespace

from retriever.backends.zenoh.runs import MAX_LINE_BYTES, OUTPUT_BATCH, DaemonRuns

BOUND_S = 30.0


def forwarding(code: str):
    """A child running ``code``, and the batches of output lines the daemon would send of it."""
    sent: list[dict] = []
    arrived = threading.Condition()

    def tell(op: str, args: dict) -> None:
        with arrived:
            sent.append(args)
            arrived.notify_all()

    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
    thread = threading.Thread(target=DaemonRuns._forward, args=(SimpleNamespace(_tell=tell), "r1", "cam", "stdout",
                                                                proc.stdout), daemon=True)
    thread.start()
    return proc, thread, sent, arrived


def lines_of(sent: list[dict]) -> list[str]:
    return [line for batch in sent for line in batch["lines"]]


def test_held_lines_go_though_nothing_follows_them():
    """A stack dump is printed at once and then nothing: its last lines (the telling ones) must
    not wait for more output (they did: only the dump's first line reached the coordinator)."""
    proc, thread, sent, arrived = forwarding(
        "import sys, time\nprint('Thread 1\\n  File a\\n  File b', flush=True)\ntime.sleep(60)")
    try:
        with arrived:
            assert arrived.wait_for(lambda: len(lines_of(sent)) == 3, timeout=BOUND_S), sent
        assert lines_of(sent) == ["Thread 1", "  File a", "  File b"]
        assert proc.poll() is None  # still running, still silent: the batch went by itself
        assert {(b["run"], b["node"], b["stream"]) for b in sent} == {("r1", "cam", "stdout")}
    finally:
        proc.kill()
        proc.wait()
        thread.join(BOUND_S)


def test_output_goes_in_batches_and_a_line_without_end_in_pieces():
    many = OUTPUT_BATCH * 3 + 5
    proc, thread, sent, _ = forwarding(
        f"import sys\nfor i in range({many}): print(i)\nsys.stdout.write('x' * {MAX_LINE_BYTES * 2 + 10})")
    proc.wait(BOUND_S)
    thread.join(BOUND_S)
    assert not thread.is_alive()
    lines = lines_of(sent)
    assert lines[:many] == [str(i) for i in range(many)]
    assert all(len(batch["lines"]) <= OUTPUT_BATCH for batch in sent)
    rest = lines[many:]
    assert "".join(rest) == "x" * (MAX_LINE_BYTES * 2 + 10) and all(len(piece) <= MAX_LINE_BYTES * 2 for piece in rest)


def test_a_process_that_prints_nothing_sends_nothing():
    proc, thread, sent, _ = forwarding("pass")
    proc.wait(BOUND_S)
    thread.join(BOUND_S)
    assert sent == [] and not thread.is_alive()
