# SPDX-License-Identifier: Apache-2.0
"""Time synchronisation of the inputs: stereo pairs by exact stamp, poses interpolated on SE(3).

Pure buffers (no asyncio, no zenoh): the frame assembler feeds and polls them.
``T_W_C`` is camera -> world; ``pose_cov`` is the 6x6 (dt, phi) covariance of pugsd.core.types.
"""

from __future__ import annotations

import bisect
import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from pugsd.wire.codec import matrix_to_quat, quat_to_matrix

T = TypeVar("T")
L = TypeVar("L")
R = TypeVar("R")


# --- SE(3) interpolation ---


def quat_from_matrix(Rm: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (the wire codec's, reordered for slerp)."""
    x, y, z, w = matrix_to_quat(Rm)
    return np.array([w, x, y, z])


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (w, x, y, z); normalises first."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return quat_to_matrix(x, y, z, w)


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc, s in [0, 1]."""
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(d, 1.0))
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction ``s`` from T0 (s=0) to T1 (s=1): slerp rotation, lerp translation."""
    out = np.eye(4)
    out[:3, :3] = matrix_from_quat(slerp(quat_from_matrix(T0[:3, :3]), quat_from_matrix(T1[:3, :3]), s))
    out[:3, 3] = (1.0 - s) * T0[:3, 3] + s * T1[:3, 3]
    return out


# --- pose buffer ---


@dataclass(frozen=True, slots=True)
class PoseSample:
    stamp_ns: int
    T_W_C: np.ndarray  # (4, 4)
    cov: np.ndarray | None  # (6, 6) or None when the message carried no covariance


def default_pose_cov(std_translation_m: float, std_rotation_rad: float) -> np.ndarray:
    """The 6x6 covariance of ``[daemon] pose_std_translation_m`` / ``pose_std_rotation_rad``:
    given to PoseStamped input, and used before any pose carried a covariance."""
    return np.diag([std_translation_m**2] * 3 + [std_rotation_rad**2] * 3).astype(np.float64)


def carried_cov(cov: np.ndarray | None) -> np.ndarray | None:
    """A pose message's covariance as the pose buffer takes it: an all-zero matrix (a source
    that fills none in) counts as none, so the latest real one (or the default) applies."""
    return cov if cov is not None and np.any(cov != 0.0) else None


class PoseLookup:
    """A pose query's outcome: ``ready`` (pose + covariance), ``wait`` or ``fail`` (reason)."""

    __slots__ = ("T_W_C", "cov", "reason", "state")

    def __init__(
        self,
        state: str,
        T_W_C: np.ndarray | None = None,
        cov: np.ndarray | None = None,
        reason: str = "",
    ) -> None:
        self.state = state
        self.T_W_C = T_W_C
        self.cov = cov
        self.reason = reason


class PoseBuffer:
    """Time-sorted ring of recent poses; answers "pose at stamp t" by SE(3) interpolation.

    A query is answered once a pose at or after ``t`` exists and one at or before it, no more than
    ``max_gap_ns`` apart. The covariance is that of the latest pose (by stamp, not after the later
    bracketing pose) that carries one; ``default_cov`` when none has.

    A pose stamped more than ``max_gap_ns`` before the newest one is held until the next pose says
    which timeline goes on:
    - the next pose follows the held one by at most ``max_gap_ns`` (and is as far back): two poses
      agree on a timeline behind the buffer's. The pose source's clock went back (a restarted
      source, a replay loop, a stepped clock; zenoh delivers one publisher's samples in order): the
      buffer starts afresh from them (``jumps_back`` counts these), keeping only the newest
      covariance. Kept, the old timeline's poses would stay "newest" and every later pose would be
      evicted on arrival once the ring is full, so no frame would get a pose again. But when the
      held pose is within ``max_gap_ns`` of the pose before the newest one, and the newest one was
      alone more than ``max_gap_ns`` ahead of that, the newest pose was the stray (a future
      stamp): it is dropped and the two poses go on the timeline.
    - the next pose continues the buffer's timeline: the held pose was a stray (a driver that once
      sends stamp 0 or sim time, a second localiser on the topic) and is dropped (``strays`` counts
      these, ``last_stray_ns`` is the latest one's stamp). Taken at once, a single stray used to
      restart the buffer and cost the frames stamped before the next good pose.
    - neither: it is held instead (the held one counts as a stray).
    A clock that goes back thus costs one pose period. Poses ahead of the newest one are taken at
    once, however far (a source that paused, or publishes a pose per frame at a low rate: exact
    stamps need no bracketing pair). An image stamped more than ``max_gap_ns`` before the newest
    pose waits (for the restarted source's poses) rather than failing at once: its pose may come
    after it.
    """

    def __init__(self, capacity: int, max_gap_ns: int, default_cov: np.ndarray) -> None:
        self.capacity = capacity
        self.max_gap_ns = max_gap_ns
        self.default_cov = np.asarray(default_cov, dtype=np.float64)
        self._stamps: list[int] = []
        self._samples: list[PoseSample] = []
        self._cov_stamps: list[int] = []
        self._covs: list[np.ndarray] = []
        self._held: PoseSample | None = None  # off the timeline, until the next pose says
        self.jumps_back = 0
        self.strays = 0
        self.last_stray_ns: int | None = None

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def newest_ns(self) -> int | None:
        return self._stamps[-1] if self._stamps else None

    def _fits(self, stamp_ns: int) -> bool:
        """Not more than ``max_gap_ns`` before the newest pose (an empty buffer takes any)."""
        return not self._stamps or stamp_ns >= self._stamps[-1] - self.max_gap_ns

    def add(self, sample: PoseSample) -> None:
        """Take one pose (see the class docstring for poses far behind the newest one)."""
        held = self._held
        if self._fits(sample.stamp_ns):
            self._held = None
            self._insert(sample)
            if held is not None:  # the timeline went on without it
                self._stray(held)
            return
        if held is None or not 0 < sample.stamp_ns - held.stamp_ns <= self.max_gap_ns:
            # the first pose far back, or one that does not follow the held one (a repeat of its
            # stamp included): held in its place, the held one counted as a stray
            if held is not None:
                self._stray(held)
            self._held = sample
            return
        self._held = None  # two poses agree on a timeline behind the buffer's
        st, gap = self._stamps, self.max_gap_ns
        if len(st) >= 2 and st[-1] - st[-2] > gap and abs(held.stamp_ns - st[-2]) <= gap:
            self._stray(self._samples[-1])  # the newest pose was alone ahead of the timeline they go on
            newest = st.pop()
            self._samples.pop()
            if self._cov_stamps and self._cov_stamps[-1] == newest:
                self._cov_stamps.pop()
                self._covs.pop()
        else:  # the clock went back: start afresh
            last_cov = self._covs[-1] if self._covs else None
            self.clear()
            self.jumps_back += 1
            if last_cov is not None:  # still the latest covariance the source reported
                self._cov_stamps.append(held.stamp_ns)
                self._covs.append(last_cov)
        self._insert(held)
        self._insert(sample)

    def _stray(self, sample: PoseSample) -> None:
        self.strays += 1
        self.last_stray_ns = sample.stamp_ns

    def _insert(self, sample: PoseSample) -> None:
        i = bisect.bisect_left(self._stamps, sample.stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == sample.stamp_ns:
            self._samples[i] = sample
        else:
            self._stamps.insert(i, sample.stamp_ns)
            self._samples.insert(i, sample)
        if sample.cov is not None:
            j = bisect.bisect_left(self._cov_stamps, sample.stamp_ns)
            if j < len(self._cov_stamps) and self._cov_stamps[j] == sample.stamp_ns:
                self._covs[j] = sample.cov
            else:
                self._cov_stamps.insert(j, sample.stamp_ns)
                self._covs.insert(j, sample.cov)
        while len(self._stamps) > self.capacity:
            self._stamps.pop(0)
            self._samples.pop(0)
        # keep the newest covariance even when it is older than every stored pose
        while len(self._cov_stamps) > max(self.capacity, 1):
            self._cov_stamps.pop(0)
            self._covs.pop(0)

    def clear(self) -> None:
        self._held = None
        self._stamps.clear()
        self._samples.clear()
        self._cov_stamps.clear()
        self._covs.clear()

    def _cov_at(self, stamp_ns: int) -> np.ndarray:
        j = bisect.bisect_right(self._cov_stamps, stamp_ns)
        if j > 0:
            return self._covs[j - 1]
        return self.default_cov

    def lookup(self, stamp_ns: int) -> PoseLookup:
        st = self._stamps
        if not st:
            return PoseLookup("wait", reason="no pose yet")
        i = bisect.bisect_left(st, stamp_ns)
        if i < len(st) and st[i] == stamp_ns:
            s = self._samples[i]
            return PoseLookup("ready", s.T_W_C, self._cov_at(stamp_ns))
        if i == len(st):
            return PoseLookup("wait", reason="no pose after the image stamp yet")
        if i == 0:
            if stamp_ns < st[-1] - self.max_gap_ns:
                # as far back as a clock jump: the pose source may have restarted and its first
                # pose of the new timeline not be here yet (zenoh does not order different keys)
                return PoseLookup("wait", reason="image is older than every buffered pose by a clock jump")
            return PoseLookup("fail", reason="image is older than every buffered pose")
        a, b = self._samples[i - 1], self._samples[i]
        if b.stamp_ns - a.stamp_ns > self.max_gap_ns:
            if i == len(st) - 1 and stamp_ns - a.stamp_ns <= self.max_gap_ns:
                # the newest pose alone far ahead: a source that paused, or a stray future stamp
                # that the next poses show up (see add); the image's own pose may still come
                return PoseLookup("wait", reason="the newest pose is alone more than pose_max_gap_s ahead")
            # a constant head (a drop counter key); the numbers in parentheses, for the log
            gap_s, max_s = (b.stamp_ns - a.stamp_ns) / 1e9, self.max_gap_ns / 1e9
            return PoseLookup(
                "fail",
                reason=f"pose gap above pose_max_gap_s around the image stamp ({gap_s:.3f} s > {max_s:g} s)",
            )
        frac = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        T = interpolate_pose(a.T_W_C, b.T_W_C, frac)
        return PoseLookup("ready", T, self._cov_at(b.stamp_ns))


# --- stereo pairing and pose gating ---


class FrameRateLimit:
    """Thins frames to at most ``rate_hz`` by their stamps (``daemon.max_frame_rate_hz``; 0 keeps
    every frame), like a ROS ``throttle`` node but on the sensor's clock, so that a recording
    replayed faster than real time keeps the same frames.

    A frame is kept when its stamp reaches the next slot, ``period`` after the previous slot, less
    ``tolerance`` of a period for jitter: a 30 Hz camera thinned to 10 Hz keeps every third frame,
    a 25 Hz one 10 frames a second on average (gaps of 120 and 80 ms). A stamp that went back
    (a restarted source, a looping recording) or a gap of more than a period starts the slots
    afresh from that frame."""

    def __init__(self, rate_hz: float, tolerance: float = 0.1) -> None:
        if not (rate_hz >= 0.0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz must be finite and >= 0, got {rate_hz}")
        if not 0.0 <= tolerance < 1.0:
            raise ValueError(f"tolerance must be in [0, 1), got {tolerance}")
        self.period_ns = round(1e9 / rate_hz) if rate_hz > 0 else 0
        self._tolerance_ns = round(tolerance * self.period_ns)
        self._due_ns = 0  # the next slot (once a frame was kept)
        self._kept_ns: int | None = None  # the stamp of the last frame kept
        self.kept = 0
        self.skipped = 0

    def accept(self, stamp_ns: int) -> bool:
        """Whether to keep the frame stamped ``stamp_ns`` (counted in ``kept`` or ``skipped``)."""
        if self.period_ns == 0:
            self.kept += 1
            return True
        afresh = (
            self._kept_ns is None
            or stamp_ns < self._kept_ns  # stamps went back
            or stamp_ns - self._due_ns >= self.period_ns  # a gap of more than a period
        )
        if afresh:
            self._due_ns = stamp_ns + self.period_ns
        elif stamp_ns >= self._due_ns - self._tolerance_ns:
            self._due_ns += self.period_ns
        else:
            self.skipped += 1
            return False
        self._kept_ns = stamp_ns
        self.kept += 1
        return True


class ExactPairer(Generic[L, R]):
    """Pairs left and right halves with the same stamp; keeps ``capacity`` incomplete ones.

    ``unpaired_dropped`` counts halves pushed out by that bound; ``duplicates`` waiting halves
    replaced by a newer one of the same side and stamp."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._left: OrderedDict[int, L] = OrderedDict()
        self._right: OrderedDict[int, R] = OrderedDict()
        self.paired = 0
        self.unpaired_dropped = 0
        self.duplicates = 0

    def _push(self, mine: OrderedDict[int, T], stamp_ns: int, item: T) -> None:
        if stamp_ns in mine:
            self.duplicates += 1
        mine[stamp_ns] = item
        mine.move_to_end(stamp_ns)
        while len(mine) > self.capacity:
            mine.popitem(last=False)
            self.unpaired_dropped += 1

    def add_left(self, stamp_ns: int, item: L) -> tuple[L, R] | None:
        if stamp_ns in self._right:
            self.paired += 1
            return item, self._right.pop(stamp_ns)
        self._push(self._left, stamp_ns, item)
        return None

    def add_right(self, stamp_ns: int, item: R) -> tuple[L, R] | None:
        if stamp_ns in self._left:
            self.paired += 1
            return self._left.pop(stamp_ns), item
        self._push(self._right, stamp_ns, item)
        return None

    def pending(self) -> int:
        return len(self._left) + len(self._right)

    def waiting(self) -> list[L | R]:
        """The halves waiting for their partner."""
        return [*self._left.values(), *self._right.values()]

    def oldest_stamp(self) -> int | None:
        """The oldest stamp a half waits with (None: none waits)."""
        stamps = [min(d) for d in (self._left, self._right) if d]
        return min(stamps) if stamps else None

    def pop_oldest(self) -> L | R | None:
        """Remove and return the waiting half with the oldest stamp (None: none waits); the
        caller counts it."""
        sides: list[OrderedDict[int, L] | OrderedDict[int, R]] = [d for d in (self._left, self._right) if d]
        if not sides:
            return None
        side = min(sides, key=lambda d: min(d))
        return side.pop(min(side))

    def clear(self) -> int:
        """Discard the waiting halves; returns how many."""
        n = self.pending()
        self._left.clear()
        self._right.clear()
        return n


@dataclass(slots=True)
class _Waiting(Generic[T]):
    stamp_ns: int
    deadline_s: float
    item: T


class PoseGate(Generic[T]):
    """Frames waiting for a usable pose: released when one exists, dropped after ``wait_s``."""

    def __init__(self, poses: PoseBuffer, wait_s: float, capacity: int) -> None:
        self.poses = poses
        self.wait_s = wait_s
        self.capacity = capacity
        self._waiting: list[_Waiting[T]] = []

    def __len__(self) -> int:
        return len(self._waiting)

    def add(self, stamp_ns: int, item: T, now_s: float) -> list[tuple[T, str]]:
        """Queue ``item``; returns the items pushed out by the capacity bound, with a reason."""
        self._waiting.append(_Waiting(stamp_ns, now_s + self.wait_s, item))
        out: list[tuple[T, str]] = []
        while len(self._waiting) > self.capacity:
            w = self._waiting.pop(0)
            out.append((w.item, "pose wait queue full"))
        return out

    def poll(
        self,
        now_s: float,
        pending: Callable[[T, float], str | None] | None = None,
        expire_s: float | None = None,
    ) -> tuple[list[tuple[T, int, np.ndarray, np.ndarray]], list[tuple[T, str]]]:
        """(released: item, stamp, T_W_C, cov), (dropped: item, reason).

        ``pending(item, now_s)`` may hold an item back for another reason (e.g. its CameraInfo
        has not arrived): it returns that reason, or None when the item may go. Items whose
        deadline is before ``expire_s`` (default ``now_s``) are dropped: an earlier ``expire_s``
        spares those whose pose may still be on its way (received, not yet handled); it spares
        every waiting item alike, those held back by ``pending`` too, for as long as that backlog
        lasts.
        """
        ready: list[tuple[T, int, np.ndarray, np.ndarray]] = []
        dropped: list[tuple[T, str]] = []
        keep: list[_Waiting[T]] = []
        for w in self._waiting:
            res = self.poses.lookup(w.stamp_ns)
            why: str | None = res.reason
            if res.state == "ready":
                why = pending(w.item, now_s) if pending is not None else None
                if why is None:
                    assert res.T_W_C is not None and res.cov is not None
                    ready.append((w.item, w.stamp_ns, res.T_W_C, res.cov))
                    continue
            elif res.state == "fail":
                dropped.append((w.item, res.reason))
                continue
            if (now_s if expire_s is None else expire_s) >= w.deadline_s:
                what = "usable pose" if res.state != "ready" else "complete inputs"
                dropped.append((w.item, f"no {what} within {self.wait_s:g} s ({why})"))
            else:
                keep.append(w)
        self._waiting = keep
        return ready, dropped

    def items(self) -> list[T]:
        """The waiting items, oldest first."""
        return [w.item for w in self._waiting]

    def oldest_stamp(self) -> int | None:
        """The stamp of the item waiting longest (None: none)."""
        return self._waiting[0].stamp_ns if self._waiting else None

    def pop_oldest(self) -> T | None:
        """Remove and return the item waiting longest (None: none); the caller counts it."""
        return self._waiting.pop(0).item if self._waiting else None

    def clear(self) -> int:
        n = len(self._waiting)
        self._waiting.clear()
        return n
