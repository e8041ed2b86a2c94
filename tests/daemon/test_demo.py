# SPDX-License-Identifier: Apache-2.0
"""``pugsd demo`` (pugsd/daemon/demo.py): the README's command prints scored grasps within a minute,
writes an MCAP and a PNG and listens on the loopback endpoint it prints; at unit level, the
loopback endpoint it accepts, its config, what the synthetic camera puts, when the grasp printer
prints, ``run_demo``'s summary and exit code (``_demo_main`` stubbed), and one short in-process run
of ``_demo_main`` (fake pipeline) that ends on Ctrl-C once the camera's sweeps are done."""

from __future__ import annotations

import asyncio
import re
import signal
import sys
import threading
import time
import types
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pugsd.core.types import ScoredGrasps, StereoFrame
from pugsd.daemon import demo
from pugsd.errors import ConfigError
from pugsd.record.mcapio import iter_recording
from pugsd.wire import codec
from pugsd.wire.session import free_tcp_port
from tests.daemon.conftest import RIG, FakePipeline, Proc
from tests.daemon.test_daemon_inprocess import pose_at


@pytest.mark.slow
def test_demo_shows_grasps_within_a_minute(tmp_path: Path) -> None:
    port = free_tcp_port()
    out = tmp_path / "demo"
    t0 = time.monotonic()
    proc = Proc(
        [sys.executable, "-m", "pugsd", "demo", "--duration", "60", "--out", str(out),
         "--listen", f"tcp/127.0.0.1:{port}"],
        tmp_path / "demo.log",
    )  # fmt: skip
    try:
        rc = proc.wait(240)
        text = proc.log()
    finally:
        proc.signal(signal.SIGTERM)
        proc.kill()
    took = time.monotonic() - t0
    assert rc == 0, text[-4000:]
    assert f"listening on tcp/127.0.0.1:{port}" in text
    m = re.search(r"time to first scored grasps: ([0-9.]+) s", text)
    assert m, text[-4000:]
    first = float(m.group(1))
    print(f"\ndemo: first scored grasps {first:.1f} s after start; whole run {took:.0f} s")
    assert first < 60.0, text[-3000:]
    # the summary accounts for the frames: none counted twice, losses before the daemon reported
    m = re.search(
        r"frames sent (\d+), integrated (\d+), dropped (\d+) .*lost before the daemon (\d+),", text
    )
    assert m, text[-3000:]
    sent, integrated, dropped, _lost = (int(g) for g in m.groups())
    assert integrated >= 1 and integrated + dropped <= sent, m.group(0)
    assert list(out.glob("*.mcap")) and (out / "grasps.png").stat().st_size > 10_000


def test_the_synthetic_camera_waits_for_a_route_on_every_topic_it_publishes() -> None:
    """It waited for the images and the pose only: a mask or CameraInfo put before its route
    existed would be lost."""
    from types import SimpleNamespace

    from pugsd.daemon.demo import SyntheticCamera

    cam = SyntheticCamera.__new__(SyntheticCamera)
    cam.pubs = {r: SimpleNamespace(matching=True) for r in SyntheticCamera.ROLES}
    assert cam.wait_matching(0.05)
    for role in SyntheticCamera.ROLES:
        cam.pubs[role].matching = False
        assert not cam.wait_matching(0.05), role
        cam.pubs[role].matching = True


def test_the_synthetic_camera_stops_waiting_for_routes_when_the_demo_shuts_down() -> None:
    """A demo interrupted while its camera waited for the daemon's subscriptions: the camera
    thread waited out its 10 s regardless, longer than the 5 s the shutdown joins it for."""
    import threading

    from pugsd.daemon.demo import SyntheticCamera

    stop = threading.Event()
    reads = [0]

    class NeverMatches:
        @property
        def matching(self) -> bool:
            reads[0] += 1
            if reads[0] == 3:
                stop.set()  # the shutdown, while the camera waits
            return False

    cam = SyntheticCamera.__new__(SyntheticCamera)
    cam.pubs = {r: NeverMatches() for r in SyntheticCamera.ROLES}
    assert not cam.wait_matching(1e6, stop)  # returns although the timeout is days away
    assert reads[0] == 3  # the first poll after the stop ended the wait
    assert not cam.wait_matching(1e6, stop) and reads[0] == 4  # already set: one look, no wait


