# SPDX-License-Identifier: Apache-2.0
"""A camera faster than the daemon integrates: ``daemon.max_frame_rate_hz`` thins the frames by
their stamps before depth estimation (``FrameRateLimit``), and the status worker warns when newer
frames push older ones out of the stereo or depth queue (``Daemon._report_overload``). The daemon
is driven on the calling thread (no zenoh session): samples go straight to ``_on_inbound``."""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np
import pytest

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, Inbound
from pugsd.daemon.client import status_lines
from pugsd.stream.timesync import FrameRateLimit
from pugsd.wire import codec
from pugsd.wire.topics import key_for
from tests.daemon.conftest import RIG, FakePipeline, daemon_config_dict

COV = np.eye(6) * 1e-6
T0_NS = 1_700_000_000 * 10**9


def _stamps(rate_hz: float, seconds: float, jitter_ns: int = 0, seed: int = 0) -> list[int]:
    n = round(rate_hz * seconds)
    rng = np.random.default_rng(seed)
    j = rng.integers(-jitter_ns, jitter_ns + 1, n) if jitter_ns else np.zeros(n, np.int64)
    return [T0_NS + round(i * 1e9 / rate_hz) + int(j[i]) for i in range(n)]


def _kept(limit: FrameRateLimit, stamps: list[int]) -> list[int]:
    return [i for i, s in enumerate(stamps) if limit.accept(s)]


# --- FrameRateLimit -------------------------------------------------------------------------------


def test_zero_keeps_every_frame() -> None:
    lim = FrameRateLimit(0.0)
    stamps = _stamps(30.0, 2.0) + [T0_NS] * 3  # duplicates and a jump back as well
    assert _kept(lim, stamps) == list(range(len(stamps)))
    assert (lim.kept, lim.skipped) == (len(stamps), 0)


def test_30_hz_thinned_to_10_keeps_every_third_frame_even_with_jitter() -> None:
    for jitter_ns in (0, 3_000_000):  # +-3 ms of stamp jitter does not move the choice
        lim = FrameRateLimit(10.0)
        kept = _kept(lim, _stamps(30.0, 10.0, jitter_ns))
        assert kept == list(range(0, 300, 3)), jitter_ns
        assert (lim.kept, lim.skipped) == (100, 200)


def test_25_hz_thinned_to_10_holds_the_rate_on_average() -> None:
    """25 Hz does not divide by 10 Hz: the kept frames alternate 120 and 80 ms apart, 10 a second."""
    stamps = _stamps(25.0, 20.0)
    kept = _kept(FrameRateLimit(10.0), stamps)
    assert len(kept) == 200
    gaps_ms = {round((stamps[b] - stamps[a]) / 1e6) for a, b in itertools.pairwise(kept)}
    assert gaps_ms == {80, 120}


@pytest.mark.parametrize(("rate_in_hz", "limit_hz", "expect_hz"), [(20.0, 15.0, 15.0), (8.0, 10.0, 8.0)])
def test_the_kept_rate_is_the_limit_or_the_input_rate_if_slower(
    rate_in_hz: float, limit_hz: float, expect_hz: float
) -> None:
    kept = _kept(FrameRateLimit(limit_hz), _stamps(rate_in_hz, 60.0))
    assert len(kept) == pytest.approx(expect_hz * 60.0, abs=1)


def test_a_camera_at_the_limit_with_jitter_loses_no_frame() -> None:
    kept = _kept(FrameRateLimit(10.0), _stamps(10.0, 30.0, jitter_ns=5_000_000, seed=3))
    assert len(kept) == 300


def test_stamps_going_back_and_gaps_start_afresh() -> None:
    lim = FrameRateLimit(10.0)
    first = _stamps(30.0, 1.0)
    assert _kept(lim, first) == list(range(0, 30, 3))
    # a looping recording: the stamps start over; the first frame is kept, then every third
    assert _kept(lim, first) == list(range(0, 30, 3))
    # a pause of 2 s: the first frame after it is kept at once, whatever its phase
    later = [s + 3 * 10**9 + 7_000_000 for s in first]
    assert _kept(lim, later) == list(range(0, 30, 3))
    # the same stamp again is not a second frame
    assert lim.accept(later[-3]) is False


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_an_invalid_rate_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        FrameRateLimit(bad)


