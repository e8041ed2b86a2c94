# SPDX-License-Identifier: Apache-2.0
"""Encoders/decoders: round trips, golden decode by mcap_ros2 (independent CDR), malformed input."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import struct
import warnings
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.types import ScoredGrasps
from pugsd.errors import DecodeError, InputError
from pugsd.wire import codec
from pugsd.wire.types import (
    CAMERA_INFO,
    GRASP_ARRAY,
    IMAGE,
    MARKER_ARRAY,
    POINT_CLOUD2,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    STRING,
    msgdef,
)

STAMP = 1_700_000_000_123_456_789


def golden(typename: str, data: bytes) -> Any:
    """Decode ``data`` with mcap_ros2's own CDR decoder through an in-memory MCAP."""
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2", library="pugsd-test")
    sid = w.register_schema(typename, "ros2msg", msgdef(typename).encode())
    cid = w.register_channel("/t", "cdr", sid)
    w.add_message(cid, log_time=1, data=data, publish_time=1)
    w.finish()
    buf.seek(0)
    reader = make_reader(buf, decoder_factories=[DecoderFactory()])
    msgs = list(reader.iter_decoded_messages())
    assert len(msgs) == 1
    schema, _channel, _message, decoded = msgs[0]
    assert schema is not None and schema.name == typename
    return decoded


def _rot(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = (math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay),
                              math.cos(az), math.sin(az))  # fmt: skip
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _T(ax: float = 0.3, ay: float = -1.2, az: float = 2.9, t: tuple[float, ...] = (1, 2, 3)) -> Any:
    T = np.eye(4)
    T[:3, :3] = _rot(ax, ay, az)
    T[:3, 3] = t
    return T


def _grasps(n: int = 4) -> ScoredGrasps:
    rng = np.random.default_rng(1)
    angles = rng.uniform(-3, 3, (n, 3))
    poses = np.stack([_T(a, b, c, t=tuple(rng.normal(size=3))) for a, b, c in angles])
    return ScoredGrasps(
        pose_W=poses,
        contact_W=rng.normal(size=(n, 3)),
        width_m=rng.uniform(0.01, 0.08, n),
        baseline_confidence=rng.uniform(0, 1, n),
        sigma2_occ=rng.uniform(0, 0.1, n),
        pugs_confidence=rng.uniform(0, 1, n),
        grasp_id=np.arange(n, dtype=np.int64) * 7 + 3,
        stamp_ns=STAMP,
    )


# --------------------------------------------------------------------------- images


@pytest.mark.parametrize(
    ("encoding", "arr"),
    [
        ("mono8", np.arange(12 * 7, dtype=np.uint8).reshape(7, 12)),
        ("rgb8", np.arange(5 * 6 * 3, dtype=np.uint8).reshape(5, 6, 3)),
        ("bgr8", np.arange(5 * 6 * 3, dtype=np.uint8).reshape(5, 6, 3)[::-1].copy()),
        ("32FC1", np.linspace(0.1, 2.0, 20, dtype=np.float32).reshape(4, 5)),
        ("16UC1", np.arange(20, dtype=np.uint16).reshape(4, 5) * 300),
        ("8UC1", np.arange(12 * 7, dtype=np.uint8).reshape(7, 12)),
        ("rgba8", np.arange(5 * 6 * 4, dtype=np.uint8).reshape(5, 6, 4)),
        ("bgra8", np.arange(5 * 6 * 4, dtype=np.uint8).reshape(5, 6, 4)[::-1].copy()),
    ],
)
def test_image_round_trip_and_golden(encoding: str, arr: np.ndarray) -> None:
    data = codec.encode_image(arr, STAMP, "left", encoding)
    assert data[:4] == b"\x00\x01\x00\x00"
    img = codec.decode_image(data)
    assert img.encoding == encoding and img.stamp_ns == STAMP and img.frame_id == "left"
    np.testing.assert_array_equal(img.array, arr)
    assert img.array.dtype == arr.dtype
    g = golden(IMAGE, data)
    assert (g.height, g.width, g.encoding, g.is_bigendian) == (
        arr.shape[0],
        arr.shape[1],
        encoding,
        0,
    )
    assert g.step == arr.shape[1] * arr.itemsize * (arr.shape[2] if arr.ndim == 3 else 1)
    assert bytes(g.data) == np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<")).tobytes()
    assert g.header.stamp.sec * 10**9 + g.header.stamp.nanosec == STAMP
    assert g.header.frame_id == "left"


