# SPDX-License-Identifier: Apache-2.0
"""The daemon's topics (``[topics]`` config) with their message types and zenoh keys."""

from __future__ import annotations

from typing import Any

from pugsd.wire.keys import subscription_key, topic_key
from pugsd.wire.types import (
    CAMERA_INFO,
    GRASP_ARRAY,
    IMAGE,
    MARKER_ARRAY,
    POINT_CLOUD2,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    STRING,
)

#: TopicsConfig field -> default message type (``pose`` also accepts PoseStamped)
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
}
INPUT_ROLES = (
    "left_image", "right_image", "left_info", "right_info", "pose", "mask",
    "depth", "depth_info", "depth_std",
)  # fmt: skip
OUTPUT_ROLES = ("grasps", "markers", "cloud", "status")


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
POSE_TYPES = {"PoseWithCovarianceStamped": POSE_COV_STAMPED, "PoseStamped": POSE_STAMPED}


def role_type(topics: Any, role: str) -> str:
    """A role's message type where the key does not say (``ros2dds``): ``ROLE_TYPES``, except
    ``pose``, which is ``[topics] pose_type`` (as the daemon decodes it)."""
    if role == "pose":
        return POSE_TYPES[getattr(topics, "pose_type", "PoseWithCovarianceStamped")]
    return ROLE_TYPES[role]


def topic_types(topics: Any, roles: tuple[str, ...] = INPUT_ROLES + OUTPUT_ROLES) -> dict[str, str]:
    """ROS topic name -> message type for the given roles (:func:`role_type`)."""
    return {getattr(topics, r): role_type(topics, r) for r in roles}
