# SPDX-License-Identifier: Apache-2.0
"""The daemon's topics (``[topics]`` config) with their message types and zenoh keys."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pugsd.errors import ConfigError
from pugsd.wire.graph import (
    DURABILITY_TRANSIENT_LOCAL,
    PUBLISHER,
    QOS_PROFILE_DEFAULT,
    RELIABILITY_BEST_EFFORT,
    SERVICE,
    SUBSCRIPTION,
    QosProfile,
    endpoint_token,
    node_name_problem,
    node_token,
    topic_name_problem,
)
from pugsd.wire.keys import dds_type_name, strip_topic, subscription_key, topic_key
from pugsd.wire.types import (
    CAMERA_INFO,
    DIAGNOSTIC_ARRAY,
    GRASP_ARRAY,
    IMAGE,
    MARKER_ARRAY,
    ODOMETRY,
    POINT_CLOUD2,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    STRING,
    TF_MESSAGE,
    type_hash,
)

#: TopicsConfig field -> default message type (``pose`` also accepts PoseStamped and Odometry)
ROLE_TYPES: dict[str, str] = {
    "left_image": IMAGE,
    "right_image": IMAGE,
    "left_info": CAMERA_INFO,
    "right_info": CAMERA_INFO,
    "pose": POSE_COV_STAMPED,
    "mask": IMAGE,
    "depth": IMAGE,
    "depth_info": CAMERA_INFO,
    "depth_std": IMAGE,
    "grasps": GRASP_ARRAY,
    "markers": MARKER_ARRAY,
    "cloud": POINT_CLOUD2,
    "status": STRING,
    "tf": TF_MESSAGE,
    "tf_static": TF_MESSAGE,
    "diagnostics": DIAGNOSTIC_ARRAY,
}
INPUT_ROLES = (
    "left_image", "right_image", "left_info", "right_info", "pose", "mask",
    "depth", "depth_info", "depth_std",
)  # fmt: skip
OUTPUT_ROLES = ("grasps", "markers", "cloud", "status", "tf", "tf_static", "diagnostics")
#: output roles published TRANSIENT_LOCAL (role -> history depth): a zenoh AdvancedPublisher
#: caches the last message(s) for late joiners, as rmw_zenoh does for that durability
TRANSIENT_LOCAL_DEPTH = {"tf_static": 1}


def key_for(topics: Any, role: str, typename: str | None = None) -> str:
    """The publish key of a role of a ``TopicsConfig`` (``typename`` overrides the default)."""
    return topic_key(
        getattr(topics, role),
        typename or ROLE_TYPES[role],
        domain_id=topics.domain_id,
        key_style=topics.key_style,
        hash_mode=topics.hash_mode,
    )


def subscribe_key_for(topics: Any, role: str) -> str:
    """A key matching a role's topic with any type (so PoseStamped and PoseWithCovariance both
    arrive on ``pose``); use :func:`pugsd.wire.keys.parse_key` on ``sample.key_expr`` to learn
    the type (rmw_zenoh style) or :data:`ROLE_TYPES` (ros2dds style)."""
    return subscription_key(
        getattr(topics, role), domain_id=topics.domain_id, key_style=topics.key_style
    )


#: ``[topics] pose_type`` -> the ROS type the daemon decodes the pose input as
POSE_TYPES = {
    "PoseWithCovarianceStamped": POSE_COV_STAMPED,
    "PoseStamped": POSE_STAMPED,
    "Odometry": ODOMETRY,
}


def role_type(topics: Any, role: str) -> str:
    """A role's message type where the key does not say (``ros2dds``): ``ROLE_TYPES``, except
    ``pose``, which is ``[topics] pose_type`` (as the daemon decodes it)."""
    if role == "pose":
        return POSE_TYPES[getattr(topics, "pose_type", "PoseWithCovarianceStamped")]
    return ROLE_TYPES[role]


def topic_types(topics: Any, roles: tuple[str, ...] = INPUT_ROLES + OUTPUT_ROLES) -> dict[str, str]:
    """ROS topic name -> message type for the given roles (:func:`role_type`)."""
    return {getattr(topics, r): role_type(topics, r) for r in roles}


# --- ROS graph liveliness tokens (pugsd.wire.graph) ------------------------------------------------

#: QoS in pugsd's publisher tokens: rmw_qos_profile_default (RELIABLE, VOLATILE, KEEP_LAST 10) as
#: rmw_zenoh adapts it. pugsd's publishers behave as rmw_zenoh's do for it: zenoh reliability
#: RELIABLE (zenoh's default), congestion control DROP, no cache (VOLATILE)
PUBLISHER_QOS = QOS_PROFILE_DEFAULT.adapted()
#: QoS in pugsd's subscription tokens: the same but BEST_EFFORT: pugsd's plain zenoh subscribers
#: take whatever arrives, and a BEST_EFFORT reader is compatible with any writer
SUBSCRIPTION_QOS = dataclasses.replace(QOS_PROFILE_DEFAULT, reliability=RELIABILITY_BEST_EFFORT).adapted()
#: QoS in the tokens of the TRANSIENT_LOCAL outputs (tf2's static broadcaster: depth 1)
TRANSIENT_LOCAL_QOS = {
    role: dataclasses.replace(
        QOS_PROFILE_DEFAULT, durability=DURABILITY_TRANSIENT_LOCAL, depth=depth
    ).adapted()
    for role, depth in TRANSIENT_LOCAL_DEPTH.items()
}
#: QoS in pugsd's service tokens: rmw_qos_profile_services_default (RELIABLE, VOLATILE,
#: KEEP_LAST 10, the same fields as rmw_qos_profile_default) as rmw_zenoh adapts it
SERVICE_QOS = QOS_PROFILE_DEFAULT.adapted()


def full_topic_name(topic: str) -> str:
    """The fully qualified ROS name of a configured topic (``pugs/grasps/`` -> ``/pugs/grasps``)."""
    return "/" + strip_topic(topic)


def graph_token_problems(topics: Any, node_name: str | None = None) -> list[str]:
    """Why rmw_zenoh graph tokens cannot be declared for these topics (and node name): the key
    style and hash mode they describe, and names ROS 2 would not accept. Empty: they can."""
    out: list[str] = []
    if topics.key_style != "rmw_zenoh":
        out.append(f"key_style is {topics.key_style!r} (graph tokens are rmw_zenoh's)")
    if topics.hash_mode != "rihs01":
        out.append(
            f"hash_mode is {topics.hash_mode!r} (the token format was taken from Jazzy and later; "
            "Humble's was not checked)"
        )
    if node_name is not None and (p := node_name_problem(node_name)):
        out.append(f"daemon.node_name: {p}")
    for role in INPUT_ROLES + OUTPUT_ROLES:
        if p := topic_name_problem(full_topic_name(getattr(topics, role))):
            out.append(f"topics.{role}: {p}")
    return out


def graph_tokens_enabled(topics: Any, node_name: str) -> bool:
    """Whether the daemon declares graph tokens (``[topics] ros_graph_tokens``): ``off`` never,
    ``auto`` when :func:`graph_token_problems` finds none, ``on`` always (ConfigError if it
    finds one)."""
    mode = getattr(topics, "ros_graph_tokens", "auto")
    if mode == "off":
        return False
    problems = graph_token_problems(topics, node_name)
    if mode == "on" and problems:
        raise ConfigError("topics.ros_graph_tokens = 'on', but " + "; ".join(problems))
    return not problems


@dataclass(frozen=True, slots=True)
class RosGraphTokens:
    """The daemon's graph tokens: its node, a publisher per output role, a subscription per input
    role, a service server per service (numbered 0, 1, 2, ... in that order, as rmw_zenoh numbers
    a context's entities)."""

    node: str
    publishers: dict[str, str]
    subscriptions: dict[str, str]
    services: dict[str, str] = dataclasses.field(default_factory=dict)  # service name -> token

    def all(self) -> list[str]:
        return [self.node, *self.publishers.values(), *self.subscriptions.values(), *self.services.values()]


def ros_graph_tokens(
    topics: Any,
    node_name: str,
    zid: str,
    *,
    outputs: tuple[str, ...] = OUTPUT_ROLES,
    inputs: tuple[str, ...] = INPUT_ROLES,
    services: Mapping[str, str] | None = None,
) -> RosGraphTokens:
    """The graph tokens of a node ``/<node_name>`` in session ``zid`` (``str(session.zid())``)
    publishing ``outputs``, subscribing ``inputs`` and serving ``services`` (fully qualified
    service name -> service type). Namespace and enclave are ROS's default ``/``; the pose input
    is announced with ``[topics] pose_type`` (pugsd takes any of them). The QoS fields are all
    written (:data:`PUBLISHER_QOS`: ``1:2:1,10:9223372036,854775807:...``)."""
    problems = graph_token_problems(topics, node_name)
    if problems:
        raise ConfigError("no ROS graph tokens: " + "; ".join(problems))
    d = topics.domain_id

    def endpoint(kind: str, role: str, entity_id: int, qos: QosProfile) -> str:
        typename = role_type(topics, role)
        return endpoint_token(
            kind, d, zid, 0, entity_id, node_name, full_topic_name(getattr(topics, role)),
            dds_type_name(typename), type_hash(typename), qos,
            qos_defaults=None,  # every QoS field written: see pugsd.wire.graph
        )  # fmt: skip

    pubs = {
        r: endpoint(PUBLISHER, r, 1 + i, TRANSIENT_LOCAL_QOS.get(r, PUBLISHER_QOS))
        for i, r in enumerate(outputs)
    }
    first = 1 + len(outputs)
    subs = {r: endpoint(SUBSCRIPTION, r, first + i, SUBSCRIPTION_QOS) for i, r in enumerate(inputs)}
    first += len(inputs)
    srvs = {
        name: endpoint_token(
            SERVICE,
            d,
            zid,
            0,
            first + i,
            node_name,
            name,
            dds_type_name(typename),
            type_hash(typename),
            SERVICE_QOS,
            qos_defaults=None,
        )
        for i, (name, typename) in enumerate((services or {}).items())
    }
    return RosGraphTokens(node_token(d, zid, 0, node_name), pubs, subs, srvs)
