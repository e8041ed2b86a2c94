# SPDX-License-Identifier: Apache-2.0
"""rmw_zenoh ROS graph liveliness tokens (pugsd.wire.graph, pugsd.wire.topics), against rmw_zenoh's
own examples, and beyond the root namespace and node 0: goldens written by hand from the ecosystem
spec (section 2.1: ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS|SS|SC>/<enclave>/<ns>/
<node>``, then for endpoints ``/<topic>/<type>/<hash>/<qos>``, every ``/`` inside a segment written
``%``), the QoS adaptation field by field, and the tokens that must be refused.

Goldens: the example tokens of ros2/rmw_zenoh ``docs/design.md``
@99a6a2bd10b949052f4f12c5854825dc005e95a5 (demo_nodes_cpp talker/listener, ROS_DOMAIN_ID=2) and
QoS strings derived line by line from ``qos_to_keyexpr`` in
``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` @3411fdec149fe0c932f24d4d79ef908eb81d7482.
"""

from __future__ import annotations

import dataclasses

import pytest

from pugsd.config import config_warnings, load_config_dict
from pugsd.daemon.config import TopicsConfig
from pugsd.errors import ConfigError, DecodeError
from pugsd.wire import graph
from pugsd.wire.graph import (
    DURATION_INFINITE,
    QOS_PROFILE_DEFAULT,
    RMW_ZENOH_DEFAULT_QOS,
    GraphToken,
    QosProfile,
    endpoint_token,
    keyexpr_to_qos,
    node_name_problem,
    node_token,
    parse_token,
    qos_to_keyexpr,
)
from pugsd.wire.keys import dds_type_name, parse_key
from pugsd.wire.publisher import Publisher
from pugsd.wire.topics import (
    INPUT_ROLES,
    OUTPUT_ROLES,
    PUBLISHER_QOS,
    SUBSCRIPTION_QOS,
    full_topic_name,
    graph_tokens_enabled,
    key_for,
    ros_graph_tokens,
    subscribe_key_for,
)
from pugsd.wire.types import GRASP_ARRAY, POSE_STAMPED, STRING, type_hash

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"
# docs/design.md, "Graph Cache", examples using the demo_nodes_cpp package
DESIGN_LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_LISTENER_SUB = (
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
    f"{STRING_DDS}/{STRING_HASH}/::,10:,:,:,,"
)
DESIGN_TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"{STRING_DDS}/{STRING_HASH}/::,7:,:,:,,"
)


def test_design_md_examples() -> None:
    """The tokens rmw_zenoh's design.md shows, rebuilt from their parts: the listener node, its
    subscription (rclcpp QoS(10) = rmw_qos_profile_default) and the talker's publisher (QoS(7))."""
    zid_l, zid_t = "aac3178e146ba6f1fc6e6a4085e77f21", "8b20917502ee955ac4476e0266340d5c"
    assert node_token(2, zid_l, 0, "listener") == DESIGN_LISTENER_NODE
    sub = endpoint_token(graph.SUBSCRIPTION, 2, zid_l, 0, 10, "listener", "/chatter", STRING_DDS,
                         STRING_HASH, QOS_PROFILE_DEFAULT.adapted())  # fmt: skip
    assert sub == DESIGN_LISTENER_SUB
    talker_qos = dataclasses.replace(QOS_PROFILE_DEFAULT, depth=7).adapted()
    pub = endpoint_token(graph.PUBLISHER, 2, zid_t, 0, 10, "talker", "/chatter", STRING_DDS,
                         STRING_HASH, talker_qos)  # fmt: skip
    assert pub == DESIGN_TALKER_PUB
    # pugsd's own type names and hashes are the ones rmw_zenoh writes for std_msgs/String
    assert (dds_type_name(STRING), type_hash(STRING)) == (STRING_DDS, STRING_HASH)


def test_parse_design_md_examples() -> None:
    n = parse_token(DESIGN_LISTENER_NODE)
    assert (n.domain_id, n.zid) == (2, "aac3178e146ba6f1fc6e6a4085e77f21")
    assert (n.nid, n.id, n.kind) == ("0", "0", "NN")
    assert (n.enclave, n.namespace, n.node_name, n.topic, n.qos) == ("/", "/", "listener", None, None)
    p = parse_token(DESIGN_TALKER_PUB)
    assert (p.kind, p.topic, p.dds_type, p.type_hash) == ("MP", "/chatter", STRING_DDS, STRING_HASH)
    assert p.qos == dataclasses.replace(RMW_ZENOH_DEFAULT_QOS, depth=7)
    for bad in (
        "@ros2_lv/2/z/0/0/XX/%/%/listener",  # unknown entity kind
        "ros2_lv/2/z/0/0/NN/%/%/listener",  # wrong admin space
        "@ros2_lv/2/z/0/0/NN/%/%",  # too short
        DESIGN_LISTENER_SUB.rsplit("/", 1)[0],  # endpoint without QoS
        DESIGN_LISTENER_SUB.replace("::,10:", "::,10"),  # 5 QoS policies
    ):
        with pytest.raises(DecodeError):
            parse_token(bad)


