# SPDX-License-Identifier: Apache-2.0
"""``pugsd demo``: the daemon, a synthetic stereo camera and a grasp printer on one loopback peer.

Everything talks over zenoh exactly as separate ROS 2 (rmw_zenoh) nodes would: the daemon's session
listens on the loopback endpoint, and the camera/printer/recorder session connects to it, so the
camera's frames and the daemon's grasps cross a real TCP link. Console lines go to ``write``.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import re
import signal
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from pugsd.config import PugsdConfig, core_of, load_config_dict
from pugsd.core.camera import StereoRig
from pugsd.core.types import StereoFrame
from pugsd.daemon.app import Daemon
from pugsd.daemon.process import apply_malloc_arena_max, apply_thread_limits
from pugsd.errors import ConfigError, PugsdError
from pugsd.grasp_text import grasp_lines
from pugsd.wire import codec
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import close_session, loopback_config, open_session
from pugsd.wire.topics import key_for

log = logging.getLogger(__name__)

Writer = Callable[[str], None]


class SyntheticCamera:
    """Publishes StereoFrames as a stereo driver plus localiser would: CameraInfo x2, the pose
    (PoseWithCovarianceStamped), the object mask, then the left and right images, one stamp.

    Its puts use CongestionControl.BLOCK (a reliable, keep-all source, as rmw_zenoh maps
    RELIABLE + KEEP_ALL): under DROP, zenoh drops a large put that finds no free TX batch within
    ``wait_before_drop`` (1 ms by default) even on an idle loopback link, silently, and upstream
    of any sequence number the daemon can check. The bench saw it lose a whole first frame
    (mask and both images, the pose delivered) in about one run in fifteen while the daemon
    was starting; the demo, the tests and the bench measure the daemon, so their source must
    not lose frames of its own. ``congestion_control`` picks another policy."""

    ROLES = ("left_info", "right_info", "pose", "mask", "left_image", "right_image")

    def __init__(self, session: zenoh.Session, topics: Any, congestion_control: Any = None) -> None:
        self.topics = topics
        cc = zenoh.CongestionControl.BLOCK if congestion_control is None else congestion_control
        self.pubs = {r: Publisher(session, key_for(topics, r), congestion_control=cc) for r in self.ROLES}
        self.sent = 0

    def wait_matching(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until a subscriber matches every topic this camera publishes, not only the
        images and the pose: a put before its route exists is lost. (The maskless first frames
        the bench saw were another cause, keys reordered on the way: the daemon now waits for a
        first frame's mask, see ``Daemon._side_missing``.) False after ``timeout_s``, or at once
        when ``stop`` is set (the demo is shutting down)."""
        stop = threading.Event() if stop is None else stop
        t0 = time.monotonic()
        while not all(self.pubs[r].matching for r in self.ROLES):
            if time.monotonic() - t0 > timeout_s or stop.wait(0.02):
                return False
        return True

    def publish(self, frame: StereoFrame, stamp_ns: int) -> float:
        """Publish one frame under ``stamp_ns``; returns the longest ``put`` in seconds."""
        rig: StereoRig = frame.rig
        li, ri = codec.encode_stereo_infos(rig, stamp_ns)
        msgs = [
            ("left_info", li),
            ("right_info", ri),
            ("pose", codec.encode_pose_with_covariance(stamp_ns, frame.T_W_C, frame.pose_cov)),
        ]
        if frame.mask is not None:
            mask = np.where(frame.mask, 255, 0).astype(np.uint8)
            msgs.append(("mask", codec.encode_image(mask, stamp_ns, "left", "mono8")))
        msgs.append(("left_image", codec.encode_image(frame.left, stamp_ns, "left")))
        msgs.append(("right_image", codec.encode_image(frame.right, stamp_ns, "right")))
        worst = 0.0
        for role, data in msgs:
            t0 = time.perf_counter()
            self.pubs[role].put(data)
            worst = max(worst, time.perf_counter() - t0)
        self.sent += 1
        return worst

    def close(self) -> None:
        for p in self.pubs.values():
            p.undeclare()


def parse_loopback_port(endpoint: str) -> int:
    m = re.fullmatch(r"tcp/127\.0\.0\.1:(\d{1,5})", endpoint)
    if not m or not 0 < int(m.group(1)) < 65536:
        raise ConfigError(f"--listen must be tcp/127.0.0.1:PORT (loopback only), got {endpoint!r}")
    return int(m.group(1))


