"""A worker process: one flow of a run, rebuilt from the IR, ticking in real time.

    python -m retriever.backends.zenoh.worker SPEC.json NODE [--join T0 END | --fresh T0 END]

(command.py builds and reads that line.) The coordinator (``retriever.backends.zenoh.coordinator``)
writes ``SPEC.json`` — a protocol.RunSpec: the IR and its plan, the hub's endpoint, the
namespace, the Python path the flows were imported from and the coordinator's ``sys.argv``,
which the worker takes as its own — and starts one worker per node. A worker process goes
through these phases, each a function (here, or in the module of this package the list below
the phases names):

    main             the command line and the process's key → a :class:`Launch`; a thread
                     watches the parent from then on (watch_parent)
    serve            prepare_process (die with the parent, keep freed memory, signals for stacks)
      read_spec        the spec, its Python path and argv
      open_session     the Zenoh peer, the statuses it signs (StatusSender)
      build            the flow rebuilt and wired (build_loop, on the transport a Launch names),
                       SIGTERM and PARENT_DIED handled, the flow's setup()
      start            first process: declare, link, say ``ready``, wait for ``start`` {T0, end}
      | join           --join: take over a restarted flow's state when told ``resume``
      | start_afresh   --fresh: a fresh flow on fresh inputs once told ``restarted``
      run              the loop until its end, ``stop``, or a failure
      finish           say ``failed`` / ``handed_over`` / ``done``, release (teardown), wait
                       until the coordinator took every report; the session closes
    exit_process     end the process with the node's exit code

This ``__init__`` keeps the entry point and the phases' order; each phase's work is a module of
its own:

    __main__.py   ``python -m retriever.backends.zenoh.worker``: main() on the command line
    process.py    the OS process: its parent watched, its settings, its exit codes
    build.py      the session, the flow rebuilt and wired from the spec, its setup()
    starts.py     start, join and start_afresh: linked, asked, pooled, ``ready``, the start
    links.py      links to the hub and the neighbours, and the hub's link watched
    waits.py      waits on the coordinator: control, what is finished, reports taken
    ending.py     signals, ``failed``, ``done``, the hand-over, the flow released
    group.py      the process of a group of flows, the same phases over every member

A group of flows (``configure(process=NAME)``, the spec's ``groups``) is served by one process,
``python -m retriever.backends.zenoh.worker.group SPEC.json NAME``, in the same phases over every
member (group.py).

A start by dora (backends/dora/node.py) is the same phases with a :class:`Launch` of its own:
its parent to watch, its key, its loop (events over dora) and its directory.

on_error="restart": the failed worker says ``restart`` and goes on listening (node/handover.py);
the coordinator starts a new worker with ``--join``, which subscribes, says ``ready``
and waits. The coordinator then puts ``handover`` {node}: the old worker writes its loop's state
to ``<run dir>/<node>.handover``, says ``handed_over`` and exits; then ``resume`` {node}: the new
one reads the state and goes on with a fresh flow. A worker process that died (kill -9, a
segfault) has no state to hand over: the coordinator starts one with ``--fresh``, which starts
the flow afresh on fresh inputs once told ``restarted`` (node/handover.py).

A worker exits when its node is done, on ``stop``, on SIGTERM, or when its parent dies; its
session always closes. Every status it sends carries its pid, and every status and report the MAC
of its process's key (origin.py). Exit codes: 0 done or stopped,
1 failed (the status message says why), 3 handed over to a restarted flow, 4 its parent died (it
said nothing: as if killed).
"""

from __future__ import annotations

import os
import sys
import traceback
from collections.abc import Callable
from typing import NoReturn

from ..command import FRESH, JOIN, WORKER_MODULE, parse_command
from ..hub import needs_shared_memory
from ..node import Ending
from ..origin import take_key
from ..protocol import EXIT_ABANDONED, EXIT_FAILED, RunSpec
from ..wire import KeySpace
from .build import Serving, StatusSender, build, node_plan, open_session, set_up_flow
from .ending import finish, handle_signals, release, say_failed
from .links import all_linked, watch_hub_link
from .process import (Launch, Parent, exit_process, let_go_of, no_timer_slack,
                      prepare_process, watch_parent)
