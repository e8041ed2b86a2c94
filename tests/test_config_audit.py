# SPDX-License-Identifier: Apache-2.0
"""Config sections (mutation audit): every range bound of the core, daemon, topics, queues and
record sections on both sides of its boundary with the exact message, every choice list, the
sections' own cross-key checks, config_warnings, override parsing and the dump/load round trip.

The bounds and choices are written out here on purpose (not read from the fields' metadata): a
changed limit in the source must fail a test, not move the test along with it."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.config import (
    CoreConfig,
    PugsdConfig,
    config_warnings,
    core_of,
    dump_config,
    load_config,
    load_config_dict,
    parse_override,
)
from pugsd.daemon.config import DaemonConfig, TopicsConfig
from pugsd.errors import ConfigError

# (dotted key, kind, bound): kind ge/le are inclusive, gt/lt exclusive
BOUNDS: list[tuple[str, str, float]] = [
    ("stereo.downsample", "ge", 1),
    ("stereo.downsample", "le", 16),
    ("stereo.num_disparities", "ge", 0),
    ("stereo.num_disparities", "le", 65520),
    ("stereo.min_disparity", "ge", 0),
    ("stereo.min_disparity", "le", 65535),
    ("stereo.block_size", "ge", 1),
    ("stereo.block_size", "le", 31),
    ("stereo.uniqueness_ratio", "ge", 0),
    ("stereo.uniqueness_ratio", "le", 100),
    ("stereo.speckle_window_size", "ge", 0),
    ("stereo.speckle_window_size", "le", 2147483647),
    ("stereo.speckle_range", "ge", 0),
    ("stereo.speckle_range", "le", 65535),
    ("stereo.disp12_max_diff", "ge", -1),
    ("stereo.disp12_max_diff", "le", 65535),
    ("stereo.min_depth_m", "gt", 0.0),
    ("stereo.max_depth_m", "gt", 0.0),
    ("stereo.sigma_d2_m2", "gt", 0.0),
    ("stereo.sigma_disp_px", "gt", 0.0),
    ("observation.regulariser_m", "gt", 0.0),
    ("observation.max_points_per_frame", "ge", 0),
    ("fof.k_neighbours", "ge", 1),
    ("fof.k_neighbours", "le", 64),
    ("fof.voxel_size_m", "gt", 0.0),
    ("fof.max_voxels", "ge", 100),
    ("fof.query_workers", "ge", -1),
    ("svgp.num_inducing", "ge", 0),
    ("svgp.num_inducing", "le", 5000),
    ("svgp.paper_num_inducing", "ge", 8),
    ("svgp.paper_num_inducing", "le", 5000),
    ("svgp.seed", "ge", 0),
    ("svgp.paper_lr", "gt", 0.0),
    ("svgp.paper_epochs", "ge", 1),
    ("svgp.batch_size", "ge", 16),
    ("svgp.lengthscale_init_m", "gt", 0.0),
    ("svgp.noise_init", "gt", 0.0),
    ("svgp.ngd_lr", "gt", 0.0),
    ("svgp.ngd_lr", "le", 1.0),
    ("svgp.adam_lr", "gt", 0.0),
    ("svgp.inducing_lr", "ge", 0.0),
    ("svgp.steps_per_update", "ge", 1),
    ("svgp.replay_fraction", "ge", 0.0),
    ("svgp.replay_fraction", "le", 1.0),
    ("svgp.ready_min_steps", "ge", 0),
    ("svgp.ready_max_moved_fraction", "ge", 0.0),
    ("svgp.ready_max_moved_fraction", "le", 1.0),
    ("svgp.ready_move_window", "ge", 1),
    ("svgp.ready_elbo_slope", "gt", 0.0),
    ("svgp.ready_elbo_window", "ge", 1),
    ("svgp.spread_factor", "gt", 0.0),
    ("svgp.coverage_lengthscales", "gt", 0.0),
    ("svgp.predict_chunk", "ge", 256),
    ("svgp.predict_chunk_cuda", "ge", 256),
    ("cubature.alpha", "gt", 0.0),
    ("cubature.beta", "ge", 0.0),
    ("cubature.kappa", "ge", -2.9),
    ("cubature.max_query_points", "ge", 100),
    ("reconstruction.tsdf_voxel_m", "gt", 0.0),
    ("reconstruction.sdf_trunc_voxels", "gt", 0.0),
    ("reconstruction.block_count", "ge", 100),
    ("reconstruction.sample_points", "ge", 100),
    ("reconstruction.outlier_nb_neighbors", "ge", 1),
    ("reconstruction.outlier_std_ratio", "gt", 0.0),
    ("freespace.voxel_m", "gt", 0.0),
    ("freespace.voxel_m", "le", 1.0),
    ("freespace.margin_m", "ge", 0.0),
    ("freespace.margin_m", "le", 1.0),
    ("freespace.extent_m", "gt", 0.0),
    ("freespace.extent_m", "le", 5.0),
    ("freespace.background_range_m", "ge", 0.0),
    ("freespace.background_range_m", "le", 100.0),
    ("freespace.max_blocks", "ge", 1),
    ("freespace.max_blocks", "le", 10_000_000),
    ("grasp.gamma", "ge", 0.0),
    ("grasp.gamma", "le", 1e12),
    ("grasp.unknown_weight", "ge", 0.0),
    ("grasp.unknown_weight", "le", 1e6),
    ("grasp.unknown_decay_m", "gt", 0.0),
    ("grasp.unknown_decay_m", "le", 10.0),
    ("grasp.swept_step_m", "gt", 0.0),
    ("grasp.swept_step_m", "le", 0.5),
    ("grasp.single_contact_max_contacts", "ge", 1),
    ("grasp.single_contact_max_contacts", "le", 100_000),
    ("grasp.single_contact_approaches", "ge", 1),
    ("grasp.single_contact_approaches", "le", 64),
    ("grasp.single_contact_rolls", "ge", 1),
    ("grasp.single_contact_rolls", "le", 64),
    ("grasp.single_contact_face_deg", "gt", 0.0),
    ("grasp.single_contact_face_deg", "lt", 90.0),
    ("grasp.single_contact_voxel_m", "ge", 0.0),
    ("grasp.single_contact_voxel_m", "le", 0.05),
    ("grasp.top_k", "ge", 1),
    ("grasp.thin_distance_m", "ge", 0.0),
    ("grasp.normal_radius_m", "gt", 0.0),
    ("grasp.friction_cone_deg", "gt", 0.0),
    ("grasp.friction_cone_deg", "lt", 90.0),
    ("grasp.num_orientations", "ge", 1),
    ("grasp.max_contacts", "ge", 10),
    ("grasp.min_support", "ge", 1),
    ("grasp.partner_radius_m", "gt", 0.0),
    ("grasp.clearance_m", "ge", 0.0),
    ("grasp.approach_check_m", "ge", 0.0),
    ("grasp.gripper.max_width_m", "gt", 0.0),
    ("grasp.gripper.min_width_m", "ge", 0.0),
    ("grasp.gripper.depth_m", "gt", 0.0),
    ("grasp.gripper.finger_length_m", "gt", 0.0),
    ("grasp.gripper.finger_width_m", "gt", 0.0),
    ("grasp.gripper.finger_thickness_m", "gt", 0.0),
    ("grasp.gripper.palm_depth_m", "gt", 0.0),
    ("grasp.gripper.palm_width_m", "gt", 0.0),
    ("daemon.grasp_rate_hz", "gt", 0.0),
    ("daemon.pause_publish_s", "ge", 0.0),
    ("daemon.status_rate_hz", "gt", 0.0),
    ("daemon.pose_wait_s", "ge", 0.0),
    ("daemon.side_image_wait_s", "ge", 0.0),
    ("daemon.shutdown_timeout_s", "gt", 0.0),
    ("daemon.torch_threads", "ge", 0),
    ("daemon.malloc_arena_max", "ge", 0),
    ("daemon.max_frame_rate_hz", "ge", 0.0),
    ("daemon.train_steps_per_frame", "ge", 0),
    ("daemon.idle_train_steps", "ge", 0),
    ("daemon.min_train_interval_s", "gt", 0.0),
    ("daemon.idle_train_s", "ge", 0.0),
    ("daemon.idle_rate_decay_steps", "ge", 0),
    ("daemon.pose_max_gap_s", "gt", 0.0),
    ("daemon.pose_max_gap_s", "le", 3600.0),
    ("daemon.pose_publisher_hold_s", "ge", 0.0),
    ("daemon.pose_std_translation_m", "ge", 0.0),
    ("daemon.pose_std_rotation_rad", "ge", 0.0),
    ("daemon.markers_top_k", "ge", 0),
    ("daemon.cloud_interval_s", "ge", 0.0),
    ("daemon.stall_timeout_s", "gt", 0.0),
    ("daemon.input_stale_s", "ge", 0.0),
    ("daemon.max_consecutive_failures", "ge", 1),
    ("daemon.ingress_limit", "ge", 1),
    ("topics.domain_id", "ge", 0),
    ("topics.domain_id", "le", 232),
    ("queues.stereo", "ge", 1),
    ("queues.depth", "ge", 1),
    ("queues.commands", "ge", 1),
    ("queues.record", "ge", 1),
    ("queues.pose_wait", "ge", 1),
    ("queues.unpaired", "ge", 1),
    ("queues.poses", "ge", 2),
    ("queues.side_images", "ge", 1),
    ("record.chunk_size_bytes", "ge", 4096),
    ("record.flush_interval_s", "gt", 0.0),
    ("record.rotate_size_bytes", "ge", 1048576),
    ("record.rotate_duration_s", "gt", 0.0),
    ("record.max_total_bytes", "ge", 0),
    ("record.queue_max_bytes", "ge", 1048576),
]

CHOICES: dict[str, tuple[str, ...]] = {
    "stereo.mode": ("sgbm", "sgbm_3way", "hh"),
    "stereo.noise_mode": ("fixed", "disparity"),
    "observation.covariance_form": ("rotated", "paper_literal"),
    "fof.target_scale": ("max", "p99"),
    "fof.fused_mean": ("query", "information"),
    "fof.query_device": ("auto", "cpu", "cuda"),
    "svgp.kernel": ("rbf", "matern52"),
    "svgp.variance": ("latent", "observed"),
    "svgp.device": ("cpu", "cuda", "auto"),
    "svgp.dtype": ("float32", "float64"),
    "svgp.inducing_policy": ("spread", "coverage"),
    "svgp.output_units": ("density", "normalised"),
    "cubature.variance_form": ("total", "paper_literal"),
    "grasp.proposer": ("single_contact", "antipodal", "torchscript"),
    "grasp.uncertainty": ("swept", "contact"),
    "daemon.log_level": ("debug", "info", "warning", "error"),
    "topics.key_style": ("rmw_zenoh", "ros2dds"),
    "topics.hash_mode": ("rihs01", "humble"),
    "topics.ros_graph_tokens": ("auto", "on", "off"),
    "topics.pose_type": ("PoseWithCovarianceStamped", "PoseStamped", "Odometry"),
    "record.compression": ("zstd", "lz4", "none"),
}

SECTIONS = ("stereo", "observation", "fof", "svgp", "cubature", "reconstruction", "freespace", "grasp",
            "daemon", "topics", "queues", "record")  # fmt: skip

# keys whose accepted edge needs a companion setting to pass the section's cross-key check:
# max_depth_m must exceed min_depth_m > 0, so its smallest accepted value is two steps above 0
CONTEXT: dict[str, dict[str, Any]] = {
    "stereo.max_depth_m": {"min_depth_m": 5e-324},
}
ACCEPT_ABOVE: dict[str, float] = {"stereo.max_depth_m": 1e-323}


def _nested(dotted: str, value: Any) -> dict[str, Any]:
    *head, last = dotted.split(".")
    data: dict[str, Any] = {last: value}
    for part in reversed(head):
        data = {part: data}
    return data


def _load(dotted: str, value: Any) -> Any:
    data = _nested(dotted, value)
    if dotted in CONTEXT:
        section = dotted.split(".")[0]
        data[section].update(CONTEXT[dotted])
    cfg = load_config_dict(data)
    obj: Any = cfg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def _error(data: dict[str, Any], overrides: tuple[str, ...] = ()) -> str:
    with pytest.raises(ConfigError) as exc:
        load_config_dict(data, list(overrides))
    return str(exc.value)


def _walk_meta(obj: Any, path: str, out: dict[str, dict[str, Any]]) -> None:
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            _walk_meta(v, f"{path}.{f.name}", out)
        else:
            out[f"{path}.{f.name}"] = dict(f.metadata)


def _all_meta() -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    cfg = PugsdConfig()
    for s in SECTIONS:
        _walk_meta(getattr(cfg, s), s, out)
    return out


def test_the_tables_here_list_every_bound_and_choice_of_these_sections() -> None:
    """A bound or choice added, dropped or renamed in the source shows up here first."""
    meta = _all_meta()
    kinds = ("ge", "gt", "le", "lt")
    declared = {(k, kind) for k, m in meta.items() for kind in kinds if m.get(kind) is not None}
    assert declared == {(k, kind) for k, kind, _ in BOUNDS}
    assert {k for k, m in meta.items() if m.get("choices") is not None} == set(CHOICES)


@pytest.mark.parametrize(("key", "kind", "bound"), BOUNDS, ids=[f"{k}-{kind}" for k, kind, _ in BOUNDS])
def test_each_bound_on_both_sides_with_its_exact_message(key: str, kind: str, bound: float) -> None:
    down: float
    up: float
    if isinstance(bound, int):
        down, up = bound - 1, bound + 1
    else:  # the neighbouring floats
        down, up = math.nextafter(bound, -math.inf), math.nextafter(bound, math.inf)
    if kind == "ge":
        assert _load(key, bound) == bound
        assert _error(_nested(key, down)) == f"{key}: {down} is below the minimum {bound}"
    elif kind == "le":
        assert _load(key, bound) == bound
        assert _error(_nested(key, up)) == f"{key}: {up} is above the maximum {bound}"
    elif kind == "gt":
        up = ACCEPT_ABOVE.get(key, up)
        assert _load(key, up) == up
        assert _error(_nested(key, bound)) == f"{key}: {bound} must be greater than {bound}"
    else:  # lt
        assert _load(key, down) == down
        assert _error(_nested(key, bound)) == f"{key}: {bound} must be less than {bound}"


@pytest.mark.parametrize("key", sorted(CHOICES))
def test_each_choice_loads_and_anything_else_is_refused_with_the_list(key: str) -> None:
    for choice in CHOICES[key]:
        assert _load(key, choice) == choice
    assert _error(_nested(key, "bogus")) == f"{key}: 'bogus' is not one of {list(CHOICES[key])}"


# the sections' own checks across keys


def test_block_size_must_be_odd() -> None:
    assert _error({"stereo": {"block_size": 4}}) == "stereo.block_size: must be odd, got 4"
    assert _error({"stereo": {"block_size": 30}}) == "stereo.block_size: must be odd, got 30"
    assert load_config_dict({"stereo": {"block_size": 3}}).stereo.block_size == 3


@pytest.mark.parametrize("n", [8, 24, 65512 + 4])
def test_num_disparities_must_be_a_multiple_of_16(n: int) -> None:
    assert _error({"stereo": {"num_disparities": n}}) == (
        "stereo.num_disparities: must be 0 (auto) or a multiple of 16"
    )


@pytest.mark.parametrize("n", [0, 16, 32, 65520])
def test_a_multiple_of_16_disparities_loads(n: int) -> None:
    assert load_config_dict({"stereo": {"num_disparities": n}}).stereo.num_disparities == n


def test_the_depth_band_check_is_strict_and_its_message_exact() -> None:
    assert _error({"stereo": {"min_depth_m": 2.0, "max_depth_m": 1.0}}) == (
        "stereo.max_depth_m: must exceed min_depth_m"
    )
    assert _error({"stereo": {"max_depth_m": 0.2}}) == "stereo.max_depth_m: must exceed min_depth_m"
    assert load_config_dict({"stereo": {"max_depth_m": math.nextafter(0.2, 1.0)}}).stereo.max_depth_m > 0.2


# [daemon] and [topics]


_KEY_MESSAGE = "is not a usable zenoh key (non-empty '/'-separated chunks, no '*', '$', '?' or '#')"


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("daemon.prefix", "pugs$x"),
        ("daemon.prefix", "pugs#x"),
        ("daemon.prefix", "/pugs"),  # the prefix is not stripped: a leading '/' is an empty chunk
        ("daemon.node_name", "a/"),
        ("daemon.node_name", "a?b"),
        ("topics.status", "/pugs/$status"),
        ("topics.cloud", "/pugs/cl#oud"),
        ("topics.depth", "/"),  # stripped to nothing
        ("topics.mask", "//"),
    ],
)
def test_a_key_with_a_reserved_character_or_empty_chunk_is_refused_exactly(key: str, value: str) -> None:
    assert _error(_nested(key, value)) == f"{key}: {value!r} {_KEY_MESSAGE}"


def test_topics_but_not_the_prefix_have_their_outer_slashes_stripped() -> None:
    cfg = load_config_dict({"topics": {"status": "//pugs/status//", "mask": "mask"}})
    assert (cfg.topics.status, cfg.topics.mask) == ("//pugs/status//", "mask")
    # the choice-valued keys of [topics] are no topics: their values are not checked as keys
    assert load_config_dict({"topics": {"pose_type": "Odometry"}}).topics.pose_type == "Odometry"


def test_a_section_built_directly_runs_the_same_key_checks() -> None:
    with pytest.raises(ConfigError, match=r"^prefix: 'a\*' is not a usable zenoh key"):
        DaemonConfig(prefix="a*")
    with pytest.raises(ConfigError, match=r"^grasps: '/x//y' is not a usable zenoh key"):
        TopicsConfig(grasps="/x//y")


@pytest.mark.parametrize(
    ("xyz", "message"),
    [
        ((math.nan, 0.0, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [nan, 0.0, 0.0]"),
        ((0.0, math.inf, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [0.0, inf, 0.0]"),
        ((0.0, 0.0, 0.0, 0.0), "T_B_C_xyz_m: expected 3 finite values, got [0.0, 0.0, 0.0, 0.0]"),
    ],
)
def test_the_mount_translation_must_be_three_finite_values(xyz: tuple[float, ...], message: str) -> None:
    """Built directly (the loader refuses nan first): the section's own check still holds."""
    with pytest.raises(ConfigError) as exc:
        DaemonConfig(T_B_C_xyz_m=xyz)
    assert str(exc.value) == message