def test_the_config_key_is_validated() -> None:
    cfg = load_config_dict({"daemon": {"max_frame_rate_hz": 12.5}})
    assert cfg.daemon.max_frame_rate_hz == 12.5
    assert load_config_dict({}).daemon.max_frame_rate_hz == 0.0
    with pytest.raises(Exception, match="max_frame_rate_hz"):
        load_config_dict({"daemon": {"max_frame_rate_hz": -1.0}})


# --- in the daemon --------------------------------------------------------------------------------


def _feed(d: Daemon, role: str, data: bytes) -> None:
    d._on_inbound(Inbound(role, key_for(d.cfg.topics, role), data, time.monotonic()))


def _daemon(port: int, max_frame_rate_hz: float) -> Daemon:
    cfg = daemon_config_dict(port, max_frame_rate_hz=max_frame_rate_hz)
    cfg["queues"] = {"stereo": 64, "depth": 64}  # keep every emitted frame for the assertions
    return Daemon(load_config_dict(cfg), FakePipeline())


def test_the_daemon_thins_a_30_hz_stereo_camera_before_depth_estimation(port: int) -> None:
    d = _daemon(port, 10.0)
    li, ri = codec.encode_stereo_infos(RIG, 0)
    _feed(d, "left_info", li)
    _feed(d, "right_info", ri)
    h, w = RIG.left.height, RIG.left.width
    img = np.random.default_rng(0).integers(0, 255, (h, w), dtype=np.uint8)
    stamps = _stamps(30.0, 1.0)
    for s in stamps:
        _feed(d, "pose", codec.encode_pose_with_covariance(s, np.eye(4), COV))
        _feed(d, "mask", codec.encode_image(np.full((h, w), 255, np.uint8), s, "left", "mono8"))
        _feed(d, "left_image", codec.encode_image(img, s, "left"))
        _feed(d, "right_image", codec.encode_image(img, s, "right"))
    emitted = [f.stamp_ns for f, _ in list(d.stereo_box._items)]
    assert emitted == stamps[::3]
    assert d.health.counts["frames.stereo"] == 10
    assert d.health.counts["frames.skipped_rate"] == 20
    assert d.health.counts["paired"] == 30  # every pair arrived; skipping is not a drop:
    assert d.dropped_total() == 0 and not d.health.dropped
    assert not d.frames.masks, "the masks of skipped frames are let go"
    assert d.status()["counts"]["frames.skipped_rate"] == 20


@pytest.mark.parametrize(("rate_in_hz", "limit_hz", "every"), [(20.0, 5.0, 4), (30.0, 0.0, 1)])
def test_the_daemon_thins_depth_images_too(port: int, rate_in_hz: float, limit_hz: float, every: int) -> None:
    """Depth input goes through the same limit; without one (0) every frame goes on."""
    d = _daemon(port, limit_hz)
    _feed(d, "depth_info", codec.encode_camera_info(RIG.left, 0, "depth"))
    h, w = RIG.left.height, RIG.left.width
    stamps = _stamps(rate_in_hz, 1.0)
    for s in stamps:
        _feed(d, "pose", codec.encode_pose_with_covariance(s, np.eye(4), COV))
        _feed(d, "depth", codec.encode_image(np.full((h, w), 0.5, np.float32), s, "depth"))
    assert [f.stamp_ns for f, _ in list(d.depth_box._items)] == stamps[::every]
    assert d.health.counts.get("frames.skipped_rate", 0) == len(stamps) - len(stamps[::every])


# --- the overload warning -------------------------------------------------------------------------


def _overload_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if "input faster than the daemon" in r.getMessage()]


def test_queue_overflow_is_warned_of_with_the_rates_at_most_once_a_minute(
    port: int, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"depth": 2}
    d = Daemon(load_config_dict(cfg), FakePipeline())
    caplog.set_level(logging.WARNING, logger="pugsd")
    t = 1000.0
    d._report_overload(t)  # the window starts
    for _ in range(22):  # 22 frames into a queue of 2: 20 pushed out
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
    d.health.count("frames.stereo", 300)
    d.health.count("integrated", 100)
    d._report_overload(t + 5.0)  # within the window: nothing yet
    assert not _overload_lines(caplog)
    d._report_overload(t + 10.0)
    (line,) = _overload_lines(caplog)
    assert "20 frames dropped at the stereo and depth queues in the last 10 s" in line
    assert "30.0 frames/s in, 10.0 integrated" in line
    assert "daemon.max_frame_rate_hz" in line
    assert d.depth_box.stats()["overflowed"] == 20

    for _ in range(20):
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
    d._report_overload(t + 20.0)  # more overflow, but logged 10 s ago
    assert len(_overload_lines(caplog)) == 1
    for _ in range(20):
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
    d._report_overload(t + 80.0)
    assert len(_overload_lines(caplog)) == 2


