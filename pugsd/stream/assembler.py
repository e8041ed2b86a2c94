# SPDX-License-Identifier: Apache-2.0
"""Frame assembly: decoded input messages in, complete stereo or depth frames out.

Left and right images pair by exact stamp; the rig comes from the latest left/right CameraInfo;
each frame waits (``PoseGate``) for its pose, interpolated on SE(3) by the ``PoseBuffer``, taken
from one pose publisher at a time, and for its mask (and depth std image) while that topic is
active or undecided. Images above ``daemon.max_image_bytes`` or of another size than their
camera are rejected on arrival, from their declared layout, before any pixel is decoded; what
waits is held within ``queues.buffered_bytes`` (the oldest dropped first); a pose covariance
beyond ``daemon.max_pose_std_*`` is rejected before it is used. Every rejection, drop and emitted
frame goes to the caller through ``report`` and ``on_frame``.

Pure and synchronous with an injected clock: the daemon's is ``time.monotonic``, ``pugsd
replay``'s the recording's log time.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from pugsd.core.camera import StereoRig
from pugsd.core.geometry import compose_pose_cov
from pugsd.core.types import DepthFrame, StereoFrame
from pugsd.errors import DecodeError, PugsdError
from pugsd.stream.timesync import (
    ExactPairer,
    FrameRateLimit,
    PoseBuffer,
    PoseGate,
    PoseSample,
    carried_cov,
    default_pose_cov,
)
from pugsd.wire import codec
from pugsd.wire.topics import POSE_TYPES
from pugsd.wire.types import CAMERA_INFO, IMAGE

log = logging.getLogger(__name__)

STEREO_ENCODINGS = codec.STEREO_ENCODINGS
DEPTH_ENCODINGS = ("32FC1", "16UC1")
MASK_ENCODINGS = codec.MASK_ENCODINGS
SIDE_ACTIVE_S = 2.0  # a mask/std topic counts as active this long after its last message

Frame = StereoFrame | DepthFrame
Waiting = tuple[str, Any, float]  # ("stereo" | "depth", the images, receive time)


class InputRejected(PugsdError):
    """A rejection whose countable class is fixed by the code, not read from the message (which
    may quote text from the wire); ``role``, when set, is the input it is charged to (a frame
    combines several inputs)."""

    def __init__(self, reason: str, message: str, role: str | None = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.role = role


def reason_class(exc: BaseException) -> str:
    """A short, countable class for a rejection (the full reason goes to the log)."""
    if isinstance(exc, InputRejected):
        return exc.reason
    if isinstance(exc, DecodeError) and exc.reason:  # a message that quotes the wire
        return exc.reason
    text = str(exc).lower()
    for key, words in (
        ("out_of_map_range", ("voxel hash",)),
        ("beyond_any_map", ("too far for any voxel index",)),
        ("too_small_for_stereo", ("too small for the disparity search",)),
        ("touches_no_tsdf_block", ("touches no tsdf block",)),
        ("malformed_cdr", ("malformed cdr", "truncated cdr", "cdr encapsulation", "not bytes")),
        ("wrong_type", ("not accepted (expected", "unsupported pose type", "rmw_zenoh key")),
        ("no_camera_info", ("no camerainfo",)),
        ("non_psd_covariance", ("semi-definite", "not symmetric", "non-finite covariance")),
        ("bad_pose", ("non-finite pose", "quaternion", "rigid", "orthonormal", "t_w_c")),
        ("wrong_encoding", ("encoding",)),
        ("wrong_size", ("data has", "step", "size", "shape", "mismatch", "expects", "empty image")),
        ("bad_camera_info", ("camerainfo", "baseline", "intrinsics", "rectified")),
        ("bad_stamp", ("stamp",)),
    ):
        if any(w in text for w in words):
            return key
    return type(exc).__name__


def require_size(img: codec.ImageMsg, shape: tuple[int, int], what: str, role: str | None = None) -> None:
    """InputRejected ``wrong_size`` unless ``img`` is ``shape`` (height, width) pixels."""
    if img.array.shape[:2] != shape:
        msg = f"{what} is {img.array.shape[:2]}, camera expects {shape}"
        raise InputRejected("wrong_size", msg, role)


def expected_type(role: str, pose_type: str) -> str:
    """The message type an input role carries (``pose_type``: ``[topics] pose_type``)."""
    if role == "pose":
        return POSE_TYPES[pose_type]
    return CAMERA_INFO if role.endswith("_info") else IMAGE


class AssemblyReport(Protocol):
    """Where the assembler counts what it does (the daemon's health, the replay's stats)."""

    def count(self, key: str, n: int = 1) -> None: ...

    def drop(self, stage: str, reason: str, n: int = 1) -> None: ...

    def reject(self, role: str, exc: BaseException) -> None: ...

    def internal_error(self, key: str, what: str, exc: BaseException) -> None: ...


class FrameAssembler:
    """Assembles frames from the inputs of ``[daemon]`` (``d``) with the bounds of ``[queues]``
    (``q``); ``on_frame(frame, recv_s)`` receives each complete frame. ``clock()`` is the time
    now (the receive times' clock); a waiting frame expires once its deadline is before
    ``expire_before(now)`` (default: now; the daemon spares frames whose pose is still queued).
    ``pose_capacity``, ``pose_cov`` and ``max_pose_gap_ns`` override ``q.poses`` (an offline
    replay keeps more), ``d.pose_std_*`` and ``d.pose_max_gap_s``."""

    def __init__(
        self,
        d: Any,  # pugsd.config.DaemonConfig
        q: Any,  # pugsd.config.QueuesConfig
        report: AssemblyReport,
        on_frame: Callable[[Frame, float], None],
        clock: Callable[[], float],
        *,
        expire_before: Callable[[float], float] | None = None,
        pose_capacity: int | None = None,
        pose_cov: np.ndarray | None = None,
        max_pose_gap_ns: int | None = None,
    ) -> None:
        self.d = d
        self.clock = clock
        self.expire_before = expire_before
        self.q = q
        self.report = report
        self.on_frame = on_frame
        default_cov = (
            default_pose_cov(d.pose_std_translation_m, d.pose_std_rotation_rad)
            if pose_cov is None
            else np.asarray(pose_cov, dtype=np.float64)
        )
        self.pose_stamped_cov = default_cov  # the covariance PoseStamped input gets
        self.T_B_C = d.T_B_C  # the camera's mount on the body whose pose comes in (None: none)
        self.pose_publisher: bytes | None = None  # the GID poses are taken from (pose_publisher_hold_s)
        self.pose_publisher_s = 0.0  # the clock's time it was last heard
        self._slow_pose_source_warned = False  # its poses came further apart than the hold
        capacity = q.poses if pose_capacity is None else pose_capacity
        gap_ns = int(d.pose_max_gap_s * 1e9) if max_pose_gap_ns is None else int(max_pose_gap_ns)
        self.poses = PoseBuffer(capacity, gap_ns, default_cov)
        self.gate: PoseGate[Waiting] = PoseGate(self.poses, d.pose_wait_s, q.pose_wait)
        self.pairer: ExactPairer[codec.ImageMsg, codec.ImageMsg] = ExactPairer(q.unpaired)
        self.frame_rate = FrameRateLimit(d.max_frame_rate_hz)  # frames thinned before the pose gate
        self.masks: OrderedDict[int, np.ndarray] = OrderedDict()
        self.stds: OrderedDict[int, np.ndarray] = OrderedDict()
        self.infos: dict[str, codec.CameraInfoMsg] = {}
        self._rig: StereoRig | None = None
        self.last_mask_s: float | None = None
        self.last_std_s: float | None = None
        # whether a side topic (mask, depth std) is undecided: no frame has yet waited its
        # side_image_wait_s for one in vain since the start or since one last arrived.
        # Undecided, a frame waits for its own: a first frame's images can arrive before its mask
        # (zenoh does not order different keys), and one frame integrated without its mask puts
        # the whole background into the store
        self.side_undecided = {"mask": True, "depth_std": True}
        self.frame_id: str = d.world_frame  # the pose source's frame, once a pose names one
        # a frame's stamp minus the newest pose stamp when it arrived (s), the latest 200: shows a
        # clock offset between camera and pose source (frames then drop waiting for a pose)
        self.stamp_skew_s: deque[float] = deque(maxlen=200)

    # --- input ------------------------------------------------------------------------------

    def feed(
        self,
        role: str,
        data: bytes,
        recv_s: float,
        typename: str | None = None,
        publisher: bytes | None = None,
        key: str = "",
    ) -> None:
        """Take one message of input ``role`` received at ``recv_s``; ``typename`` (None: not
        checked) must be the role's type. Raises a PugsdError when the message is rejected."""
        if role in ("left_image", "right_image"):
            self._expect_type(role, typename, IMAGE)
            self._check_layout(role, data)
            img = codec.decode_image(data, STEREO_ENCODINGS)
            self._check_size(role, img)
            dups = self.pairer.duplicates
            pair = (
                self.pairer.add_left(img.stamp_ns, img)
                if role == "left_image"
                else self.pairer.add_right(img.stamp_ns, img)
            )
            if self.pairer.duplicates != dups:  # the waiting half with this stamp was replaced
                self.report.drop("unpaired", f"duplicate_stamp (a second {role} for stamp {img.stamp_ns})")
            if pair is not None:
                self.report.count("paired")
                self._admit(img.stamp_ns, ("stereo", pair, recv_s), recv_s)
            else:
                self._keep_budget()
        elif role in ("left_info", "right_info", "depth_info"):
            self._expect_type(role, typename, CAMERA_INFO)
            info = codec.decode_camera_info(data)
            self.infos[role] = info
            if role != "depth_info":
                self._rig = None  # rebuilt lazily from both infos
            self.poll()
        elif role == "pose":
            typename = typename if typename is not None else POSE_TYPES["PoseWithCovarianceStamped"]
            if typename not in POSE_TYPES.values():
                raise InputRejected("wrong_type", f"pose: type {typename[:100]!r} not accepted")
            pm = codec.decode_pose(data, typename, self.pose_stamped_cov)
            if pm.cov is not None and typename != POSE_TYPES["PoseStamped"]:  # a carried one
                self._check_plausible(pm.cov)
            self._follow_pose_publisher(publisher, recv_s, key)
            T_W_C, cov = pm.T, carried_cov(pm.cov)
            if self.T_B_C is not None:  # the pose of the body carrying the camera
                T_W_C, cov = compose_pose_cov(T_W_C, cov, self.T_B_C)
            jumps, strays = self.poses.jumps_back, self.poses.strays
            self.poses.add(PoseSample(pm.stamp_ns, T_W_C, cov))
            n = self.poses.jumps_back
            if n != jumps and log_nth(n):  # a source flapping between clocks would log each
                log.warning(
                    "pose: stamps went back by more than daemon.pose_max_gap_s (a restarted source "
                    "or a stepped clock); the pose buffer starts afresh at %d ns (#%d)",
                    pm.stamp_ns, n,
                )  # fmt: skip
            if self.poses.strays != strays:  # found out now, by the pose after it
                self.report.reject("pose", InputRejected("stray_stamp", (
                    f"a pose stamped {self.poses.last_stray_ns} ns, more than daemon.pose_max_gap_s "
                    "off the pose timeline, was a stray (the poses after it went on with the "
                    "timeline): ignored"
                )))  # fmt: skip
            if pm.frame_id:
                self.frame_id = pm.frame_id
            self.report.count("poses")
            self.poll()
        elif role == "mask":
            self._expect_type(role, typename, IMAGE)
            self._check_layout(role, data)
            m = codec.decode_image(data, MASK_ENCODINGS)
            bounded_put(self.masks, m.stamp_ns, m.array > 0, self.q.side_images)
            self._keep_budget()
            self.last_mask_s = recv_s
            self.side_undecided["mask"] = True
            self.poll()
        elif role == "depth_std":
            self._expect_type(role, typename, IMAGE)
            self._check_layout(role, data)
            s = codec.decode_image(data, ("32FC1",))
            bounded_put(self.stds, s.stamp_ns, s.array.astype(np.float32), self.q.side_images)
            self._keep_budget()
            self.last_std_s = recv_s
            self.side_undecided["depth_std"] = True
            self.poll()
        elif role == "depth":
            self._expect_type(role, typename, IMAGE)
            self._check_layout(role, data)
            img = codec.decode_image(data, DEPTH_ENCODINGS)
            self._check_size(role, img)
            self._admit(img.stamp_ns, ("depth", img, recv_s), recv_s)

    @staticmethod
    def _expect_type(role: str, got: str | None, typename: str) -> None:
        if got is not None and got != typename:
            msg = f"{role}: type {got[:100]!r} not accepted (expected {typename})"
            raise InputRejected("wrong_type", msg)

    def _check_plausible(self, cov: np.ndarray) -> None:
        """InputRejected ``implausible_covariance`` for a pose covariance whose position or
        rotation standard deviation (along its worst direction) exceeds ``daemon.max_pose_std_*``
        (a diverging localiser): refused before it changes any state."""
        for name, block, limit, unit in (
            ("position", cov[:3, :3], self.d.max_pose_std_translation_m, "m"),
            ("rotation", cov[3:, 3:], self.d.max_pose_std_rotation_rad, "rad"),
        ):
            scale = float(np.abs(block).max())  # judged scaled: entries near the float64 limit
            try:
                S = block / scale if scale > 0 else block
                worst = float(np.linalg.eigvalsh(0.5 * S + 0.5 * S.T)[-1]) * scale
            except np.linalg.LinAlgError:
                worst = math.inf
            if not worst <= limit * limit:
                raise InputRejected(
                    "implausible_covariance",
                    f"pose: {name} standard deviation {np.sqrt(max(worst, 0.0)):.3g} {unit} above "
                    f"daemon.max_pose_std_{'translation_m' if name == 'position' else 'rotation_rad'}"
                    f" = {limit:g} {unit}; pose ignored",
                    "pose",
                )

    def _follow_pose_publisher(self, gid: bytes | None, recv_s: float, key: str) -> None:
        """Take poses from one publisher at a time (``daemon.pose_publisher_hold_s``): a pose of
        another publisher while the followed one was heard within the hold is refused
        (InputRejected ``second_publisher``); after that silence the newcomer is followed."""
        hold_s = self.d.pose_publisher_hold_s
        if hold_s <= 0 or gid is None:
            return
        cur, silent_s = self.pose_publisher, recv_s - self.pose_publisher_s
        if cur is not None and gid != cur and silent_s <= hold_s:
            raise InputRejected(
                "second_publisher",
                f"a pose from publisher {gid.hex()[:12]} while publisher {cur.hex()[:12]}, whose poses "
                f"are taken, was heard {max(silent_s, 0.0):.2f} s ago: ignored (two nodes publish on "
                f"{key}? daemon.pose_publisher_hold_s = 0 takes every publisher's poses)",
            )
        if gid == cur and silent_s > hold_s and not self._slow_pose_source_warned:
            self._slow_pose_source_warned = True  # once: a second publisher would take turns
            log.warning(
                "pose: %.1f s between two poses of the followed publisher, more than "
                "daemon.pose_publisher_hold_s = %g s: a second publisher on %s would be followed in "
                "such gaps (an outage of the source, or its period: if the source publishes this "
                "slowly, raise the hold above its period; logged once)",
                silent_s, hold_s, key,
            )  # fmt: skip
        if cur is not None and gid != cur:
            self.report.count("pose_publisher_switches")
            log.warning(
                "pose: publisher %s silent for %.1f s; following publisher %s",
                cur.hex()[:12], silent_s, gid.hex()[:12],
            )  # fmt: skip
        self.pose_publisher, self.pose_publisher_s = gid, max(self.pose_publisher_s, recv_s)

    def _camera_shape(self, role: str) -> tuple[int, int] | None:
        """The (height, width) the camera of image input ``role`` has, None while unknown (no or
        inconsistent CameraInfo; masks and depth std images are judged with their frame)."""
        if role == "depth":
            info = self.infos.get("depth_info")
            return None if info is None else (info.camera.height, info.camera.width)
        if role not in ("left_image", "right_image"):
            return None
        try:
            cam = self.stereo_rig().left
        except PugsdError:
            return None
        return (cam.height, cam.width)

    def _check_layout(self, role: str, data: bytes) -> None:
        """Refuse an image above ``daemon.max_image_bytes``, or of another size than its camera,
        from its declared layout, before any of its pixels are decoded or copied."""
        what = "depth image" if role == "depth" else f"{role}: image"
        try:
            codec.check_image_layout(data, self.d.max_image_bytes, self._camera_shape(role), what)
        except DecodeError as exc:
            raise InputRejected(reason_class(exc), str(exc), role) from None

    def buffered_bytes(self) -> int:
        """The pixel bytes held: unpaired halves, frames waiting for a pose, masks and std images."""
        n = sum(img.array.nbytes for img in self.pairer.waiting())
        n += sum(waiting_nbytes(entry) for entry in self.gate.items())
        n += sum(a.nbytes for a in self.masks.values()) + sum(a.nbytes for a in self.stds.values())
        return n

    def _keep_budget(self) -> None:
        """Hold at most ``queues.buffered_bytes``: beyond it the oldest by stamp go first, of the
        unpaired halves, the masks and std images and the frames waiting for a pose (each counted
        as a drop of its stage, reason byte budget), so that the newest frame wins."""
        limit = self.q.buffered_bytes
        total = self.buffered_bytes()
        reason = f"byte budget (queues.buffered_bytes = {limit} B)"
        while total > limit:
            candidates = [
                (stamp, stage)
                for stamp, stage in (
                    (self.pairer.oldest_stamp(), "unpaired"),
                    (self.gate.oldest_stamp(), "pose_wait"),
                    (next(iter(self.masks), None), "mask"),
                    (next(iter(self.stds), None), "depth_std"),
                )
                if stamp is not None
            ]
            if not candidates:
                break
            _, stage = min(candidates)
            if stage == "unpaired":
                half = self.pairer.pop_oldest()
                total -= 0 if half is None else half.array.nbytes
            elif stage == "pose_wait":
                entry = self.gate.pop_oldest()
                total -= 0 if entry is None else waiting_nbytes(entry)
            else:
                total -= (self.masks if stage == "mask" else self.stds).popitem(last=False)[1].nbytes
                stage = "side_images"
            self.report.drop(stage, reason)

    def _check_size(self, role: str, img: codec.ImageMsg) -> None:
        """Reject an image of another size than its camera on arrival, so that it neither takes
        (or replaces) a good waiting stereo half of its stamp nor pushes good frames out of the
        pose gate. Without a usable camera (no or inconsistent CameraInfo) the frame is judged
        when it is emitted."""
        if role == "depth":
            info = self.infos.get("depth_info")
            if info is None:
                return
            cam = info.camera
        else:
            try:
                cam = self.stereo_rig().left
            except PugsdError:
                return
        what = "depth image" if role == "depth" else f"{role}: image"
        require_size(img, (cam.height, cam.width), what, role)

    def _admit(self, stamp_ns: int, entry: Waiting, now_s: float) -> None:
        if not self.frame_rate.accept(stamp_ns):  # daemon.max_frame_rate_hz: skipped, not dropped
            self.report.count("frames.skipped_rate")
            self.masks.pop(stamp_ns, None)
            self.stds.pop(stamp_ns, None)
            return
        newest = self.poses.newest_ns
        if newest is not None:
            self.stamp_skew_s.append((stamp_ns - newest) / 1e9)
        for _, reason in self.gate.add(stamp_ns, entry, now_s):
            self.report.drop("pose_wait", reason)
        self._keep_budget()
        self.poll()

    # --- release ----------------------------------------------------------------------------

    def poll(self, now_s: float | None = None) -> None:
        """Release the frames whose pose is ready; a frame that fails is counted (a rejection,
        charged to the input at fault, or an internal error) and the others still go on. Frames
        past their deadline are dropped. ``now_s`` defaults to the clock's time."""
        now_s = self.clock() if now_s is None else now_s
        expire_s = now_s if self.expire_before is None else self.expire_before(now_s)
        ready, dropped = self.gate.poll(now_s, self._pending, expire_s)
        for _, reason in dropped:
            self.report.drop("pose_wait", reason)
        for (kind, payload, recv_s), stamp_ns, T, cov in ready:
            try:
                if kind == "stereo":
                    self._emit_stereo(payload, stamp_ns, T, cov, recv_s)
                else:
                    self._emit_depth(payload, stamp_ns, T, cov, recv_s)
            except PugsdError as exc:
                self.report.reject("left_image" if kind == "stereo" else "depth", exc)
            except Exception as exc:  # a bug, not bad input: the others go on
                self.report.internal_error(f"errors.frames.{kind}", f"emitting a {kind} frame", exc)

    def _pending(self, entry: Waiting, now_s: float) -> str | None:
        """Why a pose-ready frame must still wait (missing CameraInfo, a mask on its way)."""
        kind, payload, recv_s = entry
        if kind == "stereo":
            if "left_info" not in self.infos or "right_info" not in self.infos:
                return "no CameraInfo for both cameras yet"
            stamp = payload[0].stamp_ns
        else:
            if "depth_info" not in self.infos:
                return "no CameraInfo for the depth image yet"
            stamp = payload.stamp_ns
            std_active = self._active(self.last_std_s, now_s)
            if self._side_missing("depth_std", std_active, stamp in self.stds, recv_s, now_s):
                return "depth std image not here yet"
        mask_active = self._active(self.last_mask_s, now_s)
        if self._side_missing("mask", mask_active, stamp in self.masks, recv_s, now_s):
            return "mask not here yet"
        return None

    def _side_missing(self, role: str, active: bool, here: bool, recv_s: float, now_s: float) -> bool:
        """Whether a frame must still wait for its ``role`` image: while that topic is active or
        undecided, up to ``side_image_wait_s``. An undecided wait that ends in vain (its time is
        up, or the next frame is here) decides the topic (no such publisher, for now): later
        frames go on."""
        if here or not (active or self.side_undecided[role]):
            return False
        d = self.d
        # undecided, the wait must end before the pose gate's deadline (pose_wait_s), or a rig
        # without masks would lose every frame there and never decide; and it ends when the next
        # frame is already here: keys are reordered by far less than a frame period, and frames
        # held back together would overflow the stereo mailbox when released
        limit_s = d.side_image_wait_s if active else min(d.side_image_wait_s, 0.5 * d.pose_wait_s)
        if now_s - recv_s < limit_s and (active or len(self.gate) <= 1):
            return True
        if not active:
            self.side_undecided[role] = False
        return False

    @staticmethod
    def _active(last_s: float | None, now_s: float) -> bool:
        return last_s is not None and now_s - last_s < SIDE_ACTIVE_S

    def stereo_rig(self) -> StereoRig:
        if self._rig is None:
            left, right = self.infos.get("left_info"), self.infos.get("right_info")
            if left is None or right is None:
                raise DecodeError("stereo: no CameraInfo for both cameras yet")
            # (a disparity search short of min_depth_m is logged by the stereo stage, once per rig)
            self._rig = codec.stereo_rig_from_infos(left, right)
        return self._rig

    def _emit_stereo(
        self,
        pair: tuple[codec.ImageMsg, codec.ImageMsg],
        stamp_ns: int,
        T: np.ndarray,
        cov: np.ndarray,
        recv_s: float,
    ) -> None:
        left, right = pair
        mask_in = self.masks.pop(stamp_ns, None)  # taken even if the frame is rejected
        try:
            rig = self.stereo_rig()
        except PugsdError as exc:
            raise InputRejected(reason_class(exc), str(exc), "camera_info") from None
        shape = (rig.left.height, rig.left.width)
        for role, img in (("left_image", left), ("right_image", right)):
            require_size(img, shape, f"{role}: image", role)
        if left.encoding != right.encoding:
            msg = f"stereo pair encoding mismatch: {left.encoding} vs {right.encoding}"
            raise InputRejected("wrong_encoding", msg, "right_image")
        mask = self.side_image("mask", mask_in, shape)
        try:
            frame = StereoFrame(
                stamp_ns=stamp_ns,
                left=left.rgb_or_mono(),
                right=right.rgb_or_mono(),
                rig=rig,
                T_W_C=T,
                pose_cov=cov,
                mask=mask,
            )
        except PugsdError as exc:  # the images and the mask are checked: the pose is at fault
            raise InputRejected(reason_class(exc), str(exc), "pose") from None
        self.report.count("frames.stereo")
        self.on_frame(frame, recv_s)

    def _emit_depth(
        self, img: codec.ImageMsg, stamp_ns: int, T: np.ndarray, cov: np.ndarray, recv_s: float
    ) -> None:
        std_in, mask_in = self.stds.pop(stamp_ns, None), self.masks.pop(stamp_ns, None)
        info = self.infos.get("depth_info")
        if info is None:
            raise DecodeError("depth: no CameraInfo for the depth image yet")
        shape = (info.camera.height, info.camera.width)
        require_size(img, shape, "depth image")
        sigma = self.side_image("depth_std", std_in, shape)
        mask = self.side_image("mask", mask_in, shape)
        try:
            frame = DepthFrame(
                stamp_ns=stamp_ns,
                depth_m=img.depth_m(),
                camera=info.camera,
                T_W_C=T,
                pose_cov=cov,
                sigma_m=sigma,
                mask=mask,
            )
        except PugsdError as exc:  # the images are checked: the pose is at fault
            raise InputRejected(reason_class(exc), str(exc), "pose") from None
        self.report.count("frames.depth")
        self.on_frame(frame, recv_s)

    def side_image(self, role: str, arr: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
        """A frame's mask or depth std image; one of another size than the frame is rejected
        (counted under ``role``) and the frame goes on without it."""
        if arr is None or arr.shape == shape:
            return arr
        msg = f"{role} is {arr.shape}, camera expects {shape}; frame used without it"
        self.report.reject(role, InputRejected("wrong_size", msg))
        return None

    # --- state ------------------------------------------------------------------------------

    def clear(self) -> tuple[int, int]:
        """Discard the frames waiting for a pose and the unpaired halves; returns both counts."""
        return self.gate.clear(), self.pairer.clear()

    def skew_summary(self) -> dict[str, float | int]:
        """The latest frames' stamp minus the newest pose stamp when each arrived, in seconds:
        near zero or a pose period below it with synchronised clocks; a constant far from zero
        is an offset between the camera's clock and the pose source's (or a pose source lagging
        by that much), which ``pose_max_gap_s`` and ``pose_wait_s`` cannot bridge."""
        if not self.stamp_skew_s:
            return {"n": 0}
        a = np.fromiter(self.stamp_skew_s, dtype=np.float64)
        return {
            "n": int(a.size),
            "p50": round(float(np.median(a)), 4),
            "min": round(float(a.min()), 4),
            "max": round(float(a.max()), 4),
        }


def log_nth(n: int, first: int = 5) -> bool:
    """Whether the ``n``-th (1-based) of a repeated event is logged: the first ``first``, then
    every 100th (each is counted regardless)."""
    return n <= first or n % 100 == 0


def frame_nbytes(frame: Frame) -> int:
    """The array bytes a frame holds (images, depth, std, mask, colour; 0 for anything else)."""
    arrays: tuple[np.ndarray | None, ...]
    if isinstance(frame, StereoFrame):
        arrays = (frame.left, frame.right, frame.mask)
    elif isinstance(frame, DepthFrame):
        arrays = (frame.depth_m, frame.sigma_m, frame.mask, frame.color)
    else:
        return 0
    return int(sum(a.nbytes for a in arrays if a is not None))


def waiting_nbytes(entry: Waiting) -> int:
    """The pixel bytes of a frame waiting for its pose."""
    kind, payload, _ = entry
    if kind == "stereo":
        return int(payload[0].array.nbytes + payload[1].array.nbytes)
    return int(payload.array.nbytes)


def bounded_put(d: OrderedDict[int, np.ndarray], key: int, value: np.ndarray, cap: int) -> None:
    d[key] = value
    d.move_to_end(key)
    while len(d) > cap:
        d.popitem(last=False)