@pytest.mark.parametrize(
    ("q", "message"),
    [
        ((0.0, 0.0, math.nan, 1.0), "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, nan, 1.0]"),
        ((0.0, 0.0, 1.0), "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, 1.0]"),
        (
            (0.0, 0.0, 0.0, 0.0, 1.0),
            "T_B_C_quat_xyzw: expected 4 finite values, got [0.0, 0.0, 0.0, 0.0, 1.0]",
        ),
    ],
)
def test_the_mount_rotation_must_be_four_finite_values(q: tuple[float, ...], message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        DaemonConfig(T_B_C_quat_xyzw=q)
    assert str(exc.value) == message


@pytest.mark.parametrize("w", [1.0011, 0.9989])
def test_a_quaternion_off_unit_norm_by_more_than_1e_3_is_refused(w: float) -> None:
    assert _error({"daemon": {"T_B_C_quat_xyzw": [0.0, 0.0, 0.0, w]}}) == (
        f"daemon.T_B_C_quat_xyzw: [0.0, 0.0, 0.0, {w}] is not a unit quaternion (norm {w:.6g}); "
        "the order is x y z w"
    )


@pytest.mark.parametrize("w", [1.0009, 0.9991])
def test_a_quaternion_within_1e_3_of_unit_norm_loads_as_given(w: float) -> None:
    cfg = load_config_dict({"daemon": {"T_B_C_quat_xyzw": [0.0, 0.0, 0.0, w]}})
    assert cfg.daemon.T_B_C_quat_xyzw == (0.0, 0.0, 0.0, w)  # not normalised


def test_the_mount_matrix_is_none_only_for_the_identity() -> None:
    assert DaemonConfig().T_B_C is None
    T = DaemonConfig(T_B_C_xyz_m=(0.1, -0.2, 0.3)).T_B_C
    assert T is not None
    np.testing.assert_array_equal(T, [[1, 0, 0, 0.1], [0, 1, 0, -0.2], [0, 0, 1, 0.3], [0, 0, 0, 1]])
    s = math.sqrt(0.5)
    T = DaemonConfig(T_B_C_quat_xyzw=(0.0, 0.0, s, s)).T_B_C  # 90 deg about z, no translation
    assert T is not None
    np.testing.assert_allclose(T, [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-15)


def test_graph_tokens_on_refuses_a_topic_ros_would_not_take_in_the_topics_section() -> None:
    assert _error({"topics": {"ros_graph_tokens": "on", "status": "/pugs/st%tus"}}) == (
        "topics: ros_graph_tokens = 'on', but topics.status: '/pugs/st%tus' is not a fully qualified "
        "ROS 2 topic name ('/'-separated tokens of letters, digits and '_', none starting with a digit)"
    )
    assert _error({"topics": {"ros_graph_tokens": "on", "key_style": "ros2dds"}}) == (
        "topics: ros_graph_tokens = 'on', but key_style is 'ros2dds' (graph tokens are rmw_zenoh's)"
    )
    # off and auto accept the same names
    for mode in ("off", "auto"):
        assert load_config_dict({"topics": {"ros_graph_tokens": mode, "status": "/pugs/st%tus"}})


# config_warnings


def _approach_warning(check: float, pre: float) -> str:
    return (
        f"grasp.approach_check_m = {check:g} m is shorter than arm.motion.pregrasp_distance_m = {pre:g} m: "
        "the arm approaches in a straight line from its stand-off, and the first "
        f"{pre - check:.3g} m of that line (from the stand-off) are not checked against the cloud"
    )


_NODE_WARNING = (
    "topics.ros_graph_tokens = 'auto' declares no ROS graph tokens, so ros2 node list and ros2 topic "
    "list will not show pugsd: daemon.node_name: 'pugs-1' is not a ROS 2 node name (letters, digits "
    "and '_', not starting with a digit)"
)


def test_config_warnings_exact_text_and_order() -> None:
    cfg = load_config_dict(
        {"arm": {"enabled": True}, "grasp": {"approach_check_m": 0.05}, "daemon": {"node_name": "pugs-1"}}
    )
    assert config_warnings(cfg) == [_approach_warning(0.05, 0.2), _NODE_WARNING]
    assert config_warnings(PugsdConfig()) == []


def test_the_approach_warning_rounds_the_unchecked_length_to_three_digits() -> None:
    arm = {"enabled": True, "motion": {"pregrasp_distance_m": 0.3}}
    cfg = load_config_dict({"arm": arm, "grasp": {"approach_check_m": 0.1234}})
    (w,) = config_warnings(cfg)
    assert w == _approach_warning(0.1234, 0.3)
    assert "0.1234 m is shorter than" in w and "= 0.3 m:" in w and "the first 0.177 m" in w


def test_the_approach_warning_needs_a_strictly_shorter_check() -> None:
    base = {"arm": {"enabled": True, "motion": {"pregrasp_distance_m": 0.15}}}
    assert config_warnings(load_config_dict({**base, "grasp": {"approach_check_m": 0.15}})) == []
    assert len(config_warnings(load_config_dict({**base, "grasp": {"approach_check_m": 0.149}}))) == 1


@pytest.mark.parametrize(
    "topics",
    [
        {"ros_graph_tokens": "off"},
        {"key_style": "ros2dds"},  # tokens describe rmw_zenoh only: nothing is missed
        {"hash_mode": "humble"},
    ],
)
def test_no_graph_token_warning_where_tokens_are_not_expected(topics: dict[str, str]) -> None:
    cfg = load_config_dict({"topics": topics, "daemon": {"node_name": "pugs-1"}})
    assert config_warnings(cfg) == []


def test_a_topic_ros_refuses_is_warned_of_in_auto_mode() -> None:
    (w,) = config_warnings(load_config_dict({"topics": {"grasps": "/pugs/2grasps"}}))
    assert w.startswith("topics.ros_graph_tokens = 'auto' declares no ROS graph tokens, so ros2 node list")
    assert w.endswith(
        ": topics.grasps: '/pugs/2grasps' is not a fully qualified ROS 2 topic name "
        "('/'-separated tokens of letters, digits and '_', none starting with a digit)"
    )


def test_several_graph_token_problems_are_joined_with_semicolons() -> None:
    cfg = load_config_dict({"daemon": {"node_name": "pugs-1"}, "topics": {"grasps": "/pugs/2grasps"}})
    (w,) = config_warnings(cfg)
    assert "'pugs-1' is not a ROS 2 node name (letters, digits and '_', not starting with a digit); " \
        "topics.grasps: '/pugs/2grasps' is not" in w  # fmt: skip


# overrides


@pytest.mark.parametrize(
    ("text", "parsed"),
    [
        ("fof.k_neighbours=7", ("fof.k_neighbours", 7)),
        ("grasp.gamma=2.5", ("grasp.gamma", 2.5)),
        ("grasp.gamma=-1e-3", ("grasp.gamma", -1e-3)),
        ("daemon.log_json=true", ("daemon.log_json", True)),
        ("daemon.log_json = false ", ("daemon.log_json", False)),
        ("record.keys=['a/b', \"c\"]", ("record.keys", ["a/b", "c"])),
        (
            "zenoh.scouting={multicast = {enabled = false}}",
            ("zenoh.scouting", {"multicast": {"enabled": False}}),
        ),
        ("daemon.prefix='quoted'", ("daemon.prefix", "quoted")),
        ('daemon.prefix="true"', ("daemon.prefix", "true")),  # a quoted word stays a string
        ("daemon.prefix=two words", ("daemon.prefix", "two words")),  # not TOML: the raw text
        ("daemon.prefix=", ("daemon.prefix", "")),
        ("  grasp.top_k  =  3  ", ("grasp.top_k", 3)),
        ("fof=3", ("fof", 3)),  # one part is a key too (the loader then refuses the value)
    ],
)
def test_override_values_are_toml_or_the_bare_text(text: str, parsed: tuple[str, Any]) -> None:
    assert parse_override(text) == parsed


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("noequals", "override 'noequals': expected KEY=VALUE"),
        ("=3", "override '=3': expected section.key=VALUE"),
        ("daemon. .prefix=x", "override 'daemon. .prefix=x': expected section.key=VALUE"),
        (".prefix=x", "override '.prefix=x': expected section.key=VALUE"),
        ("daemon.prefix.=x", "override 'daemon.prefix.=x': expected section.key=VALUE"),
    ],
)
def test_a_malformed_override_is_refused_exactly(text: str, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        parse_override(text)
    assert str(exc.value) == message


def test_an_override_into_a_value_that_is_no_table_names_both() -> None:
    assert _error({"fof": {"k_neighbours": 3}}, ("fof.k_neighbours.x=1",)) == (
        "fof.k_neighbours.x: k_neighbours is not a table"
    )
    assert _error({"fof": 3}, ("fof.k_neighbours=1",)) == "fof.k_neighbours: fof is not a table"
    # not set before: an empty table is made, and the loader refuses it by type
    assert _error({}, ("fof.k_neighbours.x=1",)) == "fof.k_neighbours: expected an integer, got dict"
    assert _error({}, ("fof=3",)) == "fof: expected a table, got int"


def test_overrides_apply_in_order_over_the_data_and_leave_it_unchanged() -> None:
    data = {"grasp": {"gamma": 1.0, "gripper": {"max_width_m": 0.2}}, "fof": {"k_neighbours": 5}}
    cfg = load_config_dict(data, ["grasp.gamma=2", "grasp.gripper.max_width_m=0.3", "grasp.gamma=3"])
    assert (cfg.grasp.gamma, cfg.grasp.gripper.max_width_m, cfg.fof.k_neighbours) == (3.0, 0.3, 5)
    assert data == {"grasp": {"gamma": 1.0, "gripper": {"max_width_m": 0.2}}, "fof": {"k_neighbours": 5}}


# files and the dump/load round trip


def test_load_config_file_errors_are_exact(tmp_path: Path) -> None:
    missing = tmp_path / "missing.toml"
    with pytest.raises(ConfigError) as exc:
        load_config(missing)
    assert str(exc.value) == f"{missing}: no such file"
    with pytest.raises(ConfigError) as exc:
        load_config(tmp_path)
    assert str(exc.value) == f"{tmp_path}: cannot read: Is a directory"
    binary = tmp_path / "b.toml"
    binary.write_bytes(b"[daemon]\n\xff\n")
    with pytest.raises(ConfigError) as exc:
        load_config(binary)
    assert str(exc.value) == f"{binary}: not valid TOML: not UTF-8 (byte 9)"
    bad = tmp_path / "bad.toml"
    bad.write_text("[daemon\n")
    with pytest.raises(ConfigError) as exc:
        load_config(str(bad))
    assert str(exc.value).startswith(f"{bad}: not valid TOML: ")


def test_load_config_reads_the_file_and_applies_overrides_over_it(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text("[grasp]\ngamma = 2.0\ntop_k = 4\n")
    cfg = load_config(f, ["grasp.top_k=6"])
    assert (cfg.grasp.gamma, cfg.grasp.top_k) == (2.0, 6)
    assert load_config(None, ["grasp.top_k=6"]).grasp.top_k == 6
    assert load_config() == PugsdConfig()


def test_a_non_default_config_round_trips_through_dump_and_load() -> None:
    overrides = [
        "stereo.block_size=7",
        "stereo.mode=hh",
        "observation.rotation_term=false",
        "svgp.ngd_lr=0.25",
        "cubature.kappa=-1.5",
        "grasp.gripper.palm_width_m=0.07",
        "grasp.model_path='/tmp/model \"x\".pt'",
        "daemon.T_B_C_xyz_m=[0.1, -0.2, 0.3]",
        "daemon.prefix=robot1/pugs",
        "record.keys=['a/b', 'c/**']",
        "topics.domain_id=42",
        "queues.poses=3",
        "zenoh.connect.endpoints=['tcp/127.0.0.1:7448']",
    ]
    cfg = load_config_dict({}, overrides)
    text = dump_config(cfg)
    assert text != dump_config()
    again = load_config_dict(tomllib.loads(text))
    assert again == cfg
    assert again.grasp.model_path == '/tmp/model "x".pt' and again.record.keys == ("a/b", "c/**")
    assert dump_config(again) == text


def test_core_of_takes_exactly_the_core_sections() -> None:
    cfg = load_config_dict({}, ["grasp.gamma=2", "fof.k_neighbours=3", "daemon.grasp_rate_hz=4"])
    core = core_of(cfg)
    assert isinstance(core, CoreConfig)
    assert core.grasp is cfg.grasp and core.fof is cfg.fof and core.stereo is cfg.stereo
    assert [f.name for f in dataclasses.fields(CoreConfig)] == [
        "stereo", "observation", "fof", "svgp", "cubature", "reconstruction", "freespace", "grasp"
    ]  # fmt: skip