def test_demo_says_why_there_is_no_figure_after_a_reset() -> None:
    """README invites `pugsd reset` against a running demo; when it cleared the map after the
    camera's sweep, the end summary said "no grasps were computed (model not ready)" although
    grasps had been printed all along."""
    from pugsd.daemon.demo import no_figure_reason

    assert "model not ready" in no_figure_reason(0, 0)
    assert "model not ready" in no_figure_reason(0, 1)  # a reset before any grasps
    after_reset = no_figure_reason(19, 1)
    assert "reset" in after_reset and "19 grasp update" in after_reset
    assert "no grasps were computed" not in after_reset


COV = np.eye(6) * 1e-6


@pytest.mark.parametrize(("endpoint", "port"), [("tcp/127.0.0.1:1", 1), ("tcp/127.0.0.1:65535", 65535)])
def test_a_loopback_endpoint_gives_its_port(endpoint: str, port: int) -> None:
    assert demo.parse_loopback_port(endpoint) == port


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/127.0.0.1:0",
        "tcp/127.0.0.1:65536",
        "tcp/127.0.0.1:123456",
        "tcp/0.0.0.0:7447",
        "tcp/127.0.0.10:7447",
        "tcp/localhost:7447",
        "udp/127.0.0.1:7447",
        "tcp/127.0.0.1:7447/",
    ],
)
def test_anything_but_a_loopback_tcp_port_is_refused(endpoint: str) -> None:
    with pytest.raises(ConfigError) as exc:
        demo.parse_loopback_port(endpoint)
    assert str(exc.value) == f"--listen must be tcp/127.0.0.1:PORT (loopback only), got {endpoint!r}"


def test_demo_config_settings_and_overrides() -> None:
    cfg = demo.demo_config("tcp/127.0.0.1:7555", [])
    assert cfg.stereo.downsample == 2 and cfg.queues.depth == 16
    assert (cfg.daemon.grasp_rate_hz, cfg.daemon.log_level) == (1.0, "warning")
    assert cfg.zenoh["listen"]["endpoints"] == ["tcp/127.0.0.1:7555"]
    assert cfg.zenoh["scouting"]["multicast"]["enabled"] is False
    cfg = demo.demo_config("tcp/127.0.0.1:7555", ["daemon.grasp_rate_hz=3", "queues.depth=4"])
    assert (cfg.daemon.grasp_rate_hz, cfg.queues.depth) == (3.0, 4)  # --set wins over the demo's own


class _Put:
    def __init__(self, role: str, log: list[tuple[str, bytes]]) -> None:
        self.role, self.log = role, log

    def put(self, data: bytes) -> None:
        self.log.append((self.role, data))


def test_the_camera_puts_infos_pose_mask_then_images_under_one_stamp() -> None:
    log: list[tuple[str, bytes]] = []
    cam = demo.SyntheticCamera.__new__(demo.SyntheticCamera)
    cam.pubs = {r: _Put(r, log) for r in demo.SyntheticCamera.ROLES}  # type: ignore[misc]
    cam.sent = 0
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)
    mask = np.zeros(left.shape, bool)
    mask[10:20, 5:30] = True
    frame = StereoFrame(1, left, np.roll(left, -3, axis=1), RIG, pose_at(0.2), COV, mask=mask)
    assert cam.publish(frame, 123_456_789) >= 0.0
    assert [r for r, _ in log] == list(demo.SyntheticCamera.ROLES)
    got = dict(log)
    m = codec.decode_image(got["mask"])
    assert (m.encoding, m.stamp_ns) == ("mono8", 123_456_789)
    np.testing.assert_array_equal(m.array, np.where(mask, 255, 0))
    np.testing.assert_array_equal(codec.decode_image(got["left_image"]).array, left)
    np.testing.assert_array_equal(codec.decode_image(got["right_image"]).array, frame.right)
    pose = codec.decode_pose_with_covariance(got["pose"])
    assert pose.stamp_ns == 123_456_789
    np.testing.assert_allclose(pose.T, pose_at(0.2))
    assert cam.sent == 1
    log.clear()
    cam.publish(StereoFrame(2, left, left, RIG, pose_at(0.3), COV), 5)  # no mask: none put
    assert [r for r, _ in log] == ["left_info", "right_info", "pose", "left_image", "right_image"]
    assert cam.sent == 2


