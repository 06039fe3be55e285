"""A stranger with no credentials: ``python idle_connections.py HOST PORT N`` opens N TCP
connections to HOST:PORT and sends nothing on them; each one the far end closes is opened
again (after RETRY_S), so N stay open or on their way. It prints ``holding N`` once all N were
opened, and exits when its stdin closes (its test ended, or was killed)."""

from __future__ import annotations

import resource
import selectors
import socket
import sys
import threading
import time

RETRY_S = 0.005


def main(host: str, port: int, count: int) -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (resource.getrlimit(resource.RLIMIT_NOFILE)[1],) * 2)
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    selector = selectors.DefaultSelector()

    def open_one() -> None:
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex((host, port))
        selector.register(s, selectors.EVENT_READ)

    for _ in range(count):
        open_one()
    print(f"holding {count}", flush=True)
    while not done.is_set():
        closed = 0
        for key, _ in selector.select(0.2):
            try:
                if key.fileobj.recv(4096):
                    continue
            except BlockingIOError:
                continue
            except OSError:
                pass
            selector.unregister(key.fileobj)
            key.fileobj.close()
            closed += 1
        if closed:
            time.sleep(RETRY_S)
            for _ in range(closed):
                open_one()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
