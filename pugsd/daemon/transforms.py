# SPDX-License-Identifier: Apache-2.0
"""The daemon's TF tree: ``/tf`` from the pose input and ``/tf_static`` for the rig, so that every
frame_id pugsd publishes or takes in (the outputs' pose frame, the images' camera frames)
connects to the pose frame (``world``), in Foxglove's 3D panel, RViz and every recording.

- ``/tf``, one TransformStamped per accepted pose, stamped with it: pose frame -> camera frame
  (the left CameraInfo's frame_id; the depth CameraInfo's with depth input), or pose frame ->
  body when the pose is that of a body carrying the camera (``[daemon] T_B_C_*`` set, or an
  Odometry whose child_frame_id names another frame than the camera's);
- ``/tf_static``: body -> camera (the mount ``T_B_C``, identity when not set) in that case, and
  left -> right camera (``x`` = the stereo baseline, rectified) when the right CameraInfo names
  another frame. Published TRANSIENT_LOCAL (a cache of one for late joiners, as rmw_zenoh's
  static broadcasters), again whenever it changes, and every :data:`STATIC_REPUBLISH_S` so that a
  subscriber or a recording file that missed it (a VOLATILE subscriber, a rotated MCAP) gets it.

A pose whose camera frame is not known yet (no CameraInfo) is not published on ``/tf``: no frame
would be processed without it either.
"""

from __future__ import annotations

import logging
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from pugsd.wire import codec
from pugsd.wire.types import ODOMETRY

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

log = logging.getLogger(__name__)

STATIC_REPUBLISH_S = 5.0
#: the body's frame name when the pose input names none (a PoseWithCovarianceStamped or
#: PoseStamped of the body carrying the camera, [daemon] T_B_C_*)
DEFAULT_BODY_FRAME = "body"


def camera_frames(infos: dict[str, Any]) -> tuple[str | None, str | None]:
    """(camera frame, right camera frame) from the assembler's CameraInfos (``role -> msg``)."""
    left = infos.get("left_info") or infos.get("depth_info")
    right = infos.get("right_info") if "left_info" in infos else None
    cam = (left.frame_id or None) if left is not None else None
    return cam, (right.frame_id or None) if right is not None else None


def static_transforms(
    infos: dict[str, Any], body: str | None, T_B_C: np.ndarray | None, stamp_ns: int
) -> list[codec.Transform]:
    """The rig's static transforms: body -> camera (``T_B_C``, identity when None) when ``body``
    is named, and left -> right (the baseline along the left camera's x axis) when both stereo
    CameraInfos are known and name different frames."""
    cam, right = camera_frames(infos)
    out: list[codec.Transform] = []
    if cam is None:
        return out
    if body is not None and body != cam:
        out.append(codec.Transform(stamp_ns, body, cam, np.eye(4) if T_B_C is None else np.asarray(T_B_C)))
    if right is not None and right != cam:
        T = np.eye(4)
        T[0, 3] = float(infos["right_info"].baseline_m)
        out.append(codec.Transform(stamp_ns, cam, right, T))
    return out


def _edges(ts: list[codec.Transform]) -> list[tuple[str, str, tuple[float, ...]]]:
    return [(t.parent, t.child, tuple(np.round(np.asarray(t.T_parent_child).ravel(), 12))) for t in ts]


class Transforms:
    """Publishes the TF tree of the daemon ``d`` through its outputs (roles ``tf`` and
    ``tf_static``); ``on_pose`` and ``tick`` run on the loop."""

    def __init__(self, d: Daemon) -> None:
        self.d = d
        self.body: str | None = None  # the frame the pose input moves, when not the camera's
        self._static_sent: list[tuple[str, str, tuple[float, ...]]] = []
        self._static_sent_s = -math.inf

    def on_pose(self, payload: bytes, typename: str, now_s: float | None = None) -> None:
        """An accepted pose (its CDR bytes, of ``typename``): its transform on ``/tf``."""
        d = self.d
        cam, _ = camera_frames(d.frames.infos)
        if cam is None:
            return
        pm = codec.decode_pose(payload, typename)
        child = ""
        if typename == ODOMETRY:
            child = str(codec.deserialize(payload, ODOMETRY).child_frame_id)
        if d.frames.T_B_C is not None:
            self.body = child or DEFAULT_BODY_FRAME
        elif child and child != cam:
            self.body = child
        else:
            self.body = None
        parent = pm.frame_id or d.frames.frame_id
        t = codec.Transform(pm.stamp_ns, parent, self.body or cam, pm.T)
        if parent != t.child:
            d.outputs.put("tf", codec.encode_tf([t]))
        self.tick(time.monotonic() if now_s is None else now_s)

    def tick(self, now_s: float) -> None:
        """Publish ``/tf_static`` when it changed or :data:`STATIC_REPUBLISH_S` has passed."""
        d = self.d
        ts = static_transforms(d.frames.infos, self.body, d.frames.T_B_C, time.time_ns())
        if not ts:
            return
        edges = _edges(ts)
        if edges == self._static_sent and now_s - self._static_sent_s < STATIC_REPUBLISH_S:
            return
        if edges != self._static_sent:
            log.info("tf_static: %s", ", ".join(f"{t.parent} -> {t.child}" for t in ts))
        if d.outputs.put("tf_static", codec.encode_tf(ts)):
            self._static_sent, self._static_sent_s = edges, now_s
