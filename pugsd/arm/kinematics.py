# SPDX-License-Identifier: Apache-2.0
"""Bravo 7 kinematics: FK from the datasheet's standard DH table, geometric Jacobian, and our
own damped-least-squares IK with joint limits and multiple seeds (the arm's IK is a paid option).

Units: metres and radians. Joint vector ``q`` holds the 6 revolute joints in DH order (joint 1 =
base rotate, device 0x07 ... joint 6 = end-effector rotate, device 0x02). The raw device position
of joint i is ``(theta_i - offset_i) * sign_i`` wrapped as the device reports it; see
:meth:`Bravo7Model.to_device` / :meth:`Bravo7Model.from_device`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from pugsd.errors import ArmError

THETA_S = math.atan(5.2 / 290.77)
A2 = math.hypot(5.2, 290.77)


@dataclass(frozen=True, slots=True)
class DHRow:
    """Standard DH row: T = Rz(theta + theta_offset) Tz(d) Tx(a) Rx(alpha); d and a in metres."""

    d: float
    theta_offset: float
    a: float
    alpha: float


def bravo7_dh(ft_sensor: bool = False) -> tuple[DHRow, tuple[DHRow, ...], DHRow]:
    """(fixed base row, 6 joint rows, fixed tool row) from the Bravo MKII datasheet (mm -> m)."""
    pi = math.pi
    base = DHRow(0.04145, 0.0, 0.0675, pi)
    joints = (
        DHRow(-0.11748, pi, 0.046, -pi / 2),
        DHRow(0.0, -pi / 2 + THETA_S, A2 / 1000.0, 0.0),
        DHRow(0.0, -pi / 2 - THETA_S, 0.0408, -pi / 2),
        DHRow(-0.16026, pi, 0.0408, -pi / 2),
        DHRow(0.0, 0.0, 0.0408, -pi / 2),
        DHRow(-0.28416 if ft_sensor else -0.22416, 0.0, 0.0, pi / 2),
    )
    tool = DHRow(0.0, -pi / 2, 0.120, 0.0)
    return base, joints, tool


def dh_matrix(row: DHRow, theta: float) -> np.ndarray:
    th = theta + row.theta_offset
    ct, st = math.cos(th), math.sin(th)
    ca, sa = math.cos(row.alpha), math.sin(row.alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, row.a * ct],
            [st, ct * ca, -ct * sa, row.a * st],
            [0.0, sa, ca, row.d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def rotation_error(R_target: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rotation vector of ``R_target R^T`` (base frame), radians."""
    E = R_target @ R.T
    c = (E[0, 0] + E[1, 1] + E[2, 2] - 1.0) * 0.5
    v = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    if c > 0.999999:
        return 0.5 * v
    if c < -0.99:
        return np.asarray(Rotation.from_matrix(E).as_rotvec())
    ang = math.acos(c)
    return v * (ang / (2.0 * math.sin(ang)))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def pose_error(T_target: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    """(position error m, rotation error rad) between two 4x4 poses."""
    dp = float(np.linalg.norm(T_target[:3, 3] - T[:3, 3]))
    dr = float(np.linalg.norm(rotation_error(T_target[:3, :3], T[:3, :3])))
    return dp, dr


@dataclass(frozen=True, slots=True)
class IKResult:
    """A converged IK solution (joint angles in DH order) and its residual."""

    q: np.ndarray
    pos_err_m: float
    rot_err_rad: float
    iterations: int
    seed_index: int


class Bravo7Model:
    """FK / Jacobian / IK of the Bravo 7 with joint limits (DH angles, radians)."""

    n_joints = 6

    def __init__(
        self,
        q_min: Sequence[float],
        q_max: Sequence[float],
        *,
        ft_sensor: bool = False,
        offsets: Sequence[float] = (0.0,) * 6,
        signs: Sequence[float] = (1.0,) * 6,
        T_tool_tcp: np.ndarray | None = None,
    ) -> None:
        self.base_row, self.rows, self.tool_row = bravo7_dh(ft_sensor)
        self.q_min = np.asarray(q_min, dtype=float)
        self.q_max = np.asarray(q_max, dtype=float)
        if self.q_min.shape != (6,) or self.q_max.shape != (6,) or np.any(self.q_min >= self.q_max):
            raise ArmError("joint limits: need 6 (min, max) pairs with min < max")
        # joints whose range covers (almost) a full turn are treated as wrapping during IK
        self._circular = (self.q_max - self.q_min) >= 2.0 * math.pi - 0.1
        self.offsets = np.asarray(offsets, dtype=float)
        self.signs = np.asarray(signs, dtype=float)
        self.T_base0 = dh_matrix(self.base_row, 0.0)
        self.T_tool = dh_matrix(self.tool_row, 0.0)
        if T_tool_tcp is not None:
            self.T_tool = self.T_tool @ np.asarray(T_tool_tcp, dtype=float)

    # ---------------------------------------------------------------- device mapping

    def to_device(self, q: np.ndarray) -> np.ndarray:
        """DH angles -> raw device positions (rad)."""
        return (np.asarray(q, dtype=float) - self.offsets) * self.signs

    def from_device(self, raw: np.ndarray) -> np.ndarray:
        """Raw device positions -> DH angles, unwrapped into the joint limits where possible."""
        q = np.asarray(raw, dtype=float) * self.signs + self.offsets
        return self.wrap_into_limits(q)

    def wrap_into_limits(self, q: np.ndarray) -> np.ndarray:
        """Shift each angle by multiples of 2 pi into [q_min, q_max] when that is possible.
        ArmError for non-finite angles (NaN feedback must never reach the planner)."""
        q = np.array(q, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ArmError(f"joint angles must be 6 finite values, got {q.tolist()}")
        two_pi = 2.0 * math.pi
        for i in range(6):
            if self.q_min[i] <= q[i] <= self.q_max[i]:
                continue
            k = math.ceil((self.q_min[i] - q[i]) / two_pi)
            cand = q[i] + k * two_pi
            if cand <= self.q_max[i]:
                q[i] = cand
        return q

    def _project(self, q: np.ndarray) -> np.ndarray:
        """Wrap joints whose range spans a full turn, then clip to the limits."""
        q = np.array(q, dtype=float)
        c = self._circular
        if c.any():
            q[c] = self.q_min[c] + np.mod(q[c] - self.q_min[c], 2.0 * math.pi)
        return np.clip(q, self.q_min, self.q_max)

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> bool:
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= self.q_min - tol) and np.all(q <= self.q_max + tol))

    # ---------------------------------------------------------------- kinematics

    def frames(self, q: npt.ArrayLike) -> list[np.ndarray]:
        """Frames 0..6 (after the fixed base row and after each joint) in the base frame."""
        T = self.T_base0.copy()
        out = [T]
        for row, th in zip(self.rows, np.asarray(q, dtype=float)):
            T = T @ dh_matrix(row, float(th))
            out.append(T)
        return out

    def fk(self, q: npt.ArrayLike) -> np.ndarray:
        """Tool (TCP) pose in the arm base frame, 4x4."""
        return self.frames(q)[-1] @ self.T_tool

    def jacobian(self, q: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(6x6 geometric Jacobian [v; w] at the TCP, TCP pose)."""
        fr = self.frames(q)
        T = fr[-1] @ self.T_tool
        p = T[:3, 3]
        J = np.empty((6, 6))
        for i in range(6):
            z = fr[i][:3, 2]
            o = fr[i][:3, 3]
            J[:3, i] = _cross(z, p - o)
            J[3:, i] = z
        return J, T

    def pose_error_bound(self, q: npt.ArrayLike, dq_max_rad: float) -> tuple[float, float]:
        """First-order bound on the TCP (position m, rotation rad) error when every joint is within
        ``dq_max_rad`` of ``q``: sum_i |J_i| dq_max over the Jacobian's columns. Controllers that
        converge joint by joint to a tolerance can promise the pose only to this bound."""
        J, _ = self.jacobian(q)
        pos = float(np.linalg.norm(J[:3], axis=0).sum()) * dq_max_rad
        rot = float(np.linalg.norm(J[3:], axis=0).sum()) * dq_max_rad
        return pos, rot

    def ik(
        self,
        T_target: np.ndarray,
        seeds: Sequence[np.ndarray],
        *,
        q_ref: np.ndarray | None = None,
        tol_m: float = 1e-4,
        tol_rad: float = 1e-3,
        max_iter: int = 150,
        damping: float = 0.02,
        max_step_rad: float = 0.3,
        stop_at_first: bool = False,
        pause: Callable[[], None] | None = None,
    ) -> IKResult | None:
        """Damped least squares from each seed, joint limits enforced by projection.

        Returns the converged solution closest to ``q_ref`` (default: the first seed), or None.
        ``pause`` is called every iteration (e.g. ``time.sleep(0)`` in a worker thread, so that
        the event loop thread gets the GIL often).
        """
        T_target = np.asarray(T_target, dtype=float)
        ref = np.asarray(q_ref if q_ref is not None else seeds[0], dtype=float)
        best: IKResult | None = None
        best_d = math.inf
        W = np.array([1.0, 1.0, 1.0, 0.2, 0.2, 0.2])  # 1 rad of rotation ~ 0.2 m
        eye = np.eye(6)
        for si, seed in enumerate(seeds):
            q = self._project(np.asarray(seed, dtype=float))
            lam2 = damping * damping
            prev = math.inf
            for it in range(max_iter):
                if pause is not None:
                    pause()
                J, T = self.jacobian(q)
                e = np.concatenate([T_target[:3, 3] - T[:3, 3], rotation_error(T_target[:3, :3], T[:3, :3])])
                ep = float(np.linalg.norm(e[:3]))
                er = float(np.linalg.norm(e[3:]))
                if ep <= tol_m and er <= tol_rad:
                    d = float(np.abs(q - ref).max())
                    if d < best_d:
                        best, best_d = IKResult(q.copy(), ep, er, it, si), d
                    break
                ew = e * W
                cost = float(ew @ ew)
                # Levenberg-style damping: relax when improving, stiffen when not
                lam2 = max(lam2 * 0.5, 1e-8) if cost < prev else min(lam2 * 4.0, 1.0)
                prev = cost
                Jw = J * W[:, None]
                dq = Jw.T @ np.linalg.solve(Jw @ Jw.T + lam2 * eye, ew)
                # active set: joints on a hard limit pushed outwards are frozen for this step
                blocked = ((q <= self.q_min + 1e-9) & (dq < 0) & ~self._circular) | (
                    (q >= self.q_max - 1e-9) & (dq > 0) & ~self._circular
                )
                if blocked.any():
                    Jw = Jw * (~blocked)[None, :]
                    dq = Jw.T @ np.linalg.solve(Jw @ Jw.T + lam2 * eye, ew)
                m = float(np.abs(dq).max())
                if m > max_step_rad:
                    dq *= max_step_rad / m
                q = self._project(q + dq)
            if best is not None and stop_at_first:
                break
        return best

    def random_q(self, rng: np.random.Generator, n: int, margin: float = 0.0) -> np.ndarray:
        """``n`` random joint vectors uniformly inside the limits shrunk by ``margin``."""
        return rng.uniform(self.q_min + margin, self.q_max - margin, size=(n, 6))


def pose_from_xyz_quat(xyz: npt.ArrayLike, quat_xyzw: npt.ArrayLike) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(quat_xyzw, dtype=float)).as_matrix()
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def pose_from_xyz_rpy(xyz: npt.ArrayLike, rpy: npt.ArrayLike) -> np.ndarray:
    """Roll, pitch, yaw about fixed x, y, z (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", np.asarray(rpy, dtype=float)).as_matrix()
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def km_end_pos_to_pose(values: Sequence[float]) -> np.ndarray:
    """KM_END_POS [x, y, z mm, yaw, pitch, roll rad] -> 4x4 (m), R = Rz(yaw) Ry(pitch) Rx(roll)."""
    x, y, z, yaw, pitch, roll = (float(v) for v in values)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    T[:3, 3] = [x / 1000.0, y / 1000.0, z / 1000.0]
    return T


def pose_to_km_end_pos(T: np.ndarray) -> tuple[float, ...]:
    yaw, pitch, roll = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("ZYX")
    x, y, z = (float(v) * 1000.0 for v in np.asarray(T)[:3, 3])
    return (x, y, z, float(yaw), float(pitch), float(roll))
