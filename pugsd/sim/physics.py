# SPDX-License-Identifier: Apache-2.0
"""Headless MuJoCo grasp trial: a free-floating parallel-jaw gripper against a free object.

The three outcomes follow the paper (Sec. V-A) and are decided as documented in ``docs/sim.md``:

1. **traversal**: the open gripper moves in a straight line from 0.2 m back along the approach axis
   to the grasp pose, checked kinematically every millimetre; success if no gripper geom ever
   penetrates an object geom by more than ``traversal_tol_m`` (the object is held in place during
   this phase and the next, so a collision is recorded, not pushed away).
2. **closed**: the fingers close with a ramped position target (0.5 s ramp, force-limited at
   ``grip_force_n`` per finger, 0.8 s total); success if traversal succeeded, part of the object
   lies in the region between the finger pads (sampled on a grid), the jaws did not close
   completely, and the deepest gripper-object penetration is below ``penetration_tol_m``.
3. **lifted**: the object is released, the gripper rises 0.1 m (1 s) and holds for 5 s; success if
   closing succeeded and at the end both fingers still touch the object, the object is off the
   ground, and its centre of mass rose by at least ``lift_success_m`` (half the lift: an object
   held off-centre may swing like a pendulum, which lowers its centre without dropping it).

The gripper does not collide with the ground (the paper likewise ignores the environment and
moves the object when the arm cannot reach a grasp); the object rests on the ground.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pugsd.config import GripperConfig
from pugsd.sim.objects import ObjectSpec, mesh_occupancy

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrialConfig:
    """Physics and decision parameters of one grasp trial (stated values, see docs/sim.md)."""

    gripper: GripperConfig = field(default_factory=GripperConfig)
    # fingertips reach this far past the grasp centre; None: half the finger length (the pads are
    # centred on the contact line, as the proposer assumes)
    finger_tip_beyond_contact_m: float | None = None
    grip_force_n: float = 60.0  # force limit per finger
    finger_kp: float = 3000.0  # N/m position gain of each finger
    timestep_s: float = 0.002
    pregrasp_offset_m: float = 0.2
    sweep_step_m: float = 0.001  # traversal is checked every millimetre of the path
    close_ramp_s: float = 0.5
    close_time_s: float = 0.8
    lift_height_m: float = 0.1
    lift_time_s: float = 1.0
    hold_time_s: float = 5.0
    traversal_tol_m: float = 0.002
    penetration_tol_m: float = 0.003
    lift_success_m: float = 0.05
    friction: float | None = None  # None: the object's stated friction


@dataclass
class TrialResult:
    """Outcome of one trial; the three metrics are cumulative (each needs the previous one)."""

    traversal: bool
    closed: bool
    lifted: bool
    details: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"traversal": self.traversal, "closed": self.closed, "lifted": self.lifted, **self.details}


def _tip_beyond(cfg: TrialConfig) -> float:
    if cfg.finger_tip_beyond_contact_m is None:
        return 0.5 * cfg.gripper.finger_length_m
    return cfg.finger_tip_beyond_contact_m


def _fmt(v: np.ndarray) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(v))


def _mat2quat(R: np.ndarray) -> np.ndarray:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def build_model_xml(obj: ObjectSpec, T_W_O: np.ndarray, cfg: TrialConfig) -> str:
    """The MJCF model: ground, the object (free body of convex parts) and the gripper (mocap)."""
    g = cfg.gripper
    mu = obj.friction if cfg.friction is None else cfg.friction
    com, inertia = obj.inertia()
    I = 0.5 * (inertia + inertia.T)
    full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
    assets = []
    geoms = []
    for i, part in enumerate(obj.parts):
        assets.append(f'<mesh name="part{i}" vertex="{_fmt(np.asarray(part.vertices))}"/>')
        geoms.append(
            f'<geom name="obj{i}" type="mesh" mesh="part{i}" contype="3" conaffinity="3" '
            f'friction="{mu} 0.005 0.0001" solref="0.004 1" density="0" group="1"/>'
        )
    tip = g.depth_m + _tip_beyond(cfg)
    f_lo = tip - g.finger_length_m
    p_lo = f_lo - g.palm_depth_m
    half_open = 0.5 * g.max_width_m
    th = g.finger_thickness_m
    palm_half_x = half_open + th
    pos = T_W_O[:3, 3]
    quat = _mat2quat(T_W_O[:3, :3])
    finger_geom = (
        'type="box" size="{hx} {hy} {hz}" pos="{px} 0 {pz}" contype="1" conaffinity="1" '
        'friction="{mu} 0.005 0.0001" solref="0.004 1" mass="0.05"'
    )
    fx, fy, fz = 0.5 * th, 0.5 * g.finger_width_m, 0.5 * g.finger_length_m
    fzc = 0.5 * (f_lo + tip)
    left = finger_geom.format(hx=fx, hy=fy, hz=fz, px=-fx, pz=fzc, mu=mu)
    right = finger_geom.format(hx=fx, hy=fy, hz=fz, px=fx, pz=fzc, mu=mu)
    return f"""
