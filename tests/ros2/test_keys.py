"""rmw_zenoh's key expressions and liveliness tokens, held to the examples of its docs/design.md."""

from __future__ import annotations

import re

import pytest

from retriever.ros2 import Ros2Publisher, Ros2Subscriber
from retriever.ros2.keys import (BEST_EFFORT, KEEP_ALL, PUBLISHER, SUBSCRIPTION, TRANSIENT_LOCAL, Node, QoS,
                                 dds_type_name, fully_qualified, parse_endpoint_token, qos_chunk, ros_type_name,
                                 topic_key)

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


# ---------------------------------------------------------------------------------------------
# ROS 2's rules for names (design.ros2.org/articles/topic_and_service_names.html): a name given
# that breaks one is refused, naming the rule
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("topic, rule", [
    ("", r"must not be empty"),
    ("/joint__states", r"must not contain '__' \(a repeated underscore\)"),
    ("__ns/chatter", r"must not contain '__'"),
    ("/joint_states/", r"must not end with '/'"),
    ("/", r"must not end with '/'"),
    ("/robot//cmd_vel", r"must not contain '//' \(an empty token\)"),
    ("/2d/points", r"a token must not start with a digit \('2d'\)"),
    ("123abc", r"a token must not start with a digit"),
    ("/cmd-vel", r"may hold only ASCII letters, digits, '_' and '/', not '-'"),
    ("/cäm", r"may hold only ASCII letters.*, not 'ä'"),
    ("/foo bar", r"may hold only ASCII letters.*, not ' '"),
    ("~foo", r"'~' stands alone, first: '~' or '~/name'"),
    ("foo/~/bar", r"'~' stands alone, first"),
    ("{robot}/cmd_vel", r"substitutions \('\{robot\}'\) are not expanded here: write the name out"),
])
def test_a_topic_name_ros_2_does_not_allow_is_refused_naming_the_rule(topic, rule):
    message = rf"ROS topic name {re.escape(repr(topic))}: {rule}(.|\n)*hint: .*topic_and_service_names"
    with pytest.raises(ValueError, match=message):
        fully_qualified(topic)
    with pytest.raises(ValueError, match=message):  # where users give it
        Ros2Subscriber(topic, "std_msgs/msg/String", domain_id=0)


@pytest.mark.parametrize("topic, namespace, node, expected", [
    ("joint_states_", "/", "retriever", "/joint_states_"),  # a token may end with '_'
    ("/_hidden/x", "/", "retriever", "/_hidden/x"),  # or start with one: hidden from ROS tools
    ("image", "/robot1/front", "cam", "/robot1/front/image"),
    ("image", "robot1", "cam", "/robot1/image"),  # a relative namespace is in the root one, as rclcpp has it
    ("~", "/robot1", "arm", "/robot1/arm"),  # the node's private namespace
    ("~/status", "/robot1", "arm", "/robot1/arm/status"),
    ("~/status", "/", "arm", "/arm/status"),
])
def test_names_ros_2_allows_resolve_as_ros_does(topic, namespace, node, expected):
    assert Ros2Publisher(topic, "std_msgs/msg/String", node=node, namespace=namespace, domain_id=0).topic == expected


@pytest.mark.parametrize("options, said", [
    ({"node": "my__node"}, r"ROS node name 'my__node': must not contain '__'"),
    ({"node": "my-node"}, r"ROS node name 'my-node': may hold only ASCII letters, digits and '_', not '-'"),
    ({"node": "2nd"}, r"ROS node name '2nd': must not start with a digit"),
    ({"node": ""}, r"ROS node name '': must not be empty"),
    ({"node": "a/b"}, r"ROS node name 'a/b': may hold only ASCII letters, digits and '_', not '/'"),
    ({"namespace": "/robot__1"}, r"ROS namespace '/robot__1': must not contain '__'"),
    ({"namespace": "/robot1/"}, r"ROS namespace '/robot1/': must not end with '/'"),
    ({"namespace": "/1robot"}, r"ROS namespace '/1robot': a token must not start with a digit"),
    ({"namespace": "~/x"}, r"ROS namespace '~/x': may hold only ASCII letters, digits, '_' and '/', not '~'"),
])
def test_a_node_name_or_namespace_ros_2_does_not_allow_is_refused_naming_the_rule(options, said):
    for end in (Ros2Publisher, Ros2Subscriber):
        with pytest.raises(ValueError, match=rf"{said}(.|\n)*hint: .*topic_and_service_names"):
            end("/chatter", "std_msgs/msg/String", domain_id=0, **options)


