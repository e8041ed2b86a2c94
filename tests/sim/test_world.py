# SPDX-License-Identifier: Apache-2.0
"""Rendering: exact ground-truth depth, stereo consistency (SGBM), masks, noise, determinism."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest
import trimesh

from pugsd.core.geometry import look_at
from pugsd.sim import make_sequence, object_pose
from pugsd.sim.objects import get_object
from pugsd.sim.render import OBJECT_ID, World, default_rig, render_stereo
from pugsd.sim.sequence import (
    TRAJECTORY_SPECS,
    perturb_pose,
    pose_covariance,
    reported_pose_covariance,
    se3_exp,
)


def _sphere_world(r: float, c: np.ndarray) -> World:
    s = trimesh.creation.icosphere(subdivisions=5, radius=r)
    s.apply_translation(c)
    return World(np.asarray(s.vertices), np.asarray(s.faces), np.eye(4))


def test_depth_of_ground_plane_is_analytic() -> None:
    world = _sphere_world(0.05, np.array([5.0, 5.0, 0.0]))  # out of view
    cam = default_rig(160, 120).left
    T = look_at(np.array([0.0, -0.5, 0.4]), np.array([0.0, 0.0, 0.0]))
    out = world.render(cam, T)
    rays_W = cam.rays().reshape(-1, 3) @ T[:3, :3].T
    t = -T[2, 3] / rays_W[:, 2]  # ray parameter to z = 0 (rays have unit camera z)
    expect = np.where(t > 0, t, np.nan).reshape(cam.height, cam.width)
    hit = np.isfinite(out.depth_m)
    assert hit.mean() > 0.9
    np.testing.assert_allclose(out.depth_m[hit], expect[hit], atol=1e-4)


def test_depth_of_sphere_centre_pixel() -> None:
    r, d = 0.06, 0.5
    world = _sphere_world(r, np.array([0.0, 0.0, 0.3]))
    cam = default_rig(161, 121).left  # odd size: a pixel on the optical axis
    T = look_at(np.array([0.0, -d, 0.3]), np.array([0.0, 0.0, 0.3]))
    out = world.render(cam, T)
    assert out.depth_m[60, 80] == pytest.approx(d - r, abs=5e-4)
    assert out.geometry[60, 80] == OBJECT_ID
    # the silhouette radius matches the projected sphere (f r / sqrt(d^2 - r^2)) within a pixel
    rows = np.flatnonzero(out.geometry[:, 80] == OBJECT_ID)
    radius_px = 0.5 * (rows.max() - rows.min() + 1)
    assert radius_px == pytest.approx(cam.fx * r / np.sqrt(d * d - r * r), abs=1.0)


def test_sgbm_on_rendered_pair_matches_ground_truth() -> None:
    seq = make_sequence("kettlebell", "partial", n_frames=1, width=320, height=240, seed=3)
    f, gt, mask = seq.frames[0], seq.depth_gt_m[0], seq.masks[0]
    rig = seq.rig
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=48, blockSize=5, P1=8 * 25, P2=32 * 25,
        uniquenessRatio=10, speckleWindowSize=50, speckleRange=2, disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    gl = cv2.cvtColor(f.left, cv2.COLOR_RGB2GRAY)
    gr = cv2.cvtColor(f.right, cv2.COLOR_RGB2GRAY)
    disp = sgbm.compute(gl, gr).astype(np.float32) / 16.0
    z = np.where(disp > 0, rig.left.fx * rig.baseline_m / np.maximum(disp, 1e-6), np.nan)
    err = np.abs(z - gt)[mask]
    assert np.isfinite(err).mean() > 0.9  # valid on the object
    assert np.nanmedian(err) < 0.006  # 6 mm at 0.45 m, 320 x 240 (measured about 3 mm)


def test_mask_and_depth_lie_on_the_mesh() -> None:
    import open3d as o3d

    seq = make_sequence("mug", "complete", n_frames=2, width=160, height=120, seed=1)
    m_W = seq.mesh_W
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(m_W.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(m_W.faces, np.uint32)),
    )
    for i in range(2):
        mask, depth, T = seq.masks[i], seq.depth_gt_m[i], seq.T_W_C_true[i]
        assert mask.sum() > 200
        assert np.all(np.isfinite(depth[mask]))
        p_C = seq.rig.left.rays()[mask] * depth[mask][:, None]
        p_W = p_C @ T[:3, :3].T + T[:3, 3]
        d = scene.compute_distance(o3d.core.Tensor(p_W.astype(np.float32))).numpy()
        assert np.max(d) < 1e-4


def test_deterministic_for_a_seed() -> None:
    a = make_sequence("box", "noisy_partial", n_frames=2, width=160, height=120, seed=5)
    b = make_sequence("box", "noisy_partial", n_frames=2, width=160, height=120, seed=5)
    c = make_sequence("box", "noisy_partial", n_frames=2, width=160, height=120, seed=6)
    for fa, fb in zip(a.frames, b.frames):
        assert np.array_equal(fa.left, fb.left) and np.array_equal(fa.right, fb.right)
        assert np.array_equal(fa.T_W_C, fb.T_W_C)
    assert not np.array_equal(a.frames[0].T_W_C, c.frames[0].T_W_C)
    assert a.core_overrides == {"stereo.sigma_d2_m2": 0.01}


def test_pose_noise_follows_its_covariance() -> None:
    """The covariance a frame reports is that of its pose noise in the core's convention:
    ``dt = t - t_true`` and ``phi = log(R R_true^T)``, estimated from 20000 noisy poses."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    cov_xi = pose_covariance(TRAJECTORY_SPECS["noisy_partial"])
    T0 = look_at(np.array([0.3, -0.3, 0.3]), np.zeros(3))
    Ts = [perturb_pose(T0, cov_xi, rng) for _ in range(20_000)]
    err = np.array(
        [np.r_[T[:3, 3] - T0[:3, 3], Rotation.from_matrix(T[:3, :3] @ T0[:3, :3].T).as_rotvec()] for T in Ts]
    )
    reported = reported_pose_covariance(T0, cov_xi)
    scale = np.sqrt(np.outer(np.diag(reported), np.diag(reported)))
    np.testing.assert_allclose(np.cov(err.T) / scale, reported / scale, atol=0.03)
    # the rotation noise about the world origin moves the camera centre: dt is correlated with phi
    assert np.abs(reported[:3, 3:]).max() > 0.5 * cov_xi[3, 3] * 0.3
    assert np.abs(err.mean(axis=0) / np.sqrt(np.diag(reported))).max() < 4 / np.sqrt(20_000) * 2
    # se3_exp of a pure translation is a translation
    T = se3_exp(np.array([0.1, -0.2, 0.3, 0, 0, 0]))
    np.testing.assert_allclose(T[:3, 3], [0.1, -0.2, 0.3])


