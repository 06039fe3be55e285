"""A deployment: the coordinator (coordinator/), hosted on worker daemons (docs/deploy.md).

    retriever deploy app.py --connect tcp/10.0.0.2:7447 --placement lab.toml --secret lab.key
        │ join the namespace (its control session: Zenoh peer, the namespace's credentials) and
        │ open the run's hub (the credentials of this run alone: access.py), find its workers
        │ (liveliness tokens workers/<name>) and ask each for its info: protocol, labels, load, clock offset
        │ place every node (placement.py: pins, labels, load; a group of flows as one), refuse what cannot be met
        │ prepare each chosen worker (remote.py: the spec; it checks every class it will import)
        │ declare the deployment's liveliness token: a worker stops its flows once it goes
        ▼ from here on as the embedded run: spawn, ready, T0, reports, the log, faults, stop

Two sessions, so that nothing of one run links to the daemons or to another run: the control
session links to the worker daemons alone (prepare, spawn, their events and tokens, ``retriever
status``/``stop``); the hub, whose dictionary holds this run's users alone, listens for the run's
flows, which each daemon points at it (the address it reached that daemon from, the hub's port)
with the run's passwords, derived there from the secret and the run id. With ``--router
ENDPOINT`` every session (the coordinator's, each daemon's, each flow's) is instead a client of
that Zenoh router (router.py), which routes between them: none listens, one coordinator session
does both, and every password is the namespace's (a router's dictionary is fixed when it starts).

A worker that is lost mid-run (its token went) takes its nodes' processes with it; with
``on_worker_loss="replace"`` (the default) each of them starts afresh on another worker that its
placement allows, as a flow whose process died does (node/handover.py); with "stop", or nowhere to go,
the run stops naming the worker.

Deployment, the Hosting, only wires its parts, one concern each::

    core.py        Deployment: the Hosting handed to the coordinator; open_deployment
    links.py       the control session and the run's hub (or one client of the routers), and
                   where each worker's host reaches the hub
    discovery.py   the workers up and their info; a name taken twice, another protocol, a clock off
    book.py        WorkerBook: each daemon found, its host in the run, where each node is placed
    status.py      the queryable that answers retriever status / stop, and their asker
    usage.py       the usage poller: each node's CPU seconds, from its worker
    loss.py        the worker-loss policy: move a lost worker's nodes, wait for it, or stop
    config.py      retriever deploy --config deploy.toml, read and checked
"""

from __future__ import annotations

from .book import WorkerBook, placement_target
from .config import DEPLOY_CONFIG, load_deploy_config
from .core import PHASES, Deployment, open_deployment
from .discovery import CLOCK_REFUSE_NS, CLOCK_WARN_NS, DISCOVER_S, package_differences
from .links import ANY_ADDRESS, JOIN_S
from .loss import WORKER_LOSS
from .status import ask_deployment
from .usage import USAGE_EVERY_S

__all__ = ["ANY_ADDRESS", "CLOCK_REFUSE_NS", "CLOCK_WARN_NS", "DEPLOY_CONFIG", "DISCOVER_S", "JOIN_S", "PHASES",
           "USAGE_EVERY_S", "WORKER_LOSS", "Deployment", "WorkerBook", "ask_deployment", "load_deploy_config",
           "open_deployment", "package_differences", "placement_target"]
