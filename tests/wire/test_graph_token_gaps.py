# SPDX-License-Identifier: Apache-2.0
"""ROS graph liveliness tokens (``pugsd.wire.graph``, ``pugsd.wire.topics``) beyond the root
namespace and node 0: goldens written by hand from the ecosystem spec (section 2.1:
``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<ns>/<node>``, then for
endpoints ``/<topic>/<type>/<hash>/<qos>``, every ``/`` inside a segment written ``%``), the QoS
adaptation field by field, and the tokens that must be refused."""

from __future__ import annotations

import dataclasses

import pytest

from pugsd.daemon.config import TopicsConfig
from pugsd.errors import ConfigError, DecodeError
from pugsd.wire import graph
from pugsd.wire.graph import (
    DURATION_INFINITE,
    RMW_ZENOH_DEFAULT_QOS,
    GraphToken,
    QosProfile,
    endpoint_token,
    node_name_problem,
    node_token,
    parse_token,
)
from pugsd.wire.topics import (
    PUBLISHER_QOS,
    SUBSCRIPTION_QOS,
    full_topic_name,
    key_for,
    ros_graph_tokens,
    subscribe_key_for,
)
from pugsd.wire.types import GRASP_ARRAY, POSE_STAMPED, type_hash

ZID = "1f2e3d4c5b6a79880123456789abcdef"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"
QOS_DEFAULT = "::,10:,:,:,,"  # rmw_qos_profile_default with rmw_zenoh's defaults left empty


def test_a_node_in_a_namespace_with_its_own_number() -> None:
    tok = node_token(3, ZID, 7, "cam_node", namespace="/robot/left", enclave="/secure")
    assert tok == f"@ros2_lv/3/{ZID}/7/7/NN/%secure/%robot%left/cam_node"
    assert parse_token(tok) == GraphToken(3, ZID, "7", "7", "NN", "/secure", "/robot/left", "cam_node")


def test_endpoints_of_every_kind_name_their_node_and_their_own_number() -> None:
    qos = dataclasses.replace(graph.QOS_PROFILE_DEFAULT).adapted()
    for kind in (graph.PUBLISHER, graph.SUBSCRIPTION, graph.SERVICE, graph.CLIENT):
        tok = endpoint_token(kind, 0, ZID, 4, 11, "talker", "/ns/chatter", STRING_DDS, STRING_HASH,
                             qos, namespace="/ns")  # fmt: skip
        assert tok == (
            f"@ros2_lv/0/{ZID}/4/11/{kind}/%/%ns/talker/%ns%chatter/{STRING_DDS}/{STRING_HASH}/"
            + QOS_DEFAULT
        )
        p = parse_token(tok)
        assert (p.nid, p.id, p.kind, p.enclave, p.namespace, p.topic) == (
            "4", "11", kind, "/", "/ns", "/ns/chatter")  # fmt: skip
        assert p.qos == dataclasses.replace(RMW_ZENOH_DEFAULT_QOS, depth=10)
    with pytest.raises(ValueError, match="not an endpoint kind"):
        endpoint_token(graph.NODE, 0, ZID, 4, 11, "talker", "/chatter", STRING_DDS, STRING_HASH, qos)


def test_a_segment_that_would_split_the_token_is_refused() -> None:
    """Names are mangled, but the session id is written as given: a ``/`` in it would shift every
    later segment, and an empty one leaves ``//`` that no reader parses."""
    with pytest.raises(ValueError, match="unmangled"):
        node_token(0, "ab/cd", 0, "n")
    with pytest.raises(ValueError, match="empty segment"):
        node_token(0, "", 0, "n")


_CHATTER = f"%chatter/{STRING_DDS}/{STRING_HASH}"


@pytest.mark.parametrize(
    "bad",
    [
        f"@ros2_lv/x/{ZID}/0/0/NN/%/%/n",  # the domain is not a number
        f"@ros2_lv/-1/{ZID}/0/0/NN/%/%/n",
        "@ros2_lv/0//0/0/NN/%/%/n",  # an empty segment (the zid)
        f"@ros2_lv/0/{ZID}/0/0/NN/%//n",
        f"@ros2_lv/0/{ZID}/0/0/NN/%/%/n/{_CHATTER}/{QOS_DEFAULT}",  # a node with a topic
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/n",  # a publisher without one
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/n/{_CHATTER}/1,2::,:,:,:,,",  # two numbers for the reliability
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/n/{_CHATTER}/:2,1:,:,:,:,,",  # ... for the durability
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/n/{_CHATTER}/x::,:,:,:,,",  # not a number
    ],
)
def test_parse_token_refuses(bad: str) -> None:
    with pytest.raises(DecodeError):
        parse_token(bad)


