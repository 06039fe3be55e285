"""The Rerun live view's process against a viewer that takes nothing more (``stop``: a gRPC
server of Rerun's SDK in a process of its own, stopped with SIGSTOP after the view connected)
or that is gone (``kill``: killed after 3 s), or that is stopped and resumed half way
(``pause``), or that takes it all (``healthy``): 230 kB frames
and a number at 30 Hz for 10 s (or SECONDS); the process's RSS growth every 2 s and its peak, what the view
dropped (its ``dropped``, where it has one), how long closing it took and, for ``kill``, the
error lines the SDK writes on stderr (count them: ``2>&1 | grep -c ERROR``). The viewer is
left stopped while the view closes (``stop``), then killed.

    PYTHONPATH=CODE python benchmarks/rerun_live_slow_viewer.py stop|kill|pause|healthy [SECONDS]
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np

from retriever.backends.zenoh.hub import free_port
from retriever.log.live import LiveViews
from retriever.log.rerun_live import RerunLiveView

SERVER = "import rerun as rr, time\ns = rr.RecordingStream('v', send_properties=False)\ns.serve_grpc(grpc_port={})\n" \
         "time.sleep(120)"


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main() -> None:
    mode = sys.argv[1]
    frames = round(30 * float(sys.argv[2] if len(sys.argv) > 2 else 10))
    port = free_port()
    server = subprocess.Popen([sys.executable, "-c", SERVER.format(port)])
    try:
        for _ in range(400):
            try:
                socket.create_connection(("127.0.0.1", port), 0.1).close()
                break
            except OSError:
                time.sleep(0.05)
        view = RerunLiveView(f"rerun+http://127.0.0.1:{port}/proxy", "slow")
        views = LiveViews([view])  # as the coordinator feeds it: a view that fails is stopped with a warning
        if mode in ("stop", "pause"):
            os.kill(server.pid, signal.SIGSTOP)
        frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
        start, before = time.monotonic(), rss_mb()
        peak = before
        for i in range(frames):
            time.sleep(max(0.0, start + i / 30 - time.monotonic()))
            now = time.time_ns()
            views.event("cam", "rgb", (now, 0), i, frame, now)
            views.event("sensor", "x", (now, 0), i, float(i), now)
            if mode == "pause" and i == frames // 2:
                os.kill(server.pid, signal.SIGCONT)
            if mode == "kill" and i == 90:
                server.kill()
                server.wait()
            peak = max(peak, rss_mb())
            if i % 60 == 59:
                print(f"{(i + 1) / 30:.0f} s: {(i + 1) * frame.nbytes / 1e6:.0f} MB of frames, "
                      f"RSS +{rss_mb() - before:.0f} MB; frames sent {view.written['/cam/rgb']}", flush=True)
        print(f"peak RSS +{peak - before:.0f} MB; dropped {dict(getattr(view, 'dropped', {}))}", flush=True)
        if not hasattr(view, "dropped"):  # the code before: its close waited for a stopped viewer without bound
            server.kill()
        closing = time.monotonic()
        views.close()  # what fails is said in a warning
        print(f"close took {time.monotonic() - closing:.1f} s", flush=True)
    finally:
        server.kill()
        server.wait()


if __name__ == "__main__":
    main()
