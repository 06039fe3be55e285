"""A dora node's process: one flow of a dora run, or a group of flows (``configure(process=)``),
served as the zenoh backend's worker serves one, or its group worker a group.

    python -m retriever.backends.dora.node SPEC.json DORA_ID       (dataflow.py writes this line)

dora starts it; the zenoh worker's phases (backends/zenoh/worker/; a group's: worker/group.py)
serve it, from a :class:`~retriever.backends.zenoh.worker.Launch` made here:

    node       the node whose dora id is DORA_ID, or the group whose is (the spec's ``dora`` part:
               protocol.DoraPart, and its ``groups``)
    parent     the coordinator, which is not this process's parent (dora's daemon is): ``adopted``
    key        the one the coordinator wrote for the node or group in the private spec (origin.py)
    transport  each node's events and progress over the process's dora node (:func:`transport_maker`)
    folders    dora's directory, removed with the run's once the coordinator is gone

Before that, the process says what a child of the coordinator would say by being one: its pid in
``<node>.pid`` (a group's: ``<group>.pid``) of the run's directory, its output in the named pipes
``<dora id>.stdout`` and ``.stderr`` there (the coordinator reads them: host.py), and, at its end,
its exit code in ``<node>.exit`` (``<group>.exit``). It works in the coordinator's directory, as a
child would.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable
from pathlib import Path

from ...errors import WireError
from ..zenoh import worker
from ..zenoh.command import DORA_NODE_MODULE, parse_command
from ..zenoh.folders import DORA_FOLDER
from ..zenoh.protocol import RunSpec, Stream
from ..zenoh.worker.group import serve_group
from .dataflow import DoraNames

#: dora's own directory (its logs) is named so; only such a directory is removed
DORA_DIR_PREFIX = f"{DORA_FOLDER}-"


def main(argv: list[str]) -> None:
    """``SPEC.json DORA_ID`` (zenoh/command.py): serve that node, then end the process."""
    try:
        command = parse_command(argv, DORA_NODE_MODULE)
    except ValueError as e:
        print(e, file=sys.stderr, flush=True)
        worker.exit_process(worker.EXIT_FAILED)
    spec_path, dora_id = command.spec_path, command.name
    spec = RunSpec.read_file(spec_path)
    dora = spec.dora_part
    if dora is None:
        raise WireError(f"the run's spec {spec_path} has no dora part: no dora run's coordinator wrote it")
    names = DoraNames.of_part(dora)
    members = names.members(dora_id)
    group = next((name for name, nodes in spec.groups.items() if members[0] in nodes), None)
    process = members[0] if group is None else group  # what the coordinator knows the process by
    dora_dir = Path(dora.dir)
    launch = worker.Launch(spec_path, process, worker.Parent(dora.coordinator, adopted=True), dora.keys.get(members[0]),
                           transport=transport_maker(names),
                           folders=(dora_dir,) if dora_dir.name.startswith(DORA_DIR_PREFIX) else ())
    worker.watch_parent(launch)  # first: a named pipe's open waits for its reader, which may be dead
    run_dir = spec_path.parent
    (run_dir / f"{process}.pid").write_text(str(os.getpid()))
    _output_to_pipes(run_dir, dora_id)
    os.chdir(dora.cwd)
    code = worker.serve(launch, None if group is None else serve_group)
    with contextlib.suppress(OSError):  # gone with the run's directory when the coordinator is
        (run_dir / f"{process}.exit").write_text(str(code))
    worker.exit_process(code)


def transport_maker(names: DoraNames) -> Callable:
    """``(session, node) -> DoraTransport``: a node's events and progress over this process's
    one dora node (shared by a group's members). The one place a dora node's transport is made."""
    from .link import DoraLink, DoraTransport

    link = DoraLink()
    return lambda session, node: DoraTransport(link, names, node)


def _output_to_pipes(run_dir: Path, dora_id: str) -> None:
    """This process's stdout and stderr to the coordinator, which reads them (host.py)."""
    for fd, stream in ((1, Stream.STDOUT), (2, Stream.STDERR)):
        with contextlib.suppress(OSError):
            pipe = os.open(run_dir / f"{dora_id}.{stream}", os.O_WRONLY)
            os.dup2(pipe, fd)
            os.close(pipe)


if __name__ == "__main__":
    main(sys.argv[1:])