def test_qos_keyexpr_field_by_field() -> None:
    """``qos_to_keyexpr``: a field is written only where it differs from rmw_zenoh's default
    (RELIABLE 1, VOLATILE 2, KEEP_LAST 1, depth 42, infinite durations, AUTOMATIC 1)."""
    assert qos_to_keyexpr(RMW_ZENOH_DEFAULT_QOS) == "::,:,:,:,,"
    assert qos_to_keyexpr(QosProfile().adapted()) == "::,:,:,:,,"  # all SYSTEM_DEFAULT, depth 0
    assert qos_to_keyexpr(QOS_PROFILE_DEFAULT.adapted()) == "::,10:,:,:,,"
    full = QosProfile(
        reliability=graph.RELIABILITY_BEST_EFFORT,
        durability=graph.DURABILITY_TRANSIENT_LOCAL,
        history=graph.HISTORY_KEEP_ALL,
        depth=5,
        deadline=(1, 2),
        lifespan=(3, DURATION_INFINITE[1]),
        liveliness=graph.LIVELINESS_MANUAL_BY_TOPIC,
        liveliness_lease_duration=(DURATION_INFINITE[0], 6),
    )
    assert qos_to_keyexpr(full) == "2:1:2,5:1,2:3,:3,,6"
    assert keyexpr_to_qos("2:1:2,5:1,2:3,:3,,6") == full
    assert keyexpr_to_qos("::,:,:,:,,") == RMW_ZENOH_DEFAULT_QOS
    # every field written (pugsd's own tokens): the same profile, whatever the reader's defaults
    explicit = qos_to_keyexpr(QOS_PROFILE_DEFAULT.adapted(), None)
    assert explicit == "1:2:1,10:9223372036,854775807:9223372036,854775807:1,9223372036,854775807"
    assert keyexpr_to_qos(explicit) == QOS_PROFILE_DEFAULT.adapted()
    # rmw_zenoh's graph cache keys endpoints by qos_to_keyexpr of what it parsed: design.md's form
    assert qos_to_keyexpr(keyexpr_to_qos(explicit)) == "::,10:,:,:,,"
    for bad in ("::,10", "::,10:,:,:,", "x::,:,:,:,,", "::,:,:,:,,:"):
        with pytest.raises(DecodeError):
            keyexpr_to_qos(bad)


