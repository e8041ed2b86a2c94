# SPDX-License-Identifier: Apache-2.0
"""ROS 2 CDR encoders and decoders for pugsd's wire messages (rosbags, Jazzy type store).

Every ``decode_*`` validates what it reads and raises :class:`pugsd.errors.DecodeError` with a
reason (truncated CDR, unsupported encoding, size mismatch, non-finite pose, ...); no other
exception escapes. Encoders take numpy arrays / pugsd types and return ``bytes``.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.types import ScoredGrasps
from pugsd.errors import DecodeError, PugsdError
from pugsd.wire.types import (
    CAMERA_INFO,
    DIAGNOSTIC_ARRAY,
    GRASP,
    GRASP_ARRAY,
    IMAGE,
    MARKER_ARRAY,
    ODOMETRY,
    POINT_CLOUD2,
    POINT_FIELD,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    STRING,
    TF_MESSAGE,
    msg_class,
    typestore,
)

# ---------------------------------------------------------------------------------------------
# generic helpers

#: encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[np.dtype[Any], int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),  # cv_bridge's name for the same bytes
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),  # e.g. ZED cameras' rectified images
    "32FC1": (np.dtype(np.float32), 1),
    "16UC1": (np.dtype(np.uint16), 1),
}

#: the encodings a stereo image may have (``ImageMsg.rgb_or_mono`` gives mono or RGB), and a mask
STEREO_ENCODINGS = ("mono8", "8UC1", "rgb8", "bgr8", "rgba8", "bgra8")
MASK_ENCODINGS = ("mono8", "8UC1")

_CDR_LE = b"\x00\x01\x00\x00"
_CDR_BE = b"\x00\x00\x00\x00"


def serialize(msg: Any, typename: str) -> bytes:
    """CDR bytes (little endian, 4-byte encapsulation header) of a rosbags message object."""
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data: bytes | bytearray | memoryview, typename: str) -> Any:
    """Decode CDR into a rosbags message object; any failure is a DecodeError."""
    try:
        b = bytes(data)
    except Exception as exc:
        raise DecodeError(f"{typename}: payload is not bytes ({type(data).__name__})") from exc
    if len(b) < 4:
        raise DecodeError(f"{typename}: truncated CDR ({len(b)} bytes)")
    if b[:4] not in (_CDR_LE, _CDR_BE) and b[:2] not in (_CDR_LE[:2], _CDR_BE[:2]):
        raise DecodeError(f"{typename}: unsupported CDR encapsulation {b[:4].hex()}")
    try:
        return typestore().deserialize_cdr(b, typename)
    except Exception as exc:  # rosbags SerdeError, struct.error, UnicodeDecodeError, ...
        raise DecodeError(f"{typename}: malformed CDR ({len(b)} bytes): {exc}") from None


def _time(stamp_ns: int) -> Any:
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise ValueError(f"negative stamp {stamp_ns}")
    return msg_class("builtin_interfaces/msg/Time")(
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
    )


def _header(stamp_ns: int, frame_id: str) -> Any:
    return msg_class("std_msgs/msg/Header")(stamp=_time(stamp_ns), frame_id=str(frame_id))


def _stamp_ns(header: Any, typename: str) -> int:
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if nsec >= 1_000_000_000 or sec < 0:
        raise DecodeError(f"{typename}: invalid stamp sec={sec} nanosec={nsec}")
    return sec * 1_000_000_000 + nsec


def stamp_of(data: bytes, typename: str) -> int:
    """The header stamp (ns) of any message whose first field is a ``std_msgs/Header``."""
    return _stamp_ns(deserialize(data, typename).header, typename)


# ---------------------------------------------------------------------------------------------
# rotations


def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation matrix of a unit quaternion (normalised here)."""
    q = np.array([x, y, z, w], dtype=np.float64)
    q /= np.linalg.norm(q)
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) with w >= 0 of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        w, x, y, z = (
            0.25 * s,
            (R[2, 1] - R[1, 2]) / s,
            (R[0, 2] - R[2, 0]) / s,
            (R[1, 0] - R[0, 1]) / s,
        )
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x, y, z = (
            (R[2, 1] - R[1, 2]) / s,
            0.25 * s,
            (R[0, 1] + R[1, 0]) / s,
            (R[0, 2] + R[2, 0]) / s,
        )
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x, y, z = (
            (R[0, 2] - R[2, 0]) / s,
            (R[0, 1] + R[1, 0]) / s,
            0.25 * s,
            (R[1, 2] + R[2, 1]) / s,
        )
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x, y, z = (
            (R[1, 0] - R[0, 1]) / s,
            (R[0, 2] + R[2, 0]) / s,
            (R[1, 2] + R[2, 1]) / s,
            0.25 * s,
        )
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _pose_msg(T: np.ndarray) -> Any:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("pose must be a finite 4x4 matrix")
    qx, qy, qz, qw = matrix_to_quat(T[:3, :3])
    Point = msg_class("geometry_msgs/msg/Point")
    Quat = msg_class("geometry_msgs/msg/Quaternion")
    return msg_class("geometry_msgs/msg/Pose")(
        position=Point(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        orientation=Quat(x=qx, y=qy, z=qz, w=qw),
    )


def _pose_matrix(pose: Any, typename: str, *, quat_tol: float = 1e-3) -> np.ndarray:
    p, o = pose.position, pose.orientation
    vals = np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w], dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise DecodeError(f"{typename}: non-finite pose")
    with np.errstate(all="ignore"):
        n = float(np.linalg.norm(vals[3:]))
    if abs(n - 1.0) > quat_tol:
        raise DecodeError(f"{typename}: quaternion norm {n:.6g} is not 1")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(*vals[3:])
    T[:3, 3] = vals[:3]
    return T


