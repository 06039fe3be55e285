"""The Rerun live view's process against a viewer that takes nothing more (``stop``: a gRPC
server of Rerun's SDK in a process of its own, stopped with SIGSTOP after the view connected)
or that is gone (``kill``: killed after 3 s): 230 kB frames and a number at 30 Hz for 10 s,
the process's RSS growth and, for ``kill``, the error lines the SDK writes on stderr (count
them: ``2>&1 | grep -c ERROR``).

    PYTHONPATH=CODE python benchmarks/rerun_live_slow_viewer.py stop|kill
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
from retriever.log.rerun_live import RerunLiveView

SERVER = "import rerun as rr, time\ns = rr.RecordingStream('v', send_properties=False)\ns.serve_grpc(grpc_port={})\n" \
         "time.sleep(120)"


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main() -> None:
    mode = sys.argv[1]
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
        if mode == "stop":
            os.kill(server.pid, signal.SIGSTOP)
        frame = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
        start, before = time.monotonic(), rss_mb()
        for i in range(300):
            time.sleep(max(0.0, start + i / 30 - time.monotonic()))
            now = time.time_ns()
            view.event("cam", "rgb", (now, 0), i, frame, now)
            view.event("sensor", "x", (now, 0), i, float(i), now)
            if mode == "kill" and i == 90:
                server.kill()
                server.wait()
            if i % 60 == 59:
                print(f"{(i + 1) / 30:.0f} s: {(i + 1) * frame.nbytes / 1e6:.0f} MB of frames, "
                      f"RSS +{rss_mb() - before:.0f} MB", flush=True)
    finally:
        server.kill()
        server.wait()
    try:
        view.close()
    except Exception as e:  # noqa: BLE001 - the viewer is gone: said, not raised
        print(f"close: {type(e).__name__}: {e}")


if __name__ == "__main__":
    main()
