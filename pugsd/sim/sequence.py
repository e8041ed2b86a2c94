# SPDX-License-Identifier: Apache-2.0
"""Scenes, object-centric camera trajectories and rendered stereo sequences.

World frame W: z up, the ground is the plane z = 0. Cameras use the OpenCV convention (x right,
y down, z forward). ``make_sequence`` is the one-call entry point.

Trajectories (camera on a sphere around the object's bounding-box centre, looking at it):

* ``complete``: two rings (elevations 25 and 55 deg) all around the object plus nothing hidden
  except the underside;
* ``partial``: one arc of 40 deg azimuth at 30 deg elevation, centred on a seeded azimuth, so the
  far side stays unseen;
* ``noisy_partial``: the same arc, with larger pose noise, sensor noise, and the pipeline's depth
  variance sigma_d^2 = 0.01 m^2 (``core_overrides``).

Each reported pose ``T_W_C`` is the true pose perturbed by ``exp(xi^)`` (left perturbation, world
frame) with ``xi = (rho, phi) ~ N(0, pose_covariance(spec))``. The frame reports that noise's
covariance in the convention of pugsd.core.types (ROS's: camera-centre error ``dt``, rotation
``phi`` about the world axes through the camera), ``reported_pose_covariance``.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from pugsd.core.camera import StereoRig
from pugsd.core.geometry import look_at, skew
from pugsd.core.types import StereoFrame
from pugsd.errors import InputError
from pugsd.sim.objects import ObjectSpec, get_object
from pugsd.sim.render import Underwater, World, default_rig, render_stereo

log = logging.getLogger(__name__)

PARTIAL_ARC_DEG = 40.0  # azimuth span of the partial trajectories
POSES = ("upright", "lying", "tilted", "sideways")
TRAJECTORIES = ("complete", "partial", "noisy_partial")


@dataclass(frozen=True)
class TrajectorySpec:
    """Parameters of one trajectory type."""

    name: str
    sigma_t_m: float  # pose covariance: translation std per axis
    sigma_r_rad: float  # pose covariance: rotation std per axis
    image_noise_std: float  # grey levels
    sigma_d2_m2: float  # the pipeline's depth variance for this experiment (paper values)


TRAJECTORY_SPECS: dict[str, TrajectorySpec] = {
    "complete": TrajectorySpec("complete", 0.001, 0.001, 1.0, 0.001),
    "partial": TrajectorySpec("partial", 0.001, 0.001, 1.0, 0.001),
    "noisy_partial": TrajectorySpec("noisy_partial", 0.004, 0.004, 4.0, 0.01),
}


# ----------------------------------------------------------------------------- SE(3) helpers


def so3_exp(phi: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(phi))
    K = skew(phi)
    if th < 1e-9:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """exp of xi = (rho, phi) (translation first) as a 4x4 transform."""
    rho, phi = np.asarray(xi[:3], float), np.asarray(xi[3:], float)
    th = float(np.linalg.norm(phi))
    K = skew(phi)
    if th < 1e-9:
        J = np.eye(3) + 0.5 * K
    else:
        J = np.eye(3) + (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K
    T = np.eye(4)
    T[:3, :3] = so3_exp(phi)
    T[:3, 3] = J @ rho
    return T


def perturb_pose(T: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``exp(xi^) T`` with ``xi = (rho, phi) ~ N(0, cov)`` (left perturbation, world frame)."""
    L = np.linalg.cholesky(np.asarray(cov, float) + 1e-18 * np.eye(6))
    return se3_exp(L @ rng.standard_normal(6)) @ np.asarray(T, float)


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# ----------------------------------------------------------------------------- scene placement