def test_image_bgr_to_rgb_and_depth() -> None:
    bgr = np.zeros((2, 3, 3), dtype=np.uint8)
    bgr[..., 0] = 255  # blue
    img = codec.decode_image(codec.encode_image(bgr, 1, encoding="bgr8"))
    assert (img.rgb_or_mono()[..., 2] == 255).all() and (img.rgb_or_mono()[..., 0] == 0).all()
    mm = np.array([[0, 1500]], dtype=np.uint16)
    d = codec.decode_image(codec.encode_image(mm, 1)).depth_m()
    assert np.isnan(d[0, 0]) and d[0, 1] == pytest.approx(1.5)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_images_come_out_rgb_with_alpha_dropped(encoding: str) -> None:
    rgb = np.random.default_rng(3).integers(0, 256, (4, 5, 3), dtype=np.uint8)
    alpha = np.full((4, 5, 1), 77, dtype=np.uint8)
    arr = {"rgb8": rgb, "bgr8": rgb[..., ::-1], "rgba8": np.concatenate([rgb, alpha], axis=2),
           "bgra8": np.concatenate([rgb[..., ::-1], alpha], axis=2)}[encoding]  # fmt: skip
    img = codec.decode_image(codec.encode_image(arr, 1, encoding=encoding), codec.STEREO_ENCODINGS)
    out = img.rgb_or_mono()
    assert out.shape == (4, 5, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)


def test_image_with_row_padding_and_big_endian() -> None:
    ts = codec.typestore()
    Image = ts.types[IMAGE]
    arr = np.arange(6, dtype=np.uint16).reshape(2, 3) + 1000
    rows = [arr[i].astype(">u2").tobytes() + b"\xee\xee" for i in range(2)]  # step 8 > 6
    data = np.frombuffer(b"".join(rows), dtype=np.uint8)
    msg = Image(header=codec._header(5, "x"), height=2, width=3, encoding="16UC1",
                is_bigendian=1, step=8, data=data)  # fmt: skip
    img = codec.decode_image(codec.serialize(msg, IMAGE))
    np.testing.assert_array_equal(img.array, arr)


# --------------------------------------------------------------------------- camera info


def test_camera_info_round_trip_baseline_and_golden() -> None:
    cam = PinholeCamera(fx=500.0, fy=501.0, cx=319.5, cy=239.5, width=640, height=480, skew=0.5)
    rig = StereoRig(cam, 0.12)
    left_b, right_b = codec.encode_stereo_infos(rig, STAMP)
    left, right = codec.decode_camera_info(left_b), codec.decode_camera_info(right_b)
    assert left.camera == cam and left.baseline_m == 0.0
    assert right.baseline_m == pytest.approx(0.12)
    rig2 = codec.stereo_rig_from_infos(left, right)
    assert rig2.left == cam and rig2.baseline_m == pytest.approx(0.12)
    g = golden(CAMERA_INFO, right_b)
    assert g.p[3] == pytest.approx(-500.0 * 0.12)
    assert list(g.k) == pytest.approx(cam.K.reshape(-1).tolist())
    assert (g.width, g.height, g.distortion_model) == (640, 480, "plumb_bob")


def _info_with(data: bytes, binning: tuple[int, int], roi: tuple[int, int, int, int]) -> bytes:
    """``data`` (a CameraInfo) with binning (x, y) and ROI (x_offset, y_offset, width, height)."""
    m = codec.deserialize(data, CAMERA_INFO)
    r = dataclasses.replace(m.roi, x_offset=roi[0], y_offset=roi[1], width=roi[2], height=roi[3])
    m = dataclasses.replace(m, binning_x=binning[0], binning_y=binning[1], roi=r)
    return codec.serialize(m, CAMERA_INFO)


def _project(cam: PinholeCamera, X_C: np.ndarray) -> np.ndarray:
    return (cam.K @ X_C)[:2] / X_C[2]


