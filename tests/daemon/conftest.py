# SPDX-License-Identifier: Apache-2.0
"""Fixtures for the daemon tests: safe loopback zenoh sessions, a fake pipeline, publishers."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from pugsd.core.camera import PinholeCamera, StereoRig
from pugsd.core.types import DepthFrame, ScoredGrasps, StereoFrame
from pugsd.errors import Preempted
from pugsd.wire.session import check_loopback_safe, free_tcp_port, loopback_config, open_session


def safe_session(cfg: dict[str, Any]) -> zenoh.Session:
    """Assert the loopback-only config (no multicast, no gossip, tcp/127.0.0.1 only), then open."""
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["scouting"]["gossip"]["enabled"] is False
    for ep in cfg["listen"]["endpoints"] + cfg["connect"]["endpoints"]:
        assert ep.startswith("tcp/127.0.0.1:"), ep
    check_loopback_safe(cfg)
    return open_session(cfg, require_loopback=True)


@pytest.fixture
def port() -> int:
    return free_tcp_port()


@pytest.fixture
def client(port: int) -> Iterator[zenoh.Session]:
    """A test-side peer that connects to the daemon's listen port."""
    s = safe_session(loopback_config(None, [port]))
    yield s
    s.close()


@pytest.fixture
def root_saved() -> Iterator[None]:
    """The root logger's handlers and level put back afterwards (``pugsd run``/``demo`` and
    ``setup_logging`` replace them)."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        yield
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])


def daemon_config_dict(port: int, **daemon: Any) -> dict[str, Any]:
    d = {"grasp_rate_hz": 5.0, "status_rate_hz": 5.0, "pose_wait_s": 0.3}
    d.update(daemon)
    return {"daemon": d, "zenoh": loopback_config(port)}


@dataclass
class TrainStats:
    elbo: float
    ready: bool


@dataclass
class Result:
    grasps: ScoredGrasps
    cloud_W: np.ndarray
    sigma2_occ: np.ndarray
    pugs_conf_points: np.ndarray
    model_version: int


class RecordingPublisher:
    """Stands in for a daemon output publisher (``Daemon._publishers``): keeps what was put."""

    def __init__(self) -> None:
        self.puts: list[bytes] = []

    def put(self, payload: bytes) -> int:
        self.puts.append(bytes(payload))
        return len(self.puts)


@contextlib.asynccontextmanager
async def running_worker(d: Any, worker: Coroutine[Any, Any, None]) -> AsyncIterator[None]:
    """No zenoh: run one of the daemon's workers (``d._grasp_worker()``, ...) on this event loop;
    on exit stop it and shut the daemon's executors down."""
    d._loop = asyncio.get_running_loop()
    task = asyncio.create_task(worker)
    try:
        yield
    finally:
        d._stopping = True
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
            ex.shutdown(wait=True)


def sleep_unless_stopped(duration_s: float, should_stop: Callable[[], bool] | None) -> None:
    """Sleep ``duration_s`` in 10 ms slices, raising Preempted as soon as ``should_stop`` says so
    (a stand-in for a proposal that gives way)."""
    t_end = time.monotonic() + duration_s
    while True:
        if should_stop is not None and should_stop():
            raise Preempted("the grasp proposal gave way")
        left = t_end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(left, 0.01))