def object_pose(obj: ObjectSpec, pose: str = "upright", yaw_deg: float = 0.0) -> np.ndarray:
    """T_W_O placing the object in a paper pose, resting on z = 0, bounding box centred at x=y=0.

    ``upright``: as modelled; ``lying``: on its side (90 deg about x); ``tilted``: leaning 30 deg
    about x (its top towards +y, so its -y face turns upwards; it rests on an edge, held in
    place in the physics trial until lifted); ``sideways``: turned 90 deg about z. ``yaw_deg``
    turns it about z.
    """
    if pose not in POSES:
        raise InputError(f"unknown pose {pose!r}; known: {', '.join(POSES)}")
    R = {
        "upright": np.eye(3),
        "lying": _rot("x", 90.0),
        "tilted": _rot("x", -30.0),
        "sideways": _rot("z", 90.0),
    }[pose]
    R = _rot("z", yaw_deg) @ R
    v = np.asarray(obj.mesh.vertices) @ R.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2]]
    return T


def camera_path(
    trajectory: str,
    n_frames: int,
    target_W: np.ndarray,
    rng: np.random.Generator,
    radius_m: float = 0.45,
) -> list[np.ndarray]:
    """True T_W_C poses of an object-centric trajectory (see the module docstring)."""
    if trajectory not in TRAJECTORIES:
        raise InputError(f"unknown trajectory {trajectory!r}; known: {', '.join(TRAJECTORIES)}")
    if n_frames < 1:
        raise InputError("n_frames must be >= 1")
    az0 = float(rng.uniform(0.0, 360.0))
    if trajectory == "complete":
        n1 = (n_frames + 1) // 2
        n2 = n_frames - n1
        az = np.concatenate(
            [
                az0 + np.arange(n1) * 360.0 / n1,
                az0 + 180.0 / max(n1, 1) + np.arange(n2) * 360.0 / max(n2, 1),
            ]
        )
        el = np.concatenate([np.full(n1, 25.0), np.full(n2, 55.0)])
    else:
        half = PARTIAL_ARC_DEG / 2.0
        az = az0 + (np.linspace(-half, half, n_frames) if n_frames > 1 else np.zeros(1))
        el = np.full(n_frames, 30.0)
    el = el + rng.uniform(-3.0, 3.0, el.shape)
    r = radius_m + rng.uniform(-0.02, 0.02, el.shape)
    poses = []
    for a, e, rr in zip(np.deg2rad(az), np.deg2rad(el), r):
        eye = np.asarray(target_W, float) + rr * np.array(
            [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]
        )
        poses.append(look_at(eye, target_W))
    return poses


def pose_covariance(spec: TrajectorySpec) -> np.ndarray:
    """The 6x6 covariance of ``xi = (rho, phi)``, the trajectory's pose noise (``perturb_pose``)."""
    return np.diag([spec.sigma_t_m**2] * 3 + [spec.sigma_r_rad**2] * 3)


def reported_pose_covariance(T_W_C: np.ndarray, cov_xi: np.ndarray) -> np.ndarray:
    """The (dt, phi) covariance (pugsd.core.types) of the pose ``exp(xi^) T_W_C``, xi ~ N(0, cov_xi).

    To first order ``t' = t + rho + phi x t``, so ``dt = rho - [t]_x phi``: ``B cov_xi B^T`` with
    ``B = [[I, -[t]_x], [0, I]]``; the rotation error ``phi`` is the same in both.
    """
    B = np.eye(6)
    B[:3, 3:] = -skew(np.asarray(T_W_C, float)[:3, 3])
    return B @ np.asarray(cov_xi, float) @ B.T


# ----------------------------------------------------------------------------- sequence