@pytest.mark.parametrize(
    "binning, roi",
    [
        ((2, 2), (0, 0, 0, 0)),
        ((4, 2), (0, 0, 0, 0)),
        ((1, 1), (100, 40, 320, 240)),
        ((2, 2), (64, 48, 512, 384)),
    ],
)
def test_camera_info_binning_and_roi_as_image_geometry(
    binning: tuple[int, int], roi: tuple[int, int, int, int]
) -> None:
    """K and P describe the full-resolution camera; a binned or cropped image's pixel of a point
    is the full-resolution pixel minus the ROI offset, divided by the binning (image_geometry's
    PinholeCameraModel). The baseline does not change. Before: the full-resolution intrinsics and
    size, so every binned image was refused for its size (or an ROI crop mis-projected)."""
    cam = PinholeCamera(fx=500.0, fy=501.0, cx=319.5, cy=239.5, width=640, height=480, skew=0.5)
    left_b, right_b = codec.encode_stereo_infos(StereoRig(cam, 0.12), STAMP)
    left = codec.decode_camera_info(_info_with(left_b, binning, roi))
    right = codec.decode_camera_info(_info_with(right_b, binning, roi))
    (bx, by), (x0, y0, w, h) = binning, roi
    assert (left.camera.width, left.camera.height) == ((w or 640) // bx, (h or 480) // by)
    rig = codec.stereo_rig_from_infos(left, right)
    assert rig.baseline_m == pytest.approx(0.12)
    for X_C in (np.array([0.1, -0.05, 1.0]), np.array([-0.3, 0.2, 2.5])):
        uv_full = _project(cam, X_C)
        expected = (uv_full - [x0, y0]) / [bx, by]
        np.testing.assert_allclose(_project(rig.left, X_C), expected, rtol=0, atol=1e-9)


def test_camera_info_roi_outside_the_image_is_refused() -> None:
    cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    data = _info_with(codec.encode_camera_info(cam, 1), (1, 1), (400, 0, 320, 240))
    with pytest.raises(DecodeError, match="region of interest 320x240"):
        codec.decode_camera_info(data)
    with pytest.raises(DecodeError, match="image size"):  # binned to nothing
        codec.decode_camera_info(_info_with(codec.encode_camera_info(cam, 1), (1024, 1), (0, 0, 0, 0)))


def test_stereo_rig_rejects_unrectified() -> None:
    a = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    b = PinholeCamera(510.0, 500.0, 320.0, 240.0, 640, 480)
    li = codec.decode_camera_info(codec.encode_camera_info(a, 1))
    ri = codec.decode_camera_info(codec.encode_camera_info(b, 1, baseline_m=0.1))
    with pytest.raises(DecodeError, match="fx"):
        codec.stereo_rig_from_infos(li, ri)
    with pytest.raises(DecodeError, match="baseline"):
        codec.stereo_rig_from_infos(li, li)


def test_stereo_rig_with_principal_points_apart_as_image_geometry() -> None:
    """A pair rectified without zero disparity at infinity (OpenCV ``stereoRectify`` without
    ``CALIB_ZERO_DISPARITY``): the right P has its own cx. The rig keeps ``cx_left - cx_right``,
    and a point's disparity less that offset is ``f B / z`` (image_geometry's
    ``StereoCameraModel.getZ``: ``z = -Tx / (d - (cx_l - cx_r))``). Before, such a pair was refused
    as "not rectified". Rows that differ (cy) or a skew that differs are still refused."""
    a = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    rig = StereoRig(a, 0.12, 19.25)
    left_b, right_b = codec.encode_stereo_infos(rig, STAMP)
    g = golden(CAMERA_INFO, right_b)
    assert (g.p[2], g.p[3], g.k[2]) == pytest.approx((300.25, -500.0 * 0.12, 300.25))
    left, right = codec.decode_camera_info(left_b), codec.decode_camera_info(right_b)
    rig2 = codec.stereo_rig_from_infos(left, right)
    assert rig2.principal_offset_px == pytest.approx(19.25) and rig2.baseline_m == pytest.approx(0.12)
    X_L = np.array([0.2, -0.1, 1.5])  # a point in the left camera; the right one sits at +B along x
    d = _project(rig2.left, X_L)[0] - _project(rig2.right, X_L - [0.12, 0.0, 0.0])[0]
    assert d - rig2.principal_offset_px == pytest.approx(500.0 * 0.12 / 1.5)
    for changed in ({"cy": 241.0}, {"skew": 0.5}):
        b = dataclasses.replace(rig.right, **changed)
        ri = codec.decode_camera_info(codec.encode_camera_info(b, 1, baseline_m=0.12))
        with pytest.raises(DecodeError, match=next(iter(changed))):
            codec.stereo_rig_from_infos(left, ri)
    with pytest.raises(InputError, match="principal point offset"):
        StereoRig(a, 0.12, 640.0)


# --------------------------------------------------------------------------- poses


def test_odometry_pose_round_trip_and_golden() -> None:
    from pugsd.wire.types import ODOMETRY

    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T[:3, 3] = [1.0, -2.0, 3.5]
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6)) * 0.01
    cov = A @ A.T
    data = codec.encode_odometry(STAMP, T, cov, "odom", "base_link")
    p = codec.decode_pose(data, ODOMETRY)
    assert p.stamp_ns == STAMP and p.frame_id == "odom"
    np.testing.assert_allclose(p.T, T, atol=1e-12)
    assert p.cov is not None
    np.testing.assert_allclose(p.cov, cov, rtol=0, atol=1e-15)
    g = golden(ODOMETRY, data)
    assert g.child_frame_id == "base_link" and g.header.frame_id == "odom"
    assert (g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z) == (1.0, -2.0, 3.5)
    np.testing.assert_allclose(np.asarray(g.pose.covariance).reshape(6, 6), cov, rtol=0, atol=1e-15)
    bad = cov.copy()
    bad[0, 0] = -1.0
    with pytest.raises(DecodeError, match="Odometry: covariance is not positive semi-definite"):
        codec.decode_pose(codec.encode_odometry(STAMP, T, bad), ODOMETRY)


