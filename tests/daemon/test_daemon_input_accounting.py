# SPDX-License-Identifier: Apache-2.0
"""The daemon's input path and its accounting: bad input gets a counted rejection charged to the
input at fault, with a log line that names the sizes, rate-limited; every drop counts in
``dropped_total``; the status message carries the counters it claims. The daemon is driven on the
calling thread (no zenoh session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import logging
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Command, Daemon, Inbound
from pugsd.errors import PugsdError
from pugsd.stream.assembler import InputRejected, reason_class
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6
H, W = RIG.left.height, RIG.left.width


def _daemon(port: int, queues: dict[str, int] | None = None, **daemon: Any) -> Daemon:
    cfg = daemon_config_dict(port, **daemon)
    cfg["queues"] = {"stereo": 64, "depth": 64, **(queues or {})}
    return Daemon(load_config_dict(cfg), FakePipeline())


def _feed(d: Daemon, role: str, data: bytes, **kw: Any) -> None:
    d._on_inbound(Inbound(role, key_for(d.cfg.topics, role), data, time.monotonic(), **kw))


def _infos(d: Daemon) -> None:
    li, ri = codec.encode_stereo_infos(RIG, 0)
    _feed(d, "left_info", li)
    _feed(d, "right_info", ri)


def _pose(stamp_ns: int, frame_id: str = "world") -> bytes:
    return codec.encode_pose_with_covariance(stamp_ns, np.eye(4), COV, frame_id)


IMG = np.random.default_rng(0).integers(0, 255, (H, W), dtype=np.uint8)


# --- counting and logging -------------------------------------------------------------------------


def test_drops_count_under_the_reasons_head_and_log_the_first_five_then_each_hundred_crossed(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="pugsd")
    d = _daemon(port)
    for i in range(1, 206):
        d.report.drop("unpaired", f"duplicate_stamp (a second left_image for stamp {i})")
    assert dict(d.health.dropped) == {"unpaired: duplicate_stamp": 205}
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped 1 at unpaired")]
    assert [int(ln.split("(#")[1].split(")")[0]) for ln in lines] == [1, 2, 3, 4, 5, 100, 200]
    assert lines[-1] == "dropped 1 at unpaired (#200): duplicate_stamp (a second left_image for stamp 200)"
    caplog.clear()
    for _ in range(40):  # drops of 3: totals 3, 6, ..., 120; logged while under 5 before, and at 102
        d.report.drop("pose_wait", "no pose (waited 0.5 s)", 3)
    lines = [r.getMessage() for r in caplog.records if "at pose_wait" in r.getMessage()]
    assert lines == [
        "dropped 3 at pose_wait (#3): no pose (waited 0.5 s)",
        "dropped 3 at pose_wait (#6): no pose (waited 0.5 s)",
        "dropped 3 at pose_wait (#102): no pose (waited 0.5 s)",
    ]
    assert d.health.counts["dropped"] == 205 + 120


def test_a_rejection_is_charged_to_the_input_at_fault_and_logged_rate_limited(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port)
    for _ in range(105):
        d.report.reject("left_image", InputRejected("wrong_size", "right is small", "right_image"))
    d.report.reject("left_image", PugsdError("bad stamp"))
    assert dict(d.health.rejected) == {"right_image: wrong_size": 105, "left_image: bad_stamp": 1}
    assert d.health.counts["rejected"] == 106
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("rejected")]
    assert len(lines) == 7
    assert lines[5] == "rejected right_image input (wrong_size, #100): right is small"
    assert lines[6] == "rejected left_image input (bad_stamp, #1): bad stamp"


def test_an_internal_error_logs_its_traceback_once_then_one_line_rate_limited(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.ERROR, logger="pugsd")
    d = _daemon(port)
    for i in range(100):
        d.report.internal_error("errors.input.pose", "handling pose input", ValueError(f"boom {i}"))
    recs = [r for r in caplog.records if r.getMessage().startswith("handling pose input failed")]
    assert [r.getMessage() for r in recs] == [
        "handling pose input failed: boom 0",
        *(f"handling pose input failed (#{n}): ValueError: boom {n - 1}" for n in (2, 3, 4, 5, 100)),
    ]
    assert recs[0].exc_info is not None and all(r.exc_info is None for r in recs[1:])
    assert d.health.counts["errors.input.pose"] == 100


def test_dropped_total_sums_every_kind_of_drop(port: int) -> None:
    d = _daemon(port, queues={"stereo": 1, "depth": 1, "unpaired": 1}, ingress_limit=1)
    for _ in range(3):
        d.stereo_box.offer((None, 0.0))  # type: ignore[arg-type]
    for _ in range(4):
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
    assert [d.bridge.ingress.enter() for _ in range(6)] == [True] + [False] * 5
    d.bridge.ingress.leave()
    small = np.zeros((4, 4), np.uint8)
    for i in range(8):  # left halves without partners (no CameraInfo: not judged on arrival)
        assert d.bridge.ingress.enter()
        _feed(d, "left_image", codec.encode_image(small, (i + 1) * 10**9, "left"))
    assert d.bridge.ingress.enter()  # one sample handed over, not yet handled
    d.report.drop("pose_wait", "no pose", 11)
    assert (d.stereo_box.dropped, d.depth_box.dropped, d.frames.pairer.unpaired_dropped) == (2, 3, 7)
    st = d.status()
    assert d.dropped_total() == st["dropped_total"] == 2 + 3 + 5 + 7 + 11
    assert (st["ingress"]["pending"], st["ingress"]["dropped"]) == (1, 5)
    assert st["ingress"]["refused"] == {"count_bound": 5} and st["ingress"]["too_large"] == {}
    assert st["waiting"]["unpaired"] == 1 and st["waiting"]["unpaired_dropped"] == 7


# --- the handlers ---------------------------------------------------------------------------------


def test_inbound_accounting_received_gaps_ages_backlog_and_no_handling_when_stopping(port: int) -> None:
    d = _daemon(port)
    d.bridge.pose_backlog_s.extend([1.0, 2.0])
    assert d.bridge.ingress.enter()
    _feed(d, "pose", _pose(10**9, "odom"), lost_before=2)
    assert d.bridge.ingress.pending == 0
    assert list(d.bridge.pose_backlog_s) == [2.0]
    assert d.health.counts["received.pose"] == 1 and d.health.counts["upstream_gaps.pose"] == 1
    assert d.health.counts["poses"] == 1 and len(d.frames.poses) == 1
    assert d.frames.frame_id == "odom"  # the outputs' frame follows the poses'
    _feed(d, "pose", _pose(2 * 10**9, ""))
    assert d.frames.frame_id == "odom" and "upstream_gaps.pose" in d.health.counts
    assert d.health.counts["upstream_gaps.pose"] == 1
    li, ri = codec.encode_stereo_infos(RIG, 0)
    _feed(d, "left_info", li)
    assert sorted(d.inputs.last_recv_s) == ["pose"]  # CameraInfo is not a stream
    d._stopping = True
    _feed(d, "right_info", ri)
    assert d.health.counts["received.right_info"] == 1 and "right_info" not in d.frames.infos
    assert "rejected" not in d.health.counts


def test_a_frame_whose_infos_came_late_charges_the_bad_half_and_the_good_frames_go_on(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    """Images before any CameraInfo are judged when the frame is released: a right half of the
    wrong size is charged to ``right_image`` (not the frame's default, ``left_image``), and so is
    a right half of another encoding than its left."""
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port, side_image_wait_s=0.0)
    s1, s2, s3 = 10**9, 2 * 10**9, 3 * 10**9
    _feed(d, "pose", _pose(s1))
    _feed(d, "left_image", codec.encode_image(IMG, s1, "left"))
    _feed(d, "right_image", codec.encode_image(np.ascontiguousarray(IMG[:, : W // 2]), s1, "right"))
    assert not d.health.rejected and len(d.frames.gate) == 1  # waiting for CameraInfo
    _infos(d)  # releases the frame
    assert dict(d.health.rejected) == {"right_image: wrong_size": 1} and len(d.frames.gate) == 0
    (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("rejected")]
    assert line == (
        f"rejected right_image input (wrong_size, #1): right_image: image is ({H}, {W // 2}), "
        f"camera expects ({H}, {W})"
    )
    _feed(d, "pose", _pose(s2))
    _feed(d, "left_image", codec.encode_image(IMG, s2, "left"))
    _feed(d, "right_image", codec.encode_image(np.repeat(IMG[:, :, None], 3, axis=2), s2, "right"))
    assert dict(d.health.rejected) == {"right_image: wrong_size": 1, "right_image: wrong_encoding": 1}
    _feed(d, "pose", _pose(s3))
    _feed(d, "left_image", codec.encode_image(IMG, s3, "left"))
    _feed(d, "right_image", codec.encode_image(IMG, s3, "right"))
    assert [f.stamp_ns for f, _ in list(d.stereo_box._items)] == [s3]
    assert d.health.counts["frames.stereo"] == 1 and d.health.counts["paired"] == 3


def test_a_new_right_camera_info_rebuilds_the_rig(port: int) -> None:
    d = _daemon(port)
    _infos(d)
    assert d.frames.stereo_rig().baseline_m == pytest.approx(0.05)
    _feed(d, "right_info", codec.encode_camera_info(RIG.right, 0, "right", 0.1))
    assert d.frames.stereo_rig().baseline_m == pytest.approx(0.1)


def test_a_frame_waiting_for_its_mask_goes_on_when_the_mask_comes_and_uses_it(port: int) -> None:
    """Before any mask was seen a frame waits for its own (undecided); the mask's arrival releases
    it at once, with the mask's nonzero pixels as the mask."""
    d = _daemon(port, side_image_wait_s=30.0, pose_wait_s=60.0)
    _infos(d)
    s = 10**9
    _feed(d, "pose", _pose(s))
    _feed(d, "left_image", codec.encode_image(IMG, s, "left"))
    _feed(d, "right_image", codec.encode_image(IMG, s, "right"))
    assert d.health.counts.get("frames.stereo", 0) == 0 and len(d.frames.gate) == 1
    mask = np.zeros((H, W), np.uint8)
    mask[:, W // 2 :] = 7
    _feed(d, "mask", codec.encode_image(mask, s, "left", "mono8"))
    assert d.health.counts["frames.stereo"] == 1
    ((frame, _),) = list(d.stereo_box._items)
    assert frame.mask is not None and frame.mask.dtype == np.bool_
    assert np.array_equal(frame.mask, mask > 0) and int(frame.mask.sum()) == H * (W - W // 2)


def test_a_depth_frame_waiting_for_its_std_goes_on_when_the_std_comes(port: int) -> None:
    d = _daemon(port, side_image_wait_s=30.0, pose_wait_s=60.0)
    _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
    s = 10**9
    _feed(d, "pose", _pose(s))
    _feed(d, "mask", codec.encode_image(np.full((H, W), 255, np.uint8), s, "left", "mono8"))
    _feed(d, "depth", codec.encode_image(np.full((H, W), 0.5, np.float32), s, "depth"))
    assert d.health.counts.get("frames.depth", 0) == 0 and len(d.frames.gate) == 1
    std = np.full((H, W), 0.01, np.float32)
    _feed(d, "depth_std", codec.encode_image(std, s, "depth", "32FC1"))
    assert d.health.counts["frames.depth"] == 1
    ((frame, _),) = list(d.depth_box._items)
    assert frame.sigma_m is not None and np.array_equal(frame.sigma_m, std)


def test_frames_skipped_by_the_rate_limit_let_their_std_images_go(port: int) -> None:
    d = _daemon(port, max_frame_rate_hz=10.0, side_image_wait_s=0.0)
    _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
    stamps = [10**9 + i * 10**9 // 30 for i in range(9)]
    for s in stamps:
        _feed(d, "pose", _pose(s))
        _feed(d, "depth_std", codec.encode_image(np.full((H, W), 0.01, np.float32), s, "depth", "32FC1"))
        _feed(d, "depth", codec.encode_image(np.full((H, W), 0.5, np.float32), s, "depth"))
    assert d.health.counts["frames.skipped_rate"] == 6 and d.health.counts["frames.depth"] == 3
    assert not d.frames.stds, "the std images of skipped frames are let go"


# --- the status message ---------------------------------------------------------------------------


class _NoStats(FakePipeline):
    def stats(self) -> dict[str, Any]:
        raise RuntimeError("no stats yet")


def test_status_carries_its_counters(port: int) -> None:
    d = Daemon(load_config_dict(daemon_config_dict(port)), _NoStats())
    d.bridge.deletes_ignored = 3
    d.bridge.errors["pose"] = 2
    d.was_ready, d.ready = True, False
    d.recorder = SimpleNamespace(stats=SimpleNamespace(as_dict=lambda: {"written": 4}))
    gid = bytes(range(16))
    _feed(d, "pose", _pose(10**9), publisher=gid)
    _feed(d, "pose", _pose(2 * 10**9), publisher=gid)
    st = d.status()
    assert st["healthy"] is True and st["problems"] == []
    assert st["deletes_ignored"] == 3 and st["bridge_errors"] == {"pose": 2}
    assert st["ready"] is False and st["was_ready"] is True
    assert st["recorder"] == {"written": 4}
    assert st["pipeline"] == {"error": "no stats yet"}
    assert sorted(st["mailboxes"]) == ["commands", "depth", "stereo"]
    assert st["upstream"]["pose_publisher"] == "000102030405"
    assert st["waiting"]["poses"] == 2 and st["counts"]["received.pose"] == 2
    for _ in range(d.cfg.daemon.max_consecutive_failures):
        d.health.failed("train")
    st = d.status()
    assert st["healthy"] is False
    assert st["problems"] == [f"train failed {d.cfg.daemon.max_consecutive_failures} times in a row"]


def test_input_ages_and_staleness_at_a_given_time(port: int) -> None:
    d = _daemon(port, input_stale_s=5.0)
    d.inputs.last_recv_s.update({"pose": 100.0, "depth": 105.0})
    assert d.input_ages_s(110.1234) == {"depth": 5.123, "pose": 10.123}
    assert d.stale_inputs(110.0) == ["pose"]  # depth is exactly 5 s old: not yet stale
    assert d.stale_inputs(110.001) == ["depth", "pose"]
    off = _daemon(port, input_stale_s=0.0)
    off.inputs.last_recv_s["pose"] = 0.0
    assert off.stale_inputs(1e6) == []


def test_a_refused_command_is_counted_as_queue_full_or_as_shutting_down(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="pugsd")
    d = _daemon(port)
    n = d.cfg.queues.commands
    assert all(d._offer_command(Command("reset", None)) for _ in range(n))
    assert not d._offer_command(Command("reset", None))
    d._stopping = True
    d.commands.close()
    assert not d._offer_command(Command("reset", None))
    assert dict(d.health.rejected) == {"commands: queue full": 1, "commands: shutting down": 1}
    assert [r.getMessage() for r in caplog.records if "rejected (#" in r.getMessage()] == [
        f"command reset rejected (#1): commands: busy ({n}/{n} queued)",
        "command reset rejected (#1): commands: shutting down",
    ]


def test_a_second_half_of_a_waiting_stamp_is_a_counted_duplicate_drop(port: int) -> None:
    d = _daemon(port)
    _infos(d)
    _feed(d, "left_image", codec.encode_image(IMG, 10**9, "left"))
    _feed(d, "left_image", codec.encode_image(IMG, 10**9, "left"))
    assert dict(d.health.dropped) == {"unpaired: duplicate_stamp": 1}
    assert d.frames.pairer.pending() == 1 and d.dropped_total() == 1


@pytest.mark.parametrize("role", ["mask", "depth_std"])
def test_a_side_image_of_another_size_is_charged_to_its_own_input_and_left_out(port: int, role: str) -> None:
    d = _daemon(port)
    same = np.ones((H, W), np.float32)
    assert d.frames.side_image(role, same, (H, W)) is same
    assert d.frames.side_image(role, None, (H, W)) is None
    small = np.ones((H // 2, W), np.float32)
    assert d.frames.side_image(role, small, (H, W)) is None  # the frame goes on without it
    assert dict(d.health.rejected) == {f"{role}: wrong_size": 1}


def test_the_status_lists_the_inputs_silent_for_longer_than_input_stale_s(port: int) -> None:
    d = _daemon(port, input_stale_s=5.0)
    now = time.monotonic()
    d.inputs.last_recv_s.update({"pose": now - 60.0, "left_image": now - 1.0})  # one long silent, one fresh
    assert d.status()["inputs"]["stale"] == ["pose"]


def test_frames_pushed_out_of_the_full_pose_wait_queue_are_counted_oldest_first(port: int) -> None:
    d = _daemon(port, queues={"pose_wait": 2}, side_image_wait_s=0.0, pose_wait_s=60.0)
    _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
    for i in range(1, 5):  # no pose comes: four frames for a queue of two
        _feed(d, "depth", codec.encode_image(np.full((H, W), 0.5, np.float32), i * 10**9, "depth"))
    assert dict(d.health.dropped) == {"pose_wait: pose wait queue full": 2}
    assert len(d.frames.gate) == 2


@pytest.mark.parametrize("kind", ["stereo", "depth"])
def test_a_frame_the_core_refuses_for_its_pose_is_charged_to_the_pose(
    port: int, kind: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The images were checked before the frame is built, so a refusal there is the pose's."""

    def refuse(**_: Any) -> None:
        raise PugsdError("pose covariance is not positive semi-definite")

    monkeypatch.setattr(f"pugsd.stream.assembler.{kind.capitalize()}Frame", refuse)
    d = _daemon(port, side_image_wait_s=0.0)
    s = 10**9
    if kind == "stereo":
        _infos(d)
        _feed(d, "pose", _pose(s))
        _feed(d, "left_image", codec.encode_image(IMG, s, "left"))
        _feed(d, "right_image", codec.encode_image(IMG, s, "right"))
    else:
        _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
        _feed(d, "pose", _pose(s))
        _feed(d, "depth", codec.encode_image(np.full((H, W), 0.5, np.float32), s, "depth"))
    cls = reason_class(PugsdError("pose covariance is not positive semi-definite"))
    assert dict(d.health.rejected) == {f"pose: {cls}": 1}
    assert d.health.counts.get(f"frames.{kind}", 0) == 0