def check_port_free(port: int) -> None:
    """ConfigError when something listens on 127.0.0.1:``port`` already (another demo, a zenoh
    router): said at once, before the scene is rendered, not after."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a closed port's TIME_WAIT is free
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise ConfigError(
                f"tcp/127.0.0.1:{port} is in use ({exc.strerror}: another pugsd demo or a zenoh "
                "router?); choose another port with --listen tcp/127.0.0.1:PORT"
            ) from None


def figure_result(outputs: Any) -> Any:
    """The result the demo draws: the last one whose cloud went out (sigma^2_occ on the whole
    cloud), else the last one (a round stopped at shutdown computes sigma^2_occ at its grasps only)."""
    complete = outputs.latest_cloud_result
    return complete if complete is not None else outputs.latest_result


def no_figure_reason(grasps_published: int, resets: int) -> str:
    """Why the demo wrote no ``grasps.png``: the model never got ready, or a reset (``pugsd
    reset`` from another shell) cleared the map after its grasps and no frame came since."""
    if grasps_published and resets:
        return (
            f"no PNG written: the map was reset after {grasps_published} grasp update(s) "
            "(pugsd reset) and no frame came since, so there are no grasps to draw"
        )
    return "no grasps were computed (model not ready); no PNG written"


@dataclass
class GraspPrinter:
    """Prints the top grasps whenever the ranking improves or changes."""

    write: Writer
    t0: float
    first_s: float | None = None
    received: int = 0
    best: float = -1.0
    last_ident: tuple[int, ...] = ()
    last_print_s: float = 0.0
    history: list[tuple[float, int, float]] = field(default_factory=list)

    def on_grasps(self, data: bytes) -> None:
        self.received += 1
        try:
            g = codec.decode_grasp_array(data)
        except PugsdError as exc:
            self.write(f"  (undecodable GraspArray: {exc})")
            return
        t = time.monotonic() - self.t0
        if len(g) == 0:  # a reset's empty array (or none found): said once, after grasps were shown
            if self.last_ident:
                self.write(f"[{t:6.1f} s] no grasps (the map was reset, or none were found)")
                self.best, self.last_ident, self.last_print_s = -1.0, (), t
            return
        if self.first_s is None:
            self.first_s = t
            self.write(f"[{t:6.1f} s] first scored grasps")
        top = float(g.pugs_confidence[0])
        self.history.append((t, len(g), top))
        ident = tuple(np.round(g.contact_W[: min(3, len(g))] / 0.005).astype(int).ravel())
        changed = abs(top - self.best) > 0.05 * max(abs(self.best), 1e-300)
        if ident != self.last_ident or changed or t - self.last_print_s > 15:
            self.best = top
            self.last_ident = ident
            self.last_print_s = t
            self.write(f"[{t:6.1f} s] {len(g)} grasps, best first:")
            for line in grasp_lines(g, 3, codec.grasp_array_frame_id(data)):
                self.write("  " + line)


def render_scene(object_name: str, n_frames: int, width: int, height: int, seed: int) -> list[StereoFrame]:
    """The synthetic world's stereo sequence (all around the object)."""
    from pugsd.sim.sequence import make_sequence  # trimesh and the renderer: only for the demo

    seq = make_sequence(object_name, "complete", n_frames=n_frames, width=width, height=height, seed=seed)
    return list(seq.frames)


