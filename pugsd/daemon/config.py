# SPDX-License-Identifier: Apache-2.0
"""Config sections of the streaming daemon."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from pugsd.configbase import opt
from pugsd.core.geometry import make_T
from pugsd.errors import ConfigError
from pugsd.wire.codec import quat_to_matrix
from pugsd.wire.topics import graph_token_problems


def _check_key(name: str, value: str, *, strip: bool = False) -> None:
    """``value`` must be a concrete zenoh key expression: non-empty ``/``-separated chunks without
    the wildcard and reserved characters ``* $ ? #`` (zenoh refuses it only when the daemon declares
    it; a topic's leading and trailing ``/`` are stripped as the wire layer does)."""
    v = value.strip("/") if strip else value
    if not v or any(not chunk for chunk in v.split("/")) or any(c in v for c in "*$?#"):
        raise ConfigError(
            f"{name}: {value!r} is not a usable zenoh key (non-empty '/'-separated chunks, "
            "no '*', '$', '?' or '#')"
        )


@dataclass(frozen=True, slots=True)
class DaemonConfig:
    """The streaming daemon: rates, readiness and health."""

    prefix: str = opt("pugs", "zenoh key prefix of pugsd's own API (queries, status, reset)")
    grasp_rate_hz: float = opt(1.0, "how often grasps are recomputed and published", unit="Hz", gt=0.0)
    pause_publish_s: float = opt(
        0.15,
        "when no frame came for this long and the newest one has had its training steps, publish "
        "grasps at once instead of at the next grasp_rate_hz tick (at most 2 x grasp_rate_hz; "
        "0: off)",
        unit="s",
        ge=0.0,
    )
    status_rate_hz: float = opt(1.0, "status message rate", unit="Hz", gt=0.0)
    pose_wait_s: float = opt(
        0.5, "how long a frame waits for a usable pose before it is dropped", unit="s", ge=0.0
    )
    side_image_wait_s: float = opt(
        0.1,
        "while masks (or depth std images) arrive, how long a frame waits for its own; before the "
        "first one, and after they lapse, one frame waits too (at most half of pose_wait_s): "
        "its images can come before its mask",
        unit="s",
        ge=0.0,
    )
    shutdown_timeout_s: float = opt(
        1.0,
        "bound on finishing a grasp round, reset or arm call in flight at shutdown (depth, integrate "
        "and training calls are abandoned at once)",
        unit="s",
        gt=0.0,
    )
    log_json: bool = opt(False, "structured JSON log lines (for the journal)")
    log_level: str = opt("info", "log level", choices=("debug", "info", "warning", "error"))
    node_name: str = opt(
        "pugsd",
        "name in the liveliness token <prefix>/alive/<node_name>, in status and, with [topics] "
        "ros_graph_tokens, the ROS node /<node_name> (then letters, digits and '_' only)",
    )
    allow_non_loopback: bool = opt(
        False,
        "permit [zenoh] endpoints other than tcp/127.0.0.1 and multicast/gossip scouting "
        "(set true to join a LAN or a router; see docs/deploy.md)",
    )
    world_frame: str = opt("world", "frame_id of outputs when the poses name none")
    ready_latch: bool = opt(
        True,
        "keep publishing grasps after the model was first ready (until a reset), even while "
        "new views make the streaming readiness criterion fail again",
    )
    torch_threads: int = opt(
        1,
        "torch intra-op threads for SVGP training and prediction (0: torch's default); depth "
        "estimation runs on its own thread in parallel, and oversubscribed cores slow torch "
        "down several-fold",
        ge=0,
        le=1024,
    )
    blas_threads: int = opt(
        1,
        "threads of numpy's BLAS (0: the library's default, one per core): pugsd's matrices are "
        "small, and an idle OpenBLAS worker spins on a core between calls",
        ge=0,
        le=1024,
    )
    malloc_arena_max: int = opt(
        2,
        "glibc malloc arenas (M_ARENA_MAX), set when `pugsd run` or `pugsd demo` starts (0: glibc's "
        "default, 8 per core; a MALLOC_ARENA_MAX environment variable wins): with the default, "
        "image buffers freed across zenoh's and pugsd's threads fragment per-thread arenas and "
        "the RSS grows",
        ge=0,
    )
    max_frame_rate_hz: float = opt(
        0.0,
        "keep at most this many frames (stereo pairs or depth images) a second, chosen by their "
        "stamps before depth estimation; the others are skipped and counted (frames.skipped_rate), "
        "not dropped. 0: every frame. For a camera faster than the daemon integrates (the status' "
        "overload warning), so that frames do not wait in the depth queue (docs/deploy.md)",
        unit="Hz",
        ge=0.0,
    )
    train_steps_per_frame: int = opt(4, "SVGP steps (NGD + Adam) after each integrated frame", ge=0)
    idle_train_steps: int = opt(4, "SVGP steps per round while no frame is waiting", ge=0)
    min_train_interval_s: float = opt(
        0.5,
        "training yields to waiting frames, except that one step is forced when the last one is "
        "older than this (so the model still improves under sustained overload)",
        unit="s",
        gt=0.0,
    )
    idle_train_s: float = opt(
        60.0, "keep training without new frames for this long after the last one", unit="s", ge=0.0
    )
    idle_rate_decay_steps: int = opt(
        100,
        "idle training: the SVGP's learning rates fall as 1 / (1 + k / this), k the idle steps of "
        "the ready model since the last integrated frame (a frame restores them; before the model "
        "is ready idle steps run at full rates), so that a model with nothing new to learn settles "
        "instead of jittering with its minibatches and swapping near-tied grasps at every "
        "republish; 0 keeps them constant",
        ge=0,
    )
    pose_max_gap_s: float = opt(
        0.5,
        "never interpolate between poses further apart than this; two poses in a row stamped this "
        "much before the newest one restart the pose buffer (the source's clock went back), one "
        "alone is ignored as a stray",
        unit="s",
        gt=0.0,
        le=3600.0,
    )
    pose_publisher_hold_s: float = opt(
        1.0,
        "poses are taken from one publisher (its rmw_zenoh GID) at a time: while the one followed "
        "was heard within this long, poses of any other are ignored and counted (a localiser "
        "launched twice, two nodes on one topic); after that much silence the next publisher is "
        "followed (a restarted localiser). Poses without an rmw_zenoh attachment are always "
        "taken. Keep it above the pose source's period (a slower source is warned of once). 0: "
        "take poses from every publisher",
        unit="s",
        ge=0.0,
    )
    pose_std_translation_m: float = opt(
        0.002,
        "pose std for PoseStamped input and before any pose carried a covariance",
        unit="m",
        ge=0.0,
    )
    pose_std_rotation_rad: float = opt(
        0.0,
        "rotation std for PoseStamped input and before any pose carried one",
        unit="rad",
        ge=0.0,
    )
    T_B_C_xyz_m: tuple[float, ...] = opt(
        (0.0, 0.0, 0.0),
        "camera origin in the frame of the pose input (a body carrying the camera, e.g. an "
        "Odometry's child_frame_id): the pose of the left camera's optical frame (x right, y down, "
        "z forward) is pose * T_B_C, its covariance propagated to first order; identity: the "
        "input is the camera pose",
        unit="m",
    )
    T_B_C_quat_xyzw: tuple[float, ...] = opt(
        (0.0, 0.0, 0.0, 1.0),
        "camera rotation in the frame of the pose input, a unit quaternion in ROS order x y z w "
        "(as tf2's static transforms)",
    )
    markers_top_k: int = opt(10, "grasps drawn in the MarkerArray", ge=0, le=10000)
    publish_cloud: bool = opt(True, "publish the fused cloud with sigma2_occ and PUGS confidence")
    cloud_interval_s: float = opt(
        5.0,
        "while frames stream, the cloud (Algorithm 1 on every query point) is recomputed at most "
        "this often; grasps are not held back by it, and it always follows a pause",
        unit="s",
        ge=0.0,
    )
    stall_timeout_s: float = opt(
        60.0,
        "a stage inside one call for longer than this is unhealthy (watchdog pings stop)",
        unit="s",
        gt=0.0,
    )
    input_stale_s: float = opt(
        2.0,
        "an input stream (left/right image, depth, pose) silent this long after it last sent is "
        "reported stale in the status, the STATUS= line and the log (0: off); the watchdog is "
        "not affected: a silent camera is not a hung daemon",
        unit="s",
        ge=0.0,
    )
    max_consecutive_failures: int = opt(
        20, "a stage failing this many calls in a row is unhealthy (watchdog pings stop)", ge=1
    )
    ingress_limit: int = opt(
        64,
        "samples handed from zenoh threads to the loop and not yet handled; beyond it the "
        "callback drops (zenoh is never blocked)",
        ge=1,
        le=65536,
    )
    ingress_max_bytes: int = opt(
        268435456,
        "payload bytes handed from zenoh threads to the loop and not yet handled; a sample "
        "beyond it is dropped and counted (ingress.refused.byte_bound), like one beyond "
        "ingress_limit",
        unit="B",
        ge=1048576,
        le=17179869184,
    )
    max_image_bytes: int = opt(
        33554432,
        "largest image accepted (height * step; a 2448 x 2048 bgra8 image is 20 MB): a larger "
        "input message is refused before it is copied or decoded (counted as too_large), as is an "
        "image whose declared size differs from its camera's CameraInfo",
        unit="B",
        ge=4096,
        le=1073741824,
    )
    max_pose_std_translation_m: float = opt(
        10.0,
        "a pose whose covariance gives a position standard deviation above this (a diverging "
        "localiser) is refused and counted (implausible_covariance) before it is used",
        unit="m",
        gt=0.0,
        le=1e6,
    )
    max_pose_std_rotation_rad: float = opt(
        math.pi,
        "a pose whose covariance gives a rotation standard deviation above this is refused and "
        "counted (implausible_covariance) before it is used",
        unit="rad",
        gt=0.0,
        le=1e3,
    )

    def __post_init__(self) -> None:
        _check_key("prefix", self.prefix)
        _check_key("node_name", self.node_name)
        xyz, q = self.T_B_C_xyz_m, self.T_B_C_quat_xyzw
        if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
            raise ConfigError(f"T_B_C_xyz_m: expected 3 finite values, got {list(xyz)}")
        if len(q) != 4 or not all(math.isfinite(v) for v in q):
            raise ConfigError(f"T_B_C_quat_xyzw: expected 4 finite values, got {list(q)}")
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > 1e-3:  # a typo, not rounding: refused rather than normalised
            raise ConfigError(
                f"T_B_C_quat_xyzw: {list(q)} is not a unit quaternion (norm {norm:.6g}); "
                "the order is x y z w"
            )

    @property
    def T_B_C(self) -> np.ndarray | None:
        """The camera's mount in the pose input's frame (4x4), None when it is the identity."""
        if tuple(self.T_B_C_xyz_m) == (0.0, 0.0, 0.0) and tuple(self.T_B_C_quat_xyzw) == (0.0, 0.0, 0.0, 1.0):
            return None
        return make_T(quat_to_matrix(*self.T_B_C_quat_xyzw), np.asarray(self.T_B_C_xyz_m, dtype=np.float64))