@dataclass
class FakePipeline:
    """The PugsPipeline interface with trivial maths, for plumbing tests."""

    ready_after: int = 4
    depth_delay_s: float = 0.0
    integrate_delay_s: float = 0.0
    train_delay_s: float = 0.0
    compute_delay_s: float = 0.0
    steps: int = 0
    integrated: list[int] = field(default_factory=list)
    frames: list[DepthFrame] = field(default_factory=list)
    resets: int = 0
    version: int = 0
    rate_scales: list[float] = field(default_factory=list)  # each train_steps call's rate_scale

    @property
    def ready(self) -> bool:
        return self.steps >= self.ready_after and bool(self.integrated)

    def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
        time.sleep(self.depth_delay_s)
        cam = frame.rig.left
        return DepthFrame(
            stamp_ns=frame.stamp_ns,
            depth_m=np.full((cam.height, cam.width), 0.5, np.float32),
            camera=cam,
            T_W_C=frame.T_W_C,
            pose_cov=frame.pose_cov,
        )

    def integrate(self, depth: DepthFrame) -> int:
        time.sleep(self.integrate_delay_s)
        self.integrated.append(depth.stamp_ns)
        self.frames.append(depth)
        self.version += 1
        return int(np.isfinite(depth.depth_m).sum())

    def training_batch(self) -> int:
        """The stand-in's batch: the map's version when it was taken."""
        return self.version

    def train_on(self, batch: int, n: int, rate_scale: float = 1.0) -> TrainStats:
        return self.train_steps(n, rate_scale)

    def train_steps(self, n: int, rate_scale: float = 1.0) -> TrainStats:
        time.sleep(self.train_delay_s)
        self.rate_scales.append(rate_scale)
        self.steps += n
        self.version += 1
        return TrainStats(-1.0 / (1 + self.steps), self.ready)

    def grasp_input(self) -> int:
        return self.version

    def propose(self, inp: int, should_stop: Callable[[], bool] | None = None) -> int:
        sleep_unless_stopped(self.compute_delay_s, should_stop)
        return inp

    def score(self, proposal: int) -> Result:
        return self.compute(full_cloud=False)

    def compute(self, *, full_cloud: bool = True) -> Result:
        n = 3
        pose = np.tile(np.eye(4), (n, 1, 1))
        pose[:, 0, 3] = [0.0, 0.1, 0.2]
        g = ScoredGrasps(
            pose_W=pose,
            contact_W=pose[:, :3, 3].copy(),
            width_m=np.full(n, 0.05),
            baseline_confidence=np.array([0.9, 0.8, 0.7]),
            sigma2_occ=np.array([0.01, 0.02, 0.03]),
            pugs_confidence=np.array([0.85, 0.7, 0.6]),
            grasp_id=np.arange(n, dtype=np.int64),
        )
        cloud = np.random.default_rng(0).normal(size=(50, 3))
        s2 = np.full(50, 0.1) if full_cloud else np.full(50, np.nan)
        return Result(g, cloud, s2, np.full(50, 0.5), self.version)

    def cloud_job(self, result: Result) -> Result:
        return result

    def finish_cloud(self, result: Result, should_stop: Any = None) -> Result:
        return dataclasses.replace(result, sigma2_occ=np.nan_to_num(result.sigma2_occ, nan=0.1))

    def reset(self) -> None:
        self.resets += 1
        self.integrated.clear()
        self.steps = 0

    def stats(self) -> dict[str, Any]:
        return {"frames": len(self.integrated), "steps": self.steps}


RIG = StereoRig(PinholeCamera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=64, height=48), 0.05)


def wait_for(pred: Any, timeout_s: float, what: str, every_s: float = 0.02) -> None:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(every_s)


def query_json(s: zenoh.Session, key: str, timeout: float = 2.0) -> dict[str, Any]:
    for r in s.get(key, timeout=timeout):
        if r.ok is not None:
            return dict(json.loads(r.ok.payload.to_string()))
    raise AssertionError(f"no reply on {key}")


class Source:
    """Publishes inputs the way a ROS 2 (rmw_zenoh) camera driver and localiser would."""

    def __init__(self, session: zenoh.Session, topics: Any | None = None) -> None:
        from pugsd.daemon.config import TopicsConfig
        from pugsd.wire.publisher import Publisher
        from pugsd.wire.topics import key_for
        from pugsd.wire.types import POSE_STAMPED

        self.topics = topics if topics is not None else TopicsConfig()
        roles = (
            "left_image",
            "right_image",
            "left_info",
            "right_info",
            "pose",
            "mask",
            "depth",
            "depth_info",
            "depth_std",
        )
        self.pubs = {r: Publisher(session, key_for(self.topics, r)) for r in roles}
        self.pubs["pose_stamped"] = Publisher(session, key_for(self.topics, "pose", POSE_STAMPED))

    def wait_matching(self, role: str | None = None, timeout_s: float = 10.0) -> None:
        """Wait until the daemon subscribes ``role`` (default: every input role)."""
        for r in [role] if role else [r for r in self.pubs if r != "pose_stamped"]:
            wait_for(lambda r=r: self.pubs[r].matching, timeout_s, f"a subscriber on {r}")

    def put(self, role: str, data: bytes) -> None:
        self.pubs[role].put(data)

    def infos(self, rig: StereoRig = RIG, stamp_ns: int = 0) -> None:
        from pugsd.wire import codec

        li, ri = codec.encode_stereo_infos(rig, stamp_ns)
        self.put("left_info", li)
        self.put("right_info", ri)

    def stereo(
        self,
        stamp_ns: int,
        T: np.ndarray,
        cov: np.ndarray | None = None,
        rig: StereoRig = RIG,
        seed: int = 0,
        pose_first: bool = True,
    ) -> None:
        from pugsd.wire import codec

        rng = np.random.default_rng(seed)
        h, w = rig.left.height, rig.left.width
        left = rng.integers(0, 255, (h, w), dtype=np.uint8)
        right = np.roll(left, -3, axis=1)
        cov = np.eye(6) * 1e-6 if cov is None else cov
        pose = codec.encode_pose_with_covariance(stamp_ns, T, cov)
        if pose_first:
            self.put("pose", pose)
        self.put("left_image", codec.encode_image(left, stamp_ns, "left"))
        self.put("right_image", codec.encode_image(right, stamp_ns, "right"))
        if not pose_first:
            self.put("pose", pose)

    def close(self) -> None:
        for p in self.pubs.values():
            p.undeclare()