# ---------------------------------------------------------------------------------------------
# the ROS domain id: the first chunk of every key expression, so only an int 0..232 is taken
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("domain_id", ["0/**", "0", -1, 233, 999, True, False, 1.5, 2.0])
def test_a_domain_id_that_is_not_an_int_from_0_to_232_is_refused_naming_the_fix(domain_id):
    for end in (Ros2Publisher, Ros2Subscriber):
        with pytest.raises(ValueError, match=r"domain_id=.*: a ROS domain id is an int from 0 to 232(.|\n)*"
                                             r"hint: pass domain_id=<0\.\.232> \(an int\), or set ROS_DOMAIN_ID"):
            end("/chatter", "std_msgs/msg/String", domain_id=domain_id)
    with pytest.raises(ValueError, match="a ROS domain id is an int"):
        topic_key(domain_id, "/chatter", "std_msgs/msg/String", STRING_HASH)


@pytest.mark.parametrize("domain_id", [0, 1, 101, 232])
def test_a_domain_id_from_0_to_232_is_taken(domain_id):
    end = Ros2Subscriber("/chatter", "std_msgs/msg/String", domain_id=domain_id)
    assert end.key.startswith(f"{domain_id}/chatter/")


@pytest.mark.parametrize("value", ["0/**", "-1", "233", "1.5", "²", "0x10", "abc"])
def test_a_ros_domain_id_from_the_environment_out_of_range_is_refused_naming_the_fix(value, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    with pytest.raises(ValueError, match=r"ROS_DOMAIN_ID=.*: a ROS domain id is a decimal number from 0 to 232"
                                         r"(.|\n)*hint: set ROS_DOMAIN_ID to one"):
        Ros2Subscriber("/chatter", "std_msgs/msg/String")


@pytest.mark.parametrize("value, domain_id", [("", 0), (" 7 ", 7), ("232", 232)])
def test_a_ros_domain_id_from_the_environment_in_range_is_taken(value, domain_id, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    assert Ros2Subscriber("/chatter", "std_msgs/msg/String").domain_id == domain_id


# ---------------------------------------------------------------------------------------------
# rmw's limits on a name's length (rmw/validate_*.h): refused where the flow is made
# ---------------------------------------------------------------------------------------------
def test_names_up_to_rmws_limits_are_taken():
    assert len(fully_qualified("/" + "t" * 246)) == 247  # RMW_TOPIC_MAX_NAME_LENGTH = 255 - 8
    end = Ros2Publisher("/x", "std_msgs/msg/String", node="n" * 255, namespace="/" + "s" * 244, domain_id=0)
    assert len(end.node_name) == 255 and len(end.namespace) == 245


@pytest.mark.parametrize("options, said", [
    ({"topic": "/" + "t" * 247}, r"ROS topic name '/t{39}\.\.\.': is 248 characters long, past the 247 rmw takes"),
    ({"topic": "t" * 200, "namespace": "/" + "s" * 50},  # long only once resolved in its namespace
     r"ROS topic name 't{40}\.\.\.': is 252 characters long \(resolved: 252 characters\), past the 247"),
    ({"topic": "~/" + "t" * 200, "node": "n" * 50},
     r"ROS topic name '~/t{38}\.\.\.': is 252 characters long \(resolved: 252 characters\), past the 247"),
    ({"node": "n" * 256}, r"ROS node name 'n{40}\.\.\.': is 256 characters long, past the 255 rmw takes"),
    ({"namespace": "/" + "s" * 245}, r"ROS namespace '/s{39}\.\.\.': is 246 characters long, past the 245 rmw takes"),
])
def test_a_name_past_rmws_limit_is_refused_where_the_flow_is_made(options, said):
    """They were taken, and rmw_zenoh's nodes would not see (or refuse) the topic."""
    topic = options.pop("topic", "/chatter")
    for end in (Ros2Publisher, Ros2Subscriber):
        with pytest.raises(ValueError, match=rf"{said}(.|\n)*hint: .*topic_and_service_names"):
            end(topic, "std_msgs/msg/String", domain_id=0, **options)