_NOT_TOPICS = ("key_style", "hash_mode", "pose_type", "ros_graph_tokens")


@dataclass(frozen=True, slots=True)
class TopicsConfig:
    """ROS 2 topic names, domain and key style of the wire format."""

    domain_id: int = opt(0, "ROS 2 domain id (first key segment for rmw_zenoh)", ge=0, le=232)
    key_style: str = opt("rmw_zenoh", "key expression style", choices=("rmw_zenoh", "ros2dds"))
    hash_mode: str = opt(
        "rihs01", "type hash in keys: rihs01 (Jazzy+) or humble", choices=("rihs01", "humble")
    )
    ros_graph_tokens: str = opt(
        "auto",
        "declare rmw_zenoh's ROS graph liveliness tokens (@ros2_lv/...: a node [daemon] "
        "node_name, its publishers and subscriptions) so that ros2 node list / ros2 topic list "
        "show pugsd; data flows without them. auto: with key_style rmw_zenoh, hash_mode rihs01 "
        "and ROS-valid names; on: the same, refusing a config that does not allow them",
        choices=("auto", "on", "off"),
    )
    left_image: str = opt("/stereo/left/image_raw", "left rectified image (sensor_msgs/Image)")
    right_image: str = opt("/stereo/right/image_raw", "right rectified image (sensor_msgs/Image)")
    left_info: str = opt("/stereo/left/camera_info", "left CameraInfo")
    right_info: str = opt("/stereo/right/camera_info", "right CameraInfo")
    pose: str = opt(
        "/camera_pose",
        "camera pose (PoseWithCovarianceStamped, PoseStamped or Odometry), or the pose of the "
        "body carrying the camera with [daemon] T_B_C_xyz_m / T_B_C_quat_xyzw",
    )
    pose_type: str = opt(
        "PoseWithCovarianceStamped",
        "pose message type when the key does not say (ros2dds keys)",
        choices=("PoseWithCovarianceStamped", "PoseStamped", "Odometry"),
    )
    mask: str = opt("/stereo/left/mask", "optional object mask aligned with the left image")
    depth: str = opt("/depth/image", "depth image input (32FC1 m or 16UC1 mm) instead of stereo")
    depth_info: str = opt("/depth/camera_info", "CameraInfo of the depth image")
    depth_std: str = opt("/depth/std", "optional per-pixel depth std image (32FC1 m)")
    grasps: str = opt("/pugs/grasps", "output pugs_msgs/GraspArray")
    markers: str = opt("/pugs/grasp_markers", "output visualization_msgs/MarkerArray")
    cloud: str = opt("/pugs/cloud", "output sensor_msgs/PointCloud2 with sigma2_occ and confidence")
    status: str = opt("/pugs/status", "output status (JSON in std_msgs/String)")
    tf: str = opt("/tf", "output tf2_msgs/TFMessage: the camera (or the body carrying it) in the pose frame")
    tf_static: str = opt(
        "/tf_static",
        "output tf2_msgs/TFMessage, transient local: left -> right camera and the camera mount",
    )
    diagnostics: str = opt("/diagnostics", "output diagnostic_msgs/DiagnosticArray from the status")

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, str) and f.name not in _NOT_TOPICS:
                _check_key(f.name, value, strip=True)
        if self.ros_graph_tokens == "on":
            problems = graph_token_problems(self)
            if problems:
                raise ConfigError("ros_graph_tokens = 'on', but " + "; ".join(problems))