def test_pose_with_covariance_round_trip_and_golden() -> None:
    T = _T()
    A = np.random.default_rng(0).normal(size=(6, 6))
    cov = A @ A.T * 1e-4
    data = codec.encode_pose_with_covariance(STAMP, T, cov, "world")
    p = codec.decode_pose_with_covariance(data)
    assert p.stamp_ns == STAMP and p.frame_id == "world"
    np.testing.assert_allclose(p.T, T, atol=1e-12)
    assert p.cov is not None
    np.testing.assert_allclose(p.cov, cov, atol=1e-15)
    g = golden(POSE_COV_STAMPED, data)
    assert [g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z] == [1, 2, 3]
    np.testing.assert_allclose(np.asarray(g.pose.covariance).reshape(6, 6), cov)
    q = g.pose.pose.orientation
    np.testing.assert_allclose(codec.quat_to_matrix(q.x, q.y, q.z, q.w), T[:3, :3], atol=1e-12)


def test_pose_stamped_with_configured_cov() -> None:
    T = _T(0.0, 0.0, math.pi)  # 180 degree case of the quaternion conversion
    data = codec.encode_pose_stamped(STAMP, T)
    p = codec.decode_pose_stamped(data, cov=np.eye(6) * 1e-4)
    np.testing.assert_allclose(p.T, T, atol=1e-12)
    assert p.cov is not None and p.cov[0, 0] == 1e-4
    assert codec.decode_pose(data, POSE_STAMPED).cov is None
    g = golden(POSE_STAMPED, data)
    assert g.pose.position.z == 3


@pytest.mark.parametrize("angles", [(0, 0, 0), (math.pi, 0, 0), (0, math.pi, 0), (0.1, 3.1, -3.1)])
def test_quaternion_conversion(angles: tuple[float, float, float]) -> None:
    R = _rot(*angles)
    q = codec.matrix_to_quat(R)
    np.testing.assert_allclose(codec.quat_to_matrix(*q), R, atol=1e-12)


# --------------------------------------------------------------------------- grasps


def test_grasp_array_round_trip_and_golden() -> None:
    gr = _grasps()
    data = codec.encode_grasp_array(gr, "world")
    back = codec.decode_grasp_array(data)
    assert len(back) == len(gr) and back.stamp_ns == STAMP
    np.testing.assert_allclose(back.pose_W, gr.pose_W, atol=1e-12)
    for f in ("contact_W", "width_m", "baseline_confidence", "sigma2_occ", "pugs_confidence"):
        np.testing.assert_array_equal(getattr(back, f), getattr(gr, f))
    np.testing.assert_array_equal(back.grasp_id, gr.grasp_id)
    g = golden(GRASP_ARRAY, data)
    assert len(g.grasps) == 4
    for i, m in enumerate(g.grasps):
        assert m.width == gr.width_m[i] and m.id == gr.grasp_id[i]
        assert m.pugs_confidence == gr.pugs_confidence[i]
        assert m.sigma2_occ == gr.sigma2_occ[i]
        assert m.baseline_confidence == gr.baseline_confidence[i]
        assert [m.contact.x, m.contact.y, m.contact.z] == gr.contact_W[i].tolist()
        assert m.pose.position.x == gr.pose_W[i, 0, 3]
    empty = ScoredGrasps(np.zeros((0, 4, 4)), np.zeros((0, 3)), *(np.zeros(0),) * 4,
                         np.zeros(0, dtype=np.int64), 5)  # fmt: skip
    assert len(codec.decode_grasp_array(codec.encode_grasp_array(empty))) == 0


