# SPDX-License-Identifier: Apache-2.0
"""``pugsd replay``: run the PUGS pipeline directly on a recording, without zenoh.

Frames are assembled by the daemon's :class:`~pugsd.stream.assembler.FrameAssembler` on the
recording's clock: topic names normalised (``camera_pose`` = ``/camera_pose/`` =
``/camera_pose``), left/right images paired by exact stamp, the rig from the latest left/right
CameraInfo, the pose interpolated to the image stamp between bracketing poses at most
``[daemon] pose_max_gap_s`` apart (the covariance from the latest pose that carries a non-zero
one, else ``[daemon] pose_std_*``, which PoseStamped input also gets), the mask by exact stamp.
Deterministic for a given file, config and seed.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pugsd.config import DaemonConfig, QueuesConfig, TopicsConfig
from pugsd.core.types import ScoredGrasps, StereoFrame
from pugsd.errors import ConfigError, InputError, PugsdError
from pugsd.record.mcapio import ChannelTable, file_error, iter_recording, new_writer, versions
from pugsd.stream.assembler import FrameAssembler, InputRejected
from pugsd.stream.timesync import default_pose_cov
from pugsd.wire import codec
from pugsd.wire.keys import strip_topic
from pugsd.wire.topics import ROLE_TYPES, key_for
from pugsd.wire.types import POSE_COV_STAMPED

log = logging.getLogger(__name__)

#: poses kept for interpolation (offline there is no reason for the daemon's small real-time ring)
POSE_CAPACITY = 10_000
_POSE_WAIT_S = 3600.0  # offline a frame waits for its pose by count (max_pending), not by time
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


class _ReplayReport:
    """What the frame assembler reports, counted in :class:`AssembleStats`."""

    def __init__(self, stats: AssembleStats) -> None:
        self.st = stats

    def count(self, key: str, n: int = 1) -> None:
        if key in ("frames.stereo", "frames.depth"):
            self.st.frames += n

    def drop(self, stage: str, reason: str, n: int = 1) -> None:
        if stage == "unpaired":
            self.st.unpaired += n
        elif "CameraInfo" in reason:
            self.st.no_info += n
        else:
            self.st.no_pose += n
            log.debug("replay: a frame has no pose: %s", reason)

    def reject(self, role: str, exc: BaseException) -> None:
        if isinstance(exc, InputRejected) and exc.role == "camera_info":
            self.st.no_info += 1
        else:
            self.st.rejected += 1
        log.warning("replay: rejected a %s message: %s", role, exc)

    def internal_error(self, key: str, what: str, exc: BaseException) -> None:
        raise exc


class _Replayer:
    """Feeds a recording's messages, on the recording's clock, to the frame assembler the daemon
    uses; frames wait for their pose as long as the pending bounds allow, and the end of the
    recording flushes them."""

    def __init__(
        self,
        topics: TopicsConfig,
        d: DaemonConfig,
        stats: AssembleStats,
        max_pending: int,
        pose_capacity: int,
        pose_cov: np.ndarray,
        max_pose_gap_ns: int,
    ) -> None:
        # normalised topic -> role (the first role listed wins when two share a topic)
        self.roles: dict[str, str] = {}
        for role in reversed(_ROLES):
            self.roles[_norm_topic(getattr(topics, role))] = role
        self._seen: dict[str, str] = {}  # recorded topic -> role ("" when none)
        self.now_s = 0.0  # the log time of the message being fed
        self.st = stats
        self.report = _ReplayReport(stats)
        self.out: list[StereoFrame] = []
        q = dataclasses.replace(
            QueuesConfig(), pose_wait=max_pending, unpaired=max_pending, side_images=2 * max_pending
        )
        # offline nothing is thinned, and a frame waits for its pose as long as the bounds allow
        d = dataclasses.replace(d, max_frame_rate_hz=0.0, pose_wait_s=_POSE_WAIT_S)
        self.asm = FrameAssembler(
            d, q, self.report, self._on_frame, lambda: self.now_s,
            pose_capacity=pose_capacity, pose_cov=pose_cov, max_pose_gap_ns=max_pose_gap_ns,
        )  # fmt: skip

    def _on_frame(self, frame: Any, recv_s: float) -> None:
        self.out.append(frame)

    def _role(self, topic: str) -> str:
        role = self._seen.get(topic)
        if role is None:
            try:
                role = self.roles.get(_norm_topic(topic), "")
            except ConfigError:  # not a valid ROS name: none of ours
                role = ""
            self._seen[topic] = role
        return role

    def feed(self, topic: str, typename: str, data: bytes, log_time_ns: int) -> list[StereoFrame]:
        role = self._role(topic)
        if not role:
            return []
        self.now_s = log_time_ns / 1e9
        try:
            # the recorded type decides how a pose is read; images are not checked by type
            self.asm.feed(role, data, self.now_s, (typename or POSE_COV_STAMPED) if role == "pose" else None)
        except PugsdError as exc:
            self.report.reject(role, exc)
        return self._take()

    def _take(self) -> list[StereoFrame]:
        out, self.out = self.out, []
        return out

    def finish(self) -> list[StereoFrame]:
        self.asm.poll(math.inf)
        self.st.unpaired += self.asm.pairer.unpaired_dropped + self.asm.pairer.clear()
        return self._take()


def count_left_images(paths: Iterable[str | Path], topics: TopicsConfig) -> int | None:
    """The left images in the recordings (from their summaries, or counted through a file
    without one): about the frames a replay will have; None for a file that cannot be read."""
    from pugsd.record.mcapio import scan

    left = _norm_topic(topics.left_image)
    n = 0
    try:
        for p in paths:
            n += sum(c.count for c in scan(p).channels if _norm_topic(c.topic) == left)
    except (PugsdError, OSError):
        return None
    return n


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
    """StereoFrames of a recording, streamed in the order they complete, with bounded memory
    (``max_pending`` frames and halves waiting): assembled by the daemon's frame assembler on the
    recording's clock, the pose exact or interpolated between bracketing poses, the covariance
    from the latest pose carrying a non-zero one, the mask by stamp.

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
    rep = _Replayer(topics or TopicsConfig(), d, st, max_pending, pose_capacity, pose_cov, max_pose_gap_ns)
    for m in iter_recording(paths):
        yield from rep.feed(m.topic, m.typename, m.data, m.log_time_ns)
    yield from rep.finish()


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
    on_frame: Callable[[], None] | None = None,
) -> ReplayResult:
    """Run ``PugsPipeline`` on the frames of a recording; write ``grasps.json`` and
    ``grasps.mcap`` (GraspArray, MarkerArray, PointCloud2 on the ``[topics]`` outputs).
    ``on_frame`` is called after each frame is taken in (and, streaming, trained on)."""
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
        if on_frame is not None:
            on_frame()
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


