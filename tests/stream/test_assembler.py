# SPDX-License-Identifier: Apache-2.0
"""FrameAssembler on a clock the test sets: stereo pairing by stamp, the pose wait and its
interpolation, masks, CameraInfo, size and type checks, and the reason each rejection or drop
is counted under."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.errors import DecodeError, PugsdError
from pugsd.stream.assembler import (
    FrameAssembler,
    InputRejected,
    bounded_put,
    log_nth,
    reason_class,
    require_size,
)
from pugsd.wire import codec
from pugsd.wire.types import CAMERA_INFO, IMAGE, POSE_COV_STAMPED

RIG = StereoRig(PinholeCamera(60.0, 60.0, 15.5, 11.5, 32, 24), 0.05)
IMG = np.random.default_rng(0).integers(0, 255, (24, 32), dtype=np.uint8)
S = 10**9  # one second in ns
H, W = RIG.left.height, RIG.left.width


class Report:
    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.drops: list[tuple[str, str]] = []
        self.rejects: list[tuple[str, str]] = []

    def count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n

    def drop(self, stage: str, reason: str, n: int = 1) -> None:
        self.drops.append((stage, reason))

    def reject(self, role: str, exc: BaseException) -> None:
        if isinstance(exc, InputRejected) and exc.role:
            role = exc.role
        self.rejects.append((role, reason_class(exc)))

    def internal_error(self, key: str, what: str, exc: BaseException) -> None:
        raise exc


class Rig:
    """An assembler, its report, the frames it emitted and the clock it reads."""

    def __init__(self, **daemon: Any) -> None:
        cfg = load_config_dict({"daemon": {"pose_wait_s": 0.5, "side_image_wait_s": 0.1, **daemon}})
        self.t = 0.0
        self.report = Report()
        self.frames: list[Any] = []
        self.asm = FrameAssembler(cfg.daemon, cfg.queues, self.report,
                                  lambda f, recv_s: self.frames.append(f), lambda: self.t)  # fmt: skip

    def feed(
        self, role: str, data: bytes, typename: str | None = None, publisher: bytes | None = None
    ) -> None:
        self.asm.feed(role, data, self.t, typename, publisher, key=role)

    def infos(self, rig: StereoRig = RIG) -> None:
        li, ri = codec.encode_stereo_infos(rig, 0)
        self.feed("left_info", li)
        self.feed("right_info", ri)

    def pose(self, stamp_ns: int, x: float = 0.0, publisher: bytes | None = None) -> None:
        T = np.eye(4)
        T[0, 3] = x
        self.feed("pose", codec.encode_pose_with_covariance(stamp_ns, T, np.eye(6) * 1e-6), POSE_COV_STAMPED,
                  publisher)  # fmt: skip

    def pair(self, stamp_ns: int, img: np.ndarray = IMG) -> None:
        self.feed("left_image", codec.encode_image(img, stamp_ns, "left"))
        self.feed("right_image", codec.encode_image(img, stamp_ns, "right"))


def test_a_pair_waits_for_a_bracketing_pose_and_takes_the_interpolated_one() -> None:
    r = Rig(side_image_wait_s=0.0)
    r.infos()
    r.pose(S, x=0.0)
    r.pair(S + S // 40)
    assert r.frames == [] and len(r.asm.gate) == 1  # no pose after the image stamp yet
    r.t = 0.1
    r.pose(S + S // 10, x=1.0)
    (f,) = r.frames
    assert f.stamp_ns == S + S // 40 and f.T_W_C[0, 3] == pytest.approx(0.25)
    assert r.report.counts == {"poses": 2, "paired": 1, "frames.stereo": 1}


def test_a_frame_without_a_usable_pose_is_dropped_at_its_deadline_with_the_reason() -> None:
    r = Rig()
    r.infos()
    r.pair(S)
    r.t = 0.49
    r.asm.poll()
    assert r.report.drops == []
    r.t = 0.5
    r.asm.poll()
    assert r.report.drops == [("pose_wait", "no usable pose within 0.5 s (no pose yet)")]


def test_a_frame_waits_for_its_camera_info_and_is_dropped_without_it() -> None:
    r = Rig()
    r.pose(S)
    r.pair(S)
    r.t = 0.6
    r.asm.poll()
    assert r.report.drops == [
        ("pose_wait", "no complete inputs within 0.5 s (no CameraInfo for both cameras yet)")
    ]


def test_an_undecided_mask_topic_holds_the_first_frame_briefly_then_frames_go_without() -> None:
    r = Rig(side_image_wait_s=0.1, pose_wait_s=0.5)
    r.infos()
    r.pose(S)
    r.pair(S)
    assert r.frames == []  # its mask may come after its images
    r.t = 0.05
    r.feed("mask", codec.encode_image(np.full((24, 32), 255, np.uint8), S, "left"))
    (f,) = r.frames
    assert f.mask is not None and f.mask.all()
    r.t = 3.0  # the mask topic lapsed (undecided again after its last mask): one frame waits
    r.pose(2 * S)
    r.pair(2 * S)
    assert len(r.frames) == 1
    r.t = 3.1
    r.asm.poll()
    assert len(r.frames) == 2 and r.frames[1].mask is None  # decided: no masks now
    r.pose(3 * S)
    r.pair(3 * S)
    assert len(r.frames) == 3  # decided: later frames do not wait


def test_an_image_of_another_size_is_rejected_on_arrival_and_charged_to_its_role() -> None:
    r = Rig()
    r.infos()
    with pytest.raises(InputRejected) as exc:
        r.feed("right_image", codec.encode_image(np.zeros((24, 30), np.uint8), S, "right"))
    assert (exc.value.reason, exc.value.role) == ("wrong_size", "right_image")
    assert r.asm.pairer.pending() == 0  # it took no waiting half's place


def test_a_message_of_the_wrong_type_is_rejected() -> None:
    r = Rig()
    with pytest.raises(InputRejected, match="not accepted") as exc:
        r.feed("left_image", codec.encode_image(IMG, S), CAMERA_INFO)
    assert exc.value.reason == "wrong_type"
    with pytest.raises(InputRejected, match="pose: type"):
        r.feed("pose", b"", IMAGE)


def test_a_second_half_with_the_same_stamp_replaces_the_first_and_is_counted() -> None:
    r = Rig()
    r.feed("left_image", codec.encode_image(IMG, S))
    r.feed("left_image", codec.encode_image(IMG, S))
    assert r.report.drops == [("unpaired", f"duplicate_stamp (a second left_image for stamp {S})")]
    assert r.asm.pairer.pending() == 1


def test_poses_come_from_one_publisher_until_it_falls_silent_for_the_hold() -> None:
    r = Rig(pose_publisher_hold_s=1.0)
    a, b = b"a" * 16, b"b" * 16
    r.pose(S, publisher=a)
    r.t = 0.5
    with pytest.raises(InputRejected) as exc:
        r.pose(2 * S, publisher=b)
    assert exc.value.reason == "second_publisher" and len(r.asm.poses) == 1
    r.t = 1.6  # a silent for 1.1 s: b is followed
    r.pose(3 * S, publisher=b)
    assert r.asm.pose_publisher == b and r.report.counts["pose_publisher_switches"] == 1


def test_a_mask_of_another_size_is_rejected_and_the_frame_goes_on_without_it() -> None:
    r = Rig()
    r.infos()
    r.pose(S)
    r.feed("mask", codec.encode_image(np.zeros((12, 16), np.uint8), S))
    r.pair(S)
    (f,) = r.frames
    assert f.mask is None and r.report.rejects == [("mask", "wrong_size")]


def test_a_frame_the_core_refuses_is_charged_to_the_pose(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(**_: Any) -> None:
        raise PugsdError("pose covariance is not positive semi-definite")

    monkeypatch.setattr("pugsd.stream.assembler.StereoFrame", refuse)
    r = Rig(side_image_wait_s=0.0)
    r.infos()
    r.pose(S)
    r.pair(S)
    assert r.frames == [] and r.report.rejects == [("pose", "non_psd_covariance")]


def test_clear_discards_the_waiting_frames_and_halves() -> None:
    r = Rig()
    r.pair(S)
    r.feed("left_image", codec.encode_image(IMG, 2 * S))
    assert r.asm.clear() == (1, 1)
    assert len(r.asm.gate) == 0 and r.asm.pairer.pending() == 0


def test_side_images_keep_exactly_the_newest_cap() -> None:
    d: OrderedDict[int, np.ndarray] = OrderedDict()
    for stamp in range(1, 6):
        bounded_put(d, stamp, np.full(2, stamp), 3)
    assert list(d) == [3, 4, 5]
    bounded_put(d, 3, np.full(2, 30), 3)  # a second image of a waiting stamp replaces it
    assert list(d) == [4, 5, 3] and d[3].tolist() == [30, 30]
    bounded_put(d, 6, np.full(2, 6), 3)
    assert list(d) == [5, 3, 6]
    bounded_put(d, 7, np.full(2, 7), 1)
    assert list(d) == [7]


def test_require_size_names_both_sizes_and_the_input_it_charges() -> None:
    narrow = codec.ImageMsg(5, "right", "mono8", np.zeros((H, W // 2), np.uint8))
    with pytest.raises(InputRejected) as ei:
        require_size(narrow, (H, W), "right_image: image", "right_image")
    assert ei.value.reason == "wrong_size" and ei.value.role == "right_image"
    assert str(ei.value) == f"right_image: image is ({H}, {W // 2}), camera expects ({H}, {W})"
    with pytest.raises(InputRejected) as ei:
        require_size(codec.ImageMsg(5, "d", "32FC1", np.zeros((H - 1, W), np.float32)), (H, W), "depth image")
    assert ei.value.role is None
    assert str(ei.value) == f"depth image is ({H - 1}, {W}), camera expects ({H}, {W})"
    # a colour image is judged by its height and width only
    require_size(codec.ImageMsg(5, "left", "rgb8", np.zeros((H, W, 3), np.uint8)), (H, W), "left")


@pytest.mark.parametrize(
    ("text", "cls"),
    [
        ("Voxel Hash exhausted", "out_of_map_range"),  # matched case-insensitively
        ("a point too far for any voxel index", "beyond_any_map"),
        ("images too small for the disparity search", "too_small_for_stereo"),
        ("Malformed CDR", "malformed_cdr"),
        ("truncated CDR at byte 3", "malformed_cdr"),
        ("unknown CDR encapsulation 0x0009", "malformed_cdr"),
        ("payload is not bytes", "malformed_cdr"),
        ("pose: type 'x' not accepted (expected y)", "wrong_type"),
        ("unsupported pose type", "wrong_type"),
        ("not an rmw_zenoh key", "wrong_type"),
        ("depth: no CameraInfo for the depth image yet", "no_camera_info"),
        ("covariance not positive semi-definite", "non_psd_covariance"),
        ("covariance not symmetric", "non_psd_covariance"),
        ("non-finite covariance", "non_psd_covariance"),
        ("non-finite pose", "bad_pose"),
        ("quaternion of norm 0", "bad_pose"),
        ("not rigid", "bad_pose"),
        ("rotation not orthonormal", "bad_pose"),
        ("T_W_C must be 4x4", "bad_pose"),
        ("unsupported encoding 'yuv422'", "wrong_encoding"),
        ("stereo pair encoding mismatch: mono8 vs rgb8", "wrong_encoding"),  # encoding before mismatch
        ("data has 3 bytes", "wrong_size"),
        ("step 3 < width", "wrong_size"),
        ("wrong size", "wrong_size"),
        ("bad shape", "wrong_size"),
        ("sizes mismatch", "wrong_size"),
        ("camera expects (4, 4)", "wrong_size"),
        ("empty image", "wrong_size"),
        ("CameraInfo size 0x0", "wrong_size"),  # size before camerainfo
        ("CameraInfo K is zero", "bad_camera_info"),
        ("baseline 0", "bad_camera_info"),
        ("bad intrinsics", "bad_camera_info"),
        ("not rectified", "bad_camera_info"),
        ("bad stamp", "bad_stamp"),
    ],
)
def test_reason_class_maps_each_known_message_to_its_class(text: str, cls: str) -> None:
    assert reason_class(PugsdError(text)) == cls


def test_reason_class_takes_a_fixed_class_before_the_text_and_falls_back_to_the_type() -> None:
    assert reason_class(InputRejected("custom", "voxel hash")) == "custom"
    assert reason_class(DecodeError("voxel hash", reason="wrong_type")) == "wrong_type"
    assert reason_class(DecodeError("voxel hash")) == "out_of_map_range"
    assert reason_class(PugsdError("nothing known")) == "PugsdError"
    assert reason_class(ValueError("nothing known")) == "ValueError"


def test_log_nth_logs_the_first_five_then_every_hundredth() -> None:
    assert [n for n in range(1, 1001) if log_nth(n)] == [1, 2, 3, 4, 5, *range(100, 1001, 100)]
    assert [n for n in range(1, 201) if log_nth(n, first=2)] == [1, 2, 100, 200]


def test_an_implausible_pose_covariance_is_refused_before_it_changes_any_state() -> None:
    """A diverging localiser's 1e30 * I passes the wire checks (finite, symmetric, PSD) but gives
    a position std of 1e15 m: refused as implausible_covariance, neither buffered nor followed as
    the pose publisher; the next good pose is taken as usual."""
    r = Rig(max_pose_std_translation_m=10.0)
    a = b"a" * 16
    with pytest.raises(InputRejected, match="position standard deviation 1e\\+15 m") as exc:
        r.feed("pose", codec.encode_pose_with_covariance(S, np.eye(4), np.eye(6) * 1e30), POSE_COV_STAMPED, a)
    assert (exc.value.reason, exc.value.role) == ("implausible_covariance", "pose")
    assert len(r.asm.poses) == 0 and r.asm.pose_publisher is None
    rot = np.eye(6) * 1e-6
    rot[3:, 3:] = np.eye(3) * 16.0  # a rotation std of 4 rad
    with pytest.raises(InputRejected, match="rotation standard deviation 4 rad") as exc:
        r.feed("pose", codec.encode_pose_with_covariance(S, np.eye(4), rot), POSE_COV_STAMPED)
    assert exc.value.reason == "implausible_covariance"
    ok = np.eye(6) * 99.0  # a std just below 10 m and 10 rad, refused only for its rotation
    with pytest.raises(InputRejected, match="rotation"):
        r.feed("pose", codec.encode_pose_with_covariance(S, np.eye(4), ok), POSE_COV_STAMPED)
    r.pose(S, publisher=a)
    assert len(r.asm.poses) == 1 and r.asm.pose_publisher == a
