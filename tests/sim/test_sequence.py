# SPDX-License-Identifier: Apache-2.0
"""``pugsd.sim.sequence``: the SE(3) exponential against the matrix exponential, the
object poses as exact rotations with the bounding box centred, the trajectories' rings, arcs and
radii, and what ``make_sequence`` records per frame (frame count, stamps, reported covariance,
rig, underwater switch)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from pugsd.core.geometry import skew
from pugsd.errors import InputError
from pugsd.sim.objects import get_object
from pugsd.sim.sequence import (
    TRAJECTORY_SPECS,
    camera_path,
    make_sequence,
    object_pose,
    pose_covariance,
    reported_pose_covariance,
    se3_exp,
    so3_exp,
)


def _twist_hat(xi: np.ndarray) -> np.ndarray:
    X = np.zeros((4, 4))
    X[:3, :3] = skew(xi[3:])
    X[:3, 3] = xi[:3]
    return X


@pytest.mark.parametrize(
    "xi",
    [
        [0.1, -0.2, 0.3, 0.4, -0.5, 0.6],  # 0.88 rad
        [0.05, 0.02, -0.3, 0.0, 2.5, 0.0],  # a large turn
        [0.3, 0.1, -0.2, 1e-3, -2e-3, 5e-4],  # the trajectories' pose noise scale
        [0.3, 0.1, -0.2, 1e-11, -2e-11, 5e-12],  # below the small-angle switch (1e-9 rad)
    ],
)
def test_se3_exp_is_the_matrix_exponential_of_the_twist(xi: list[float]) -> None:
    """``se3_exp(rho, phi) = expm([[phi^, rho], [0, 0]])``: the rotation is Rodrigues' formula and the
    translation ``J(phi) rho`` with the left Jacobian, at every angle (``so3_exp = expm(phi^)``)."""
    x = np.asarray(xi, dtype=np.float64)
    np.testing.assert_allclose(se3_exp(x), expm(_twist_hat(x)), rtol=0, atol=1e-14)
    np.testing.assert_allclose(so3_exp(x[3:]), expm(skew(x[3:])), rtol=0, atol=1e-14)


def _rx(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(
    ("pose", "yaw_deg", "R", "extents_m"),
    [
        ("upright", 0.0, np.eye(3), (0.06, 0.08, 0.14)),
        ("lying", 0.0, _rx(90.0), (0.06, 0.14, 0.08)),  # on its side: its z along world y
        ("sideways", 0.0, _rz(90.0), (0.08, 0.06, 0.14)),
        ("lying", 90.0, _rz(90.0) @ _rx(90.0), (0.14, 0.06, 0.08)),  # yaw about the world z, after
        ("tilted", 0.0, _rx(-30.0), None),
    ],
)
def test_object_poses_are_the_documented_rotations_with_the_box_centred(
    pose: str, yaw_deg: float, R: np.ndarray, extents_m: tuple[float, float, float] | None
) -> None:
    """The 6 x 8 x 14 cm box in each pose: the rotation is exact, the world bounding box has the
    rotated extents, rests on z = 0 and is centred on x = y = 0 (the mug too, whose handle makes
    its own frame's box off-centre in x)."""
    for name in ("box", "mug"):
        obj = get_object(name)
        T = object_pose(obj, pose, yaw_deg)
        np.testing.assert_allclose(T[:3, :3], R, atol=1e-15)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
        v = np.asarray(obj.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        lo, hi = v.min(axis=0), v.max(axis=0)
        np.testing.assert_allclose([lo[0] + hi[0], lo[1] + hi[1], lo[2]], 0.0, atol=1e-12)
        if name == "box" and extents_m is not None:
            np.testing.assert_allclose(hi - lo, extents_m, atol=1e-12)
    # tilted: the object's z axis is 30 deg from the world's, turned about the world x axis
    if pose == "tilted":
        z_O = T[:3, 2]
        assert np.degrees(np.arccos(z_O[2])) == pytest.approx(30.0, abs=1e-9) and z_O[0] == 0.0


def _az_el_r(poses: list[np.ndarray], target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.array([T[:3, 3] for T in poses]) - target
    r = np.linalg.norm(d, axis=1)
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])), np.degrees(np.arcsin(d[:, 2] / r)), r