def save_figure(result: Any, path: Path, top_k: int = 5, gripper_depth_m: float = 0.09) -> None:
    """The fused cloud coloured by sigma^2_occ and the top grasps (PUGS-ranked) as grippers; points
    whose sigma^2_occ was not computed (NaN: a round without the whole cloud) are drawn grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    cloud = np.asarray(result.cloud_W)
    s2 = np.asarray(result.sigma2_occ)
    fig = plt.figure(figsize=(8, 7))
    ax: Any = fig.add_subplot(111, projection="3d")
    known = np.isfinite(s2)
    pos = s2[known & (s2 > 0)]
    norm = LogNorm(vmin=float(pos.min()), vmax=float(pos.max())) if pos.size else None
    if not known.all():
        rest = cloud[~known]
        ax.scatter(rest[:, 0], rest[:, 1], rest[:, 2], s=1, color="0.7", label="sigma^2_occ not computed")
        ax.legend(loc="upper left")
    sc = ax.scatter(
        cloud[known, 0],
        cloud[known, 1],
        cloud[known, 2],
        c=np.clip(s2[known], 1e-30, None),
        s=2,
        cmap="viridis",
        norm=norm,
    )
    fig.colorbar(sc, ax=ax, shrink=0.6, label="sigma^2_occ (Algorithm 1)")
    g = result.grasps
    for i in range(min(top_k, len(g))):
        seg = codec.gripper_lines(g.pose_W[i], float(g.width_m[i]), gripper_depth_m)
        best = float(np.max(g.pugs_confidence)) or 1.0
        color = codec.confidence_color(float(g.pugs_confidence[i]) / best)
        for a, b in zip(seg[0::2], seg[1::2]):
            ax.plot(*zip(a, b), color=color, linewidth=2)
        ax.text(*g.contact_W[i], f"{i + 1}", color="black")
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.5 * float((hi - lo).max()) + 0.03
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"PUGS: top {min(top_k, len(g))} grasps on the fused cloud (model v{result.model_version})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def demo_config(listen: str, overrides: Sequence[str]) -> PugsdConfig:
    port = parse_loopback_port(listen)
    base: dict[str, Any] = {
        "stereo": {"downsample": 2},
        "daemon": {"grasp_rate_hz": 1.0, "log_level": "warning"},
        "queues": {"depth": 16},  # one sweep: keep every view while the model warms up
        "zenoh": loopback_config(port),
    }
    return load_config_dict(base, overrides)


async def _demo_main(
    cfg: PugsdConfig,
    render: Callable[[], list[StereoFrame]],
    duration_s: float,
    out_dir: Path,
    rate_hz: float,
    write: Writer,
    t_start: float,
    sweeps: int,
) -> tuple[Daemon, GraspPrinter, list[Path], dict[str, Any]]:
    from pugsd.pipeline_factory import make_pipeline
    from pugsd.record.recorder import Recorder
    from pugsd.wire.topics import topic_types

    port = parse_loopback_port(cfg.zenoh["listen"]["endpoints"][0])
    rendering = asyncio.create_task(asyncio.to_thread(render))  # overlaps the daemon's start-up
    daemon = Daemon(cfg, make_pipeline(core_of(cfg)))
    apply_thread_limits(cfg)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    serve = asyncio.create_task(daemon.run(stop), name="daemon")
    while not daemon.serving:
        if serve.done():  # it failed to start (raised here), or a signal stopped it while starting
            try:
                await serve
            finally:
                for sig in (signal.SIGTERM, signal.SIGINT):
                    loop.remove_signal_handler(sig)
            rendering.cancel()
            write("interrupted while the daemon started; shutting down")
            none_sent = {"frames_sent": 0, "max_put_s": 0.0, "recorder": None}
            return daemon, GraspPrinter(write, t_start), [], none_sent
        await asyncio.sleep(0.01)
    peer = open_session(loopback_config(None, [port]), require_loopback=True)
    printer = GraspPrinter(write, t_start)
    recorder = Recorder(
        cfg.record, directory=out_dir, queue_size=4096, topic_types=topic_types(cfg.topics)
    ).start()
    stop_camera = threading.Event()
    cam_thread: threading.Thread | None = None
    camera = SyntheticCamera(peer, cfg.topics)
    sub: Any = None
    put_worst = [0.0]
    try:
        recorder.subscribe(peer, [f"{cfg.topics.domain_id}/**"])
        sub = peer.declare_subscriber(
            key_for(cfg.topics, "grasps"),
            lambda s: loop.call_soon_threadsafe(printer.on_grasps, s.payload.to_bytes()),
        )
        frames = await rendering
        write(f"[{time.monotonic() - t_start:6.1f} s] rendered {len(frames)} views; daemon serving")

        def run_camera() -> None:
            if not camera.wait_matching(10.0, stop_camera):
                if stop_camera.is_set():
                    return
                log.warning("camera: the daemon's subscriptions did not match within 10 s")
            i = 0
            next_t = time.monotonic()
            # stamps on an exact 1 / rate_hz grid, as a camera's clock would give: with wall-clock
            # jitter a 2 Hz pose stream came 0.495-0.505 s apart, against daemon.pose_max_gap_s
            # (0.5 s), and a looped replay of its recording lost frames to "stray" poses
            t0_ns, period_ns = time.time_ns(), round(1e9 / rate_hz)
            while not stop_camera.is_set() and (sweeps <= 0 or i < sweeps * len(frames)):
                worst = camera.publish(frames[i % len(frames)], t0_ns + i * period_ns)
                put_worst[0] = max(put_worst[0], worst)
                i += 1
                next_t += 1.0 / rate_hz
                stop_camera.wait(max(0.0, next_t - time.monotonic()))
            msg = (
                f"[{time.monotonic() - t_start:6.1f} s] camera done: {i} frames; training on "
                "(the daemon will log the camera's streams as silent: expected here)"
            )
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(write, msg)

        cam_thread = threading.Thread(target=run_camera, name="demo-camera", daemon=True)
        cam_thread.start()
        write(
            f"[{time.monotonic() - t_start:6.1f} s] camera publishing {len(frames)} views "
            f"at {rate_hz:g} Hz" + (f", {sweeps} sweep(s)" if sweeps > 0 else " in a loop")
        )
        stopped = asyncio.create_task(stop.wait())
        try:  # until the duration is over, a signal comes, or the daemon has failed
            await asyncio.wait({stopped, serve}, timeout=duration_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopped.cancel()
        if serve.done():
            write("the daemon stopped; shutting down")
        elif stop.is_set():
            write("interrupted; shutting down")
    finally:
        stop_camera.set()
        if cam_thread is not None:  # it never waits on this loop: a plain join cannot deadlock
            cam_thread.join(5.0)
            if cam_thread.is_alive():
                log.warning("camera: its thread did not stop within 5 s (a put blocked?); going on")
        stop.set()
        try:
            await serve  # re-raises the daemon's failure, after the clean-up below
        finally:
            if sub is not None:
                with contextlib.suppress(Exception):
                    sub.undeclare()
            with contextlib.suppress(Exception):
                camera.close()
            try:
                files = recorder.stop(timeout=10.0)  # finishes the MCAP (no .part left behind)
            finally:
                close_session(peer)
                for sig in (signal.SIGTERM, signal.SIGINT):
                    loop.remove_signal_handler(sig)
    extra = {"frames_sent": camera.sent, "max_put_s": put_worst[0], "recorder": recorder.stats}
    return daemon, printer, files, extra


def run_demo(
    duration_s: float = 60.0,
    out_dir: str | Path = "pugsd-demo",
    listen: str = "tcp/127.0.0.1:7447",
    overrides: Sequence[str] = (),
    write: Writer = lambda s: None,
    *,
    object_name: str = "mug",
    n_frames: int = 12,
    width: int = 320,
    height: int = 240,
    rate_hz: float = 2.0,
    sweeps: int = 1,
) -> int:
    """Run the demo for ``duration_s``; returns 0 when scored grasps were received."""
    cfg = demo_config(listen, overrides)
    check_port_free(parse_loopback_port(listen))
    # the simulation extras it needs (the renderer's trimesh, the figure's matplotlib): a missing
    # one is said now, not once the daemon serves
    for module in ("pugsd.sim.sequence", "matplotlib"):
        importlib.import_module(module)
    apply_malloc_arena_max(cfg.daemon.malloc_arena_max)  # before the daemon's threads start
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    write(f"pugsd demo: zenoh peer listening on {listen} (loopback only; multicast scouting off)")
    write(f"  grasps:  {key_for(cfg.topics, 'grasps')}")
    write(f"  markers: {key_for(cfg.topics, 'markers')}")
    write(f"  cloud:   {key_for(cfg.topics, 'cloud')}")
    write(f"  query:   {cfg.daemon.prefix}/grasps/latest   status: {cfg.daemon.prefix}/status")
    write(
        f"rendering a synthetic {object_name} from {n_frames} views ({width}x{height}) while "
        "the daemon starts..."
    )

    def render() -> list[StereoFrame]:
        return render_scene(object_name, n_frames, width, height, seed=0)

    daemon, printer, files, extra = asyncio.run(
        _demo_main(cfg, render, duration_s, out, rate_hz, write, t_start, sweeps)
    )
    st = daemon.status()
    c = st["counts"]
    mb = st["mailboxes"]
    ingress = st["ingress"]["dropped"]  # messages, not frames: reported on their own
    write(
        f"frames sent {extra['frames_sent']}, integrated {c.get('integrated', 0)}, dropped "
        f"{daemon.dropped_total() - ingress} (newest frame wins: stereo queue "
        f"{mb['stereo']['dropped']}, depth queue {mb['depth']['dropped']}; no pose/reset/duplicate "
        f"{c.get('dropped', 0)}, unpaired halves {st['waiting']['unpaired_dropped']}), messages "
        f"dropped at the ingress bound {ingress}, rejected "
        f"{c.get('rejected', 0)}, lost before the daemon {sum(st['upstream']['lost'].values())}, "
        f"grasp updates {daemon.outputs.grasps_published}; "
        f"slowest zenoh put {1e3 * extra['max_put_s']:.2f} ms"
    )
    lat = st["latency"]
    write(
        "stage times p50/max [ms]: "
        + ", ".join(f"{k} {v['p50_ms']:.0f}/{v['max_ms']:.0f}" for k, v in lat.items() if "p50_ms" in v)
    )
    if printer.first_s is not None:
        write(f"time to first scored grasps: {printer.first_s:.1f} s after the command started")
    for f in files:
        write(f"MCAP: {f}")
    drawn = figure_result(daemon.outputs)
    if drawn is not None and len(drawn.cloud_W):
        png = out / "grasps.png"
        save_figure(drawn, png, gripper_depth_m=cfg.grasp.gripper.depth_m)
        write(f"PNG:  {png}")
    else:
        write(no_figure_reason(daemon.outputs.grasps_published, c.get("resets", 0)))
    return 0 if printer.first_s is not None else 1
