# SPDX-License-Identifier: Apache-2.0
"""``pugsd replay``: run the PUGS pipeline directly on a recording, without zenoh.

Frames are assembled as the daemon does: topic names normalised (``camera_pose`` =
``/camera_pose/`` = ``/camera_pose``), left/right images paired by exact stamp, the rig from the
latest left/right CameraInfo, the pose from the daemon's own :class:`PoseBuffer` (interpolated to
the image stamp between bracketing poses at most ``[daemon] pose_max_gap_s`` apart; the
covariance from the latest pose that carries a non-zero one, else ``[daemon] pose_std_*``, which
PoseStamped input also gets), the mask by exact stamp. Deterministic for a given file, config
and seed.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pugsd.core.camera import StereoRig
from pugsd.core.geometry import compose_pose_cov
from pugsd.core.types import ScoredGrasps, StereoFrame
from pugsd.daemon.config import DaemonConfig, TopicsConfig
from pugsd.daemon.timesync import PoseBuffer, PoseLookup, PoseSample, carried_cov, default_pose_cov
from pugsd.errors import ConfigError, DecodeError, InputError
from pugsd.record.mcapio import ChannelTable, file_error, iter_recording, new_writer, versions
from pugsd.wire import codec
from pugsd.wire.keys import strip_topic
from pugsd.wire.topics import ROLE_TYPES, key_for
from pugsd.wire.types import POSE_COV_STAMPED

log = logging.getLogger(__name__)

#: poses kept for interpolation (offline there is no reason for the daemon's small real-time ring)
POSE_CAPACITY = 10_000
_ROLES = ("left_image", "right_image", "left_info", "right_info", "pose", "mask")


def _norm_topic(topic: str) -> str:
    """``/a/b`` for ``a/b``, ``/a/b/`` ...: the ROS name the wire layer uses for the key."""
    return "/" + strip_topic(topic)


@dataclass
class AssembleStats:
    frames: int = 0
    unpaired: int = 0
    no_pose: int = 0
    no_info: int = 0
    rejected: int = 0


class _FrameAssembler:
    """Streaming assembly: bounded memory (pending pairs and images are capped)."""

    def __init__(
        self,
        topics: TopicsConfig,
        pose_cov: np.ndarray,
        max_pose_gap_ns: int,
        stats: AssembleStats,
        max_pending: int,
        pose_capacity: int = POSE_CAPACITY,
        T_B_C: np.ndarray | None = None,
    ) -> None:
        self.t = topics
        self.T_B_C = T_B_C  # the camera's mount on the body whose pose was recorded (None: none)
        self.pose_cov = pose_cov  # PoseStamped input, and before any pose carried a covariance
        self.st = stats
        self.max_pending = max_pending
        # normalised topic -> role (the first role listed wins when two share a topic)
        self.roles: dict[str, str] = {}
        for role in reversed(_ROLES):
            self.roles[_norm_topic(getattr(topics, role))] = role
        self._seen: dict[str, str] = {}  # recorded topic -> role ("" when none)
        self.left: dict[int, codec.ImageMsg] = {}
        self.right: dict[int, codec.ImageMsg] = {}
        self.masks: dict[int, np.ndarray] = {}
        self.rigs: dict[int, StereoRig | None] = {}  # stamp -> rig when the pair completed
        self.info: dict[str, codec.CameraInfoMsg] = {}
        self.poses = PoseBuffer(pose_capacity, int(max_pose_gap_ns), pose_cov)
        self.newest_image = -1

    def _role(self, topic: str) -> str:
        role = self._seen.get(topic)
        if role is None:
            try:
                role = self.roles.get(_norm_topic(topic), "")
            except ConfigError:  # not a valid ROS name: none of ours
                role = ""
            self._seen[topic] = role
        return role

    def feed(self, topic: str, typename: str, data: bytes) -> list[StereoFrame]:
        role = self._role(topic)
        if not role:
            return []
        try:
            if role in ("left_image", "right_image"):
                img = codec.decode_image(data, codec.STEREO_ENCODINGS)
                (self.left if role == "left_image" else self.right)[img.stamp_ns] = img
                if img.stamp_ns in self.left and img.stamp_ns in self.right:
                    self.rigs[img.stamp_ns] = self._rig()
                self._note_image(img.stamp_ns)
            elif role in ("left_info", "right_info"):
                self.info["l" if role == "left_info" else "r"] = codec.decode_camera_info(data)
            elif role == "pose":
                p = codec.decode_pose(data, typename or POSE_COV_STAMPED, self.pose_cov)
                T_W_C, cov = p.T, carried_cov(p.cov)
                if self.T_B_C is not None:  # as the daemon does
                    T_W_C, cov = compose_pose_cov(T_W_C, cov, self.T_B_C)
                self.poses.add(PoseSample(p.stamp_ns, T_W_C, cov))
            elif role == "mask":
                mk = codec.decode_image(data, codec.MASK_ENCODINGS)
                self.masks[mk.stamp_ns] = mk.array > 0
                self._note_image(mk.stamp_ns)
        except DecodeError as exc:
            self.st.rejected += 1
            log.warning("replay: rejected a %s message: %s", topic, exc)
        return self._emit(final=False)

    def _note_image(self, stamp: int) -> None:
        self.newest_image = max(self.newest_image, stamp)

    def _rig(self) -> StereoRig | None:
        if "l" not in self.info or "r" not in self.info:
            return None
        try:
            return codec.stereo_rig_from_infos(self.info["l"], self.info["r"])
        except DecodeError as exc:
            log.warning("replay: %s", exc)
            return None

    def _emit(self, final: bool) -> list[StereoFrame]:
        out: list[StereoFrame] = []
        for stamp in sorted(self.rigs):
            # wait for everything of this stamp (mask, a later pose) until a newer image arrives
            if not final and stamp >= self.newest_image:
                break
            pose: PoseLookup = self.poses.lookup(stamp)
            if pose.state == "wait" and not final and len(self.rigs) <= self.max_pending:
                continue  # a bracketing pose may still come
            rig = self.rigs.pop(stamp) or self._rig()  # infos may come after images
            left, right = self.left.pop(stamp), self.right.pop(stamp)
            mask = self.masks.pop(stamp, None)
            if rig is None:
                self.st.no_info += 1
            elif pose.state != "ready" or pose.T_W_C is None or pose.cov is None:
                self.st.no_pose += 1
                log.debug("replay: frame %d has no pose: %s", stamp, pose.reason)
            else:
                try:
                    out.append(StereoFrame(stamp, left.rgb_or_mono(), right.rgb_or_mono(), rig,
                                           pose.T_W_C, pose.cov, mask))  # fmt: skip
                except InputError as exc:
                    self.st.rejected += 1
                    log.warning("replay: frame %d rejected: %s", stamp, exc)
        self._trim(final)
        self.st.frames += len(out)
        return out

    def _trim(self, final: bool) -> None:
        """Unpaired images older than the pending window are dropped (and counted)."""
        for d in (self.left, self.right):
            extra = [s for s in d if s not in self.rigs]
            if final:
                self.st.unpaired += len(extra)
                for s in extra:
                    del d[s]
                continue
            for s in sorted(extra)[: max(0, len(extra) - self.max_pending)]:
                del d[s]
                self.st.unpaired += 1
        keep = max(0, len(self.masks) - 2 * self.max_pending)
        for s in sorted(self.masks)[:keep]:
            del self.masks[s]

    def finish(self) -> list[StereoFrame]:
        return self._emit(final=True)


def iter_frames(
    paths: Iterable[str | Path],
    topics: TopicsConfig | None = None,
    *,
    daemon: DaemonConfig | None = None,
    pose_cov: np.ndarray | None = None,
    max_pose_gap_ns: int | None = None,
    stats: AssembleStats | None = None,
    max_pending: int = 32,
    pose_capacity: int = POSE_CAPACITY,
) -> Iterator[StereoFrame]:
    """StereoFrames of a recording, streamed in stamp order with bounded memory: left/right
    paired by exact stamp, the rig from the latest CameraInfos when the pair completes, the pose
    exact or interpolated between bracketing poses (the daemon's :class:`PoseBuffer`), the
    covariance from the latest pose carrying a non-zero one, the mask by stamp.

    ``daemon`` (``[daemon]``, default: its defaults) gives ``max_pose_gap_ns``
    (``pose_max_gap_s``) and ``pose_cov`` (``pose_std_translation_m`` / ``pose_std_rotation_rad``:
    the covariance of ``PoseStamped`` input and of frames before any pose carried one) unless
    these are given explicitly, and the camera's mount ``T_B_C`` on the body whose pose was
    recorded (``T_B_C_xyz_m`` / ``T_B_C_quat_xyzw``)."""
    d = daemon if daemon is not None else DaemonConfig()
    if pose_cov is None:
        pose_cov = default_pose_cov(d.pose_std_translation_m, d.pose_std_rotation_rad)
    if max_pose_gap_ns is None:
        max_pose_gap_ns = int(d.pose_max_gap_s * 1e9)
    st = stats if stats is not None else AssembleStats()
    asm = _FrameAssembler(topics or TopicsConfig(), np.asarray(pose_cov, dtype=np.float64), max_pose_gap_ns,
                          st, max_pending, pose_capacity, d.T_B_C)  # fmt: skip
    for m in iter_recording(paths):
        yield from asm.feed(m.topic, m.typename, m.data)
    yield from asm.finish()


def assemble_frames(
    paths: Iterable[str | Path],
    topics: TopicsConfig | None = None,
    *,
    daemon: DaemonConfig | None = None,
    pose_cov: np.ndarray | None = None,
    max_pose_gap_ns: int | None = None,
    stats: AssembleStats | None = None,
) -> list[StereoFrame]:
    """All frames of :func:`iter_frames` as a list."""
    return list(iter_frames(paths, topics, daemon=daemon, pose_cov=pose_cov,
                            max_pose_gap_ns=max_pose_gap_ns, stats=stats))  # fmt: skip


@dataclass
class ReplayResult:
    grasps: ScoredGrasps
    frames: int
    stats: dict[str, Any]
    json_path: Path | None
    mcap_path: Path | None


def grasps_to_json(g: ScoredGrasps) -> list[dict[str, Any]]:
    return [
        {
            "rank": i,
            "id": int(g.grasp_id[i]),
            "pose_W": np.asarray(g.pose_W[i]).tolist(),
            "contact_W": np.asarray(g.contact_W[i]).tolist(),
            "width_m": float(g.width_m[i]),
            "baseline_confidence": float(g.baseline_confidence[i]),
            "sigma2_occ": float(g.sigma2_occ[i]),
            "pugs_confidence": float(g.pugs_confidence[i]),
        }
        for i in range(len(g))
    ]


def replay(
    paths: Iterable[str | Path],
    cfg: Any,
    *,
    out_dir: str | Path | None = None,
    mode: str = "paper",
    seed: int = 0,
) -> ReplayResult:
    """Run ``PugsPipeline`` on the frames of a recording; write ``grasps.json`` and
    ``grasps.mcap`` (GraspArray, MarkerArray, PointCloud2 on the ``[topics]`` outputs)."""
    paths = [Path(p) for p in paths]
    od = None if out_dir is None else Path(out_dir)
    if od is not None:  # before the pipeline runs: an unusable --out is a one-line error at once
        try:
            od.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise file_error(od, exc, "cannot write") from None
    ast = AssembleStats()
    from pugsd.config import core_of
    from pugsd.pipeline_factory import make_pipeline  # torch and open3d: only when replaying

    pipe = make_pipeline(core_of(cfg), seed)
    n = 0
    for f in iter_frames(paths, cfg.topics, daemon=cfg.daemon, stats=ast):
        pipe.add_stereo(f)
        n += 1
        if mode == "streaming":
            pipe.train_steps()
    if n == 0:
        raise InputError(f"replay: no usable stereo frames in {', '.join(map(str, paths))} ({ast})")
    if mode == "paper":
        pipe.fit_paper()
    result = pipe.compute()
    grasps: ScoredGrasps = result.grasps
    stats = {"frames": n, "assemble": ast.__dict__, "pipeline": pipe.stats()}
    jp = mp = None
    if od is not None:
        jp = od / "grasps.json"
        mp = od / "grasps.mcap"
        try:
            jp.write_text(
                json.dumps(
                    {
                        "source": [str(p) for p in paths],
                        "mode": mode,
                        "seed": seed,
                        "stats": stats,
                        "grasps": grasps_to_json(grasps),
                    },
                    indent=1,
                    default=str,
                )
            )
            _write_outputs(mp, cfg.topics, result, grasps)
        except OSError as exc:
            raise file_error(od, exc, "cannot write") from None
    return ReplayResult(grasps, n, stats, jp, mp)


def _write_outputs(path: Path, topics: TopicsConfig, result: Any, grasps: ScoredGrasps) -> None:
    st = int(grasps.stamp_ns)
    msgs: list[tuple[str, bytes]] = [
        ("grasps", codec.encode_grasp_array(grasps)),
        ("markers", codec.encode_grasp_markers(grasps)),
        (
            "cloud",
            codec.encode_cloud(
                result.cloud_W,
                st,
                sigma2_occ=result.sigma2_occ,
                pugs_confidence=result.pugs_conf_points,
            ),
        ),
    ]
    with open(path, "wb") as f:
        w = new_writer(f, 1 << 20)
        w.add_metadata("pugsd.versions", versions())
        table = ChannelTable(w)
        for role, data in msgs:
            cid = table.channel_id(getattr(topics, role), ROLE_TYPES[role], key_for(topics, role))
            w.add_message(cid, st, data, st)
        w.finish()


def iter_top(g: ScoredGrasps, k: int = 5) -> Iterator[str]:
    for i in range(min(k, len(g))):
        p = g.pose_W[i][:3, 3]
        yield (
            f"#{i} id={int(g.grasp_id[i])} pugs={g.pugs_confidence[i]:.3g} "
            f"base={g.baseline_confidence[i]:.3f} s2={g.sigma2_occ[i]:.2e} "
            f"at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) w={g.width_m[i] * 1000:.1f} mm"
        )
