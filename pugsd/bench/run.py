# SPDX-License-Identifier: Apache-2.0
"""One benchmark run: render, measure, compare, judge against the targets."""

from __future__ import annotations

import dataclasses
import datetime as dt
import os
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from pugsd.bench import measure as m
from pugsd.bench.options import BenchOptions
from pugsd.bench.targets import evaluate_targets
from pugsd.config import PugsdConfig, core_of, load_config_dict
from pugsd.core.predictive import NUM_INDUCING_AUTO_CPU, NUM_INDUCING_AUTO_CUDA, resolve_num_inducing
from pugsd.pipeline_factory import make_pipeline

SCHEMA = "pugsd-bench/1"

STAGE_ORDER = (
    "stereo_depth",
    "backproject",
    "fof_update",
    "tsdf",
    "ingest",
    "ingest_with_tsdf",
    "svgp_step",
    "train_per_frame",
    "query_cloud",
    "grasp_proposal",
    "algorithm1",
    "eq13",
    "algorithm1_cloud",
    "algorithm1_query_cloud",
    "end_to_end",
)


def resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def build_config(overrides: Sequence[str], device: str) -> PugsdConfig:
    ov = list(overrides)
    if not any(o.split("=", 1)[0].strip() == "svgp.device" for o in ov):
        ov.append(f"svgp.device={device}")
    return load_config_dict({"daemon": {"log_level": "warning"}}, ov)


def _with(cfg_overrides: Sequence[str], extra: dict[str, Any], device: str) -> PugsdConfig:
    ov = list(cfg_overrides) + [f"{k}={_toml(v)}" for k, v in extra.items()]
    return build_config(ov, device)


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


def _cuda_section(
    cfg_overrides: Sequence[str], frames: list[Any], opts: BenchOptions
) -> dict[str, Any]:
    """SVGP steps per second on CUDA versus CPU on the same store, at both automatic inducing-point
    counts (250: the CPU's, 500: CUDA's), and Algorithm 1 for 20k query points on CUDA at CUDA's
    (after one warm-up call). The target is judged at the M the daemon runs on CUDA."""
    out: dict[str, Any] = {}
    m_cuda = resolve_num_inducing(build_config(cfg_overrides, "cuda").svgp.num_inducing, "cuda")
    for m_ind in sorted({NUM_INDUCING_AUTO_CPU, NUM_INDUCING_AUTO_CUDA, m_cuda}):
        per_m: dict[str, Any] = {}
        for dev in ("cpu", "cuda"):
            cfg = build_config([*cfg_overrides, f"svgp.device={dev}", f"svgp.num_inducing={m_ind}"], dev)
            pipe = make_pipeline(core_of(cfg), seed=opts.seed)
            for f in frames:
                pipe.add_stereo(f)
            pipe.train_steps(1)  # initialises the model
            ts = []
            for _ in range(max(opts.svgp_step_repeats, 5)):
                t0 = time.perf_counter()
                pipe.train_steps(1)
                if dev == "cuda":
                    torch.cuda.synchronize()
                ts.append(time.perf_counter() - t0)
            per_m[f"svgp_step_{dev}"] = m.summarize(ts)
            per_m[f"svgp_steps_per_s_{dev}"] = round(1.0 / float(np.median(ts)), 2)
            if dev == "cuda" and m_ind == m_cuda:
                rng = np.random.default_rng(opts.seed)
                mu = pipe.store.mu_W
                q = mu[rng.integers(0, len(mu), 20000)] + rng.normal(0.0, 1e-3, (20000, 3))
                pipe.sigma2_occ(q)  # warm-up
                ta = []
                for _ in range(5):
                    t0 = time.perf_counter()
                    pipe.sigma2_occ(q)
                    torch.cuda.synchronize()
                    ta.append(time.perf_counter() - t0)
                out["algorithm1_20k_cuda"] = m.summarize(ta)
            del pipe
        per_m["speedup_steps_per_s"] = round(
            per_m["svgp_steps_per_s_cuda"] / per_m["svgp_steps_per_s_cpu"], 2
        )
        out[f"M{m_ind}"] = per_m
    out["num_inducing_cuda"] = m_cuda
    # the daemon's M on CUDA: what the target is judged on
    for k in ("svgp_step_cpu", "svgp_step_cuda", "svgp_steps_per_s_cpu", "svgp_steps_per_s_cuda",
              "speedup_steps_per_s"):  # fmt: skip
        out[k] = out[f"M{m_cuda}"][k]
    return out


