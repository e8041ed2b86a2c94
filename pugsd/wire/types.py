# SPDX-License-Identifier: Apache-2.0
"""The ROS 2 (Jazzy) type store with pugsd's own ``pugs_msgs`` types registered.

Type names are ROS 2 style (``sensor_msgs/msg/Image``). :func:`msgdef` gives the ``ros2msg``
schema text used in MCAP files and :func:`type_hash` the RIHS01 hash used in rmw_zenoh keys.
"""

from __future__ import annotations

import functools
from importlib import resources
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

#: message types of pugsd's own package (``pugsd/msg/*.msg``)
PUGS_MSGS = ("pugs_msgs/msg/Grasp", "pugs_msgs/msg/GraspArray")

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POINT_FIELD = "sensor_msgs/msg/PointField"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
STRING = "std_msgs/msg/String"
GRASP = "pugs_msgs/msg/Grasp"
GRASP_ARRAY = "pugs_msgs/msg/GraspArray"


def msg_definition_text(name: str) -> str:
    """The text of ``pugsd/msg/<name>.msg`` (packaged with pugsd)."""
    return resources.files("pugsd").joinpath("msg", f"{name}.msg").read_text(encoding="utf-8")


@functools.cache
def typestore() -> Any:
    """The shared Jazzy typestore (built once; thread-safe to read afterwards)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    for full in PUGS_MSGS:
        ts.register(get_types_from_msg(msg_definition_text(full.rsplit("/", 1)[1]), full))
    return ts


def msg_class(typename: str) -> Any:
    """The generated dataclass of a message type (``KeyError`` if unknown)."""
    return typestore().types[typename]


@functools.cache
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex>`` of a message type (Jazzy and later)."""
    return str(typestore().hash_rihs01(typename))


@functools.cache
def msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text (with dependencies) for MCAP."""
    return str(typestore().generate_msgdef(typename, ros_version=2)[0])


def known_type(typename: str) -> bool:
    return typename in typestore().types
