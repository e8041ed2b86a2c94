# SPDX-License-Identifier: Apache-2.0
"""The type store (``pugsd.wire.types``): both pugs_msgs types are registered under their ROS 2 names,
the packaged .msg texts are what the store and the MCAP schemas are built from, and the type
names and hashes are the ones rmw_zenoh keys carry."""

from __future__ import annotations

from importlib import resources

from pugsd.wire import types


def test_both_pugs_msgs_types_are_registered_and_nothing_else_is_made_up() -> None:
    assert types.PUGS_MSGS == ("pugs_msgs/msg/Grasp", "pugs_msgs/msg/GraspArray")
    assert (types.GRASP, types.GRASP_ARRAY) == types.PUGS_MSGS
    for name in types.PUGS_MSGS:
        assert types.known_type(name)
        assert types.msg_class(name).__msgtype__ == name
    assert not types.known_type("pugs_msgs/msg/Nope")
    assert not types.known_type("pugs_msgs/Grasp")  # ROS 2 names carry /msg/


def test_the_ros_type_names() -> None:
    assert (types.IMAGE, types.CAMERA_INFO, types.POINT_CLOUD2, types.POINT_FIELD) == (
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CameraInfo",
        "sensor_msgs/msg/PointCloud2",
        "sensor_msgs/msg/PointField",
    )
    assert (types.POSE_COV_STAMPED, types.POSE_STAMPED, types.ODOMETRY) == (
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "geometry_msgs/msg/PoseStamped",
        "nav_msgs/msg/Odometry",
    )
    assert (types.MARKER_ARRAY, types.STRING) == ("visualization_msgs/msg/MarkerArray", "std_msgs/msg/String")
    ros: tuple[str, ...] = (types.IMAGE, types.CAMERA_INFO, types.POINT_CLOUD2, types.POINT_FIELD)
    ros += (types.POSE_COV_STAMPED,)
    ros += (types.POSE_STAMPED, types.ODOMETRY, types.MARKER_ARRAY, types.STRING)
    for name in ros:
        assert types.known_type(name), name


def test_the_packaged_definitions_feed_the_schema_text() -> None:
    text = resources.files("pugsd").joinpath("msg", "GraspArray.msg").read_text(encoding="utf-8")
    assert types.msg_definition_text("GraspArray") == text
    schema = types.msgdef(types.GRASP_ARRAY)
    assert schema.startswith("std_msgs/Header header\npugs_msgs/Grasp[] grasps\n" + "=" * 80 + "\n")
    assert "\nMSG: pugs_msgs/Grasp\n" in schema and "\nMSG: std_msgs/Header\n" in schema
    assert types.msgdef(types.GRASP_ARRAY) is schema  # cached


def test_the_grasp_type_hash() -> None:
    assert types.type_hash(types.GRASP) == (
        "RIHS01_2680dae04039ca3471d8dd29d3e97d0b35e61cd95c9881c02f3ddfd44331c4df"
    )
    assert types.typestore() is types.typestore()
