"""Discovery: the worker daemons of a namespace that are up, each asked what it is; every
problem with them (a name taken twice, another protocol, a clock too far off) said at once."""

from __future__ import annotations

import sys

import zenoh

from ....errors import BackendError
from ..daemon import QUERY_S, DaemonInfo, credentials, describe
from ..protocol import PROTOCOL_VERSION, DaemonOp, InfoRequest, decode_reply
from ..reach import REFUSES_LINKS, why_no_session
from ..wire import KeySpace, WireError
from ..coordinator.hosting import HostedRun
from .links import Links

#: how long a liveliness get for the namespace's workers waits for answers
DISCOVER_S = 2.0
#: clock offsets between the coordinator and a worker: past the first a warning, past the second
#: (by default) the deployment is refused: Rate ticks and T0 come from each worker's clock
CLOCK_WARN_NS = 1_000_000
CLOCK_REFUSE_NS = 10_000_000


def discover(links: Links, run: HostedRun, max_offset_ns: int) -> dict[str, DaemonInfo]:
    """The namespace's live workers and their info; every problem with them at once (a clock
    past ``max_offset_ns`` off this machine's among them)."""
    hub, keys, namespace = links.control, run.keys, run.namespace
    names = sorted({str(r.ok.key_expr).rsplit("/", 1)[-1]
                    for r in hub.liveliness().get(keys.workers(), timeout=DISCOVER_S) if r.ok})
    # tokens of one key are one to Zenoh: ask each name who answers, every reply kept
    twice = [name for name in names if answering(hub, keys, name) > 1]
    if twice:  # workers that never linked to each other, so neither refused to start
        raise BackendError(f"several workers are named {', '.join(map(repr, twice))} in namespace "
                           f"'{namespace}': a node placed on that name could run twice\n    hint: give each "
                           "worker a name of its own (retriever workers --connect ... lists them), then deploy")
    if not names:
        none_found(links, namespace)
    problems, found = [], {}
    for name in names:
        daemon = describe(hub, namespace, name)
        info = daemon.info
        if daemon.other_protocol is not None:
            protocol, retriever = daemon.other_protocol
            problems.append(f"worker '{name}' speaks protocol {protocol}, this coordinator {PROTOCOL_VERSION}"
                            "\n    hint: install the same Retriever version on both machines "
                            f"(the worker has {retriever or '?'!r:.30})")
        elif info is None:
            problems.append(f"worker '{name}' did not say what it is: {daemon.error}")
        elif daemon.offset_ns is not None and abs(daemon.offset_ns) > max_offset_ns:
            problems.append(f"worker '{name}' (host {info.host}) has a clock {daemon.offset_ns / 1e6:+.3f} ms "
                            f"off this machine's, past {max_offset_ns / 1e6:g} ms\n    hint: sync both "
                            "clocks (chrony or ntpd, or PTP on a robot's LAN), then deploy again")
        else:
            if daemon.offset_ns is not None and abs(daemon.offset_ns) > CLOCK_WARN_NS:
                print(f"retriever: warning: worker '{name}' has a clock {daemon.offset_ns / 1e6:+.3f} ms off "
                      "this machine's", file=sys.stderr, flush=True)
            found[name] = daemon
    if problems:
        raise BackendError("the deployment cannot start:\n" + "\n".join(f"  - {p}" for p in problems))
    return found

def none_found(links: Links, namespace: str) -> None:
    """No worker answered: say why that may be."""
    refusing = [e for e in links.connect if why_no_session(e, credentials(links.tls)) == REFUSES_LINKS]
    if refusing:  # a stranger's idle connections, not the secret (hub.ACCEPT_TIMEOUT_S)
        raise BackendError(f"no worker found in namespace '{namespace}': {', '.join(refusing)}: "
                           f"{REFUSES_LINKS}\n    hint: see who holds connections to it (ss -tn state "
                           "established on the worker), and keep strangers off the workers' ports: a "
                           "firewall, or TLS (docs/security.md)")
    reached = links.router or links.connect or links.listen_at
    raise BackendError(f"no worker is up in namespace '{namespace}' (reached through "
                       f"{', '.join(reached)}), or none holds this --secret"
                       f"{' and TLS certificate' if links.tls else ''}\n    hint: start one on each machine: "
                       f"retriever-worker --name NAME --namespace {namespace} --secret FILE"
                       + (f" --router {links.router[0]}" if links.router else ""))

def answering(hub: zenoh.Session, keys: KeySpace, name: str) -> int:
    """How many daemons answer as worker ``name`` (distinct pids and hosts)."""
    who = set()
    for reply in hub.get(keys.ctl(name), payload=InfoRequest().encode(), timeout=QUERY_S,
                         consolidation=zenoh.ConsolidationMode.NONE):
        try:
            info = decode_reply(reply.ok.payload.to_bytes(), DaemonOp.INFO)
        except (AttributeError, WireError):  # an error reply, garbage, or a daemon of another protocol
            continue
        who.add((info.host, info.pid))
    return len(who)


def package_differences(ours: dict[str, str], theirs: dict[str, str]) -> list[str]:
    """``numpy 2.4.6 here, 2.3.0 there`` for each package of ``ours`` that a worker's info
    (``theirs``, as it answered) has in another version."""
    return [f"{name} {version} here, {theirs[name]:.40} there" for name, version in sorted(ours.items())
            if isinstance(theirs.get(name), str) and theirs[name] != version]
