# SPDX-License-Identifier: Apache-2.0
"""Config sections of the streaming daemon."""

from __future__ import annotations

from dataclasses import dataclass

from pugsd.configbase import opt


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """The streaming daemon: rates, readiness and health."""

    prefix: str = opt("pugs", "zenoh key prefix of pugsd's own API (queries, status, reset)")
    grasp_rate_hz: float = opt(1.0, "how often grasps are recomputed and published", unit="Hz", gt=0.0)
    status_rate_hz: float = opt(1.0, "status message rate", unit="Hz", gt=0.0)
    pose_wait_s: float = opt(0.5, "how long a frame waits for a usable pose before it is dropped", unit="s", ge=0.0)
    shutdown_timeout_s: float = opt(5.0, "bound on finishing in-flight work at shutdown", unit="s", gt=0.0)
    log_json: bool = opt(False, "structured JSON log lines (for the journal)")
    log_level: str = opt("info", "log level", choices=("debug", "info", "warning", "error"))


@dataclass(frozen=True, slots=True)
class TopicsConfig:
    """ROS 2 topic names, domain and key style of the wire format."""

    domain_id: int = opt(0, "ROS 2 domain id (first key segment for rmw_zenoh)", ge=0, le=232)
    key_style: str = opt("rmw_zenoh", "key expression style", choices=("rmw_zenoh", "ros2dds"))
    hash_mode: str = opt("rihs01", "type hash in keys: rihs01 (Jazzy+) or humble", choices=("rihs01", "humble"))
    left_image: str = opt("/stereo/left/image_raw", "left rectified image (sensor_msgs/Image)")
    right_image: str = opt("/stereo/right/image_raw", "right rectified image (sensor_msgs/Image)")
    left_info: str = opt("/stereo/left/camera_info", "left CameraInfo")
    right_info: str = opt("/stereo/right/camera_info", "right CameraInfo")
    pose: str = opt("/camera_pose", "camera pose (PoseWithCovarianceStamped or PoseStamped)")
    mask: str = opt("/stereo/left/mask", "optional object mask aligned with the left image")
    depth: str = opt("/depth/image", "depth image input (32FC1 m or 16UC1 mm) instead of stereo")
    depth_info: str = opt("/depth/camera_info", "CameraInfo of the depth image")
    depth_std: str = opt("/depth/std", "optional per-pixel depth std image (32FC1 m)")
    grasps: str = opt("/pugs/grasps", "output pugs_msgs/GraspArray")
    markers: str = opt("/pugs/grasp_markers", "output visualization_msgs/MarkerArray")
    cloud: str = opt("/pugs/cloud", "output sensor_msgs/PointCloud2 with sigma2_occ and confidence")
    status: str = opt("/pugs/status", "output status (JSON in std_msgs/String)")


@dataclass(frozen=True, slots=True)
class QueuesConfig:
    """Bounded mailboxes between stages (sizes)."""

    stereo: int = opt(2, "stereo frames waiting for depth (drop oldest)", ge=1)
    depth: int = opt(4, "depth frames waiting for fusion (drop oldest)", ge=1)
    commands: int = opt(8, "commands waiting (reject when full)", ge=1)
    record: int = opt(256, "messages waiting for the recorder (drop oldest)", ge=1)
