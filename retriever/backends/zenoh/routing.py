"""What a Zenoh session in router mode is opened with: its access control and its config.

Two kinds of router open one: ``retriever router`` (router.py), which serves the namespaces it
was told for as long as it runs, and a worker daemon's router for one run (daemon/run_router.py,
a process of its own: daemon/router_process.py), which its flows join in place of the remote
router, so that their edges on that machine stay on it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import zenoh

from .access import ROUTER_USER, WATCHER_MAY_NOT, TlsFiles, run_user, watch_user
from .hub import ACCEPT_TIMEOUT_S, accept_pending
from .wire import KeySpace

#: every kind of message Zenoh's access control tells apart
ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "liveliness_query", "declare_liveliness_subscriber")

#: A router forwards shared memory between clients on its host only if it maps their pools, and
#: a process keeps every pool it mapped until it exits (hub.HUB_SHARED_MEMORY): a router that
#: outlives many runs (``retriever router``) would hold all of their flows' pools in /dev/shm.
#: So its links carry every message over TCP.
ROUTER_SHARED_MEMORY = False
#: A worker daemon's router for one run is a process of that run's (daemon/router_process.py),
#: which exits with it and lets go of its flows' pools then: between two flows of its machine a
#: big message goes through shared memory (benchmarks/reports/router.md §4).
RUN_ROUTER_SHARED_MEMORY = True


def access_control(namespaces: Iterable[str], router_ids: Iterable[str] = ()) -> dict:
    """A router's access control: deny by default; per namespace, its run user everything on
    its keys, its watcher access.py's read-only share; the routers linked to (by their user when
    they connect here, by ``router_ids`` when this router connects to them) every served key."""
    rules, subjects, policies = [], [{"id": "routers", "usernames": [ROUTER_USER]}], []
    served = []
    for ns in namespaces:
        keys = KeySpace(ns)
        own = keys.everything()
        served.append(own)
        rules += [{"id": f"run:{ns}", "messages": list(ALL_MESSAGES), "flows": ["ingress", "egress"],
                   "permission": "allow", "key_exprs": [own]},
                  {"id": f"watch-sends:{ns}", "messages": [m for m in ALL_MESSAGES if m not in WATCHER_MAY_NOT],
                   "flows": ["ingress"], "permission": "allow", "key_exprs": [own]},
                  {"id": f"watch-gets:{ns}", "messages": list(ALL_MESSAGES), "flows": ["egress"],
                   "permission": "allow", "key_exprs": [own]},
                  {"id": f"watch-sees-no-control:{ns}", "messages": ["put", "delete"], "flows": ["egress"],
                   "permission": "deny", "key_exprs": [keys.ctl("**")]}]
        subjects += [{"id": f"run:{ns}", "usernames": [run_user(ns)]},
                     {"id": f"watch:{ns}", "usernames": [watch_user(ns)]}]
        policies += [{"rules": [f"run:{ns}"], "subjects": [f"run:{ns}"]},
                     {"rules": [f"watch-sends:{ns}", f"watch-gets:{ns}", f"watch-sees-no-control:{ns}"],
                      "subjects": [f"watch:{ns}"]}]
    rules.append({"id": "routers", "messages": list(ALL_MESSAGES), "flows": ["ingress", "egress"],
                  "permission": "allow", "key_exprs": served})
    policies.append({"rules": ["routers"], "subjects": ["routers"]})
    if router_ids := list(router_ids):
        subjects.append({"id": "linked", "zids": router_ids})
        policies.append({"rules": ["routers"], "subjects": ["linked"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_session_config(*, listen: Iterable[str], connect: Iterable[str], user: str, password: str,
                          dictionary_file: Path, access: dict, tls: TlsFiles | None, lease: float | None,
                          max_sessions: int, shared_memory: bool = ROUTER_SHARED_MEMORY) -> zenoh.Config:
    """Router mode on ``listen``, linked to the routers at ``connect`` proving ``user`` and
    ``password``, checking every link to it against ``dictionary_file`` and every message against
    ``access`` (access_control); mutual TLS on its ``tls/`` links with ``tls``; ``lease``: seconds
    (None: Zenoh's 10 s); at most ``max_sessions`` links at once; ``shared_memory``: whether its
    links on this host carry big messages through the senders' shared-memory pools (see
    ROUTER_SHARED_MEMORY)."""
    config = zenoh.Config()
    entries = {
        "mode": "router",
        "listen/endpoints": list(listen),
        "connect/endpoints": list(connect),
        "connect/retry": {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2},
        "scouting/multicast/enabled": False,
        "transport/unicast/max_sessions": max_sessions,
        # strangers' idle connections must not keep the deployments' links out (hub.ACCEPT_TIMEOUT_S)
        "transport/unicast/accept_timeout": round(ACCEPT_TIMEOUT_S * 1000),
        "transport/unicast/accept_pending": accept_pending(),
        "transport/shared_memory/enabled": shared_memory,
        "transport/auth/usrpwd": {"user": user, "password": password, "dictionary_file": str(dictionary_file)},
        "access_control": access,
    }
    if lease is not None:
        entries["transport/link/tx/lease"] = round(lease * 1000)
    for key, value in entries.items():
        config.insert_json5(key, json.dumps(value))
    for key, value in (tls.session_config() if tls else {}).items():
        config.insert_json5(key, value)
    return config