@pytest.mark.parametrize(
    ("pushed", "came", "warned"), [(4, 10, False), (5, 10, True), (14, 300, False), (15, 300, True)]
)
def test_a_hiccup_is_not_an_overload(
    port: int, caplog: pytest.LogCaptureFixture, pushed: int, came: int, warned: bool
) -> None:
    """A frame pushed out of the 2-deep stereo queue while the depth worker was slow once is
    counted, not warned of: the warning needs at least 5 frames and 5 % of those that came in the
    window."""
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"stereo": 1}
    d = Daemon(load_config_dict(cfg), FakePipeline())
    caplog.set_level(logging.WARNING, logger="pugsd")
    d._report_overload(0.0)
    for _ in range(pushed + 1):
        d.stereo_box.offer((None, 0.0))  # type: ignore[arg-type]
    d.health.count("frames.stereo", came)
    d._report_overload(10.0)
    assert d.stereo_box.overflowed == pushed
    assert bool(_overload_lines(caplog)) is warned


def test_a_reset_clearing_the_queues_is_not_an_overload(port: int, caplog: pytest.LogCaptureFixture) -> None:
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"stereo": 2, "depth": 8}
    d = Daemon(load_config_dict(cfg), FakePipeline())
    caplog.set_level(logging.WARNING, logger="pugsd")
    d._report_overload(0.0)
    for _ in range(7):
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
        d.stereo_box.offer((None, 0.0))  # type: ignore[arg-type]
    assert d.depth_box.clear() == 7
    d.stereo_box.clear()
    assert d.depth_box.dropped == 7 and d.depth_box.overflowed == 0
    assert d.stereo_box.overflowed == 5  # 7 into a queue of 2
    d._report_overload(10.0)
    (line,) = _overload_lines(caplog)
    assert line.startswith("input faster than the daemon integrates: 5 frames dropped")
    d.depth_box.clear()
    d._report_overload(100.0)  # nothing pushed out since: no second line
    assert len(_overload_lines(caplog)) == 1


# --- what `pugsd status` shows of it --------------------------------------------------------------


def test_status_lines_count_every_drop_and_the_skipped_frames() -> None:
    """The operator's summary counted only the drops with a reason (pose wait, duplicates): 327
    frames pushed out of the depth queue under overload read as "dropped 0"."""
    st = {
        "node": "pugsd", "healthy": True, "uptime_s": 40.0, "ready": True, "model_version": 3,
        "grasps_published": 23,
        "counts": {"frames.stereo": 1200, "integrated": 870, "dropped": 2, "frames.skipped_rate": 15},
        "dropped": {"pose_wait: no pose": 2},
        "dropped_total": 2 + 300 + 27 + 5 + 4 + 1,
        "mailboxes": {
            "stereo": {"dropped": 27, "overflowed": 27},
            "depth": {"dropped": 305, "overflowed": 300},
            "commands": {"dropped": 1, "overflowed": 0},  # not a frame queue
        },
        "ingress": {"dropped": 4},
        "waiting": {"unpaired_dropped": 1},
    }  # fmt: skip
    lines = status_lines(st)
    assert lines[1] == (
        "frames 1200, integrated 870, grasps published 23, rejected 0, dropped 339, "
        "skipped 15 (daemon.max_frame_rate_hz)"
    )
    assert [ln for ln in lines if ln.startswith("  dropped")] == [
        "  dropped      300  depth queue: pushed out by newer frames (input faster than the daemon)",
        "  dropped       27  stereo queue: pushed out by newer frames (input faster than the daemon)",
        "  dropped        5  depth queue: cleared (reset)",
        "  dropped        4  ingress bound: messages faster than the loop took them",
        "  dropped        2  pose_wait: no pose",
        "  dropped        1  unpaired stereo halves",
    ]


def test_the_daemons_status_carries_the_total_of_its_drops(port: int) -> None:
    cfg = daemon_config_dict(port)
    cfg["queues"] = {"depth": 2}
    d = Daemon(load_config_dict(cfg), FakePipeline())
    for _ in range(5):
        d.depth_box.offer((None, 0.0))  # type: ignore[arg-type]
    d.report.drop("pose_wait", "no pose for the frame")
    st = d.status()
    assert st["dropped_total"] == d.dropped_total() == 4
    assert status_lines(st)[1].endswith("dropped 4")
