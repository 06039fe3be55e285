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


#: where ROS 2's rules for names are written; a name that breaks one is refused, naming it
NAME_RULES = "https://design.ros2.org/articles/topic_and_service_names.html"


#: the longest names rmw takes (rmw/validate_full_topic_name.h, validate_node_name.h,
#: validate_namespace.h): a fully qualified topic of 255 - 8 characters (8 are kept for the
#: prefixes a DDS rmw adds), a node name of 255, a namespace of the topic's less 2 (room for '/X')
MAX_TOPIC_LENGTH = 255 - 8
MAX_NODE_NAME_LENGTH = 255
MAX_NAMESPACE_LENGTH = MAX_TOPIC_LENGTH - 2


def _shown(name: str) -> str:
    """A name as an error says it: its start only, if long."""
    return name if len(name) <= 60 else name[:40] + "..."


def _too_long(name: str, most: int, resolved: str = "") -> str:
    shown = f" (resolved: {len(resolved)} characters)" if resolved and resolved != name else ""
    return (f"is {len(resolved or name)} characters long{shown}, past the {most} rmw takes "
            "(RMW_TOPIC_MAX_NAME_LENGTH etc.): shorten it")


def _name_error(what: str, name: str, rule: str) -> ValueError:
    return ValueError(f"{what} {name!r}: {rule}\n    hint: ROS 2's rules for names are in {NAME_RULES}")


def _path_problem(name: str, extra: str = "") -> str | None:
    """What is wrong with ``name`` as ``/``-separated tokens (ROS 2's rules; ``extra``: other
    characters allowed, already checked by the caller), or None: only ASCII letters, digits,
    ``_`` and ``/``; no ``__``, no ``//``, no ``/`` at the end, no token that starts with a digit.
    A token may start or end with ``_`` (a leading one hides it from ROS tools)."""
    if not name:
        return "must not be empty"
    bad = next((c for c in name if not (c.isascii() and (c.isalnum() or c in "_/" + extra))), None)
    if bad is not None:
        return f"may hold only ASCII letters, digits, '_' and '/', not {bad!r}"
    if "__" in name:
        return "must not contain '__' (a repeated underscore)"
    if name.endswith("/"):
        return "must not end with '/'"
    if "//" in name:
        return "must not contain '//' (an empty token)"
    token = next((t for t in name.split("/") if t[:1].isdigit()), None)
    if token is not None:
        return f"a token must not start with a digit ({token!r})"
    return None


def check_node_name(name: str) -> str:
    """``name`` if ROS 2 allows it as a node's name (ASCII letters, digits and ``_``, not
    starting with a digit, no ``__``), else a ValueError naming the rule it breaks."""
    if not isinstance(name, str) or not name:
        raise _name_error("ROS node name", name, "must not be empty")
    bad = next((c for c in name if not (c.isascii() and (c.isalnum() or c == "_"))), None)
    if bad is not None:
        raise _name_error("ROS node name", name, f"may hold only ASCII letters, digits and '_', not {bad!r}")
    if "__" in name:
        raise _name_error("ROS node name", name, "must not contain '__' (a repeated underscore)")
    if name[0].isdigit():
        raise _name_error("ROS node name", name, "must not start with a digit")
    if len(name) > MAX_NODE_NAME_LENGTH:
        raise _name_error("ROS node name", _shown(name), _too_long(name, MAX_NODE_NAME_LENGTH))
    return name


def check_namespace(namespace: str) -> str:
    """``namespace`` as the absolute namespace ROS makes of it (a relative one is in the root
    namespace, as rclcpp and rclpy have it: ``robot1`` is ``/robot1``; ``""`` is ``/``), or a
    ValueError naming the rule it breaks."""
    absolute = namespace if namespace.startswith("/") else "/" + namespace
    problem = None if absolute == "/" else _path_problem(absolute)
    if problem is not None:
        raise _name_error("ROS namespace", namespace, problem)
    if len(absolute) > MAX_NAMESPACE_LENGTH:
        raise _name_error("ROS namespace", _shown(namespace), _too_long(namespace, MAX_NAMESPACE_LENGTH, absolute))
    return absolute


def fully_qualified(topic: str, namespace: str = "/", node: str | None = None) -> str:
    """A topic's fully qualified name: a relative name resolves in ``namespace``, and ``~`` (the
    private namespace, first and alone: ``~`` or ``~/name``) is ``namespace/node``. A ValueError
    names the rule of ROS 2 a name breaks; substitutions (``{...}``) are refused, not expanded."""
    what = "ROS topic name"
    if "{" in topic or "}" in topic:
        start = topic.find("{")
        shown = topic[start:topic.find("}", start) + 1] if start >= 0 and "}" in topic[start:] else topic
        raise _name_error(what, topic, f"substitutions ({shown!r}) are not expanded here: write the name out")
    problem = _path_problem(topic, extra="~")
    if problem is None and "~" in topic and not (topic == "~" or topic.startswith("~/") and "~" not in topic[1:]):
        problem = "'~' stands alone, first: '~' or '~/name' (the node's private namespace)"
    if problem is not None:
        raise _name_error(what, topic, problem)
    namespace = check_namespace(namespace)
    if topic.startswith("~"):
        if node is None:
            raise _name_error(what, topic, "'~' is the node's private namespace: it needs the node's name")
        full = namespace.rstrip("/") + "/" + check_node_name(node) + topic[1:]
    elif topic.startswith("/"):
        full = topic
    else:
        full = namespace.rstrip("/") + "/" + topic
    if len(full) > MAX_TOPIC_LENGTH:
        raise _name_error(what, _shown(topic), _too_long(topic, MAX_TOPIC_LENGTH, full))
    return full


#: the largest ROS domain id: ROS 2's documented range is 0 to 232 (DDS maps a domain to UDP
#: ports, and 232 is the last whose ports fit; rmw_zenoh keeps the same range so one
#: ROS_DOMAIN_ID means one thing on every rmw)
MAX_DOMAIN_ID = 232


def check_domain_id(domain_id: object, where: str = "domain_id") -> int:
    """``domain_id`` if it is an int (not a bool) from 0 to :data:`MAX_DOMAIN_ID`, else a
    ValueError that names the fix. It becomes the first chunk of every key expression, so a
    string such as ``"0/**"`` would make a wildcard: only an int is taken."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ValueError(f"{where}={domain_id!r}: a ROS domain id is an int from 0 to {MAX_DOMAIN_ID}\n"
                         f"    hint: pass domain_id=<0..{MAX_DOMAIN_ID}> (an int), or set ROS_DOMAIN_ID "
                         "to one, as the ROS nodes you talk to have it")
    return domain_id


def topic_key(domain_id: int, topic: str, type_name: str, type_hash: str) -> str:
    """The key expression a topic's samples travel on."""
    return f"{check_domain_id(domain_id)}/{fully_qualified(topic).strip('/')}/{dds_type_name(type_name)}/{type_hash}"


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