def _grasps(top: float, n: int = 4, dx: float = 0.0) -> bytes:
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, 3] = (0.1 * i + dx, -0.05, 0.5)
    g = ScoredGrasps(
        pose_W=poses,
        contact_W=poses[:, :3, 3].copy(),
        width_m=np.full(n, 0.04),
        baseline_confidence=np.full(n, 0.5),
        sigma2_occ=np.full(n, 2e-4),
        pugs_confidence=np.linspace(top, top / 2, n),
        grasp_id=np.arange(n, dtype=np.int64),
    )
    return codec.encode_grasp_array(g)


def _body(line: str) -> str:
    m = re.fullmatch(r"\[ *\d+\.\d s\] (.*)", line)
    assert m, line
    return m.group(1)


def test_the_grasp_printer_prints_when_the_ranking_changes() -> None:
    lines: list[str] = []
    p = demo.GraspPrinter(lines.append, time.monotonic())

    def updates() -> list[str]:  # the timed lines: an update's header, a reset, the first grasps
        return [_body(s) for s in lines if s.startswith("[")]

    p.on_grasps(b"\x00\x01 not cdr")
    assert len(lines) == 1 and lines[0].startswith("  (undecodable GraspArray: ")
    p.on_grasps(_grasps(1.0, n=0))  # an empty array: nothing to show yet
    assert len(lines) == 1 and p.first_s is None
    p.on_grasps(_grasps(10.0))
    assert [s if s.startswith("  ") else _body(s) for s in lines[1:]] == [
        "first scored grasps",
        "4 grasps, best first:",
        "  grasp 1: PUGS confidence 10 (baseline 0.500, sigma^2_occ 0.0002), contact (+0.000, -0.050, "
        "+0.500) m in world, approach (+0.00, +0.00, +1.00), width 4.0 cm, id 0",
        "  grasp 2: PUGS confidence 8.33 (baseline 0.500, sigma^2_occ 0.0002), contact (+0.100, -0.050, "
        "+0.500) m in world, approach (+0.00, +0.00, +1.00), width 4.0 cm, id 1",
        "  grasp 3: PUGS confidence 6.67 (baseline 0.500, sigma^2_occ 0.0002), contact (+0.200, -0.050, "
        "+0.500) m in world, approach (+0.00, +0.00, +1.00), width 4.0 cm, id 2",
    ]
    assert p.first_s is not None and p.received == 3
    first = p.first_s
    p.on_grasps(_grasps(10.0))  # the same ranking
    p.on_grasps(_grasps(10.4))  # the top score within 5 %
    p.on_grasps(_grasps(10.0, dx=0.002))  # contacts moved less than the 5 mm grid
    assert len(updates()) == 2
    p.on_grasps(_grasps(10.6))  # more than 5 %
    assert len(updates()) == 3 and lines[-3].startswith("  grasp 1: PUGS confidence 10.6 ")
    p.on_grasps(_grasps(10.6, dx=0.01))  # the top contacts moved
    assert len(updates()) == 4
    p.on_grasps(_grasps(10.6, n=2, dx=0.01))  # fewer than three: the ranking changed
    assert updates()[-1] == "2 grasps, best first:" and lines[-2].startswith("  grasp 1: ")
    p.t0 -= 14.0  # 14 s on without a change: quiet
    p.on_grasps(_grasps(10.6, n=2, dx=0.01))
    assert len(updates()) == 5
    p.t0 -= 2.0  # more than 15 s since the last line: printed again
    p.on_grasps(_grasps(10.6, n=2, dx=0.01))
    assert len(updates()) == 6
    assert p.first_s == first and p.received == 11 and len(p.history) == 9
    assert [n for _, n, _ in p.history].count(2) == 3
    p.on_grasps(_grasps(1.0, n=0))  # a reset: said once
    p.on_grasps(_grasps(1.0, n=0))
    assert len(updates()) == 7 and _body(lines[-1]) == "no grasps (the map was reset, or none were found)"
    p.on_grasps(_grasps(10.6, n=2, dx=0.01))  # the same grasps as before the reset: shown again
    assert updates()[-1] == "2 grasps, best first:" and len(updates()) == 8
    assert lines[-2].startswith("  grasp 1: PUGS confidence 10.6 ")


class _StubDaemon:
    def __init__(self, latest: Any = None, grasps: int = 4, resets: int = 0) -> None:
        self.outputs = SimpleNamespace(
            latest_result=latest, latest_cloud_result=None, grasps_published=grasps
        )
        self.resets = resets

    def status(self) -> dict[str, Any]:
        return {
            "counts": {"integrated": 5, "dropped": 1, "rejected": 2, "resets": self.resets},
            "mailboxes": {"stereo": {"dropped": 3}, "depth": {"dropped": 4}},
            "ingress": {"dropped": 7},
            "waiting": {"unpaired_dropped": 6},
            "upstream": {"lost": {"left": 1, "right": 2}},
            "latency": {"depth": {"p50_ms": 12.4, "max_ms": 30.6}, "train": {"n": 0}},
        }

    def dropped_total(self) -> int:
        return 15


