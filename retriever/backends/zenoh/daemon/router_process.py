"""The process of one run's router (run_router.py), which a worker daemon starts for the run:

    python -m retriever.backends.zenoh.daemon.router_process < SETTINGS

SETTINGS, on its stdin (so that no password is on its command line, nor on disk), is a JSON
object (run_router.RouterProcessSettings): where it listens, the upstream routers and their
Zenoh ids, the run's password, which alone it admits, and the daemon's, which it proves
upstream; with TLS, the certificate files. It opens its router session (routing.router_session_config, shared memory
on), waits until it is linked to an upstream router, says READY on its stdout, then routes until
SIGTERM, or until the daemon that started it is gone: as a worker process, it gets PARENT_DIED
when the daemon dies (a SIGKILL too), and watches it besides (worker/process.py). Either way it
closes its session and exits as Python exits, in which Zenoh removes the shared-memory segments
no one maps any more. What keeps it from starting goes to its stderr, which the daemon reads,
and it exits with EXIT_FAILED.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time

import zenoh

from ..access import SessionDictionary, run_user
from ..folders import private_folder
from ..hub import remove_orphaned_segments_at_exit
from ..routing import RUN_ROUTER_SHARED_MEMORY, access_control, router_session_config
from ..stopping import Stop
from ..worker.process import PARENT_DIED, Parent, prepare_process
from .run_router import (EXIT_FAILED, LINK_POLL_S, MAX_RUN_SESSIONS, PARENT_CHECK_S, READY, ROUTER_PROCESS_FOLDER,
                         UPSTREAM_LINK_S, RouterProcessSettings)

#: the most its stdin's settings may be (a daemon's are a few hundred characters): no more is read
SETTINGS_MAX = 1 << 20


def open_router(settings: RouterProcessSettings) -> zenoh.Session:
    """The run's router session, linked to an upstream router (see the module's docstring);
    RuntimeError with what went wrong, said for the daemon's reader."""
    user = run_user(settings.namespace)
    folder = private_folder(ROUTER_PROCESS_FOLDER)
    dictionary = SessionDictionary(f"{user}:{settings.run_password}\n", folder / "zenoh-run-router-users.txt")
    try:
        session = zenoh.open(router_session_config(
            listen=[settings.listen], connect=settings.upstream, user=user, password=settings.upstream_password,
            dictionary_file=dictionary.path, access=access_control([settings.namespace], settings.upstream_ids),
            tls=settings.tls, lease=None, max_sessions=MAX_RUN_SESSIONS, shared_memory=RUN_ROUTER_SHARED_MEMORY))
    except zenoh.ZError as e:
        raise RuntimeError(f"it cannot open on {settings.listen}: {e}") from None
    finally:
        dictionary.close()
        shutil.rmtree(folder, ignore_errors=True)
    give_up = time.monotonic() + UPSTREAM_LINK_S
    while not set(settings.upstream_ids) & {str(z) for z in session.info.routers_zid()}:
        if time.monotonic() > give_up:
            session.close()
            raise RuntimeError(f"it got no link to the upstream router ({', '.join(settings.upstream)}) "
                               f"within {UPSTREAM_LINK_S:g} s")
        time.sleep(LINK_POLL_S)
    return session


def serve(settings: RouterProcessSettings, parent: Parent, stat: int | None) -> int:
    """Route until SIGTERM or PARENT_DIED, or until ``parent`` is gone (``stat``: Parent.gone's);
    the exit code."""
    stop = Stop(signal.SIGTERM, PARENT_DIED)
    remove_orphaned_segments_at_exit()  # the segments of the run's flows, once no one maps them
    try:
        session = open_router(settings)
    except RuntimeError as e:
        print(e, file=sys.stderr, flush=True)
        return EXIT_FAILED
    with session:
        print(READY, flush=True)
        while not stop.wait(PARENT_CHECK_S) and not parent.gone(stat):
            pass
    return 0


def main() -> int:
    parent = Parent(os.getppid())
    try:  # read through one descriptor, opened while the parent lives (Parent.gone)
        stat = os.open(f"/proc/{parent.pid}/stat", os.O_RDONLY)
    except OSError:
        stat = None
    if not prepare_process():  # its daemon is gone already
        return EXIT_FAILED
    try:
        text = sys.stdin.read(SETTINGS_MAX + 1)
        if len(text) > SETTINGS_MAX:
            raise ValueError(f"the run router's settings are not a daemon's: more than {SETTINGS_MAX:,} characters")
        settings = RouterProcessSettings.from_json(text)
    except ValueError as e:
        print(e, file=sys.stderr, flush=True)
        return EXIT_FAILED
    return serve(settings, parent, stat)


if __name__ == "__main__":
    sys.exit(main())