@dataclass(frozen=True, slots=True)
class QueuesConfig:
    """Bounded mailboxes between stages (sizes)."""

    stereo: int = opt(
        2,
        "complete frames waiting for depth estimation (drop oldest): the newest win before "
        "stereo matching; 2 bridges a hiccup of the model at a rate it sustains",
        ge=1,
        le=64,
    )
    depth: int = opt(
        1,
        "depth frames waiting for fusion (drop oldest); depth estimation starts on a frame only "
        "while this has room, so that a frame is never matched only to wait or be dropped here",
        ge=1,
        le=64,
    )
    commands: int = opt(8, "commands waiting (reject when full)", ge=1, le=1024)
    record: int = opt(256, "messages waiting for the recorder (drop oldest)", ge=1, le=1048576)
    pose_wait: int = opt(8, "frames waiting for a usable pose (drop oldest)", ge=1, le=1024)
    unpaired: int = opt(8, "stereo halves waiting for their partner stamp (drop oldest)", ge=1, le=1024)
    poses: int = opt(512, "poses kept for interpolation", ge=2, le=1048576)
    side_images: int = opt(8, "masks and depth-std images kept for matching by stamp", ge=1, le=1024)
    buffered_bytes: int = opt(
        268435456,
        "pixel bytes the frame assembly holds (unpaired halves, frames waiting for a pose, masks "
        "and depth std images), and each of the stereo and depth queues; beyond it the oldest "
        "are dropped and counted (reason: byte budget). At least twice daemon.max_image_bytes",
        unit="B",
        ge=1048576,
        le=17179869184,
    )