# --- subprocess helpers (end-to-end tests) ---------------------------------------------------------


HERE = Path(__file__).resolve().parent


def toml_text(d: dict[str, Any], prefix: str = "") -> str:
    """A tiny TOML writer for test configs (tables, strings, numbers, bools, string arrays)."""
    scalars, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            scalars.append(f"{k} = {json.dumps(v)}")
    out = ""
    if prefix and scalars:
        out += f"[{prefix}]\n"
    out += "".join(s + "\n" for s in scalars)
    for k, v in tables:
        out += toml_text(v, f"{prefix}.{k}" if prefix else k)
    return out


@pytest.fixture(scope="session")
def sequence_npz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A rendered synthetic stereo sequence (mug, all around, 320x240), saved once per session."""
    from pugsd.sim.sequence import make_sequence

    seq = make_sequence("mug", "complete", n_frames=12, width=320, height=240, seed=0)
    path = tmp_path_factory.mktemp("seq") / "mug.npz"
    cam = seq.rig.left
    mesh = seq.mesh_W
    np.savez(
        path,
        left=np.stack([f.left for f in seq.frames]),
        right=np.stack([f.right for f in seq.frames]),
        mask=np.stack([f.mask for f in seq.frames]),
        T_W_C=np.stack([f.T_W_C for f in seq.frames]),
        pose_cov=np.stack([f.pose_cov for f in seq.frames]),
        camera=np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height]),
        baseline_m=seq.rig.baseline_m,
        mesh_vertices=np.asarray(mesh.vertices),
        mesh_faces=np.asarray(mesh.faces),
    )
    return path


class Proc:
    """A subprocess this test started; stopped only through its own pid."""

    def __init__(self, args: list[str], log_path: Path, env: dict[str, str] | None = None) -> None:
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115
        e = dict(os.environ)
        e.setdefault("OMP_NUM_THREADS", "1")
        e.update(env or {})
        self.p = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, env=e)
        self.pid = self.p.pid

    def signal(self, sig: int) -> None:
        if self.p.poll() is None:
            os.kill(self.pid, sig)

    def wait(self, timeout_s: float) -> int | None:
        try:
            return self.p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def kill(self) -> None:
        """Last resort at teardown: SIGKILL by pid if still running."""
        if self.p.poll() is None:
            os.kill(self.pid, signal.SIGKILL)
            self.p.wait(10)
        self._log.close()


def start_daemon(
    tmp: Path, port: int, extra: dict[str, Any] | None = None, env: dict[str, str] | None = None
) -> tuple[Proc, Path]:
    cfg: dict[str, Any] = {
        "stereo": {"downsample": 2},
        "daemon": {
            "grasp_rate_hz": 2.0,
            "status_rate_hz": 2.0,
            "log_json": True,
            "log_level": "info",
            "shutdown_timeout_s": 5.0,
        },
        "zenoh": loopback_config(port),
    }
    for k, v in (extra or {}).items():
        cfg.setdefault(k, {}).update(v)
    z = cfg["zenoh"]
    assert z["scouting"]["multicast"]["enabled"] is False
    assert z["scouting"]["gossip"]["enabled"] is False
    assert all(e.startswith("tcp/127.0.0.1:") for e in z["listen"]["endpoints"])
    check_loopback_safe(z)
    path = tmp / "pugsd.toml"
    path.write_text(toml_text(cfg))
    proc = Proc([sys.executable, "-m", "pugsd", "run", "--config", str(path)], tmp / "daemon.log", env)
    return proc, path


def start_publisher(
    tmp: Path,
    seq: Path,
    port: int,
    rate: float,
    duration: float,
    frames: int = 0,
    name: str = "publisher",
) -> tuple[Proc, Path]:
    stats = tmp / f"{name}.json"
    args = [
        sys.executable,
        str(HERE / "stereo_publisher.py"),
        str(seq),
        str(port),
        "--rate",
        str(rate),
        "--duration",
        str(duration),
        "--frames",
        str(frames),
        "--stats",
        str(stats),
    ]
    return Proc(args, tmp / f"{name}.log"), stats


def wait_alive(s: zenoh.Session, proc: Proc, timeout_s: float = 90.0) -> float:
    """Seconds until the daemon's liveliness token is visible (READY follows the same point)."""
    t0 = time.monotonic()
    while True:
        if proc.p.poll() is not None:
            raise AssertionError(f"daemon exited with {proc.p.returncode}:\n{proc.log()[-3000:]}")
        if any(r.ok is not None for r in s.liveliness().get("pugs/alive/**", timeout=0.5)):
            return time.monotonic() - t0
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"daemon not alive after {timeout_s} s:\n{proc.log()[-3000:]}")
        time.sleep(0.1)