from .starts import POOL_PADDING, join, start, start_afresh

#: the node this process serves, once it is a worker: a run started here (a flow's module that
#: runs a pipeline when imported) is refused, or every worker would start a run of its own
serving: str | None = None


def main(argv: list[str], serve_with: Callable[[Launch, RunSpec, set[str]], int] | None = None,
         module: str = WORKER_MODULE) -> NoReturn:
    """``SPEC.json NODE [MODE]``, the command line of ``module`` (command.py): serve the node
    (``serve_with``: what serves it, another module's, such as group.py's), then end the process."""
    key = take_key()  # before any flow code runs (origin.py)
    try:
        command = parse_command(argv, module)
    except ValueError as e:
        print(e, file=sys.stderr, flush=True)
        exit_process(EXIT_FAILED)
    launch = Launch(command.spec_path, command.name, Parent(os.getppid()), key, command.mode)
    watch_parent(launch)
    exit_process(serve(launch, serve_with or _serve_node))


def serve(launch: Launch, serve_with: Callable[[Launch, RunSpec, set[str]], int] | None = None) -> int:
    """Serve one node (``serve_with``: what serves it; default the node's own loop), from this
    process's settings to its session's close: its exit code. A worker whose parent died
    meanwhile also removes the run's folders (the spec and unreported events, in /dev/shm),
    which no one else would."""
    code = EXIT_FAILED
    try:
        if prepare_process():
            pool: set[str] = set()
            code = (serve_with or _serve_node)(launch, read_spec(launch), pool)
            let_go_of(pool)
    except Exception:
        traceback.print_exc()
    finally:
        if launch.parent.gone():
            launch.remove_folders()
    return code


def read_spec(launch: Launch) -> RunSpec:
    """The run's spec; its Python path joins this process's, and its argv becomes ours: the
    coordinator's ``sys.argv``, as multiprocessing gives its children the parent's (a script or
    a flow's module that parses sys.argv when imported must see its own arguments, not this
    worker's, or it parses the wrong ones and exits)."""
    global serving
    serving = launch.node
    spec = RunSpec.read_file(launch.spec_path)
    for path in reversed(spec.python_path):
        if path not in sys.path:
            sys.path.insert(0, path)
    if spec.argv is not None:
        sys.argv = list(spec.argv)
    return spec


def _serve_node(launch: Launch, spec: RunSpec, pool: set[str]) -> int:
    keys = KeySpace(spec.namespace)
    plan = node_plan(spec, launch.node) if spec.links else None
    # a node whose every edge is a same-host link sends nothing big through Zenoh to this host:
    # its session has no shared memory, and makes no pool
    shared_memory = needs_shared_memory(spec.ir, launch.node) and not all_linked(spec, plan, launch.run_dir)
    with open_session(spec, launch.node, launch.mode, shared_memory) as session:
        w = Serving(launch, spec, session, keys, StatusSender(session, keys, launch.node, launch.key),
                    padding=bytes(POOL_PADDING) if shared_memory else None, pool=pool, plan=plan)
        if not build(w):
            return EXIT_FAILED
        try:
            handle_signals([w.loop], launch.parent)
            if not set_up_flow(w):
                return EXIT_FAILED
            return run(w)
        finally:
            release(w.loop, w.node)


def run(w: Serving) -> int:
    """Wait for the start as the mode says, run the loop, and finish: the exit code."""
    loop = w.loop
    wait = {None: start, JOIN: join, FRESH: start_afresh}[w.launch.mode.kind]
    try:
        begin = wait(w)
        if begin is None:  # stopped first
            return 0
        if not loop.virtual:
            no_timer_slack()
        hub_link = watch_hub_link(w.session, w.spec.hub_zid, w.node, routers=list(w.spec.router))
        try:
            loop.run(begin.t0, begin.end, resume=begin.resume)
        finally:
            if hub_link is not None:
                hub_link.undeclare()
        if loop.ending is Ending.ABANDONED:
            loop.undeclare()
            return EXIT_ABANDONED
    except BaseException as exc:  # StopRun (the flow's failure, on_error="stop"), or a crash of the loop
        say_failed(w, exc)
        return EXIT_FAILED
    return finish(w, begin)