@pytest.fixture
def stub_main(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """``_demo_main`` replaced: it records its arguments, renders through ``render_scene`` (also
    stubbed) and returns what ``state`` holds."""
    state: dict[str, Any] = {"daemon": _StubDaemon(), "first_s": 4.3, "files": [Path("/x/a.mcap")]}

    async def fake_main(cfg: Any, render: Any, duration_s: float, out_dir: Path, rate_hz: float,
                        write: Any, t_start: float, sweeps: int) -> Any:  # fmt: skip
        state["args"] = (duration_s, out_dir, rate_hz, sweeps, cfg.zenoh["listen"]["endpoints"])
        state["rendered"] = render()
        printer = demo.GraspPrinter(write, t_start, first_s=state["first_s"])
        return state["daemon"], printer, state["files"], {"frames_sent": 12, "max_put_s": 0.0015}

    monkeypatch.setattr(demo, "_demo_main", fake_main)
    monkeypatch.setattr(demo, "render_scene", lambda *a, **kw: ("scene", a, kw))
    monkeypatch.setattr(demo, "apply_malloc_arena_max", lambda n: None)
    monkeypatch.setattr(
        demo, "save_figure", lambda r, path, **kw: state.setdefault("figures", []).append((path, kw))
    )
    return state


def test_run_demo_summary_and_exit_code(stub_main: dict[str, Any], tmp_path: Path) -> None:
    lines: list[str] = []
    out = tmp_path / "a" / "b"
    rc = demo.run_demo(3.5, out, "tcp/127.0.0.1:7600", write=lines.append, object_name="box",
                       n_frames=5, width=64, height=48, rate_hz=4.0, sweeps=2)  # fmt: skip
    assert rc == 0 and out.is_dir()
    assert stub_main["args"] == (3.5, out, 4.0, 2, ["tcp/127.0.0.1:7600"])
    assert stub_main["rendered"] == ("scene", ("box", 5, 64, 48), {"seed": 0})
    assert lines[0] == (
        "pugsd demo: zenoh peer listening on tcp/127.0.0.1:7600 (loopback only; multicast scouting off)"
    )
    assert "rendering a synthetic box from 5 views (64x48) while the daemon starts..." in lines
    assert lines[-5:] == [
        "frames sent 12, integrated 5, dropped 8 (newest frame wins: stereo queue 3, depth queue 4; "
        "no pose/reset/duplicate 1, unpaired halves 6), messages dropped at the ingress bound 7, "
        "rejected 2, lost before the daemon 3, grasp updates 4; slowest zenoh put 1.50 ms",
        "stage times p50/max [ms]: depth 12/31",
        "time to first scored grasps: 4.3 s after the command started",
        "MCAP: /x/a.mcap",
        "no grasps were computed (model not ready); no PNG written",
    ]
    assert "figures" not in stub_main


def test_run_demo_exits_1_without_grasps_and_says_why(stub_main: dict[str, Any], tmp_path: Path) -> None:
    stub_main.update(first_s=None, files=[], daemon=_StubDaemon(grasps=19, resets=1))
    lines: list[str] = []
    assert demo.run_demo(1.0, tmp_path, "tcp/127.0.0.1:7600", write=lines.append) == 1
    assert not any(s.startswith(("time to first", "MCAP:")) for s in lines)
    assert lines[-1] == demo.no_figure_reason(19, 1)


def test_run_demo_draws_the_figure_from_the_latest_result(stub_main: dict[str, Any], tmp_path: Path) -> None:
    latest = types.SimpleNamespace(cloud_W=np.zeros((3, 3)))
    stub_main["daemon"] = _StubDaemon(latest=latest)
    lines: list[str] = []
    rc = demo.run_demo(1.0, tmp_path, "tcp/127.0.0.1:7600", ["grasp.gripper.depth_m=0.07"], lines.append)
    assert rc == 0
    assert stub_main["figures"] == [(tmp_path / "grasps.png", {"gripper_depth_m": 0.07})]
    assert lines[-1] == f"PNG:  {tmp_path / 'grasps.png'}"
    stub_main["daemon"] = _StubDaemon(latest=types.SimpleNamespace(cloud_W=np.zeros((0, 3))))
    lines.clear()
    demo.run_demo(1.0, tmp_path, "tcp/127.0.0.1:7600", write=lines.append)  # an empty cloud: no figure
    assert len(stub_main["figures"]) == 1 and lines[-1].startswith("no grasps were computed")


def test_run_demo_refuses_a_non_loopback_endpoint_before_it_starts(
    stub_main: dict[str, Any], tmp_path: Path
) -> None:
    with pytest.raises(ConfigError, match="loopback only"):
        demo.run_demo(1.0, tmp_path / "never", "tcp/0.0.0.0:7447")
    assert "args" not in stub_main and not (tmp_path / "never").exists()


def test_run_demo_refuses_a_busy_port_before_it_renders(stub_main: dict[str, Any], tmp_path: Path) -> None:
    """A port something listens on already: the demo said "listening", rendered for over a
    minute, then failed; now it stops at once with a clear error, nothing rendered or written."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        lines: list[str] = []
        with pytest.raises(ConfigError, match=rf"tcp/127\.0\.0\.1:{port} is in use .*--listen"):
            demo.run_demo(1.0, tmp_path / "never", f"tcp/127.0.0.1:{port}", write=lines.append)
    assert lines == [] and "rendered" not in stub_main and not (tmp_path / "never").exists()
    demo.check_port_free(port)  # closed: free again


def test_demo_main_sends_its_sweeps_prints_grasps_and_stops_on_ctrl_c(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In-process (fake pipeline): two sweeps of three views, the grasps printed, then Ctrl-C
    (raised from the console writer once the camera is done and grasps were printed) ends it well
    before its duration; the MCAP is finished and the signal handlers are gone."""
    from pugsd.wire.session import free_tcp_port

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: FakePipeline())
    cfg = demo.demo_config(f"tcp/127.0.0.1:{free_tcp_port()}", ["daemon.grasp_rate_hz=20"])
    img = np.random.default_rng(0).integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)

    def render() -> list[StereoFrame]:
        return [StereoFrame(i, img, np.roll(img, -3, axis=1), RIG, pose_at(0.01 * i), COV) for i in range(3)]

    lines: list[str] = []

    def write(line: str) -> None:
        lines.append(line)
        done = any("camera done" in s for s in lines)
        if done and any("first scored grasps" in s for s in lines) and "sent" not in lines:
            lines.append("sent")
            signal.raise_signal(signal.SIGINT)  # the demo's own handler: a clean stop

    assert threading.current_thread() is threading.main_thread()
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}

    async def main_() -> Any:
        got = await demo._demo_main(cfg, render, 20.0, tmp_path, 50.0, write, time.monotonic(), 2)
        # its handlers are gone once it returns, not only when asyncio.run closes the loop
        assert {s: signal.getsignal(s) for s in before} == before
        return got

    daemon, printer, files, extra = asyncio.run(main_())
    assert "sent" in lines and "interrupted; shutting down" in lines, lines
    assert extra["frames_sent"] == 6
    stamp = r"\[ *\d+\.\d s\] "
    assert any(re.fullmatch(stamp + r"camera publishing 3 views at 50 Hz, 2 sweep\(s\)", s) for s in lines)
    assert any(re.fullmatch(stamp + r"camera done: 6 frames; training on .*", s) for s in lines)
    assert printer.first_s is not None and printer.received >= 1
    assert daemon.outputs.grasps_published >= 1 and not daemon.serving
    assert [f.suffix for f in files] == [".mcap"] and files[0].exists()
    assert not list(tmp_path.glob("*.part"))
    assert extra["recorder"] is not None
    # the camera's stamps are on an exact 1 / 50 Hz grid (they were wall-clock times, jittered
    # around daemon.pose_max_gap_s at the demo's 2 Hz)
    poses = [codec.decode_pose(m.data, m.typename).stamp_ns for m in iter_recording(files)
             if m.topic == cfg.topics.pose]  # fmt: skip
    assert len(poses) == 6 and set(np.diff(poses)) == {20_000_000}