def test_the_complete_trajectory_is_two_rings_at_25_and_55_degrees() -> None:
    """7 frames: a first ring of (7 + 1) // 2 = 4 cameras at 25 +- 3 deg elevation, 90 deg apart in
    azimuth, then 3 at 55 +- 3 deg, 120 deg apart and starting 180 / 4 = 45 deg after the first;
    every camera 0.45 +- 0.02 m from the target (another ``radius_m`` moves them all)."""
    target = np.array([0.1, -0.2, 0.07])
    poses = camera_path("complete", 7, target, np.random.default_rng(3))
    az, el, r = _az_el_r(poses, target)
    assert np.all((el[:4] > 22.0) & (el[:4] < 28.0)) and np.all((el[4:] > 52.0) & (el[4:] < 58.0))
    np.testing.assert_allclose(np.diff(az[:4]) % 360.0, 90.0, atol=1e-9)
    np.testing.assert_allclose(np.diff(az[4:]) % 360.0, 120.0, atol=1e-9)
    assert (az[4] - az[0]) % 360.0 == pytest.approx(45.0, abs=1e-9)
    assert np.all(np.abs(r - 0.45) <= 0.02)
    far = camera_path("complete", 7, target, np.random.default_rng(3), radius_m=0.8)
    assert np.all(np.abs(_az_el_r(far, target)[2] - 0.8) <= 0.02)


def test_the_partial_trajectory_is_an_even_arc_at_30_degrees() -> None:
    """5 frames over the 40 deg arc: 10 deg apart at 30 +- 3 deg elevation; one frame sits at the
    arc's centre; fewer than one frame or an unknown trajectory is an InputError."""
    target = np.zeros(3)
    poses = camera_path("noisy_partial", 5, target, np.random.default_rng(5))
    az, el, r = _az_el_r(poses, target)
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(az))), np.radians(10.0), atol=1e-12)
    assert np.all((el > 27.0) & (el < 33.0)) and np.all(np.abs(r - 0.45) <= 0.02)
    assert len(camera_path("partial", 1, target, np.random.default_rng(5))) == 1
    with pytest.raises(InputError, match="n_frames"):
        camera_path("partial", 0, target, np.random.default_rng(5))
    with pytest.raises(InputError, match="unknown trajectory"):
        camera_path("spiral", 3, target, np.random.default_rng(5))


def test_a_sequence_records_its_frames_stamps_covariances_and_rig() -> None:
    """A partial sequence has 8 frames by default, stamped 0.1 s apart from 0.1 s; each frame
    reports a pose near the true one (pose noise 1 mm, 1 mrad) with the covariance of that noise
    in the core's convention for the reported pose; the rig has the baseline asked for, and the
    paper's sigma_d^2 = 0.001 m^2 is the pipeline override."""
    seq = make_sequence("box", "partial", width=160, height=120, seed=4, baseline_m=0.06)
    assert len(seq.frames) == len(seq.depth_gt_m) == len(seq.masks) == len(seq.T_W_C_true) == 8
    assert [f.stamp_ns for f in seq.frames] == [100_000_000 * (i + 1) for i in range(8)]
    cov = pose_covariance(TRAJECTORY_SPECS["partial"])
    np.testing.assert_allclose(cov, np.diag([1e-6] * 6), rtol=1e-12, atol=0)
    for f, T_true, mask in zip(seq.frames, seq.T_W_C_true, seq.masks):
        assert f.rig.baseline_m == 0.06 and f.rig is seq.rig
        assert f.mask is mask and f.left.shape == (120, 160, 3)
        assert not np.array_equal(f.T_W_C, T_true)
        assert np.abs(f.T_W_C - T_true).max() < 0.01
        np.testing.assert_allclose(f.pose_cov, reported_pose_covariance(f.T_W_C, cov), rtol=1e-12, atol=1e-20)
    assert seq.sigma_d2_m2 == 0.001 and seq.core_overrides == {"stereo.sigma_d2_m2": 0.001}
    assert seq.rig.baseline_m == 0.06
    assert len(make_sequence("box", "complete", n_frames=None, width=16, height=12, seed=4).frames) == 16


def test_underwater_true_turns_the_water_on() -> None:
    """``underwater=True`` renders through the water model: the same seed's left image changes and
    red, absorbed first, loses most on the object."""
    dry = make_sequence("box", "partial", n_frames=1, width=160, height=120, seed=2)
    wet = make_sequence("box", "partial", n_frames=1, width=160, height=120, seed=2, underwater=True)
    m = dry.masks[0]
    np.testing.assert_array_equal(m, wet.masks[0])
    d, w = dry.frames[0].left[m].astype(float).mean(axis=0), wet.frames[0].left[m].astype(float).mean(axis=0)
    assert w[0] < 0.9 * d[0] and w[0] / d[0] < w[2] / d[2]