# ---------------------------------------------------------------------------------------------
# sensor_msgs/Image


@dataclass(frozen=True, slots=True)
class ImageMsg:
    """A decoded image: ``array`` is (H, W) or (H, W, 3) in the wire's channel order."""

    stamp_ns: int
    frame_id: str
    encoding: str
    array: np.ndarray

    def rgb_or_mono(self) -> np.ndarray:
        """mono8/8UC1 as (H, W); rgb8, bgr8, rgba8, bgra8 as RGB (H, W, 3), alpha dropped;
        depth encodings unchanged."""
        if self.encoding == "bgr8":
            return np.ascontiguousarray(self.array[:, :, ::-1])
        if self.encoding == "rgba8":
            return np.ascontiguousarray(self.array[:, :, :3])
        if self.encoding == "bgra8":
            return np.ascontiguousarray(self.array[:, :, 2::-1])
        return self.array

    def depth_m(self) -> np.ndarray:
        """32FC1 (metres) or 16UC1 (millimetres) as float32 metres, NaN where invalid (0, inf)."""
        if self.encoding == "32FC1":
            d = self.array.astype(np.float32, copy=True)
        elif self.encoding == "16UC1":
            d = self.array.astype(np.float32) * np.float32(0.001)
        else:
            raise DecodeError(f"image encoding {self.encoding!r} is not a depth encoding")
        d[~np.isfinite(d) | (d <= 0)] = np.nan
        return d


