# SPDX-License-Identifier: Apache-2.0
"""The measurements of ``pugsd bench``: per-stage latency, paper versus streaming, sustained
throughput and a long replay through the daemon, memory, and the machine.

Everything here returns plain data; progress lines go to the ``write`` callable passed in by the
CLI (nothing prints below the CLI layer).
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import resource
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import psutil
import torch

from pugsd.bench.options import BenchOptions
from pugsd.config import CoreConfig, PugsdConfig
from pugsd.core.pipeline import PipelineResult, PugsPipeline
from pugsd.core.types import ScoredGrasps, StereoFrame
from pugsd.stream.schedule import idle_rate_scale

Writer = Callable[[str], None]


# ---------------------------------------------------------------------------------- helpers
def summarize(values_s: Sequence[float]) -> dict[str, float | int | None]:
    """Median, p95 and max in milliseconds of durations given in seconds."""
    a = np.asarray([v for v in values_s if np.isfinite(v)], dtype=np.float64) * 1e3
    if len(a) == 0:
        return {"n": 0, "median_ms": None, "p95_ms": None, "max_ms": None}
    return {
        "n": len(a),
        "median_ms": round(float(np.median(a)), 3),
        "p95_ms": round(float(np.percentile(a, 95)), 3),
        "max_ms": round(float(a.max()), 3),
    }


def rss_mb() -> float:
    return float(psutil.Process().memory_info().rss) / 2**20


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (Linux: ru_maxrss is in KiB)."""
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) / 1024.0


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_info(device: str) -> dict[str, Any]:
    info: dict[str, Any] = {
        "cpu_model": cpu_model(),
        "logical_cores": os.cpu_count(),
        "affinity_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "memory_gb": round(psutil.virtual_memory().total / 2**30, 1),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "omp_num_threads_env": os.environ.get("OMP_NUM_THREADS"),
        "device": device,
        "cuda_available": torch.cuda.is_available(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
        # the float arithmetic the SVGP runs on: the agreement figures move with it
        "torch_cpu_capability": str(torch.backends.cpu.get_cpu_capability()),  # torch >= 2.1
        "packages": _package_versions(
            ("numpy", "scipy", "gpytorch", "linear_operator", "opencv-python-headless", "open3d")
        ),
    }
    if torch.cuda.is_available():
        info["cuda_device"] = torch.cuda.get_device_name(0)
    return info


def _package_versions(names: Sequence[str]) -> dict[str, str | None]:
    from importlib import metadata

    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def restamp(frame: StereoFrame, stamp_ns: int) -> StereoFrame:
    return dataclasses.replace(frame, stamp_ns=stamp_ns)


def render_sequences(opts: BenchOptions) -> tuple[dict[str, list[StereoFrame]], dict[str, Any]]:
    """Render each trajectory once (rendering is not part of what is measured)."""
    from pugsd.sim import make_sequence

    out: dict[str, list[StereoFrame]] = {}
    overrides: dict[str, Any] = {}
    for traj in opts.trajectories:
        seq = make_sequence(
            opts.object_name, traj, n_frames=opts.n_frames, width=opts.width, height=opts.height,
            seed=opts.seed,
        )  # fmt: skip
        period = round(1e9 / opts.rate_hz)
        out[traj] = [restamp(f, (i + 1) * period) for i, f in enumerate(seq.frames)]
        overrides[traj] = dict(seq.core_overrides)
    return out, overrides


# ---------------------------------------------------------------------------------- streaming
@dataclasses.dataclass
class StreamRun:
    samples: dict[str, list[float]]
    result: PipelineResult
    last_frame_to_grasps_s: float
    last_frame_to_cloud_s: float
    extra_steps_after_last_frame: int
    ready: bool
    was_ready_before_last_frame: bool
    steps_total: int
    points: int
    voxels: int
    pipe: PugsPipeline


def _ingest(pipe: PugsPipeline, frame: StereoFrame, samples: dict[str, list[float]]) -> None:
    t0 = time.perf_counter()
    depth = pipe.depth_from_stereo(frame)
    t1 = time.perf_counter()
    pipe.integrate(depth)
    t2 = time.perf_counter()
    tm = pipe.timings_s
    samples["stereo_depth"].append(t1 - t0)
    samples["backproject"].append(tm["backproject"])
    samples["fof_update"].append(tm["fof"])
    samples["tsdf"].append(tm["tsdf"])
    samples["ingest"].append(t1 - t0 + tm["backproject"] + tm["fof"])
    samples["ingest_with_tsdf"].append(t2 - t0)


def _add_compute(res: PipelineResult, samples: dict[str, list[float]]) -> None:
    t = res.timings_s
    samples["query_cloud"].append(t["cloud"])
    samples["grasp_proposal"].append(t["propose"])
    samples["algorithm1"].append(t["algorithm1"])
    if "algorithm1_cloud" in t:
        samples["algorithm1_cloud"].append(t["algorithm1_cloud"])
        samples["algorithm1_query_cloud"].append(t["algorithm1"] + t["algorithm1_cloud"])
    samples["eq13"].append(t["eq13"])


def run_streaming(
    core: CoreConfig, frames: list[StereoFrame], opts: BenchOptions, steps_per_frame: int,
    idle_steps: int, ready_latch: bool = True,
) -> StreamRun:  # fmt: skip
    """The daemon's model path, synchronously: each frame is ingested and followed by
    ``steps_per_frame`` SVGP steps. After the last frame: its ingest and steps; then, as the
    daemon does, grasps are computed at once if the model is ready, or was ready before and
    ``ready_latch`` holds (the daemon's default); otherwise idle rounds of ``idle_steps`` run
    until the readiness criterion holds (the daemon publishes nothing before). Grasps first
    (Algorithm 1 at the contacts, Eq. 13), then the rest of the query cloud; the latency is taken
    at the grasps, the cloud's completion is timed as well. The pipeline is warmed up first, as
    the daemon's is before it serves."""
    pipe = PugsPipeline(core, seed=opts.seed)
    pipe.warm_up()
    samples: dict[str, list[float]] = defaultdict(list)
    was_ready = False
    for f in frames[:-1]:
        _ingest(pipe, f, samples)
        t0 = time.perf_counter()
        pipe.train_steps(steps_per_frame)
        samples["train_per_frame"].append(time.perf_counter() - t0)
        was_ready = was_ready or pipe.ready
    t_arrival = time.perf_counter()
    _ingest(pipe, frames[-1], samples)
    t0 = time.perf_counter()
    pipe.train_steps(steps_per_frame)
    samples["train_per_frame"].append(time.perf_counter() - t0)
    extra = 0
    publishable = pipe.ready or (ready_latch and was_ready)
    while not publishable and time.perf_counter() - t_arrival < opts.ready_timeout_s:
        pipe.train_steps(idle_steps)
        extra += idle_steps
        publishable = pipe.ready
    res = pipe.compute(full_cloud=False)
    elapsed = time.perf_counter() - t_arrival
    res = pipe.complete_cloud(res)
    cloud_elapsed = time.perf_counter() - t_arrival
    _add_compute(res, samples)
    return StreamRun(
        samples=samples,
        result=res,
        last_frame_to_grasps_s=elapsed,
        last_frame_to_cloud_s=cloud_elapsed,
        extra_steps_after_last_frame=extra,
        ready=pipe.ready,
        was_ready_before_last_frame=was_ready,
        steps_total=pipe.svgp.total_steps,
        points=pipe.points,
        voxels=len(pipe.store),
        pipe=pipe,
    )


def idle_refinement(
    run: StreamRun, steps: Sequence[int], decay_steps: int = 0
) -> list[tuple[int, float, np.ndarray]]:
    """What the daemon publishes while it trains on after the last frame (idle rounds, for
    ``daemon.idle_train_s``): sigma2_occ on the streaming run's query cloud after each cumulative
    number of extra SVGP steps, with the training time they took. The i-th extra step runs at the
    daemon's idle rate scale (:func:`~pugsd.stream.schedule.idle_rate_scale` of
    ``daemon.idle_rate_decay_steps``; 0: constant rates). Trains ``run.pipe`` on."""
    out: list[tuple[int, float, np.ndarray]] = []
    done, train_s = 0, 0.0
    for k in sorted(steps):
        t0 = time.perf_counter()
        for i in range(done, k):
            run.pipe.train_steps(1, rate_scale=idle_rate_scale(i, decay_steps))
        train_s += time.perf_counter() - t0
        done = k
        _, s2 = run.pipe.sigma2_occ(run.result.cloud_W)
        out.append((k, train_s, s2))
    return out


def steady_state_cycles(
    run: StreamRun, frames: list[StereoFrame], opts: BenchOptions, steps_per_frame: int
) -> None:
    """Single SVGP steps and newest-frame -> grasps cycles on the trained streaming model."""
    pipe, samples = run.pipe, run.samples
    for _ in range(opts.svgp_step_repeats):
        t0 = time.perf_counter()
        pipe.train_steps(1)
        samples["svgp_step"].append(time.perf_counter() - t0)
    stamp = max(f.stamp_ns for f in frames)
    period = round(1e9 / opts.rate_hz)
    for i in range(opts.compute_repeats):
        stamp += period
        f = restamp(frames[i % len(frames)], stamp)
        t0 = time.perf_counter()
        _ingest(pipe, f, samples)
        pipe.train_steps(steps_per_frame)
        res = pipe.compute(full_cloud=False)
        samples["end_to_end"].append(time.perf_counter() - t0)
        _add_compute(pipe.complete_cloud(res), samples)


def svgp_thread_sweep(run: StreamRun, threads: Sequence[int], repeats: int) -> dict[str, Any]:
    """Median single SVGP step (the pipeline's ``train_steps(1)``) at several torch thread counts."""
    before = torch.get_num_threads()
    out: dict[str, Any] = {}
    try:
        for n in threads:
            torch.set_num_threads(n)
            ts = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                run.pipe.train_steps(1)
                ts.append(time.perf_counter() - t0)
            out[str(n)] = summarize(ts)
    finally:
        torch.set_num_threads(before)
    return out


# ---------------------------------------------------------------------------------- paper mode
def run_paper(
    core: CoreConfig, frames: list[StereoFrame], cloud_W: np.ndarray, opts: BenchOptions
) -> tuple[PipelineResult, float, int, PugsPipeline]:
    """The paper's batch pipeline on the same frames: ingest everything (no training while frames
    arrive), then after the last frame a fresh SVGP, Adam lr 1e-3, ``paper_epochs`` epochs, and
    compute on the given query cloud. Returns (result, last frame -> grasps [s], SVGP steps, the
    pipeline). Warmed up first, as the streaming run."""
    pipe = PugsPipeline(core, seed=opts.seed)
    pipe.warm_up()
    for f in frames[:-1]:
        pipe.add_stereo(f)
    t_arrival = time.perf_counter()
    pipe.add_stereo(frames[-1])
    stats = pipe.fit_paper(opts.paper_epochs)
    res = pipe.compute(cloud_W=cloud_W, full_cloud=False)  # the same grasps-first path
    elapsed = time.perf_counter() - t_arrival
    return pipe.complete_cloud(res), elapsed, int(stats.steps), pipe


@dataclasses.dataclass
class OptimalQ:
    """A fitted model's q(u) set to its closed-form optimum (same hyperparameters and Z)."""

    elbo_before: float  # full-data ELBO per point, as fitted
    elbo_after: float  # at the optimal q(u)
    sigma2_occ: np.ndarray  # Algorithm 1 on the query cloud with the optimal q(u)


def optimal_q(pipe: PugsPipeline, cloud_W: np.ndarray, restore: bool = False) -> OptimalQ:
    """Converge ``pipe``'s q(u) in closed form and take sigma2_occ on ``cloud_W``. With
    ``restore`` the model is put back as it was afterwards (its state dict)."""
    saved = pipe.svgp.state() if restore else None
    before, after = pipe.set_optimal_q()
    _, s2 = pipe.sigma2_occ(cloud_W)
    if saved is not None:
        pipe.svgp.load_state(saved)
    return OptimalQ(before, after, s2)


def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
    from scipy.stats import spearmanr

    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return None
    return float(spearmanr(a, b).statistic)


def same_top_grasp(a: PipelineResult, b: PipelineResult) -> bool | None:
    ga, gb = a.grasps, b.grasps
    if len(ga) == 0 or len(gb) == 0:
        return None
    return bool(np.allclose(ga.pose_W[0], gb.pose_W[0], atol=1e-9) and
                np.isclose(ga.width_m[0], gb.width_m[0]))  # fmt: skip


def topk_overlap(a: PipelineResult, b: PipelineResult, k: int = 5) -> float | None:
    ga, gb = a.grasps, b.grasps
    n = min(k, len(ga), len(gb))
    if n == 0:
        return None
    ca, cb = ga.contact_W[:n], gb.contact_W[:n]
    d = np.linalg.norm(ca[:, None, :] - cb[None, :, :], axis=-1)
    return float(np.mean(d.min(axis=1) < 1e-9))


# ---------------------------------------------------------------------------------- daemon runs
class _RssTrace:
    def __init__(self) -> None:
        self.points: list[tuple[float, float]] = []  # (simulated s, RSS MiB)

    def add(self, sim_s: float) -> None:
        self.points.append((sim_s, rss_mb()))

    def floor(self, sim_s: float, window_s: float) -> float | None:
        """Lowest RSS in the ``window_s`` of simulated time ending at ``sim_s``: the resident
        baseline without the transient buffers of a grasp computation (a leak raises it)."""
        v = [r for s, r in self.points if sim_s - window_s <= s <= sim_s + 1e-9]
        return min(v) if v else None

    def peak(self, t0_s: float, t1_s: float) -> float | None:
        v = [r for s, r in self.points if t0_s <= s <= t1_s + 1e-9]
        return max(v) if v else None


def daemon_config(base: PugsdConfig, port: int) -> PugsdConfig:
    """The run's config with a loopback-only zenoh peer listening on ``port``."""
    from pugsd.wire.session import loopback_config

    return dataclasses.replace(base, zenoh=loopback_config(port))  # type: ignore[type-var]


def _assert_loopback(cfg: dict[str, Any]) -> None:
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["scouting"]["gossip"]["enabled"] is False
    for ep in list(cfg["listen"]["endpoints"]) + list(cfg["connect"]["endpoints"]):
        assert str(ep).startswith("tcp/127.0.0.1:"), ep


def daemon_feed(
    base: PugsdConfig,
    frames: list[StereoFrame],
    n_offer: int,
    interval_s: float,
    drain_timeout_s: float,
    wall_cap_s: float | None = None,
    sim_period_s: float = 0.1,
    rss: _RssTrace | None = None,
    grasps_timeout_s: float = 0.0,
    cloud_timeout_s: float = 0.0,
    steady_s: float = 0.0,
) -> dict[str, Any]:
    """Run the real daemon in-process (loopback zenoh), offer ``n_offer`` stereo frames (cycling
    ``frames`` with fresh stamps) every ``interval_s`` (0: as fast as possible), wait for the
    pipeline to drain, and return the daemon's counters and latencies. With ``grasps_timeout_s``
    the run also subscribes to the daemon's GraspArray and waits that long for the grasps of the
    last frame offered (header stamp = that frame's stamp): ``last_frame_to_grasps_s`` is the
    time from publishing that frame to receiving them (None if they did not come). With
    ``cloud_timeout_s`` as well it then waits that long for the PointCloud2 stamped with that
    frame (sigma2_occ over the daemon's query cloud, from the model that scored those grasps):
    ``last_frame_cloud`` (a decoded ``CloudMsg`` or None) and ``last_frame_to_cloud_s``.
    With ``steady_s`` the offer goes on past ``n_offer`` frames until the daemon's first
    GraspArray came ``steady_s`` before (within ``wall_cap_s``): the daemon in operation, its
    grasp rounds and clouds competing with the ingest, not only the warm-up before it is ready.
    ``first_grasps_after_s`` (from the first frame offered; None: none came) and
    ``fed_after_first_grasps_s`` say how much of the offer that covered."""
    import asyncio
    import threading

    from pugsd.config import core_of
    from pugsd.daemon.app import Daemon
    from pugsd.daemon.demo import SyntheticCamera
    from pugsd.daemon.notify import Notifier
    from pugsd.wire import codec
    from pugsd.wire.session import close_session, free_tcp_port, loopback_config, open_session
    from pugsd.wire.topics import key_for

    port = free_tcp_port()
    cfg = daemon_config(base, port)
    _assert_loopback(cfg.zenoh)
    out: dict[str, Any] = {}

    async def main() -> None:
        pipe = PugsPipeline(core_of(cfg))
        daemon = Daemon(cfg, pipe, notifier=Notifier(""))
        stop = asyncio.Event()
        serve = asyncio.create_task(daemon.run(stop), name="daemon")
        t_start = time.monotonic()
        while not daemon.serving:
            if serve.done():
                await serve
            if time.monotonic() - t_start > 30.0:
                raise RuntimeError("daemon did not start within 30 s")
            await asyncio.sleep(0.01)
        peer_cfg = loopback_config(None, [port])
        _assert_loopback(peer_cfg)
        peer = open_session(peer_cfg, require_loopback=True)
        camera = SyntheticCamera(peer, cfg.topics)
        sent = [0]
        t_feed = [0.0, 0.0]
        last_sent: list[tuple[float, int]] = []  # (monotonic time, stamp) of the last frame
        # (receipt time, the GraspArray, the model's training steps so far at receipt)
        grasps_rx: list[tuple[float, ScoredGrasps, int]] = []
        first_grasps_t: list[float] = []
        sub = None
        if grasps_timeout_s > 0 or steady_s > 0:

            def on_grasps(sample: Any) -> None:
                g = codec.decode_grasp_array(sample.payload.to_bytes())
                now = time.monotonic()
                if not first_grasps_t:
                    first_grasps_t.append(now)
                if grasps_timeout_s > 0:
                    grasps_rx.append((now, g, pipe.svgp.total_steps))  # a plain int read

            sub = peer.declare_subscriber(key_for(cfg.topics, "grasps"), on_grasps)
        clouds_rx: list[tuple[float, Any, int]] = []
        sub_cloud = None
        if grasps_timeout_s > 0 and cloud_timeout_s > 0:

            def on_cloud(sample: Any) -> None:
                c = codec.decode_cloud(sample.payload.to_bytes())
                clouds_rx.append((time.monotonic(), c, pipe.svgp.total_steps))

            sub_cloud = peer.declare_subscriber(key_for(cfg.topics, "cloud"), on_cloud)

        def feed() -> None:
            if not camera.wait_matching(10.0):
                raise RuntimeError("the daemon's subscriptions did not match within 10 s")
            t0 = time.monotonic()
            t_feed[0] = t0
            next_t = t0
            i = 0
            while i < n_offer or (
                steady_s > 0 and not (first_grasps_t and time.monotonic() - first_grasps_t[0] >= steady_s)
            ):
                stamp = time.time_ns()
                t_pub = time.monotonic()
                camera.publish(frames[i % len(frames)], stamp)
                last_sent[:] = [(t_pub, stamp)]
                sent[0] += 1
                if rss is not None and (i % 10 == 0 or i == n_offer - 1):
                    rss.add((i + 1) * sim_period_s)
                if wall_cap_s is not None and time.monotonic() - t0 > wall_cap_s:
                    break
                if interval_s > 0:
                    next_t += interval_s
                    time.sleep(max(0.0, next_t - time.monotonic()))
                i += 1
            t_feed[1] = time.monotonic()

        feeder_error: list[BaseException] = []

        def feed_guarded() -> None:
            try:
                feed()
            except BaseException as exc:
                feeder_error.append(exc)

        th = threading.Thread(target=feed_guarded, name="bench-camera", daemon=True)
        th.start()
        await asyncio.to_thread(th.join)
        # drain: wait until nothing is queued (messages handed over by zenoh's callback threads
        # but not yet taken by the loop included) and the integrated count stops moving
        t_d = time.monotonic()
        last, still_since = -1, time.monotonic()
        while time.monotonic() - t_d < drain_timeout_s:
            st = daemon.status()
            n = int(st["counts"].get("integrated", 0))
            queued = drain_queued(st)
            if n != last:
                last, still_since = n, time.monotonic()
            if queued == 0 and not st["waiting"]["pose_gate"] and time.monotonic() - still_since > 1.0:
                break
            await asyncio.sleep(0.1)
        if grasps_timeout_s > 0 and last_sent:
            t_last, stamp_last = last_sent[0]
            t_w = time.monotonic()
            while time.monotonic() - t_w < grasps_timeout_s:
                if any(g.stamp_ns >= stamp_last for _, g, _ in grasps_rx):
                    break
                await asyncio.sleep(0.01)
            grasps_seen = len(grasps_rx)
            if sub_cloud is not None:
                t_w = time.monotonic()
                while time.monotonic() - t_w < cloud_timeout_s:
                    if any(c.stamp_ns >= stamp_last for _, c, _ in clouds_rx):
                        break
                    await asyncio.sleep(0.01)
            out.update(last_frame_outputs(list(grasps_rx), list(clouds_rx), t_last, stamp_last))
            out["grasps_received"] = grasps_seen
        if sub is not None:
            sub.undeclare()
        if sub_cloud is not None:
            sub_cloud.undeclare()
        st = daemon.status()
        out["status"] = st
        out["sent"] = sent[0]
        out["feed_wall_s"] = t_feed[1] - t_feed[0]
        out["first_grasps_after_s"] = first_grasps_t[0] - t_feed[0] if first_grasps_t else None
        out["fed_after_first_grasps_s"] = max(0.0, t_feed[1] - first_grasps_t[0]) if first_grasps_t else 0.0
        out["drain_s"] = time.monotonic() - t_d
        out["pipeline_stats"] = daemon.pipeline.stats()
        stop.set()
        await serve
        camera.close()
        close_session(peer)
        if feeder_error:
            raise feeder_error[0]

    asyncio.run(main())
    return out


def drain_queued(st: dict[str, Any]) -> int:
    """Messages the daemon still holds for integration (its status): the ingress queue from
    zenoh's callback threads and the stereo and depth mailboxes."""
    return (
        int(st["ingress"]["pending"])
        + int(st["mailboxes"]["stereo"]["queued"])
        + int(st["mailboxes"]["depth"]["queued"])
    )


def _drop_counts(st: dict[str, Any]) -> dict[str, int]:
    c = st["counts"]
    return {
        "stereo_mailbox": int(st["mailboxes"]["stereo"]["dropped"]),
        "depth_mailbox": int(st["mailboxes"]["depth"]["dropped"]),
        "ingress": int(st["ingress"]["dropped"]),
        "unpaired": int(st["waiting"]["unpaired_dropped"]),
        "unpaired_waiting": int(st["waiting"]["unpaired"]),  # halves whose partner never came
        "lost_before_daemon": sum(st["upstream"]["lost"].values()),  # sequence gaps
        # numbers below a publisher's first heard: the bench camera starts after the daemon
        # subscribed and matched, so these were lost on the way (zenoh's DROP lost a first frame)
        "lost_before_first_seen": sum(st["upstream"].get("before_first", {}).values()),
        "pose_wait_and_other": int(c.get("dropped", 0)),
        "rejected": int(c.get("rejected", 0)),
    }


def match_points(
    a_W: np.ndarray, b_W: np.ndarray, tol_m: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (ia, ib) of points of ``a_W`` and ``b_W`` that coincide within ``tol_m``
    (nearest neighbour, each point of ``b_W`` used once)."""
    from scipy.spatial import cKDTree

    if len(a_W) == 0 or len(b_W) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    d, ib = cKDTree(np.asarray(b_W, dtype=np.float64)).query(np.asarray(a_W, dtype=np.float64))
    ok = np.isfinite(d) & (d <= tol_m)
    ia, ib = np.flatnonzero(ok), ib[ok]
    _, first = np.unique(ib, return_index=True)
    return ia[first], ib[first]


def cloud_scored_grasps(grasps: ScoredGrasps, cloud: Any) -> bool | None:
    """Whether ``cloud`` (a decoded PointCloud2) came from the computation that scored ``grasps``.
    A grasp's id is the index of its contact's point in that computation's query cloud (what the
    cloud carries, in order), and the daemon fills the cloud's sigma2_occ around the values
    Algorithm 1 gave those points: the cloud carries each grasp's sigma2_occ at its id, to float32
    rounding; a later computation on a further-trained model carries other values there. None
    where it cannot be told (no grasps, an id outside the cloud, no sigma2_occ field)."""
    f = cloud.fields
    ids = np.asarray(grasps.grasp_id, dtype=np.int64)
    if len(grasps) == 0 or "sigma2_occ" not in f:
        return None
    s2 = np.asarray(f["sigma2_occ"], dtype=np.float32)
    if ids.min() < 0 or ids.max() >= len(s2):
        return None
    want = np.asarray(grasps.sigma2_occ, dtype=np.float64).astype(np.float32)
    return bool(np.allclose(s2[ids], want, rtol=1e-6, atol=0.0))


def last_frame_outputs(
    grasps_rx: Sequence[tuple[float, ScoredGrasps, int]],
    clouds_rx: Sequence[tuple[float, Any, int]],
    t_last: float,
    stamp_last: int,
) -> dict[str, Any]:
    """What a daemon run published for the last frame offered (stamp ``stamp_last``, published at
    monotonic ``t_last``), from the GraspArrays and PointCloud2s received, each as (receipt time,
    decoded message, the model's SVGP steps at receipt).

    The first GraspArray stamped with that frame gives ``last_frame_to_grasps_s`` and
    ``train_steps_at_grasps``. The first cloud stamped with it is ``last_frame_cloud`` only if it
    came from that same computation: while frames stream the daemon leaves the cloud out
    (``daemon.cloud_interval_s``), and then the first cloud for the frame comes from a later grasp
    round on a further-trained model. Such a cloud is ``later_cloud`` instead, with its own
    latency and step count. Told by the values (``cloud_scored_grasps``), or where the grasps
    cannot tell (none were proposed) by the order of receipt: the daemon publishes each round's
    grasps, then its cloud, then the next round's, on one session (in order), so the cloud is that
    round's if no other GraspArray came between the two."""
    out: dict[str, Any] = {
        "last_frame_to_grasps_s": None,
        "train_steps_at_grasps": None,
        "last_frame_cloud": None,
        "last_frame_to_cloud_s": None,
        "train_steps_at_cloud": None,
        "cloud_scored_first_grasps": None,
        "later_cloud": None,
    }
    first = next(((t, g, n) for t, g, n in grasps_rx if g.stamp_ns >= stamp_last), None)
    if first is not None:
        out["last_frame_to_grasps_s"] = first[0] - t_last
        out["train_steps_at_grasps"] = first[2]
    cl = next(((t, c, n) for t, c, n in clouds_rx if c.stamp_ns >= stamp_last), None)
    if cl is None:
        return out
    same = None
    if first is not None:
        same = cloud_scored_grasps(first[1], cl[1])
        if same is None:
            same = first[0] <= cl[0] and not any(first[0] < t <= cl[0] for t, _, _ in grasps_rx)
    out["cloud_scored_first_grasps"] = same
    if same is False:
        out["later_cloud"] = {"cloud": cl[1], "to_cloud_s": cl[0] - t_last, "train_steps": cl[2]}
    else:
        out["last_frame_cloud"] = cl[1]
        out["last_frame_to_cloud_s"] = cl[0] - t_last
        out["train_steps_at_cloud"] = cl[2]
    return out


def _cloud_agreement(cloud: Any, reference: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    """Spearman of a published cloud's sigma2_occ against the reference's on the points the two
    share (None below 95 % shared), with the point counts."""
    f = cloud.fields
    pts = np.stack([f["x"], f["y"], f["z"]], axis=1)
    ia, ib = match_points(pts, reference[0])
    share = len(ia) / max(len(reference[0]), 1)
    rho = None
    if "sigma2_occ" in f and share >= 0.95:
        rho = spearman(f["sigma2_occ"][ia].astype(np.float64), reference[1][ib])
    return {
        "points": len(pts),
        "reference_points": len(reference[0]),
        "shared_fraction": round(share, 4),
        "spearman_sigma2_occ": rho,
    }


def daemon_last_frame(
    base: PugsdConfig,
    frames: list[StereoFrame],
    opts: BenchOptions,
    write: Writer,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """The streaming target end to end: a fresh daemon fed one sequence (``n_frames`` at
    ``rate_hz``) over loopback zenoh; the time from publishing the last stereo pair to receiving
    the GraspArray stamped with it (the daemon's own readiness, latch and training schedule).

    ``reference`` (query cloud [m, world], sigma2_occ of the paper's fit there): the agreement of
    what the daemon published for the last frame, i.e. the PointCloud2 stamped with it that came
    from the computation that scored the first grasps for it (so its sigma2_occ is from the model
    that scored those grasps, checked at the grasp contacts), with the reference on the points the
    two clouds share (the same frames give the same query cloud). When that computation published
    no cloud (the daemon leaves it out while frames stream), the first cloud for the frame came
    from a later grasp round on a further-trained model: it is reported as ``later_cloud``, with
    its own step count, and gives no ``spearman_sigma2_occ``.

    The latency depends on where the last frame falls in the daemon's 1 Hz grasp rounds (one in
    flight finishes first), so ``daemon_repeats`` fresh daemons are fed the same sequence:
    ``last_frame_to_grasps_s`` is their median (a daemon whose grasps never came counts as
    slowest; None if that is the median), each run's in ``last_frame_to_grasps_runs_s``. The
    agreement is the first run's."""
    def feed(cloud_timeout_s: float = 0.0) -> dict[str, Any]:
        return daemon_feed(
            base, frames, len(frames), 1.0 / opts.rate_hz, opts.drain_timeout_s,
            grasps_timeout_s=opts.ready_timeout_s, cloud_timeout_s=cloud_timeout_s,
        )  # fmt: skip

    r = feed(opts.ready_timeout_s if reference is not None else 0.0)
    st = r["status"]
    runs = [r.get("last_frame_to_grasps_s")]
    runs += [feed().get("last_frame_to_grasps_s") for _ in range(opts.daemon_repeats - 1)]
    lat = median_latency(runs)
    agreement: dict[str, Any] | None = None
    if reference is not None:
        cloud = r.get("last_frame_cloud")
        later = r.get("later_cloud")
        agreement = {"cloud_received": cloud is not None, "spearman_sigma2_occ": None}
        if cloud is not None or later is not None:
            agreement["cloud_scored_first_grasps"] = r.get("cloud_scored_first_grasps")
        if cloud is not None:
            lc = r.get("last_frame_to_cloud_s")
            agreement["last_frame_to_cloud_s"] = None if lc is None else round(lc, 4)
            agreement["train_steps_at_cloud"] = r.get("train_steps_at_cloud")
            agreement.update(_cloud_agreement(cloud, reference))
        if later is not None:
            agreement["later_cloud"] = {
                "last_frame_to_cloud_s": round(later["to_cloud_s"], 4),
                "train_steps_at_cloud": later["train_steps"],
                **_cloud_agreement(later["cloud"], reference),
            }
    out = {
        "frames": r["sent"],
        "integrated": int(st["counts"].get("integrated", 0)),
        "drops": _drop_counts(st),
        "last_frame_to_grasps_s": None if lat is None else round(lat, 4),
        "last_frame_to_grasps_runs_s": [None if x is None else round(x, 4) for x in runs],
        "grasps_received": r.get("grasps_received", 0),
        "train_steps": int(st["counts"].get("train_steps", 0)),
        # SVGP steps done when the last frame's grasps arrived (those that scored them, or a few more)
        "train_steps_at_grasps": r.get("train_steps_at_grasps"),
        "ready": bool(st.get("ready")),
        "agreement_with_paper": agreement,
        # the daemon's own counters (received per topic, paired, depth, integrated, failures...)
        # and the sequence-number tracker: a frame missing without a drop is diagnosable
        "status_counts": dict(st["counts"]),
        "upstream": st.get("upstream"),
    }
    rho = None if agreement is None else agreement["spearman_sigma2_occ"]
    each = ", ".join("-" if x is None else f"{x:.2f}" for x in runs)
    write(
        f"  daemon, {r['sent']} frames at {opts.rate_hz:g} Hz: last frame -> its grasps "
        f"{'not received' if lat is None else f'{lat:.2f} s'}"
        + (f" (median of {len(runs)} fresh daemons: {each} s)" if len(runs) > 1 else "")
        + ("" if rho is None else f", its sigma2_occ vs the paper fit: spearman {rho:.3f}")
    )
    return out


def median_latency(runs: Sequence[float | None]) -> float | None:
    """The median of latencies where None (nothing came) counts as slower than any; None when
    the median is such a run."""
    if not runs:
        return None
    x = sorted(math.inf if v is None else v for v in runs)
    n = len(x)
    m = x[n // 2] if n % 2 else 0.5 * (x[n // 2 - 1] + x[n // 2])
    return None if math.isinf(m) else m


def throughput_daemon(
    base: PugsdConfig, frames: list[StereoFrame], opts: BenchOptions, write: Writer
) -> dict[str, Any]:
    """Highest offered input rate the daemon integrates without dropping a frame, in operation:
    each trial offers at least ``max(throughput_min_frames, rate * throughput_trial_s)`` frames and
    goes on until the daemon has published grasps for ``throughput_trial_s`` (the model becomes
    ready only after several seconds of input; before, no grasp round or cloud competes with the
    ingest), within ``ready_timeout_s`` more. A trial whose offer did not cover that is not held."""
    trials = []
    sustained: float | None = None
    for rate in sorted(opts.throughput_rates_hz, reverse=True):
        n = max(opts.throughput_min_frames, round(rate * opts.throughput_trial_s))
        t0 = time.monotonic()
        r = daemon_feed(
            base, frames, n, 1.0 / rate, opts.drain_timeout_s,
            wall_cap_s=n / rate + opts.throughput_trial_s + opts.ready_timeout_s,
            steady_s=opts.throughput_trial_s,
        )  # fmt: skip
        st = r["status"]
        drops = _drop_counts(st)
        integrated = int(st["counts"].get("integrated", 0))
        steady = r["fed_after_first_grasps_s"]
        in_operation = steady >= opts.throughput_trial_s
        held = integrated == r["sent"] and not any(drops.values()) and in_operation
        lat = st.get("latency", {})
        trial = {
            "rate_hz": rate,
            "offered": r["sent"],
            "integrated": integrated,
            "drops": drops,
            "held": held,
            "feed_wall_s": round(r["feed_wall_s"], 3),
            # the offer after the daemon's first grasps (held needs throughput_trial_s of it)
            "first_grasps_after_s": None
            if r["first_grasps_after_s"] is None
            else round(r["first_grasps_after_s"], 3),
            "fed_after_first_grasps_s": round(steady, 3),
            "drain_s": round(r["drain_s"], 3),
            "wall_s": round(time.monotonic() - t0, 3),
            "grasps_published": int(st.get("grasps_published", 0)),
            "ready": bool(st.get("ready")),
            "train_steps": int(st["counts"].get("train_steps", 0)),
            "latency": lat,
        }
        trials.append(trial)
        write(
            f"  throughput {rate:g} Hz: offered {r['sent']}, integrated {integrated}, "
            f"dropped {sum(drops.values())}, {steady:.1f} s of it after the first grasps -> "
            f"{'held' if held else 'not held'}"
        )
        if held:
            sustained = rate
            break
    return {"source": "daemon", "trials": trials, "sustained_hz": sustained}


def replay_daemon(
    base: PugsdConfig, frames: list[StereoFrame], opts: BenchOptions, write: Writer
) -> dict[str, Any]:
    """A long replay: ``replay_sim_min`` minutes of 10 Hz input offered faster than real time
    through the daemon (spread over ``replay_wall_s`` of wall time; whatever the daemon cannot take
    is dropped by its mailboxes, as in operation), cycling the frames with fresh stamps; RSS is
    sampled every 10 frames against simulated time (frames offered / rate)."""
    period = 1.0 / opts.rate_hz
    n = round(opts.replay_sim_min * 60.0 * opts.rate_hz)
    trace = _RssTrace()
    rss0 = rss_mb()
    r = daemon_feed(
        base, frames, n, opts.replay_wall_s / n, opts.drain_timeout_s,
        wall_cap_s=opts.replay_wall_cap_s,
        sim_period_s=period, rss=trace,
    )  # fmt: skip
    st = r["status"]
    sim_s = r["sent"] * period
    w0, w1 = opts.replay_window_min
    # one simulated minute before each mark (minutes 4-5 and 29-30), at least 20 frames
    win = max(60.0 * min(w0, w1 - w0) / 5.0, 20 * period)
    end = min(60.0 * w1, sim_s)
    a, b = trace.floor(60.0 * w0, win), trace.floor(end, win)
    growth = None if a is None or b is None else (b - a) / a
    pa, pb = trace.peak(60.0 * w0 - win, 60.0 * w0), trace.peak(end - win, end)
    peak_growth = None if pa is None or pb is None else (pb - pa) / pa
    out = {
        "source": "daemon",
        "frames_offered": r["sent"],
        "simulated_min": round(sim_s / 60.0, 3),
        "target_simulated_min": opts.replay_sim_min,
        "feed_wall_s": round(r["feed_wall_s"], 3),
        "speedup_vs_real_time": round(sim_s / max(r["feed_wall_s"], 1e-9), 2),
        "integrated": int(st["counts"].get("integrated", 0)),
        "train_steps": int(st["counts"].get("train_steps", 0)),
        "grasps_published": int(st.get("grasps_published", 0)),
        "ready_at_end": bool(st.get("ready")),
        "drops": _drop_counts(st),
        "voxels": r["pipeline_stats"].get("voxels"),
        "evicted": r["pipeline_stats"].get("evicted"),
        "rss_before_mb": round(rss0, 1),
        "window_min": [w0, w1],
        "rss_window_start_mb": None if a is None else round(a, 1),
        "rss_window_end_mb": None if b is None else round(b, 1),
        "rss_window_s": round(win, 1),
        "rss_growth_definition": "lowest RSS in the window before minute w1 over that before w0, "
        "minus 1 (the resident floor; transient grasp-computation buffers excluded)",
        "rss_growth_frac": None if growth is None else round(growth, 4),
        "rss_window_start_peak_mb": None if pa is None else round(pa, 1),
        "rss_window_end_peak_mb": None if pb is None else round(pb, 1),
        "rss_peak_growth_frac": None if peak_growth is None else round(peak_growth, 4),
        "rss_peak_during_mb": round(max((p[1] for p in trace.points), default=rss0), 1),
        "rss_trace": [
            [round(s / 60.0, 3), round(mb, 1)]
            for s, mb in trace.points[:: max(1, len(trace.points) // 60)]
        ],
    }
    write(
        f"  replay: {out['simulated_min']} simulated min in {out['feed_wall_s']} s, integrated "
        f"{out['integrated']}, RSS {out['rss_window_start_mb']} -> {out['rss_window_end_mb']} MiB"
    )
    return out