def test_trajectories_cover_what_they_claim() -> None:
    full = make_sequence("bottle", "complete", n_frames=8, width=160, height=120, seed=2)
    part = make_sequence("bottle", "partial", n_frames=8, width=160, height=120, seed=2)
    centre = 0.5 * (full.mesh_W.bounds[0] + full.mesh_W.bounds[1])

    def azimuths(seq: object) -> np.ndarray:
        cams = np.array([T[:3, 3] for T in seq.T_W_C_true])  # type: ignore[attr-defined]
        d = cams - centre
        return np.degrees(np.arctan2(d[:, 1], d[:, 0]))

    az_full = np.sort(azimuths(full) % 360)
    gaps = np.diff(np.r_[az_full, az_full[0] + 360])
    assert gaps.max() < 100  # all around
    az_part = azimuths(part)
    span = np.ptp(np.unwrap(np.radians(az_part)))
    assert np.degrees(span) == pytest.approx(40.0, abs=1e-6)
    for T in part.T_W_C_true:  # every camera looks at the object centre
        ray = centre - T[:3, 3]
        cosang = ray @ T[:3, 2] / np.linalg.norm(ray)
        assert cosang > 1.0 - 1e-9
        assert T[2, 1] < 0  # image y points down (world z up)


def test_underwater_degrades_contrast() -> None:
    o = get_object("box")
    T_W_O = object_pose(o, "upright")
    v = np.asarray(o.mesh.vertices) @ T_W_O[:3, :3].T + T_W_O[:3, 3]
    world = World(v, np.asarray(o.mesh.faces), T_W_O)
    rig = default_rig(160, 120)
    T = look_at(np.array([0.0, -0.5, 0.3]), np.array([0.0, 0.0, 0.07]))
    from pugsd.sim.render import Underwater

    dry_l, _, depth, _ = render_stereo(world, rig, T, np.random.default_rng(0), 0.0)
    wet_l = render_stereo(world, rig, T, np.random.default_rng(0), 0.0, Underwater(enabled=True))[0]
    hit = np.isfinite(depth)
    dry, wet = dry_l.astype(float)[hit], wet_l.astype(float)[hit]
    assert wet.std(axis=0).mean() < 0.9 * dry.std(axis=0).mean()  # texture contrast drops
    assert wet[:, 2].mean() > wet[:, 0].mean()  # red is absorbed first


def test_poses_rest_on_the_ground() -> None:
    for name in ("kettlebell", "mug"):
        o = get_object(name)
        for pose in ("upright", "lying", "tilted", "sideways"):
            T = object_pose(o, pose)
            v = np.asarray(o.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
            assert v[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    lying = object_pose(get_object("bottle"), "lying")
    assert lying[2, 2] == pytest.approx(0.0, abs=1e-12)  # its axis is horizontal


def test_import_does_not_load_mujoco() -> None:
    code = "import sys, pugsd.sim; print('mujoco' in sys.modules, 'open3d' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