def encode_image(
    array: np.ndarray, stamp_ns: int, frame_id: str = "camera", encoding: str | None = None
) -> bytes:
    """sensor_msgs/Image from an array. ``encoding`` defaults from dtype/shape: uint8 (H,W) mono8,
    uint8 (H,W,3) rgb8, float32 32FC1, uint16 16UC1."""
    a = np.asarray(array)
    if encoding is None:
        if a.dtype == np.uint8:
            encoding = "mono8" if a.ndim == 2 else "rgb8"
        elif a.dtype == np.float32:
            encoding = "32FC1"
        elif a.dtype == np.uint16:
            encoding = "16UC1"
        else:
            raise ValueError(f"no default image encoding for dtype {a.dtype}")
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r}")
    dtype, ch = IMAGE_ENCODINGS[encoding]
    want_ndim = 2 if ch == 1 else 3
    if a.ndim != want_ndim or (ch > 1 and a.shape[2] != ch):
        raise ValueError(f"{encoding} needs shape (H, W{f', {ch}' if ch > 1 else ''}), got {a.shape}")
    a = np.ascontiguousarray(a, dtype=dtype.newbyteorder("<"))
    h, w = a.shape[:2]
    msg = msg_class(IMAGE)(
        header=_header(stamp_ns, frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * ch * dtype.itemsize,
        data=np.frombuffer(a.tobytes(), dtype=np.uint8),
    )
    return serialize(msg, IMAGE)


@dataclass(frozen=True, slots=True)
class ImageLayout:
    """What a sensor_msgs/Image declares about its pixels, read from the CDR without decoding
    (or copying) them: ``data_bytes`` is the length of its data field."""

    height: int
    width: int
    encoding: str
    step: int
    data_bytes: int


def _cdr_string(buf: memoryview, pos: int, order: str) -> tuple[str, int] | None:
    pos = (pos + 3) & ~3
    if pos + 4 > len(buf):
        return None
    (n,) = struct.unpack_from(order + "I", buf, pos)
    pos += 4
    if n == 0 or pos + n > len(buf):
        return None
    try:
        return bytes(buf[pos : pos + n - 1]).decode("utf-8"), pos + n
    except UnicodeDecodeError:
        return None


def image_layout(data: bytes | bytearray | memoryview) -> ImageLayout | None:
    """The declared size of a CDR sensor_msgs/Image (height, width, encoding, step, data length),
    read from its fixed fields; None when they cannot be read (``decode_image`` then says why)."""
    buf = memoryview(data)
    if len(buf) < 4 or bytes(buf[:2]) not in (_CDR_LE[:2], _CDR_BE[:2]):
        return None
    order = "<" if buf[1] == 1 else ">"
    body = buf[4:]
    pos = 8  # header.stamp: sec, nanosec
    frame = _cdr_string(body, pos, order)
    if frame is None:
        return None
    pos = (frame[1] + 3) & ~3
    if pos + 8 > len(body):
        return None
    h, w = struct.unpack_from(order + "II", body, pos)
    enc = _cdr_string(body, pos + 8, order)
    if enc is None:
        return None
    pos = enc[1] + 1  # is_bigendian
    pos = (pos + 3) & ~3
    if pos + 8 > len(body):
        return None
    step, n = struct.unpack_from(order + "II", body, pos)
    return ImageLayout(int(h), int(w), enc[0], int(step), int(n))


def check_image_layout(
    data: bytes | bytearray | memoryview,
    max_bytes: int | None = None,
    shape: tuple[int, int] | None = None,
    what: str = f"{IMAGE}: image",
) -> None:
    """Refuse an image before any of its pixels are decoded or copied: a payload or declared
    pixel data (step * height) above ``max_bytes``, and one whose declared height and width are
    not ``shape``. DecodeError ``too_large`` or ``wrong_size``; a layout that cannot be read is
    left to ``decode_image``."""
    if max_bytes is not None and len(data) > max_bytes + MESSAGE_OVERHEAD_BYTES:
        raise DecodeError(
            f"{what} message of {len(data)} bytes, above the maximum image size {max_bytes} B",
            reason="too_large",
        )
    lay = image_layout(data)
    if lay is None:
        return
    if max_bytes is not None and max(lay.step * lay.height, lay.data_bytes) > max_bytes:
        raise DecodeError(
            f"{what} declares {lay.height} rows of {lay.step} bytes, above the maximum image "
            f"size {max_bytes} B",
            reason="too_large",
        )
    if shape is not None and (lay.height, lay.width) != shape:
        raise DecodeError(
            f"{what} is {(lay.height, lay.width)}, camera expects {shape}", reason="wrong_size"
        )


# header, frame_id and encoding of an image message beside its pixels: bounded by the checks of
# ``check_image_layout`` only through its declared sizes
MESSAGE_OVERHEAD_BYTES = 65536


def decode_image(
    data: bytes,
    encodings: Sequence[str] | None = None,
    *,
    max_bytes: int | None = None,
    shape: tuple[int, int] | None = None,
) -> ImageMsg:
    """Decode and validate a sensor_msgs/Image (encoding, step, data size); copies the pixels
    once. With ``max_bytes`` and ``shape`` the image is first refused by ``check_image_layout``
    (too large, or not ``shape`` (height, width)) before any of it is decoded."""
    if max_bytes is not None or shape is not None:
        check_image_layout(data, max_bytes, shape)
    m = deserialize(data, IMAGE)
    enc = str(m.encoding)
    allowed = IMAGE_ENCODINGS if encodings is None else encodings
    if enc not in IMAGE_ENCODINGS or enc not in allowed:
        shown = repr(enc[:40]) + ("..." if len(enc) > 40 else "")  # wire text: bounded
        msg = f"{IMAGE}: unsupported encoding {shown} (accepted: {list(allowed)})"
        raise DecodeError(msg, reason="wrong_encoding")
    dtype, ch = IMAGE_ENCODINGS[enc]
    h, w, step = int(m.height), int(m.width), int(m.step)
    if h <= 0 or w <= 0:
        raise DecodeError(f"{IMAGE}: empty image {w}x{h}")
    row = w * ch * dtype.itemsize
    if step < row:
        raise DecodeError(f"{IMAGE}: step {step} < width*channels*bytes {row}")
    raw = np.asarray(m.data, dtype=np.uint8)  # a view of ``data`` (rosbags does not copy)
    if raw.size != step * h:
        raise DecodeError(
            f"{IMAGE}: data has {raw.size} bytes, expected step*height = {step}*{h} = {step * h}"
        )
    if m.is_bigendian not in (0, 1):
        raise DecodeError(f"{IMAGE}: is_bigendian={m.is_bigendian}")
    rows = raw.reshape(h, step)[:, :row]
    dt = dtype.newbyteorder(">" if m.is_bigendian else "<")
    arr = np.empty((h, w) if ch == 1 else (h, w, ch), dtype=dtype)  # the one copy
    arr.reshape(h, row // dtype.itemsize)[...] = rows.view(dt)
    return ImageMsg(_stamp_ns(m.header, IMAGE), str(m.header.frame_id), enc, arr)


# ---------------------------------------------------------------------------------------------
# sensor_msgs/CameraInfo


@dataclass(frozen=True, slots=True)
class CameraInfoMsg:
    """A decoded CameraInfo: rectified intrinsics (from P) and the baseline from P's Tx."""

    stamp_ns: int
    frame_id: str
    camera: PinholeCamera
    baseline_m: float  # -Tx / fx; 0 for the left (reference) camera
    distortion_model: str
    D: np.ndarray


def encode_camera_info(
    camera: PinholeCamera, stamp_ns: int, frame_id: str = "camera", baseline_m: float = 0.0
) -> bytes:
    """Rectified CameraInfo (no distortion). For the right camera of a rig pass ``baseline_m``:
    ``P[0, 3] = Tx = -fx * B``."""
    K = camera.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    P[0, 3] = -camera.fx * float(baseline_m)
    RoI = msg_class("sensor_msgs/msg/RegionOfInterest")
    msg = msg_class(CAMERA_INFO)(
        header=_header(stamp_ns, frame_id),
        height=int(camera.height),
        width=int(camera.width),
        distortion_model="plumb_bob",
        d=np.zeros(5, dtype=np.float64),
        k=K.reshape(-1).astype(np.float64),
        r=np.eye(3).reshape(-1),
        p=P.reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )
    return serialize(msg, CAMERA_INFO)


def encode_stereo_infos(
    rig: StereoRig, stamp_ns: int, left_frame: str = "left", right_frame: str = "right"
) -> tuple[bytes, bytes]:
    """(left, right) CameraInfo of a rectified rig."""
    return (
        encode_camera_info(rig.left, stamp_ns, left_frame, 0.0),
        encode_camera_info(rig.right, stamp_ns, right_frame, rig.baseline_m),
    )


def decode_camera_info(data: bytes) -> CameraInfoMsg:
    m = deserialize(data, CAMERA_INFO)
    K = np.asarray(m.k, dtype=np.float64)
    P = np.asarray(m.p, dtype=np.float64)
    if K.size != 9 or P.size != 12:
        raise DecodeError(f"{CAMERA_INFO}: K has {K.size} values, P has {P.size}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(P))):
        raise DecodeError(f"{CAMERA_INFO}: non-finite K or P")
    P = P.reshape(3, 4)
    src = P[:, :3] if P[0, 0] > 0 else K.reshape(3, 3)
    # binning and region of interest as image_geometry's PinholeCameraModel reads them: K and P
    # are those of the full-resolution camera; the images are the ROI (the whole image when its
    # size is 0) divided by the binning (0 and 1: none); the ROI offset moves the principal point
    bx, by = max(int(m.binning_x), 1), max(int(m.binning_y), 1)
    roi = m.roi
    roi_w, roi_h = int(roi.width) or int(m.width), int(roi.height) or int(m.height)
    if int(roi.x_offset) + roi_w > int(m.width) or int(roi.y_offset) + roi_h > int(m.height):
        raise DecodeError(
            f"{CAMERA_INFO}: region of interest {roi_w}x{roi_h}+{roi.x_offset}+{roi.y_offset} is "
            f"outside the {m.width}x{m.height} image"
        )
    try:
        cam = PinholeCamera(
            fx=float(src[0, 0]) / bx,
            fy=float(src[1, 1]) / by,
            cx=(float(src[0, 2]) - int(roi.x_offset)) / bx,
            cy=(float(src[1, 2]) - int(roi.y_offset)) / by,
            width=roi_w // bx,
            height=roi_h // by,
            skew=float(src[0, 1]) / bx,
        )
    except PugsdError as exc:
        raise DecodeError(f"{CAMERA_INFO}: {exc}") from None
    baseline = -float(P[0, 3]) / float(P[0, 0]) if P[0, 0] > 0 else 0.0  # Tx / fx: binning-free
    return CameraInfoMsg(
        _stamp_ns(m.header, CAMERA_INFO),
        str(m.header.frame_id),
        cam,
        baseline,
        str(m.distortion_model),
        np.asarray(m.d, dtype=np.float64).copy(),
    )


def stereo_rig_from_infos(
    left: CameraInfoMsg, right: CameraInfoMsg, *, tol: float = 1e-6
) -> StereoRig:
    """The rectified rig of a left/right CameraInfo pair (baseline from the right P).

    fx, fy, cy and skew must agree (rows aligned, one focal length); cx may differ: a pair
    rectified without zero disparity at infinity (``principal_offset_px = cx_left - cx_right``,
    as image_geometry's ``StereoCameraModel`` reads it)."""
    a, b = left.camera, right.camera
    if (a.width, a.height) != (b.width, b.height):
        raise DecodeError("stereo CameraInfo: left and right image sizes differ")
    for name in ("fx", "fy", "cy", "skew"):
        va, vb = getattr(a, name), getattr(b, name)
        if abs(va - vb) > tol * max(1.0, abs(va)):
            raise DecodeError(f"stereo CameraInfo: {name} differs ({va} vs {vb}); not rectified")
    B = right.baseline_m - left.baseline_m
    if not (math.isfinite(B) and B > 0):
        raise DecodeError(f"stereo CameraInfo: baseline {B} m from the right P matrix is not > 0")
    offset = a.cx - b.cx
    if abs(offset) <= tol * max(1.0, abs(a.cx)):
        offset = 0.0
    try:
        return StereoRig(a, B, offset)
    except PugsdError as exc:
        raise DecodeError(f"stereo CameraInfo: {exc}") from None


# ---------------------------------------------------------------------------------------------
# poses


@dataclass(frozen=True, slots=True)
class PoseMsg:
    """A decoded camera pose: ``T`` (4x4, child -> frame_id) and 6x6 covariance (x,y,z,rx,ry,rz),
    or None when the message carries none (PoseStamped without a configured covariance)."""

    stamp_ns: int
    frame_id: str
    T: np.ndarray
    cov: np.ndarray | None


def _check_cov(C: np.ndarray, typename: str) -> np.ndarray:
    """Finite, symmetric, PSD; the checks run on ``C`` scaled to entries in [-1, 1], so that
    entries near the float64 limit cannot overflow."""
    if not np.all(np.isfinite(C)):
        raise DecodeError(f"{typename}: non-finite covariance")
    scale = float(np.abs(C).max())
    if scale == 0.0:
        return np.zeros_like(C)
    S = C / scale
    if np.abs(S - S.T).max() > 1e-6:
        raise DecodeError(f"{typename}: covariance is not symmetric")
    try:
        lowest = float(np.linalg.eigvalsh(0.5 * (S + S.T)).min())
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise DecodeError(
            f"{typename}: covariance eigenvalues failed ({exc}); not positive semi-definite"
        ) from None
    if not lowest >= -1e-9:  # NaN too
        raise DecodeError(f"{typename}: covariance is not positive semi-definite")
    return 0.5 * C + 0.5 * C.T


def _pose_with_cov_msg(T: np.ndarray, cov: np.ndarray) -> Any:
    """A geometry_msgs/PoseWithCovariance (the body of PoseWithCovarianceStamped and Odometry)."""
    C = np.asarray(cov, dtype=np.float64)
    if C.shape != (6, 6):
        raise ValueError(f"covariance must be 6x6, got {C.shape}")
    PwC = msg_class("geometry_msgs/msg/PoseWithCovariance")
    return PwC(pose=_pose_msg(T), covariance=C.reshape(-1).copy())


def _pose_msg_with_cov(m: Any, typename: str) -> PoseMsg:
    """The PoseMsg of a decoded message with ``header`` and a PoseWithCovariance ``pose``."""
    T = _pose_matrix(m.pose.pose, typename)
    C = np.asarray(m.pose.covariance, dtype=np.float64)
    if C.size != 36:
        raise DecodeError(f"{typename}: covariance has {C.size} values, expected 36")
    C = _check_cov(C.reshape(6, 6), typename)
    return PoseMsg(_stamp_ns(m.header, typename), str(m.header.frame_id), T, C)


def encode_pose_with_covariance(
    stamp_ns: int, T: np.ndarray, cov: np.ndarray, frame_id: str = "world"
) -> bytes:
    msg = msg_class(POSE_COV_STAMPED)(header=_header(stamp_ns, frame_id), pose=_pose_with_cov_msg(T, cov))
    return serialize(msg, POSE_COV_STAMPED)


def decode_pose_with_covariance(data: bytes) -> PoseMsg:
    return _pose_msg_with_cov(deserialize(data, POSE_COV_STAMPED), POSE_COV_STAMPED)


def encode_pose_stamped(stamp_ns: int, T: np.ndarray, frame_id: str = "world") -> bytes:
    msg = msg_class(POSE_STAMPED)(header=_header(stamp_ns, frame_id), pose=_pose_msg(T))
    return serialize(msg, POSE_STAMPED)


def decode_pose_stamped(data: bytes, cov: np.ndarray | None = None) -> PoseMsg:
    """PoseStamped; ``cov`` (6x6, e.g. from the config) is attached as its covariance."""
    m = deserialize(data, POSE_STAMPED)
    T = _pose_matrix(m.pose, POSE_STAMPED)
    C = None
    if cov is not None:
        C = np.asarray(cov, dtype=np.float64)
        if C.shape != (6, 6):
            raise DecodeError(f"{POSE_STAMPED}: configured covariance must be 6x6, got {C.shape}")
        C = _check_cov(C, POSE_STAMPED)
    return PoseMsg(_stamp_ns(m.header, POSE_STAMPED), str(m.header.frame_id), T, C)


def encode_odometry(
    stamp_ns: int, T: np.ndarray, cov: np.ndarray, frame_id: str = "world", child_frame_id: str = "base_link"
) -> bytes:
    """nav_msgs/Odometry with the pose and its covariance (``T``: child -> frame_id); zero twist."""
    TwC = msg_class("geometry_msgs/msg/TwistWithCovariance")
    Twist, Vector3 = msg_class("geometry_msgs/msg/Twist"), msg_class("geometry_msgs/msg/Vector3")
    zero = Vector3(x=0.0, y=0.0, z=0.0)
    msg = msg_class(ODOMETRY)(
        header=_header(stamp_ns, frame_id),
        child_frame_id=child_frame_id,
        pose=_pose_with_cov_msg(T, cov),
        twist=TwC(twist=Twist(linear=zero, angular=zero), covariance=np.zeros(36)),
    )
    return serialize(msg, ODOMETRY)


def decode_odometry(data: bytes) -> PoseMsg:
    """The pose (child -> header.frame_id) and pose covariance of a nav_msgs/Odometry; the twist
    is not used."""
    return _pose_msg_with_cov(deserialize(data, ODOMETRY), ODOMETRY)


def decode_pose(data: bytes, typename: str, cov: np.ndarray | None = None) -> PoseMsg:
    """Any pose type by name (``typename`` from the key / recording)."""
    if typename == POSE_COV_STAMPED:
        return decode_pose_with_covariance(data)
    if typename == POSE_STAMPED:
        return decode_pose_stamped(data, cov)
    if typename == ODOMETRY:
        return decode_odometry(data)
    raise DecodeError(f"unsupported pose type {typename!r}")


# ---------------------------------------------------------------------------------------------
# pugs_msgs/GraspArray


def encode_grasp_array(
    grasps: ScoredGrasps, frame_id: str = "world", stamp_ns: int | None = None
) -> bytes:
    """GraspArray (best first, as in ``grasps``); ``stamp_ns`` defaults to ``grasps.stamp_ns``."""
    st = int(grasps.stamp_ns if stamp_ns is None else stamp_ns)
    hdr = _header(st, frame_id)
    Point = msg_class("geometry_msgs/msg/Point")
    G = msg_class(GRASP)
    items = []
    for i in range(len(grasps)):
        c = np.asarray(grasps.contact_W[i], dtype=np.float64)
        items.append(
            G(
                header=hdr,
                pose=_pose_msg(grasps.pose_W[i]),
                contact=Point(x=float(c[0]), y=float(c[1]), z=float(c[2])),
                width=float(grasps.width_m[i]),
                baseline_confidence=float(grasps.baseline_confidence[i]),
                sigma2_occ=float(grasps.sigma2_occ[i]),
                pugs_confidence=float(grasps.pugs_confidence[i]),
                id=int(grasps.grasp_id[i]),
            )
        )
    return serialize(msg_class(GRASP_ARRAY)(header=hdr, grasps=items), GRASP_ARRAY)


def decode_grasp_array(data: bytes) -> ScoredGrasps:
    """ScoredGrasps from GraspArray CDR bytes (order kept); DecodeError on any invalid field."""
    m = deserialize(data, GRASP_ARRAY)
    n = len(m.grasps)
    poses = np.zeros((n, 4, 4))
    contact = np.zeros((n, 3))
    scal = np.zeros((n, 4))
    ids = np.zeros(n, dtype=np.int64)
    for i, g in enumerate(m.grasps):
        poses[i] = _pose_matrix(g.pose, GRASP_ARRAY)
        contact[i] = (g.contact.x, g.contact.y, g.contact.z)
        scal[i] = (g.width, g.baseline_confidence, g.sigma2_occ, g.pugs_confidence)
        ids[i] = g.id
    if not (np.all(np.isfinite(contact)) and np.all(np.isfinite(scal))):
        raise DecodeError(f"{GRASP_ARRAY}: non-finite contact, width or score")
    return ScoredGrasps(
        pose_W=poses,
        contact_W=contact,
        width_m=scal[:, 0].copy(),
        baseline_confidence=scal[:, 1].copy(),
        sigma2_occ=scal[:, 2].copy(),
        pugs_confidence=scal[:, 3].copy(),
        grasp_id=ids,
        stamp_ns=_stamp_ns(m.header, GRASP_ARRAY),
    )


def grasp_array_frame_id(data: bytes) -> str:
    """The frame_id of a GraspArray's header (the frame of its poses and contacts)."""
    return str(deserialize(data, GRASP_ARRAY).header.frame_id)


# ---------------------------------------------------------------------------------------------
# visualization_msgs/MarkerArray

_MARKER_LINE_LIST = 5
_MARKER_ADD = 0
_MARKER_DELETEALL = 3


def confidence_color(c: float) -> tuple[float, float, float]:
    """Red (0) -> yellow (0.5) -> green (1)."""
    c = float(np.clip(c if math.isfinite(c) else 0.0, 0.0, 1.0))
    return (min(1.0, 2.0 * (1.0 - c)), min(1.0, 2.0 * c), 0.0)


def gripper_lines(pose: np.ndarray, width: float, depth: float = 0.1) -> np.ndarray:
    """LINE_LIST segments (2k, 3) of a parallel gripper at ``pose`` (Contact-GraspNet convention:
    columns (b, a x b, a), origin at the wrist): a stem, the palm and two fingers reaching
    ``depth`` along the approach, fingertips at the contact plane."""
    T = np.asarray(pose, dtype=np.float64)
    o, b, a = T[:3, 3], T[:3, 0], T[:3, 2]
    half = 0.5 * float(width)
    palm = o + 0.5 * depth * a
    tip = o + depth * a
    pts = [
        o,
        palm,
        palm - half * b,
        palm + half * b,
        palm - half * b,
        tip - half * b,
        palm + half * b,
        tip + half * b,
    ]
    return np.asarray(pts)


def encode_grasp_markers(
    grasps: ScoredGrasps,
    frame_id: str = "world",
    stamp_ns: int | None = None,
    *,
    top_k: int = 10,
    depth: float = 0.1,
    line_width: float = 0.003,
    ns: str = "pugs_grasps",
    use_pugs_confidence: bool = True,
) -> bytes:
    """MarkerArray: a DELETEALL, then one LINE_LIST gripper per top grasp coloured by confidence
    (PUGS confidence, or the baseline one)."""
    st = int(grasps.stamp_ns if stamp_ns is None else stamp_ns)
    hdr = _header(st, frame_id)
    Marker = msg_class("visualization_msgs/msg/Marker")
    Point = msg_class("geometry_msgs/msg/Point")
    Vec3 = msg_class("geometry_msgs/msg/Vector3")
    Color = msg_class("std_msgs/msg/ColorRGBA")
    Duration = msg_class("builtin_interfaces/msg/Duration")
    ident = _pose_msg(np.eye(4))

    def marker(mid: int, action: int, points: list[Any], color: Any) -> Any:
        return Marker(
            header=hdr,
            ns=ns,
            id=mid,
            type=_MARKER_LINE_LIST,
            action=action,
            pose=ident,
            scale=Vec3(x=line_width, y=0.0, z=0.0),
            color=color,
            lifetime=Duration(sec=0, nanosec=0),
            frame_locked=False,
            points=points,
            colors=[],
            texture_resource="",
            texture=msg_class("sensor_msgs/msg/CompressedImage")(
                header=hdr, format="", data=np.zeros(0, dtype=np.uint8)
            ),
            uv_coordinates=[],
            text="",
            mesh_resource="",
            mesh_file=msg_class("visualization_msgs/msg/MeshFile")(
                filename="", data=np.zeros(0, dtype=np.uint8)
            ),
            mesh_use_embedded_materials=False,
        )

    out = [marker(0, _MARKER_DELETEALL, [], Color(r=0.0, g=0.0, b=0.0, a=0.0))]
    conf = grasps.pugs_confidence if use_pugs_confidence else grasps.baseline_confidence
    if use_pugs_confidence and len(conf) and float(np.max(conf)) > 0:
        # PUGS confidences live on a data-dependent scale (Eq. 13 in density units): colour the
        # grasps relative to the best one so the ranking is visible
        conf = conf / float(np.max(conf))
    for i in range(min(int(top_k), len(grasps))):
        seg = gripper_lines(grasps.pose_W[i], float(grasps.width_m[i]), depth)
        r, g, b = confidence_color(float(conf[i]))
        pts = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in seg]
        out.append(marker(i + 1, _MARKER_ADD, pts, Color(r=r, g=g, b=b, a=1.0)))
    return serialize(msg_class(MARKER_ARRAY)(markers=out), MARKER_ARRAY)


# ---------------------------------------------------------------------------------------------
# sensor_msgs/PointCloud2

CLOUD_FIELDS = ("x", "y", "z", "sigma2_occ", "pugs_confidence")
_FLOAT32 = 7


@dataclass(frozen=True, slots=True)
class CloudMsg:
    stamp_ns: int
    frame_id: str
    fields: dict[str, np.ndarray]  # name -> (N,) float32

    @property
    def points(self) -> np.ndarray:
        return np.stack([self.fields["x"], self.fields["y"], self.fields["z"]], axis=1)


def encode_cloud(
    points: np.ndarray,
    stamp_ns: int,
    frame_id: str = "world",
    *,
    sigma2_occ: np.ndarray | None = None,
    pugs_confidence: np.ndarray | None = None,
    extra: Mapping[str, np.ndarray] | None = None,
) -> bytes:
    """Unorganised PointCloud2 (height 1) with float32 fields x, y, z, sigma2_occ,
    pugs_confidence (NaN when not given) and any ``extra`` float32 fields."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {P.shape}")
    n = P.shape[0]
    cols: dict[str, np.ndarray] = {"x": P[:, 0], "y": P[:, 1], "z": P[:, 2]}
    for name, v in (("sigma2_occ", sigma2_occ), ("pugs_confidence", pugs_confidence)):
        cols[name] = (
            np.full(n, np.nan) if v is None else np.asarray(v, dtype=np.float64).reshape(-1)
        )
    for name, v in (extra or {}).items():
        cols[name] = np.asarray(v, dtype=np.float64).reshape(-1)
    for name, v in cols.items():
        if v.shape != (n,):
            raise ValueError(f"field {name} has {v.shape[0]} values for {n} points")
    names = list(cols)
    rec = np.empty(n, dtype=np.dtype([(k, "<f4") for k in names]))
    for k in names:
        rec[k] = cols[k]
    PF = msg_class(POINT_FIELD)
    fields = [PF(name=k, offset=4 * i, datatype=_FLOAT32, count=1) for i, k in enumerate(names)]
    step = 4 * len(names)
    msg = msg_class(POINT_CLOUD2)(
        header=_header(stamp_ns, frame_id),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * n,
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8),
        is_dense=bool(np.all(np.isfinite(P))),
    )
    return serialize(msg, POINT_CLOUD2)


def decode_cloud(data: bytes) -> CloudMsg:
    """PointCloud2 with float32 fields only (as written by :func:`encode_cloud`)."""
    m = deserialize(data, POINT_CLOUD2)
    if m.is_bigendian:
        raise DecodeError(f"{POINT_CLOUD2}: big-endian clouds are not supported")
    n = int(m.height) * int(m.width)
    step = int(m.point_step)
    raw = np.asarray(m.data, dtype=np.uint8)
    if int(m.row_step) != step * int(m.width) or raw.size != step * n:
        raise DecodeError(
            f"{POINT_CLOUD2}: data has {raw.size} bytes, expected point_step*n = {step * n}"
        )
    out: dict[str, np.ndarray] = {}
    for f in m.fields:
        if int(f.datatype) != _FLOAT32 or int(f.count) != 1:
            raise DecodeError(f"{POINT_CLOUD2}: field {f.name} is not a single float32")
        if int(f.offset) + 4 > step:
            raise DecodeError(f"{POINT_CLOUD2}: field {f.name} offset {f.offset} beyond point_step")
        if n == 0:
            out[str(f.name)] = np.zeros(0, dtype=np.float32)
            continue
        view = np.lib.stride_tricks.as_strided(
            raw[int(f.offset) :], shape=(n, 4), strides=(step, 1)
        )
        out[str(f.name)] = np.ascontiguousarray(view).view("<f4").reshape(n).astype(np.float32)
    for k in ("x", "y", "z"):
        if k not in out:
            raise DecodeError(f"{POINT_CLOUD2}: missing field {k}")
    return CloudMsg(_stamp_ns(m.header, POINT_CLOUD2), str(m.header.frame_id), out)


# ---------------------------------------------------------------------------------------------
# status (std_msgs/String holding JSON)


def encode_status(status: Mapping[str, Any]) -> bytes:
    text = json.dumps(dict(status), sort_keys=True, allow_nan=False, default=_json_default)
    return serialize(msg_class(STRING)(data=text), STRING)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def decode_status(data: bytes) -> dict[str, Any]:
    m = deserialize(data, STRING)
    try:
        obj = json.loads(m.data)
    except ValueError as exc:
        raise DecodeError(f"status: not JSON: {exc}") from None
    except RecursionError:
        raise DecodeError("status: JSON nested too deeply") from None
    if not isinstance(obj, dict):
        raise DecodeError("status: JSON is not an object")
    return obj


# ---------------------------------------------------------------------------------------------
# tf2_msgs/TFMessage


@dataclass(frozen=True, slots=True)
class Transform:
    """One edge of the TF tree: ``T_parent_child`` (4x4) maps ``child`` coordinates into
    ``parent``'s, stamped ``stamp_ns``."""

    stamp_ns: int
    parent: str
    child: str
    T_parent_child: np.ndarray


def encode_tf(transforms: Sequence[Transform]) -> bytes:
    """tf2_msgs/TFMessage with one geometry_msgs/TransformStamped per transform."""
    V3, Q = msg_class("geometry_msgs/msg/Vector3"), msg_class("geometry_msgs/msg/Quaternion")
    TS, Tr = msg_class("geometry_msgs/msg/TransformStamped"), msg_class("geometry_msgs/msg/Transform")
    out = []
    for t in transforms:
        T = np.asarray(t.T_parent_child, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"transform {t.parent} -> {t.child}: not a finite 4x4 matrix")
        qx, qy, qz, qw = matrix_to_quat(T[:3, :3])
        out.append(
            TS(
                header=_header(t.stamp_ns, t.parent),
                child_frame_id=str(t.child),
                transform=Tr(
                    translation=V3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                    rotation=Q(x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return serialize(msg_class(TF_MESSAGE)(transforms=out), TF_MESSAGE)


def decode_tf(data: bytes) -> list[Transform]:
    m = deserialize(data, TF_MESSAGE)
    out = []
    for ts in m.transforms:
        tr, ro = ts.transform.translation, ts.transform.rotation
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(ro.x, ro.y, ro.z, ro.w)
        T[:3, 3] = [tr.x, tr.y, tr.z]
        stamp_ns = _stamp_ns(ts.header, TF_MESSAGE)
        out.append(Transform(stamp_ns, str(ts.header.frame_id), str(ts.child_frame_id), T))
    return out


# ---------------------------------------------------------------------------------------------
# diagnostic_msgs/DiagnosticArray

#: diagnostic_msgs/DiagnosticStatus levels
DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE = 0, 1, 2, 3


@dataclass(frozen=True, slots=True)
class DiagnosticStatus:
    level: int  # DIAG_OK, DIAG_WARN, DIAG_ERROR or DIAG_STALE
    name: str
    message: str
    hardware_id: str
    values: Mapping[str, str]


def encode_diagnostics(stamp_ns: int, statuses: Sequence[DiagnosticStatus]) -> bytes:
    """diagnostic_msgs/DiagnosticArray (header frame_id empty, as diagnostic_updater sends it)."""
    St, KV = msg_class("diagnostic_msgs/msg/DiagnosticStatus"), msg_class("diagnostic_msgs/msg/KeyValue")
    out = [
        St(
            level=int(st.level),
            name=str(st.name),
            message=str(st.message),
            hardware_id=str(st.hardware_id),
            values=[KV(key=str(k), value=str(v)) for k, v in st.values.items()],
        )
        for st in statuses
    ]
    return serialize(msg_class(DIAGNOSTIC_ARRAY)(header=_header(stamp_ns, ""), status=out), DIAGNOSTIC_ARRAY)