@dataclass
class SyntheticSequence:
    """A rendered stereo sequence with its ground truth.

    ``frames[i].T_W_C`` is the reported (noisy) pose, ``T_W_C_true[i]`` the true one;
    ``depth_gt_m[i]`` is the left camera's true z-depth (NaN on a miss), ``masks[i]`` its object
    mask. ``mesh`` is the object in its own frame, ``mesh_W`` in the world (``T_W_O``).
    ``core_overrides`` are the dotted config overrides this experiment implies for the pipeline
    (e.g. ``{"stereo.sigma_d2_m2": 0.01}`` for ``noisy_partial``).
    """

    frames: list[StereoFrame]
    depth_gt_m: list[np.ndarray]
    masks: list[np.ndarray]
    T_W_C_true: list[np.ndarray]
    obj: ObjectSpec
    T_W_O: np.ndarray
    rig: StereoRig
    pose: str
    trajectory: str
    seed: int
    sigma_d2_m2: float
    core_overrides: dict[str, Any] = field(default_factory=dict)

    @property
    def mesh(self) -> trimesh.Trimesh:
        return self.obj.mesh

    @property
    def mesh_W(self) -> trimesh.Trimesh:
        m = self.obj.mesh.copy()
        m.apply_transform(self.T_W_O)
        return m

    @property
    def object_name(self) -> str:
        return self.obj.name


def _seed_for(*parts: object) -> int:
    h = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(h[:4], "little")


def make_sequence(
    object_name: str = "mug",
    trajectory: str = "partial",
    n_frames: int | None = None,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    pose: str = "upright",
    yaw_deg: float = 0.0,
    obj: ObjectSpec | None = None,
    underwater: Underwater | bool | None = None,
    supersample: int = 1,
    radius_m: float = 0.45,
    baseline_m: float | None = None,
) -> SyntheticSequence:
    """Render a stereo sequence of an object on the ground; deterministic for a given seed.

    ``n_frames`` defaults to 16 for ``complete`` and 8 for the partial trajectories. Pass ``obj``
    to use a user object (``load_object_mesh``) instead of a built-in ``object_name``.
    """
    if trajectory not in TRAJECTORY_SPECS:
        raise InputError(f"unknown trajectory {trajectory!r}; known: {', '.join(TRAJECTORIES)}")
    spec = TRAJECTORY_SPECS[trajectory]
    o = obj if obj is not None else get_object(object_name)
    n = n_frames if n_frames is not None else (16 if trajectory == "complete" else 8)
    uw = underwater if isinstance(underwater, Underwater) else Underwater(enabled=bool(underwater))
    rig = default_rig(width, height) if baseline_m is None else default_rig(width, height, baseline_m)
    T_W_O = object_pose(o, pose, yaw_deg)
    verts_W = np.asarray(o.mesh.vertices) @ T_W_O[:3, :3].T + T_W_O[:3, 3]
    world = World(verts_W, np.asarray(o.mesh.faces), T_W_O, texture_seed=seed)
    target = 0.5 * (verts_W.min(axis=0) + verts_W.max(axis=0))
    rng_path = np.random.default_rng(_seed_for("path", seed, trajectory))
    rng_pose = np.random.default_rng(_seed_for("pose", seed, trajectory))
    rng_img = np.random.default_rng(_seed_for("image", seed, trajectory, width, height))
    true_poses = camera_path(trajectory, n, target, rng_path, radius_m)
    cov = pose_covariance(spec)
    frames, depths, masks = [], [], []
    for i, T_true in enumerate(true_poses):
        T_rep = perturb_pose(T_true, cov, rng_pose)
        left, right, depth, mask = render_stereo(
            world, rig, T_true, rng_img, spec.image_noise_std, uw, supersample
        )
        frames.append(
            StereoFrame(
                stamp_ns=(i + 1) * 100_000_000,
                left=left,
                right=right,
                rig=rig,
                T_W_C=T_rep,
                pose_cov=reported_pose_covariance(T_rep, cov),
                mask=mask,
            )
        )
        depths.append(depth)
        masks.append(mask)
    log.debug("rendered %s/%s seed %d: %d frames %dx%d", o.name, trajectory, seed, n, width, height)
    return SyntheticSequence(
        frames=frames,
        depth_gt_m=depths,
        masks=masks,
        T_W_C_true=true_poses,
        obj=o,
        T_W_O=T_W_O,
        rig=rig,
        pose=pose,
        trajectory=trajectory,
        seed=seed,
        sigma_d2_m2=spec.sigma_d2_m2,
        core_overrides={"stereo.sigma_d2_m2": spec.sigma_d2_m2},
    )