def test_adapted_keeps_every_field_that_was_set() -> None:
    """rmw_zenoh's best_available_qos replaces only what was left to the system (kind 0, depth 0,
    an unspecified duration); a field that was set is written as set."""
    full = QosProfile(
        reliability=graph.RELIABILITY_BEST_EFFORT, durability=graph.DURABILITY_TRANSIENT_LOCAL,
        history=graph.HISTORY_KEEP_ALL, depth=3, deadline=(1, 500), lifespan=(2, 0),
        liveliness=graph.LIVELINESS_MANUAL_BY_TOPIC, liveliness_lease_duration=(0, 250),
    )  # fmt: skip
    assert full.adapted() == full
    assert QosProfile().adapted() == RMW_ZENOH_DEFAULT_QOS
    # one field set at a time: that field kept, the rest rmw_zenoh's
    for field in dataclasses.fields(QosProfile):
        one = dataclasses.replace(QosProfile(), **{field.name: getattr(full, field.name)})
        want = dataclasses.replace(RMW_ZENOH_DEFAULT_QOS, **{field.name: getattr(full, field.name)})
        assert one.adapted() == want, field.name
    assert RMW_ZENOH_DEFAULT_QOS.deadline == DURATION_INFINITE


def test_node_names_ros_accepts() -> None:
    assert node_name_problem("a" * 255) is None and node_name_problem("_n2") is None
    for bad in ("a" * 256, "2node", "", "pugs-d", "ns/node", "n%"):
        assert node_name_problem(bad) is not None, bad


def test_tokens_for_chosen_roles_are_numbered_in_order_after_the_node() -> None:
    """A node that publishes only grasps and subscribes only to the pose: entities 0 (the node),
    1 (the publisher), 2 (the subscription), as rmw_zenoh numbers a context's entities."""
    t = TopicsConfig(pose_type="PoseStamped")
    g = ros_graph_tokens(t, "pugsd", ZID, outputs=("grasps",), inputs=("pose",))
    assert g.all() == [
        f"@ros2_lv/0/{ZID}/0/0/NN/%/%/pugsd",
        f"@ros2_lv/0/{ZID}/0/1/MP/%/%/pugsd/%pugs%grasps/pugs_msgs::msg::dds_::GraspArray_/"
        f"{type_hash(GRASP_ARRAY)}/1:2:1,10:9223372036,854775807:9223372036,854775807:1,9223372036,854775807",
        f"@ros2_lv/0/{ZID}/0/2/MS/%/%/pugsd/%camera_pose/geometry_msgs::msg::dds_::PoseStamped_/"
        f"{type_hash(POSE_STAMPED)}/2:2:1,10:9223372036,854775807:9223372036,854775807:1,9223372036,854775807",
    ]
    assert parse_token(g.publishers["grasps"]).qos == PUBLISHER_QOS
    assert parse_token(g.subscriptions["pose"]).qos == SUBSCRIPTION_QOS


def test_no_tokens_are_built_for_topics_ros_would_refuse() -> None:
    with pytest.raises(ConfigError, match="no ROS graph tokens"):
        ros_graph_tokens(TopicsConfig(), "2pugsd", ZID)
    with pytest.raises(ConfigError, match="no ROS graph tokens"):
        ros_graph_tokens(TopicsConfig(hash_mode="humble"), "pugsd", ZID)


def test_role_keys_follow_every_topics_setting() -> None:
    t = TopicsConfig(domain_id=9, hash_mode="humble", grasps="/arm/grasps")
    assert key_for(t, "grasps") == "9/arm/grasps/pugs_msgs::msg::dds_::GraspArray_/TypeHashNotSupported"
    # the type can be overridden (a pose published as PoseStamped)
    assert key_for(t, "pose", POSE_STAMPED) == (
        "9/camera_pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported"
    )
    assert subscribe_key_for(t, "pose") == "9/camera_pose/*/*"
    assert full_topic_name("pugs/grasps/") == "/pugs/grasps"
    with pytest.raises(ConfigError):
        full_topic_name("/pugs//grasps")