def test_pugsd_tokens_for_the_default_topics() -> None:
    zid = "cea815bec57ee905781668cc65688b35"
    t = TopicsConfig()
    g = ros_graph_tokens(t, "pugsd", zid, services={"/pugsd/reset": "std_srvs/srv/Trigger"})
    assert g.node == f"@ros2_lv/0/{zid}/0/0/NN/%/%/pugsd"
    inf = "9223372036,854775807"
    assert g.publishers["grasps"] == (
        f"@ros2_lv/0/{zid}/0/1/MP/%/%/pugsd/%pugs%grasps/pugs_msgs::msg::dds_::GraspArray_/"
        "RIHS01_7715ec6b4e950e9ba9250fa33c3980e4f55d5dd91b88c29d6bd0c12bf732308c/"
        f"1:2:1,10:{inf}:{inf}:1,{inf}"
    )
    # the status publisher is design.md's talker with pugsd's session, ids, names and QoS
    status = DESIGN_TALKER_PUB.replace("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/", "")
    status = status.replace("talker/%chatter", "pugsd/%pugs%status").replace("::,7:,:,:,,", "")
    assert g.publishers["status"] == f"@ros2_lv/0/{zid}/0/4/{status}1:2:1,10:{inf}:{inf}:1,{inf}"
    assert g.subscriptions["pose"].endswith(
        f"/0/{1 + len(OUTPUT_ROLES) + 4}/MS/%/%/pugsd/%camera_pose/"
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
        + type_hash("geometry_msgs/msg/PoseWithCovarianceStamped")
        + f"/2:2:1,10:{inf}:{inf}:1,{inf}"
    )
    assert list(g.publishers) == list(OUTPUT_ROLES) and list(g.subscriptions) == list(INPUT_ROLES)
    # a service server after them: the service type and its hash, rmw_qos_profile_services_default
    assert g.services["/pugsd/reset"] == (
        f"@ros2_lv/0/{zid}/0/{1 + len(OUTPUT_ROLES) + len(INPUT_ROLES)}/SS/%/%/pugsd/%pugsd%reset/"
        "std_srvs::srv::dds_::Trigger_/"
        "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f/"
        f"1:2:1,10:{inf}:{inf}:1,{inf}"
    )
    # /tf_static is announced TRANSIENT_LOCAL with a history of one, as tf2's static broadcaster
    tf_static_qos = f"/1:1:1,1:{inf}:{inf}:1,{inf}"
    tf_type = "/%tf_static/tf2_msgs::msg::dds_::TFMessage_/"
    assert g.publishers["tf_static"].endswith(tf_type + type_hash("tf2_msgs/msg/TFMessage") + tf_static_qos)
    ids = [parse_token(k).id for k in g.all()]
    assert ids == [str(i) for i in range(len(ids))]  # one counter, as rmw_zenoh numbers a context
    # each endpoint token names the data key's topic, type and hash (rmw_zenoh's TopicInfo)
    for role, tok in {**g.publishers, **g.subscriptions}.items():
        p, k = parse_token(tok), parse_key(key_for(t, role))
        assert (p.domain_id, p.topic, p.nid, p.node_name) == (k.domain_id, k.topic, "0", "pugsd")
        assert (p.dds_type, p.type_hash) == (dds_type_name(k.typename), k.type_hash)
        if role != "tf_static":
            assert p.qos == (PUBLISHER_QOS if p.kind == "MP" else SUBSCRIPTION_QOS)
    ps = ros_graph_tokens(TopicsConfig(pose_type="PoseStamped", domain_id=5, grasps="/a/b/"), "n_1", "ab")
    assert "/pose" not in ps.subscriptions["pose"] and "::PoseStamped_/" in ps.subscriptions["pose"]
    assert ps.node == "@ros2_lv/5/ab/0/0/NN/%/%/n_1" and "/%a%b/" in ps.publishers["grasps"]


def test_publishers_behave_as_their_token_says(zenoh_pair: tuple[object, object]) -> None:
    """The MP tokens say RELIABLE / VOLATILE / KEEP_LAST: rmw_zenoh declares such a publisher
    RELIABLE with congestion control DROP and no cache, and so does pugsd's Publisher."""
    import zenoh

    a, _ = zenoh_pair
    pub = Publisher(a, key_for(TopicsConfig(), "grasps"))  # type: ignore[arg-type]
    try:
        assert pub._pub.reliability == zenoh.Reliability.RELIABLE
        assert pub._pub.congestion_control == zenoh.CongestionControl.DROP
    finally:
        pub.undeclare()
    assert (PUBLISHER_QOS.reliability, PUBLISHER_QOS.durability) == (1, 2)


def test_modes_and_refusals() -> None:
    assert graph_tokens_enabled(TopicsConfig(), "pugsd")
    assert not graph_tokens_enabled(TopicsConfig(ros_graph_tokens="off"), "pugsd")
    # auto: off where the tokens would describe something else, or names ROS refuses
    assert not graph_tokens_enabled(TopicsConfig(key_style="ros2dds"), "pugsd")
    assert not graph_tokens_enabled(TopicsConfig(hash_mode="humble"), "pugsd")
    assert not graph_tokens_enabled(TopicsConfig(), "pugs-d")
    assert not graph_tokens_enabled(TopicsConfig(grasps="/pugs/2grasps"), "pugsd")
    # on: refused at load time
    for bad in ({"topics": {"ros_graph_tokens": "on", "key_style": "ros2dds"}},
                {"topics": {"ros_graph_tokens": "on", "hash_mode": "humble"}},
                {"topics": {"ros_graph_tokens": "on", "status": "/pugs/st%tus"}},
                {"topics": {"ros_graph_tokens": "on"}, "daemon": {"node_name": "pugs-1"}}):  # fmt: skip
        with pytest.raises(ConfigError, match="ros_graph_tokens = 'on'"):
            load_config_dict(bad)
    assert load_config_dict({"topics": {"ros_graph_tokens": "on"}}).topics.ros_graph_tokens == "on"
    # auto with a name ROS refuses: loads, with a warning saying why pugsd stays out of the graph
    cfg = load_config_dict({"daemon": {"node_name": "pugs-1"}})
    assert any("ros_graph_tokens = 'auto' declares no ROS graph tokens" in w for w in config_warnings(cfg))
    assert not any("ros_graph_tokens" in w for w in config_warnings(load_config_dict({})))
    with pytest.raises(ValueError):
        node_token(0, "ab", 0, "")


ZID = "1f2e3d4c5b6a79880123456789abcdef"
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