def test_marker_array_golden() -> None:
    gr = _grasps(5)
    data = codec.encode_grasp_markers(gr, top_k=3)
    g = golden(MARKER_ARRAY, data)
    assert len(g.markers) == 4
    assert g.markers[0].action == 3  # DELETEALL
    for m in g.markers[1:]:
        assert m.type == 5 and m.action == 0 and len(m.points) == 8 and m.color.a == 1.0
        assert m.header.frame_id == "world"


# --------------------------------------------------------------------------- cloud and status


def test_cloud_round_trip_and_golden() -> None:
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(50, 3))
    s2, conf = rng.uniform(0, 1, 50), rng.uniform(0, 1, 50)
    data = codec.encode_cloud(pts, STAMP, sigma2_occ=s2, pugs_confidence=conf)
    c = codec.decode_cloud(data)
    assert list(c.fields) == ["x", "y", "z", "sigma2_occ", "pugs_confidence"]
    np.testing.assert_array_equal(c.points, pts.astype(np.float32))
    np.testing.assert_array_equal(c.fields["sigma2_occ"], s2.astype(np.float32))
    g = golden(POINT_CLOUD2, data)
    assert [f.name for f in g.fields] == ["x", "y", "z", "sigma2_occ", "pugs_confidence"]
    assert all(f.datatype == 7 for f in g.fields)
    assert (g.point_step, g.width, g.height) == (20, 50, 1)
    raw = bytes(g.data)
    assert struct.unpack_from("<f", raw, 20 * 7 + 16)[0] == np.float32(conf[7])
    assert len(codec.decode_cloud(codec.encode_cloud(np.zeros((0, 3)), 1)).points) == 0


def test_status_round_trip_and_golden() -> None:
    st = {"frames": np.int64(3), "elbo": 1.5, "drops": {"stereo": 2}, "model": "v1"}
    data = codec.encode_status(st)
    assert codec.decode_status(data) == {
        "frames": 3,
        "elbo": 1.5,
        "drops": {"stereo": 2},
        "model": "v1",
    }
    assert golden(STRING, data).data.startswith("{")


# --------------------------------------------------------------------------- malformed


def _all_decoders() -> list[tuple[str, Any, bytes]]:
    cam = PinholeCamera(100.0, 100.0, 10.0, 10.0, 20, 20)
    return [
        ("image", codec.decode_image, codec.encode_image(np.zeros((4, 4), np.uint8), 1)),
        ("info", codec.decode_camera_info, codec.encode_camera_info(cam, 1)),
        ("posecov", codec.decode_pose_with_covariance,
         codec.encode_pose_with_covariance(1, np.eye(4), np.eye(6))),
        ("pose", codec.decode_pose_stamped, codec.encode_pose_stamped(1, np.eye(4))),
        ("grasps", codec.decode_grasp_array, codec.encode_grasp_array(_grasps(2))),
        ("cloud", codec.decode_cloud, codec.encode_cloud(np.zeros((3, 3)), 1)),
        ("status", codec.decode_status, codec.encode_status({"a": 1})),
    ]  # fmt: skip


