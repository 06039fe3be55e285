"""rmw_zenoh's key expressions: where a topic's samples travel, and the liveliness tokens that
make a node and its publishers and subscriptions visible to ``ros2 node list`` / ``ros2 topic list``.

From rmw_zenoh's ``docs/design.md`` ("Topic and Service name mapping", "Graph Cache") and its
``liveliness_utils.cpp``:

- a topic's samples: ``<domain_id>/<fully qualified name without its leading and trailing
  '/'>/<DDS type name>/<type hash>``, e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``;
- a node: ``@ros2_lv/<domain_id>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<name>``;
- a publisher (``MP``) or subscription (``MS``): the node's chunks with the entity's own id in the
  fifth place, then ``/<topic>/<DDS type name>/<type hash>/<qos>``.

Names inside a token are *mangled*: every ``/`` becomes ``%`` (so ``/`` is a namespace of ``%``
and ``/chatter`` is ``%chatter``), which keeps each name in one chunk. The session id is the Zenoh
session's id as Zenoh prints it (lowercase hex). The DDS type name of ``pkg/msg/Name`` is
``pkg::msg::dds_::Name_``.
"""

from __future__ import annotations

import dataclasses

ADMIN_SPACE = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"

# rmw's QoS enums (rmw/types.h), as the token writes them
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclasses.dataclass(frozen=True)
class QoS:
    """The QoS a token announces. The default is ROS 2's default profile for topics (reliable,
    volatile, keep last 10), which is what ``ros2 topic echo`` and most nodes ask for."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10


#: rmw_zenoh's own defaults (qos.cpp): a token leaves out every value equal to these
_RMW_ZENOH_DEFAULT = QoS(reliability=RELIABLE, durability=TRANSIENT_LOCAL, history=KEEP_LAST, depth=42)


def mangle(name: str) -> str:
    """A ROS name as one chunk of a token: each ``/`` as ``%``."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


def dds_type_name(type_name: str) -> str:
    """``sensor_msgs/msg/Image`` → ``sensor_msgs::msg::dds_::Image_``, the name rmw_zenoh puts in
    key expressions (the name the type has in DDS when encoded in CDR)."""
    package, kind, name = _split_type_name(type_name)
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """The inverse of :func:`dds_type_name`."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"{dds_name!r} is not a DDS type name of the form pkg::msg::dds_::Name_")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _split_type_name(type_name: str) -> tuple[str, str, str]:
    parts = type_name.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"ROS type name {type_name!r}: expected the form package/msg/Name")
    return parts[0], parts[1], parts[2]


def fully_qualified(topic: str, namespace: str = "/") -> str:
    """A topic's fully qualified name: relative names resolve in ``namespace``."""
    if not topic or topic.endswith("/") and topic != "/" or "//" in topic or "~" in topic:
        raise ValueError(f"ROS topic name {topic!r}: expected a name like /chatter or chatter")
    if topic.startswith("/"):
        return topic
    return namespace.rstrip("/") + "/" + topic


def topic_key(domain_id: int, topic: str, type_name: str, type_hash: str) -> str:
    """The key expression a topic's samples travel on."""
    return f"{domain_id}/{fully_qualified(topic).strip('/')}/{dds_type_name(type_name)}/{type_hash}"


def qos_chunk(qos: QoS) -> str:
    """rmw_zenoh's compact QoS: ``reliability:durability:history,depth:deadline:lifespan:liveliness``,
    each value left empty where it equals rmw_zenoh's default; deadline, lifespan and liveliness
    are always the defaults here (infinite, automatic), so they stay empty."""
    def unless_default(name: str) -> str:
        value = getattr(qos, name)
        return "" if value == getattr(_RMW_ZENOH_DEFAULT, name) else str(value)

    return (f"{unless_default('reliability')}:{unless_default('durability')}:"
            f"{unless_default('history')},{unless_default('depth')}:,:,:,,")


@dataclasses.dataclass(frozen=True)
class Node:
    """A ROS node as the graph sees it: the Zenoh session it lives in and its id there."""

    domain_id: int
    session_id: str
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def _chunks(self, entity_id: int, kind: str) -> str:
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.session_id}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.name}")

    def token(self) -> str:
        """The node's own liveliness token (``NN``)."""
        return self._chunks(self.node_id, NODE)

    def endpoint_token(self, kind: str, entity_id: int, topic: str, type_name: str, type_hash: str,
                       qos: QoS = QoS()) -> str:
        """A publisher's (``MP``) or subscription's (``MS``) liveliness token."""
        if kind not in (PUBLISHER, SUBSCRIPTION):
            raise ValueError(f"entity kind {kind!r}: expected {PUBLISHER!r} or {SUBSCRIPTION!r}")
        name = fully_qualified(topic, self.namespace)
        return (f"{self._chunks(entity_id, kind)}/{mangle(name)}/{dds_type_name(type_name)}/{type_hash}/"
                f"{qos_chunk(qos)}")


@dataclasses.dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription read back from its token."""

    kind: str
    domain_id: int
    session_id: str
    node: str
    namespace: str
    topic: str
    type_name: str
    type_hash: str


def parse_endpoint_token(key: str) -> Endpoint | None:
    """The publisher or subscription a token announces; None for a node's token or anything else."""
    chunks = key.split("/")
    if len(chunks) != 13 or chunks[0] != ADMIN_SPACE or chunks[5] not in (PUBLISHER, SUBSCRIPTION):
        return None
    try:
        return Endpoint(kind=chunks[5], domain_id=int(chunks[1]), session_id=chunks[2], node=chunks[8],
                        namespace=demangle(chunks[7]), topic=demangle(chunks[9]),
                        type_name=ros_type_name(chunks[10]), type_hash=chunks[11])
    except ValueError:
        return None