<mujoco model="pugs_grasp_trial">
  <option timestep="{cfg.timestep_s}" cone="elliptic" impratio="10" gravity="0 0 -9.81"/>
  <asset>
    {"".join(assets)}
  </asset>
  <worldbody>
    <geom name="ground" type="plane" size="2 2 0.1" contype="2" conaffinity="2"
          friction="{mu} 0.005 0.0001" solref="0.004 1"/>
    <body name="object" pos="{_fmt(pos)}" quat="{_fmt(quat)}">
      <freejoint name="object_free"/>
      <inertial pos="{_fmt(com)}" mass="{obj.mass_kg}" fullinertia="{_fmt(np.asarray(full))}"/>
      {"".join(geoms)}
    </body>
    <body name="target" mocap="true" pos="0 0 1"/>
    <body name="hand" pos="0 0 1" gravcomp="1">
      <freejoint name="hand_free"/>
      <geom name="palm" type="box" size="{palm_half_x} {0.5 * g.palm_width_m} {0.5 * g.palm_depth_m}"
            pos="0 0 {0.5 * (p_lo + f_lo)}" contype="1" conaffinity="1" mass="0.3"/>
      <body name="finger_l">
        <joint name="jl" type="slide" axis="-1 0 0" range="0 {half_open}" damping="2"/>
        <geom name="finger_l" {left}/>
      </body>
      <body name="finger_r">
        <joint name="jr" type="slide" axis="1 0 0" range="0 {half_open}" damping="2"/>
        <geom name="finger_r" {right}/>
      </body>
    </body>
  </worldbody>
  <contact>
    <exclude body1="finger_l" body2="finger_r"/>
  </contact>
  <equality>
    <weld name="drive" body1="hand" body2="target" relpose="0 0 0 1 0 0 0" solref="0.01 1"/>
  </equality>
  <actuator>
    <position name="al" joint="jl" kp="{cfg.finger_kp}" forcerange="-{cfg.grip_force_n} {cfg.grip_force_n}"
              forcelimited="true" ctrlrange="0 {half_open}"/>
    <position name="ar" joint="jr" kp="{cfg.finger_kp}" forcerange="-{cfg.grip_force_n} {cfg.grip_force_n}"
              forcelimited="true" ctrlrange="0 {half_open}"/>
  </actuator>