@pytest.mark.parametrize("case", _all_decoders(), ids=lambda c: c[0])
def test_truncated_and_garbage_raise_decode_error(case: tuple[str, Any, bytes]) -> None:
    _name, dec, good = case
    dec(good)
    cuts = sorted({0, 1, 3, 4, 5, 8, len(good) // 2, len(good) - 5, len(good) - 4})
    for n in cuts:
        if 0 <= n < len(good) - 3:
            with pytest.raises(DecodeError):
                dec(good[:n])
    with pytest.raises(DecodeError):
        dec(b"\x07\x07\x00\x00" + good[4:])  # unknown encapsulation
    with pytest.raises(DecodeError):
        dec(good + b"\x00" * 64)  # size mismatch
    rng = np.random.default_rng(0)
    for _ in range(50):  # random corruption: DecodeError or a valid decode, never anything else
        b = bytearray(good)
        for i in rng.integers(4, len(b), 3):
            b[int(i)] = int(rng.integers(0, 256))
        with contextlib.suppress(DecodeError):
            dec(bytes(b))


def test_wrong_image_encoding_and_size_mismatch() -> None:
    ts = codec.typestore()
    Image = ts.types[IMAGE]

    def img(enc: str, h: int, w: int, step: int, n: int) -> bytes:
        return codec.serialize(
            Image(header=codec._header(1, "x"), height=h, width=w, encoding=enc, is_bigendian=0,
                  step=step, data=np.zeros(n, np.uint8)), IMAGE)  # fmt: skip

    with pytest.raises(DecodeError, match="encoding"):
        codec.decode_image(img("yuv422", 2, 2, 4, 8))
    with pytest.raises(DecodeError, match="data has"):
        codec.decode_image(img("mono8", 4, 4, 4, 15))
    with pytest.raises(DecodeError, match="step"):
        codec.decode_image(img("rgb8", 2, 4, 4, 8))
    with pytest.raises(DecodeError, match="empty"):
        codec.decode_image(img("mono8", 0, 4, 4, 0))
    with pytest.raises(DecodeError, match="encoding"):
        codec.decode_image(codec.encode_image(np.zeros((2, 2, 3), np.uint8), 1), ["mono8"])


def test_bad_poses_and_covariances() -> None:
    T = np.eye(4)
    good = codec.encode_pose_with_covariance(1, T, np.eye(6))
    m = codec.deserialize(good, POSE_COV_STAMPED)
    m.pose.pose.position.x = float("nan")
    with pytest.raises(DecodeError, match="non-finite pose"):
        codec.decode_pose_with_covariance(codec.serialize(m, POSE_COV_STAMPED))
    m = codec.deserialize(good, POSE_COV_STAMPED)
    m.pose.pose.orientation.w = 0.0
    with pytest.raises(DecodeError, match="quaternion"):
        codec.decode_pose_with_covariance(codec.serialize(m, POSE_COV_STAMPED))
    bad = np.eye(6)
    bad[0, 0] = -1.0
    with pytest.raises(DecodeError, match="semi-definite"):
        codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, bad))
    asym = np.eye(6)
    asym[0, 1] = 0.5
    with pytest.raises(DecodeError, match="symmetric"):
        codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, asym))
    with pytest.raises(DecodeError, match="non-finite"):
        codec.decode_pose_with_covariance(
            codec.encode_pose_with_covariance(1, T, np.full((6, 6), np.nan))
        )


def test_bad_status_and_cloud() -> None:
    S = codec.msg_class(STRING)
    with pytest.raises(DecodeError, match="JSON"):
        codec.decode_status(codec.serialize(S(data="not json"), STRING))
    with pytest.raises(DecodeError, match="object"):
        codec.decode_status(codec.serialize(S(data="[1]"), STRING))
    good = codec.encode_cloud(np.zeros((3, 3)), 1)
    m = codec.deserialize(good, POINT_CLOUD2)
    m.width = 4
    with pytest.raises(DecodeError, match="data has"):
        codec.decode_cloud(codec.serialize(m, POINT_CLOUD2))
    m = codec.deserialize(good, POINT_CLOUD2)
    m.fields[0].datatype = 8
    with pytest.raises(DecodeError, match="float32"):
        codec.decode_cloud(codec.serialize(m, POINT_CLOUD2))


def test_wrong_type_bytes_raise_decode_error() -> None:
    img = codec.encode_image(np.zeros((4, 4), np.uint8), 1)
    for dec in (codec.decode_grasp_array, codec.decode_pose_with_covariance, codec.decode_cloud):
        with pytest.raises(DecodeError):
            dec(img)


def test_covariance_near_the_float64_limit_is_checked_without_overflow(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    T = np.eye(4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow RuntimeWarning either
        for C in (np.diag([1e308] * 6), np.diag([1.5e308] * 6), np.full((6, 6), 1e308)):
            pm = codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, C))
            assert pm.cov is not None and np.all(np.isfinite(pm.cov))
            assert np.array_equal(pm.cov, C)
        bad = np.diag([1e308, -1e308, 1e308, 1e308, 1e308, 1e308])
        with pytest.raises(DecodeError, match="semi-definite"):
            codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, bad))
        zero = codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, np.zeros((6, 6))))
        assert zero.cov is not None and not np.any(zero.cov)

    def no_convergence(a: Any) -> Any:
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    monkeypatch.setattr(np.linalg, "eigvalsh", no_convergence)
    with pytest.raises(DecodeError, match="semi-definite"):
        codec.decode_pose_with_covariance(codec.encode_pose_with_covariance(1, T, np.eye(6)))


def test_deeply_nested_status_json_is_a_decode_error() -> None:
    S = codec.msg_class(STRING)
    deep = codec.serialize(S(data="[" * 100_000 + "]" * 100_000), STRING)
    with pytest.raises(DecodeError, match="nested"):
        codec.decode_status(deep)
