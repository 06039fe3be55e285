"""rmw_zenoh's key expressions and liveliness tokens, held to the examples of its docs/design.md."""

from __future__ import annotations

import pytest

from retriever.ros2.keys import (BEST_EFFORT, KEEP_ALL, PUBLISHER, SUBSCRIPTION, TRANSIENT_LOCAL, Node, QoS,
                                 dds_type_name, parse_endpoint_token, qos_chunk, ros_type_name, topic_key)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_topic_keys_are_the_design_docs_examples():
    assert topic_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert topic_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"


def test_dds_type_names_both_ways():
    assert dds_type_name("sensor_msgs/msg/Image") == "sensor_msgs::msg::dds_::Image_"
    assert ros_type_name("sensor_msgs::msg::dds_::Image_") == "sensor_msgs/msg/Image"
    with pytest.raises(ValueError, match="package/msg/Name"):
        dds_type_name("Image")


def test_tokens_are_the_design_docs_examples():
    listener = Node(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener")
    assert listener.token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert listener.endpoint_token(SUBSCRIPTION, 10, "/chatter", "std_msgs/msg/String", STRING_HASH,
                                   QoS(durability=TRANSIENT_LOCAL, depth=10)) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
    talker = Node(2, "8b20917502ee955ac4476e0266340d5c", 0, "talker")
    assert talker.endpoint_token(PUBLISHER, 10, "/chatter", "std_msgs/msg/String", STRING_HASH,
                                 QoS(durability=TRANSIENT_LOCAL, depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,")


def test_qos_leaves_out_what_equals_rmw_zenohs_defaults():
    assert qos_chunk(QoS()) == ":2:,10:,:,:,,"  # ROS's default profile: reliable, volatile, keep last 10
    assert qos_chunk(QoS(reliability=BEST_EFFORT, durability=TRANSIENT_LOCAL, history=KEEP_ALL, depth=42)) == \
        "2::2,:,:,:,,"


def test_a_namespaced_node_mangles_its_namespace_and_resolves_relative_topics_in_it():
    node = Node(0, "ab", 3, "cam", namespace="/robot1/front")
    token = node.endpoint_token(PUBLISHER, 4, "image", "sensor_msgs/msg/Image", "RIHS01_x")
    assert token.startswith("@ros2_lv/0/ab/3/4/MP/%/%robot1%front/cam/%robot1%front%image/")
    endpoint = parse_endpoint_token(token)
    assert (endpoint.kind, endpoint.namespace, endpoint.topic, endpoint.type_name) == \
        (PUBLISHER, "/robot1/front", "/robot1/front/image", "sensor_msgs/msg/Image")
    assert parse_endpoint_token(node.token()) is None
