"""A ROS 2 node as rmw_zenoh's graph sees it: one Zenoh session, its node token, and a token per
publisher and subscription (keys.py says their form).

A :class:`Ros2Node` is what a flow's ``setup()`` opens and its ``teardown()`` closes. Its session
is a Zenoh peer that connects to rmw_zenoh's router (``rmw_zenohd``, ``tcp/localhost:7447`` by
default, as a ROS node's own session does), scouts by nothing else, and listens on loopback for
the peer-to-peer links the router's gossip sets up between the nodes of one machine.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections.abc import Sequence

import zenoh

from ..errors import RetrieverWarning
from .keys import MAX_DOMAIN_ID, Node, QoS, check_domain_id, check_namespace, check_node_name

#: where rmw_zenoh's router listens, and where a ROS node's session connects, by default
ROS_ROUTER = "tcp/localhost:7447"
#: how long a new node waits for its first link (to the router, or a peer) before it warns
LINK_WAIT_S = 1.0


def domain_id_from_env() -> int:
    """``ROS_DOMAIN_ID``, as ROS reads it (0 when unset)."""
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not value:
        return 0
    # ASCII decimal digits only (str.isdigit also takes '²' and other scripts' digits)
    number = int(value) if value.isascii() and value.isdigit() else -1
    if not 0 <= number <= MAX_DOMAIN_ID:
        raise ValueError(f"ROS_DOMAIN_ID={value!r}: a ROS domain id is a decimal number from 0 to "
                         f"{MAX_DOMAIN_ID}\n"
                         f"    hint: set ROS_DOMAIN_ID to one (export ROS_DOMAIN_ID=0), or unset it for domain 0, "
                         "or pass domain_id=<int> to the flow")
    return number


def session_config(connect: Sequence[str], listen: Sequence[str]) -> zenoh.Config:
    """A peer that connects to ``connect``, listens on ``listen`` and scouts by gossip only."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def gid(token: str) -> bytes:
    """An entity's 16-byte GID, from its liveliness token: stable for the entity and unique to it.
    rmw_zenoh derives its own from the token too (XXH3-128); a GID is only ever compared, so any
    hash that keeps those two properties serves."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()


class Ros2Node:
    """A Zenoh session that is a ROS node: ``declare`` its endpoints, ``close`` it all."""

    def __init__(self, name: str, *, namespace: str = "/", domain_id: int = 0,
                 connect: Sequence[str] = (ROS_ROUTER,), listen: Sequence[str] = ("tcp/127.0.0.1:0",)):
        name, namespace = check_node_name(name), check_namespace(namespace)  # before the session opens
        domain_id = check_domain_id(domain_id)
        self.session = zenoh.open(session_config(list(connect), list(listen)))
        self.node = Node(domain_id, str(self.session.info.zid()), 0, name, namespace)
        self._tokens = [self.session.liveliness().declare_token(self.node.token())]
        self._next_id = 1
        if not self.wait_linked(LINK_WAIT_S):
            warnings.warn(
                f"ROS 2 node '{name}' is linked to nothing {LINK_WAIT_S:g} s after it connected to "
                f"{', '.join(connect)}: no Zenoh router answers there, so it sees no topic and none sees its own "
                "(a peer session goes on trying to connect)\n"
                "    hint: start rmw_zenoh's router on this machine (ros2 run rmw_zenoh_cpp rmw_zenohd), or pass "
                "connect=[...] with where one listens", RetrieverWarning, stacklevel=3)

    def linked(self) -> bool:
        """Whether the session has a link: to a router (rmw_zenohd) or to a peer."""
        info = self.session.info
        return bool(list(info.routers_zid()) or list(info.peers_zid()))

    def wait_linked(self, timeout: float) -> bool:
        """Whether the session is linked within ``timeout`` s (Zenoh opens a peer's configured
        links as it opens the session: one that answers is up at once)."""
        give_up = time.monotonic() + timeout
        while not self.linked():
            if time.monotonic() >= give_up:
                return False
            time.sleep(0.01)
        return True

    def declare(self, kind: str, topic: str, type_name: str, type_hash: str, qos: QoS = QoS()) -> str:
        """Announce a publisher (``MP``) or subscription (``MS``); returns its token's key."""
        key = self.node.endpoint_token(kind, self._next_id, topic, type_name, type_hash, qos)
        self._next_id += 1
        self._tokens.append(self.session.liveliness().declare_token(key))
        return key

    def close(self) -> None:
        for token in reversed(self._tokens):
            token.undeclare()
        self._tokens.clear()
        self.session.close()
