"""ROS 2 topics as sources and sinks of a pipeline, over rmw_zenoh, with no ROS installed
(needs ``pip install 'retriever-robotics[ros2]'``).

rmw_zenoh is ROS 2's Zenoh middleware; this package speaks its conventions itself, learnt from
its ``docs/design.md`` and sources, each in a module of its own:

- ``keys.py``: a topic's key expression (domain, name, DDS type name, type hash) and the
  liveliness tokens that make a node and its endpoints visible to ``ros2 topic list``;
- ``attachment.py``: the sequence number, source timestamp and GID on every sample;
- ``types.py``: messages as Retriever values and back, CDR and RIHS01 type hashes (``rosbags``);
- ``node.py``: a Zenoh session that is a ROS node, with its tokens;
- ``flows.py``: :class:`Ros2Subscriber` (a source) and :class:`Ros2Publisher` (a sink), and
  why a message's event time is its arrival, not its ``header.stamp``.
"""

try:
    import rosbags  # noqa: F401
except ImportError:
    raise ImportError("retriever.ros2 needs rosbags, which is not installed\n"
                      "    hint: pip install 'retriever-robotics[ros2]'") from None

from .flows import MAX_PENDING, MAX_PENDING_BYTES, Ros2Publisher, Ros2Subscriber
from .keys import QoS, topic_key
from .types import from_value, register_msg, to_value, type_hash

__all__ = ["MAX_PENDING", "MAX_PENDING_BYTES", "QoS", "Ros2Publisher", "Ros2Subscriber", "from_value", "register_msg",
           "to_value", "topic_key", "type_hash"]