def run_bench(
    opts: BenchOptions,
    overrides: Sequence[str] = (),
    device: str = "auto",
    write: m.Writer = lambda s: None,
    command: str = "",
    torch_threads: int | None = None,
    progress: Callable[[float, float], None] = lambda done, total: None,
) -> dict[str, Any]:
    """Run everything ``opts`` asks for and return the JSON-ready result.

    ``torch_threads``: ``torch.set_num_threads`` for the whole run (None: the config's
    ``[daemon] torch_threads`` where it exists, as the daemon applies it; 0: torch's default).
    ``progress(done, total)`` after each section, in the units of :func:`section_weights`."""
    t_start = time.monotonic()
    dev = resolve_device(device)
    base = build_config(overrides, dev)
    d = base.daemon
    n_threads = int(getattr(d, "torch_threads", 0)) if torch_threads is None else torch_threads
    if n_threads > 0:
        torch.set_num_threads(n_threads)
    result: dict[str, Any] = {
        "schema": SCHEMA,
        "quick": opts.quick,
        "command": command,
        "started_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": m.machine_info(dev),
        "settings": {
            "object": opts.object_name,
            "trajectories": list(opts.trajectories),
            "n_frames": opts.n_frames,
            "resolution": [opts.width, opts.height],
            "rate_hz": opts.rate_hz,
            "downsample": base.stereo.downsample,
            "train_steps_per_frame": d.train_steps_per_frame,
            "idle_train_steps": d.idle_train_steps,
            "paper_epochs": opts.paper_epochs
            if opts.paper_epochs is not None
            else base.svgp.paper_epochs,
            "num_inducing": resolve_num_inducing(base.svgp.num_inducing, dev),
            "paper_num_inducing": base.svgp.paper_num_inducing,
            "batch_size": base.svgp.batch_size,
            "dtype": base.svgp.dtype,
            "overrides": list(overrides),
            # which halves ran (--no-pipeline, --no-daemon): the wall-time target needs both
            "sections": {"pipeline": opts.use_pipeline, "daemon": opts.use_daemon},
        },
        "errors": {},
    }
    weights = section_weights(opts, int(result["settings"]["paper_epochs"]), dev == "cuda")
    total, done = sum(weights.values()), [0.0]

    def finished(section: str) -> None:
        done[0] = min(total, done[0] + weights.get(section, 0.0))
        progress(done[0], total)

    write(
        f"pugsd bench{' --quick' if opts.quick else ''}: {opts.n_frames} frames "
        f"{opts.width}x{opts.height} per trajectory ({', '.join(opts.trajectories)}), "
        f"device {dev}, torch threads {torch.get_num_threads()}"
    )
    t0 = time.monotonic()
    frames, seq_overrides = m.render_sequences(opts)
    result["render_s"] = round(time.monotonic() - t0, 2)
    write(f"rendered {sum(len(v) for v in frames.values())} stereo pairs in {result['render_s']} s")
    finished("render")

    pooled: dict[str, list[float]] = {}
    per_traj: dict[str, Any] = {}
    comparison: dict[str, Any] = {}
    # per trajectory: the query cloud and the paper fit's sigma2_occ there, for the daemon's output
    references: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for traj in opts.trajectories if opts.use_pipeline else ():
        cfg = _with(overrides, seq_overrides.get(traj, {}), dev)
        core = core_of(cfg)
        write(f"[{traj}] streaming ({d.train_steps_per_frame} SVGP steps per frame)...")
        run = m.run_streaming(
            core, frames[traj], opts, d.train_steps_per_frame, d.idle_train_steps, d.ready_latch
        )
        stream_res = run.result
        write(
            f"[{traj}] streaming: last frame -> grasps {run.last_frame_to_grasps_s:.2f} s "
            f"(ready {run.ready}, ready before {run.was_ready_before_last_frame}, "
            f"{run.extra_steps_after_last_frame} idle steps after the last frame; "
            f"whole cloud {run.last_frame_to_cloud_s:.2f} s)"
        )
        refined = m.idle_refinement(run, opts.refine_steps, d.idle_rate_decay_steps)
        # the streaming model (after its idle training) against its own closed-form optimum
        stream_opt = (
            m.optimal_q(run.pipe, stream_res.cloud_W, restore=True) if opts.optimal_q else None
        )
        s2_refined = refined[-1][2] if refined else stream_res.sigma2_occ
        m.steady_state_cycles(run, frames[traj], opts, d.train_steps_per_frame)
        if opts.thread_sweep and traj == opts.trajectories[0]:
            result["svgp_step_by_torch_threads"] = m.svgp_thread_sweep(
                run, opts.thread_sweep, opts.svgp_step_repeats
            )
        write(f"[{traj}] paper mode ({result['settings']['paper_epochs']} epochs)...")
        paper_res, paper_s, paper_steps, paper_pipe = m.run_paper(
            core, frames[traj], stream_res.cloud_W, opts
        )
        rho = m.spearman(stream_res.sigma2_occ, paper_res.sigma2_occ)
        references[traj] = (stream_res.cloud_W, paper_res.sigma2_occ)
        same = m.same_top_grasp(stream_res, paper_res)
        rho_floor = None
        # the reference's repeatability at the grasp level (top grasp, top-5 contacts)
        floor_grasps: dict[str, Any] = {"top_grasp_same": None, "top5_overlap": None}
        conv: dict[str, Any] | None = None
        if opts.optimal_q:
            # a converged reference: the paper fit with q(u) at its closed-form optimum
            p_opt = m.optimal_q(paper_pipe, stream_res.cloud_W)
            conv = {
                "paper_elbo_per_point": round(p_opt.elbo_before, 4),
                "paper_optimal_q_elbo_per_point": round(p_opt.elbo_after, 4),
                "spearman_paper_vs_its_optimal_q": m.spearman(paper_res.sigma2_occ, p_opt.sigma2_occ),
                "spearman_streaming_vs_paper_optimal_q": m.spearman(
                    stream_res.sigma2_occ, p_opt.sigma2_occ
                ),
                "spearman_streaming_refined_vs_paper_optimal_q": m.spearman(
                    s2_refined, p_opt.sigma2_occ
                ),
            }
            if stream_opt is not None:
                conv.update(
                    streaming_refined_elbo_per_point=round(stream_opt.elbo_before, 4),
                    streaming_optimal_q_elbo_per_point=round(stream_opt.elbo_after, 4),
                    spearman_streaming_refined_vs_its_optimal_q=m.spearman(
                        s2_refined, stream_opt.sigma2_occ
                    ),
                )
        del paper_pipe
        if opts.paper_reference_seed is not None:
            # the reference's own repeatability: the same batch fit with another SVGP seed
            # (inducing-point FPS start, q(u) initial noise, minibatch order)
            write(f"[{traj}] paper mode again, svgp.seed = {opts.paper_reference_seed}...")
            core2 = dataclasses.replace(
                core, svgp=dataclasses.replace(core.svgp, seed=opts.paper_reference_seed)
            )
            paper2, _, _, paper2_pipe = m.run_paper(core2, frames[traj], stream_res.cloud_W, opts)
            rho_floor = m.spearman(paper_res.sigma2_occ, paper2.sigma2_occ)
            floor_grasps = {
                "top_grasp_same": m.same_top_grasp(paper_res, paper2),
                "top5_overlap": m.topk_overlap(paper_res, paper2),
            }
            if conv is not None:
                p2_opt = m.optimal_q(paper2_pipe, stream_res.cloud_W)
                conv["spearman_paper_optimal_q_vs_other_seed_optimal_q"] = m.spearman(
                    p_opt.sigma2_occ, p2_opt.sigma2_occ
                )
            del paper2, paper2_pipe
        at_paper_m: dict[str, Any] | None = None
        m_paper = core.svgp.paper_num_inducing
        if opts.streaming_at_paper_m and resolve_num_inducing(core.svgp.num_inducing, dev) != m_paper:
            write(f"[{traj}] streaming again with the paper's M = {m_paper} inducing points...")
            core_m = dataclasses.replace(
                core, svgp=dataclasses.replace(core.svgp, num_inducing=m_paper)
            )
            run_m = m.run_streaming(
                core_m, frames[traj], opts, d.train_steps_per_frame, d.idle_train_steps,
                d.ready_latch,
            )  # fmt: skip
            # on the same query cloud as everything else
            _, s2_m = run_m.pipe.sigma2_occ(stream_res.cloud_W)
            at_paper_m = {
                "num_inducing": m_paper,
                "last_frame_to_grasps_s": round(run_m.last_frame_to_grasps_s, 4),
                "train_per_frame_median_ms": m.summarize(run_m.samples["train_per_frame"])[
                    "median_ms"
                ],
                "svgp_steps": run_m.steps_total,
                "spearman_sigma2_occ": m.spearman(s2_m, paper_res.sigma2_occ),
                "top_grasp_same": m.same_top_grasp(run_m.result, paper_res),
            }
            del run_m
        comparison[traj] = {
            "streaming_last_frame_to_grasps_s": round(run.last_frame_to_grasps_s, 4),
            "streaming_last_frame_to_cloud_s": round(run.last_frame_to_cloud_s, 4),
            "streaming_was_ready_before_last_frame": run.was_ready_before_last_frame,
            "paper_last_frame_to_grasps_s": round(paper_s, 4),
            "ratio_paper_over_streaming": round(paper_s / run.last_frame_to_grasps_s, 2),
            "spearman_sigma2_occ": None if rho is None else round(rho, 4),
            "spearman_paper_vs_paper_other_seed": None if rho_floor is None else round(rho_floor, 4),
            "top_grasp_same_paper_vs_paper_other_seed": floor_grasps["top_grasp_same"],
            "top5_overlap_paper_vs_paper_other_seed": floor_grasps["top5_overlap"],
            "spearman_after_idle_steps": [
                {"steps": k, "train_s": round(t, 2), "spearman": m.spearman(s2, paper_res.sigma2_occ)}
                for k, t, s2 in refined
            ],
            "converged_reference": conv,
            "streaming_at_paper_num_inducing": at_paper_m,
            "top_grasp_same": same,
            "top5_overlap": m.topk_overlap(stream_res, paper_res),
            "query_points": len(stream_res.cloud_W),
            "grasps_streaming": len(stream_res.grasps),
            "grasps_paper": len(paper_res.grasps),
            "streaming_ready": run.ready,
            "streaming_idle_steps_after_last_frame": run.extra_steps_after_last_frame,
            "streaming_svgp_steps": run.steps_total,
            "paper_svgp_steps": paper_steps,
            "paper_epochs": result["settings"]["paper_epochs"],
            "store_voxels": run.voxels,
            "points_backprojected": run.points,
        }
        write(
            f"[{traj}] paper: {paper_s:.1f} s, ratio {paper_s / run.last_frame_to_grasps_s:.1f}, "
            f"spearman {rho if rho is None else round(rho, 3)}, top grasp same {same}"
        )
        per_traj[traj] = {k: m.summarize(v) for k, v in run.samples.items()}
        for k, v in run.samples.items():
            pooled.setdefault(k, []).extend(v)
        del run
        finished(f"pipeline {traj}")
    if opts.use_pipeline:
        result["stages"] = {k: m.summarize(pooled[k]) for k in STAGE_ORDER if k in pooled}
        result["stages_by_trajectory"] = per_traj
    result["paper_vs_streaming"] = comparison

    if dev == "cuda":
        try:
            result["cuda"] = _cuda_section(overrides, frames[opts.trajectories[0]], opts)
        except Exception as exc:
            result["errors"]["cuda"] = _err(exc)
        finished("cuda")

    feed = frames[opts.trajectories[0]]
    if opts.use_daemon:
        for traj in opts.trajectories:
            write(f"[{traj}] streaming through the daemon (loopback zenoh, in-process)...")
            cfg = _with(overrides, seq_overrides.get(traj, {}), dev)
            try:
                dm = m.daemon_last_frame(cfg, frames[traj], opts, write, references.get(traj))
                if traj in comparison:
                    comparison[traj]["daemon"] = dm
                else:  # --no-pipeline: no paper fit to compare with
                    result.setdefault("daemon_alone", {})[traj] = dm
            except Exception as exc:
                result["errors"][f"daemon_last_frame_{traj}"] = _err(exc)
            finished(f"daemon {traj}")
        write("sustained throughput through the daemon (loopback zenoh, in-process)...")
        try:
            result["throughput"] = m.throughput_daemon(base, feed, opts, write)
        except Exception as exc:
            result["errors"]["throughput"] = _err(exc)
        finished("throughput")
        write(
            f"long replay: {opts.replay_sim_min:g} simulated minutes offered in "
            f"{opts.replay_wall_s:g} s..."
        )
        try:
            result["replay"] = m.replay_daemon(base, feed, opts, write)
        except Exception as exc:
            result["errors"]["replay"] = _err(exc)
        finished("replay")
    result["memory"] = {
        "peak_rss_mb": round(m.peak_rss_mb(), 1),
        "rss_end_mb": round(m.rss_mb(), 1),
        "rss_growth_frac_replay": (result.get("replay") or {}).get("rss_growth_frac"),
    }
    result["machine"]["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    result["wall_s"] = round(time.monotonic() - t_start, 1)
    result["targets"] = evaluate_targets(result)
    return result


def section_weights(opts: BenchOptions, paper_epochs: int, cuda: bool) -> dict[str, float]:
    """Each section of a run as its typical seconds on a 2-core CPU, for the progress bar's ETA
    only (the bar scales them by the pace it observes). Rendering goes by the stereo pairs; a
    trajectory's pipeline section by its paper fits' epochs; the throughput ladder by every rate
    offered (it stops at the first rate held, and the bar then jumps); the replay by its pacing."""
    w: dict[str, float] = {"render": 1.2 * opts.n_frames * len(opts.trajectories)}
    fits = 1 + (opts.paper_reference_seed is not None)
    for traj in opts.trajectories if opts.use_pipeline else ():
        w[f"pipeline {traj}"] = 30.0 + 0.55 * paper_epochs * fits + 40.0 * opts.streaming_at_paper_m
    if cuda:
        w["cuda"] = 60.0
    if opts.use_daemon:
        for traj in opts.trajectories:
            w[f"daemon {traj}"] = 25.0 + 12.0 * (opts.daemon_repeats - 1)
        w["throughput"] = sum(
            max(opts.throughput_trial_s, opts.n_frames / r) + 12.0 for r in opts.throughput_rates_hz
        )
        w["replay"] = opts.replay_wall_s + 10.0
    return w


def _err(exc: BaseException) -> str:
    return "".join(traceback.format_exception_only(type(exc), exc)).strip()