</mujoco>
"""


class GraspTrial:
    """A MuJoCo model of one object pose; ``run(pose_W)`` evaluates one grasp from a fresh state."""

    def __init__(self, obj: ObjectSpec, T_W_O: np.ndarray, cfg: TrialConfig | None = None) -> None:
        import mujoco

        self._mj = mujoco
        self.cfg = cfg or TrialConfig()
        self.obj = obj
        self.T_W_O = np.asarray(T_W_O, dtype=np.float64)
        self.model = mujoco.MjModel.from_xml_string(build_model_xml(obj, self.T_W_O, self.cfg))
        m = self.model
        self._obj_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        self._hand = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "hand")
        self._mocap = int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "target")])
        hj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "hand_free")
        self._hand_qadr = int(m.jnt_qposadr[hj])
        self._fl = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "finger_l")
        self._fr = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "finger_r")
        self._palm = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "palm")
        self._ground = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ground")
        self._gripper_geoms = {self._fl, self._fr, self._palm}
        self._obj_geoms = {i for i in range(m.ngeom) if int(m.geom_bodyid[i]) == self._obj_body}
        self._jl = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "jl")]
        self._jr = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "jr")]
        self._obj_qadr = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_free")]
        self._obj_vadr = m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object_free")]

    # -- helpers
    def _contacts(self, data: Any) -> tuple[float, set[int], list[tuple[int, np.ndarray]]]:
        """(deepest gripper-object penetration (m, >= 0), gripper geoms touching, [(geom, pos)])."""
        depth = 0.0
        self._deepest_geom = -1
        touching: set[int] = set()
        points: list[tuple[int, np.ndarray]] = []
        for k in range(data.ncon):
            c = data.contact[k]
            g1, g2 = int(c.geom1), int(c.geom2)
            if g1 in self._gripper_geoms and g2 in self._obj_geoms:
                gg = g1
            elif g2 in self._gripper_geoms and g1 in self._obj_geoms:
                gg = g2
            else:
                continue
            if -float(c.dist) > depth:
                depth = -float(c.dist)
                self._deepest_geom = gg
            if c.dist < 0.001:
                touching.add(gg)
                points.append((gg, np.array(c.pos, dtype=np.float64)))
        return depth, touching, points

    def _object_between_pads(self, data: Any, q_l: float, q_r: float) -> float:
        """Fraction of a 7x5x7 sample grid of the region between the finger pads that lies inside
        the object (the paper's "part of the object inside the convex hull of the gripper")."""
        g = self.cfg.gripper
        tip = g.depth_m + _tip_beyond(self.cfg)
        f_lo = tip - g.finger_length_m
        xs = np.linspace(-q_l, q_r, 7)
        ys = np.linspace(-0.5 * g.finger_width_m, 0.5 * g.finger_width_m, 5)
        zs = np.linspace(f_lo, tip, 7)
        grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
        R_h = np.asarray(data.xmat[self._hand]).reshape(3, 3)
        p_W = grid @ R_h.T + np.asarray(data.xpos[self._hand])
        R_o = np.asarray(data.xmat[self._obj_body]).reshape(3, 3)
        p_O = (p_W - np.asarray(data.xpos[self._obj_body])) @ R_o
        return float(np.mean(mesh_occupancy(self.obj.mesh, p_O)))

    def _touches_ground(self, data: Any) -> bool:
        for k in range(data.ncon):
            c = data.contact[k]
            pair = {int(c.geom1), int(c.geom2)}
            if self._ground in pair and pair & self._obj_geoms and c.dist < 0.001:
                return True
        return False

    def _hold_object(self, data: Any, qpos0: np.ndarray) -> None:
        data.qpos[self._obj_qadr : self._obj_qadr + 7] = qpos0
        data.qvel[self._obj_vadr : self._obj_vadr + 6] = 0.0

    def run(self, pose_W: np.ndarray, traversal_only: bool = False) -> TrialResult:
        """Evaluate one grasp (4x4 Contact-GraspNet pose: columns b, a x b, a; wrist origin);
        ``traversal_only`` stops after the traversal (closed and lifted are then False)."""
        mj = self._mj
        cfg = self.cfg
        m = self.model
        data = mj.MjData(m)
        P = np.asarray(pose_W, dtype=np.float64)
        R = P[:3, :3]
        a = R[:, 2]
        goal = P[:3, 3].copy()
        start = goal - cfg.pregrasp_offset_m * a
        data.mocap_quat[self._mocap] = _mat2quat(R)
        half_open = 0.5 * cfg.gripper.max_width_m
        data.qpos[self._jl] = half_open
        data.qpos[self._jr] = half_open
        data.ctrl[:] = half_open
        data.mocap_pos[self._mocap] = start
        data.qpos[self._hand_qadr : self._hand_qadr + 3] = start
        data.qpos[self._hand_qadr + 3 : self._hand_qadr + 7] = data.mocap_quat[self._mocap]
        mj.mj_forward(m, data)
        qpos0 = data.qpos[self._obj_qadr : self._obj_qadr + 7].copy()
        dt = m.opt.timestep
        details: dict[str, Any] = {}

        # 1. traversal: a kinematic sweep (the hand pose is set, contacts are computed), so the
        # penetration depth is geometric and not limited by the contact solver
        n_trav = max(1, round(cfg.pregrasp_offset_m / cfg.sweep_step_m))
        worst = 0.0
        first_hit: float | None = None
        for i in range(n_trav + 1):
            s = i / n_trav
            p = start + s * (goal - start)
            data.qpos[self._hand_qadr : self._hand_qadr + 3] = p
            data.qvel[:] = 0.0
            data.mocap_pos[self._mocap] = p
            mj.mj_forward(m, data)
            depth, _, _ = self._contacts(data)
            if depth > cfg.traversal_tol_m and first_hit is None:
                first_hit = s
                details["traversal_collision_geom"] = m.geom(self._deepest_geom).name
            worst = max(worst, depth)
        traversal = first_hit is None
        details["traversal_max_penetration_m"] = worst
        details["traversal_first_collision_fraction"] = first_hit
        if not traversal or traversal_only:
            return TrialResult(traversal, False, False, details)

        # 2. close
        n_ramp = round(cfg.close_ramp_s / dt)
        n_close = round(cfg.close_time_s / dt)
        for i in range(n_close):
            target = half_open * max(0.0, 1.0 - (i + 1) / n_ramp)
            data.ctrl[:] = target
            mj.mj_step(m, data)
            self._hold_object(data, qpos0)
        mj.mj_forward(m, data)
        depth, touching, _ = self._contacts(data)
        q_l, q_r = float(data.qpos[self._jl]), float(data.qpos[self._jr])
        opening = q_l + q_r
        between = self._object_between_pads(data, q_l, q_r)
        closed = bool(between > 0 and depth < cfg.penetration_tol_m and opening > 0.001)
        details.update(
            closed_opening_m=opening,
            closed_max_penetration_m=depth,
            closed_between_fraction=between,
            closed_touching=sorted(m.geom(i).name for i in touching),
        )
        if not closed:
            return TrialResult(True, False, False, details)

        # 3. lift and hold (object released)
        z0 = float(data.xipos[self._obj_body][2])
        n_lift = round(cfg.lift_time_s / dt)
        n_hold = round(cfg.hold_time_s / dt)
        up = np.array([0.0, 0.0, cfg.lift_height_m])
        data.ctrl[:] = 0.0
        for i in range(n_lift + n_hold):
            s = min(1.0, (i + 1) / n_lift)
            data.mocap_pos[self._mocap] = goal + s * up
            mj.mj_step(m, data)
        mj.mj_forward(m, data)
        _, touching, _ = self._contacts(data)
        rise = float(data.xipos[self._obj_body][2]) - z0
        on_ground = self._touches_ground(data)
        lifted = bool(
            rise >= cfg.lift_success_m
            and self._fl in touching
            and self._fr in touching
            and not on_ground
        )
        details.update(
            lift_rise_m=rise,
            lift_touching=sorted(m.geom(i).name for i in touching),
            lift_on_ground=on_ground,
        )
        return TrialResult(True, True, lifted, details)


def grasp_pose(contact_W: np.ndarray, baseline_W: np.ndarray, approach_W: np.ndarray,
               width_m: float, depth_m: float = 0.09) -> np.ndarray:
    """A Contact-GraspNet grasp pose from a contact, baseline b, approach a (made orthogonal)."""
    b = np.asarray(baseline_W, float)
    b = b / np.linalg.norm(b)
    a = np.asarray(approach_W, float)
    a = a - (a @ b) * b
    a = a / np.linalg.norm(a)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = b, np.cross(a, b), a
    T[:3, 3] = np.asarray(contact_W, float) + 0.5 * width_m * b - depth_m * a
    return T


def run_trial(obj: ObjectSpec, T_W_O: np.ndarray, pose_W: np.ndarray,
              cfg: TrialConfig | None = None) -> TrialResult:
    """One-shot convenience: build the model and run one grasp."""
    return GraspTrial(obj, T_W_O, cfg).run(pose_W)