def test_demo_main_returns_after_its_duration_with_the_camera_looping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No signal and a healthy daemon: the duration ends the run; sweeps = 0 loops the views."""
    from pugsd.wire.session import free_tcp_port

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: FakePipeline())
    cfg = demo.demo_config(f"tcp/127.0.0.1:{free_tcp_port()}", [])
    img = np.random.default_rng(1).integers(0, 255, (RIG.left.height, RIG.left.width), dtype=np.uint8)

    def render() -> list[StereoFrame]:
        return [StereoFrame(i, img, np.roll(img, -3, axis=1), RIG, pose_at(0.01 * i), COV) for i in range(2)]

    lines: list[str] = []

    async def main_() -> Any:  # a bound far above the duration: a run that ignores it fails
        main = demo._demo_main(cfg, render, 0.5, tmp_path, 20.0, lines.append, time.monotonic(), 0)
        return await asyncio.wait_for(main, 20.0)

    daemon, _printer, files, _extra = asyncio.run(main_())
    assert any(s.endswith("camera publishing 2 views at 20 Hz in a loop") for s in lines), lines
    assert not any(s.startswith(("interrupted", "the daemon stopped")) for s in lines), lines
    assert not daemon.serving and [f.suffix for f in files] == [".mcap"]


def test_the_camera_blocks_rather_than_drops_unless_told(monkeypatch: pytest.MonkeyPatch) -> None:
    import zenoh

    made: list[tuple[str, Any]] = []

    class FakePublisher:
        def __init__(self, session: Any, key: str, congestion_control: Any = None) -> None:
            made.append((key, congestion_control))

    monkeypatch.setattr(demo, "Publisher", FakePublisher)
    topics = demo.demo_config("tcp/127.0.0.1:7555", []).topics
    demo.SyntheticCamera(object(), topics)  # type: ignore[arg-type]
    assert len(made) == len(demo.SyntheticCamera.ROLES) == len({k for k, _ in made})
    n = len(demo.SyntheticCamera.ROLES)
    assert [cc for _, cc in made] == [zenoh.CongestionControl.BLOCK] * n
    made.clear()
    demo.SyntheticCamera(object(), topics, congestion_control=zenoh.CongestionControl.DROP)  # type: ignore[arg-type]
    assert [cc for _, cc in made] == [zenoh.CongestionControl.DROP] * n


class _BrokenWarmUp(FakePipeline):
    def warm_up(self) -> None:
        raise RuntimeError("no model weights")


def test_a_daemon_that_fails_to_start_is_reraised_and_the_handlers_removed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pugsd.wire.session import free_tcp_port

    monkeypatch.setattr("pugsd.pipeline_factory.make_pipeline", lambda core, seed=0: _BrokenWarmUp())
    cfg = demo.demo_config(f"tcp/127.0.0.1:{free_tcp_port()}", [])
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    lines: list[str] = []

    async def main_() -> None:
        with pytest.raises(RuntimeError, match="no model weights"):
            await asyncio.wait_for(
                demo._demo_main(cfg, lambda: [], 20.0, tmp_path, 5.0, lines.append, time.monotonic(), 1), 15.0
            )
        assert {s: signal.getsignal(s) for s in before} == before

    asyncio.run(main_())
    assert lines == [] and not list(tmp_path.iterdir())  # no recorder was started


@pytest.mark.parametrize("computed", [10, 0])
def test_the_figure_draws_every_cloud_point_grey_where_sigma2_was_not_computed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, computed: int
) -> None:
    """The demo's grasps.png showed only the grasp contacts when its result came from a round
    without the whole cloud (sigma^2_occ NaN elsewhere): those points are now drawn grey."""
    from mpl_toolkits.mplot3d.axes3d import Axes3D

    drawn: list[tuple[int, Any]] = []
    scatter = Axes3D.scatter

    def spy(self: Any, xs: Any, ys: Any, zs: Any, *a: Any, **kw: Any) -> Any:
        drawn.append((len(xs), kw.get("color")))
        return scatter(self, xs, ys, zs, *a, **kw)

    monkeypatch.setattr(Axes3D, "scatter", spy)
    n = 40
    s2 = np.full(n, np.nan)
    s2[:computed] = np.geomspace(1e-4, 1e-2, computed)
    grasps = codec.decode_grasp_array(_grasps(1.0))
    result = types.SimpleNamespace(
        cloud_W=np.random.default_rng(1).normal(scale=0.05, size=(n, 3)),
        sigma2_occ=s2,
        grasps=grasps,
        model_version=3,
    )
    demo.save_figure(result, tmp_path / "g.png")
    assert (tmp_path / "g.png").stat().st_size > 10_000
    assert drawn == [(n - computed, "0.7"), (computed, None)]  # the grey ones first, then by sigma^2
