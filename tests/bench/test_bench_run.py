# SPDX-License-Identifier: Apache-2.0
"""The benchmark runner (pugsd/bench/run.py, options.py) with the measurements replaced by fakes:
every figure the runner derives (ratios, roundings, which arrays a Spearman compares, which sections
run) is checked against a closed form, and nothing is rendered or fitted.

The fake Spearman of two arrays is the product of their tags (each array is filled with a prime), so
a field's value names the two arrays it compared."""

from __future__ import annotations

import datetime as dt
import types
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

import pugsd.bench.run as run_mod
from pugsd.bench import measure
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import (
    SCHEMA,
    STAGE_ORDER,
    _cuda_section,
    _err,
    _toml,
    _with,
    build_config,
    resolve_device,
    run_bench,
    section_weights,
)

# tags of the sigma2_occ arrays (primes: a product names its factors)
STREAM, PAPER, PAPER2, REF1, REF2, STREAM_OPT, PAPER_OPT, PAPER2_OPT, AT_M = 2, 5, 7, 11, 13, 17, 19, 23, 29
AT_M_RES = 31  # the at-paper-M run's own result (its sigma2_occ on the shared cloud is AT_M)


def _arr(tag: int) -> np.ndarray:
    return np.full(4, float(tag))


def _summ(v: list[float]) -> dict[str, Any]:
    return {"n": len(v), "median_ms": round(float(np.median(v)) * 1000.0, 3)}


class _Fakes:
    """Stand-ins for pugsd.bench.measure, recording their calls."""

    def __init__(self, *, throughput_error: bool = False, daemon_error_on: str | None = None) -> None:
        self.calls: dict[str, list[Any]] = {}
        self.throughput_error = throughput_error
        self.daemon_error_on = daemon_error_on
        self.frames = {"complete": ["c0", "c1", "c2"], "partial": ["p0", "p1"]}
        self.cloud = {t: np.full((7, 3), float(i)) for i, t in enumerate(self.frames)}
        self.stream_runs: dict[str, Any] = {}
        self.paper_results: dict[str, Any] = {}

    def _rec(self, name: str, *args: Any) -> None:
        self.calls.setdefault(name, []).append(args)

    def traj_of(self, frames: list[str]) -> str:
        return "complete" if frames[0].startswith("c") else "partial"

    # ---- measure functions
    def render_sequences(self, opts: BenchOptions) -> tuple[dict[str, list[str]], dict[str, Any]]:
        self._rec("render_sequences", opts)
        return dict(self.frames), {"partial": {"stereo.downsample": 2}}

    def run_streaming(self, core: Any, frames: list[str], opts: Any, spf: int, idle: int, latch: bool) -> Any:
        traj = self.traj_of(frames)
        self._rec("run_streaming", traj, core.svgp.num_inducing, core.stereo.downsample,
                  core.svgp.batch_size, spf, idle, latch)  # fmt: skip
        at_m = traj in self.paper_results  # the second run of a trajectory: at the paper's M
        res = types.SimpleNamespace(
            sigma2_occ=_arr(AT_M_RES if at_m else STREAM), cloud_W=self.cloud[traj], grasps=[0] * 4
        )
        pipe = types.SimpleNamespace(sigma2_occ=lambda cloud: (None, _arr(AT_M)), name=f"stream-{traj}")
        run = types.SimpleNamespace(
            samples={"svgp_step": [0.5, 0.25], "stereo_depth": [0.125], "zzz_unlisted": [1.0]},
            result=res,
            last_frame_to_grasps_s=0.75 if at_m else 0.123456,
            last_frame_to_cloud_s=0.654321,
            extra_steps_after_last_frame=3,
            ready=True,
            was_ready_before_last_frame=False,
            steps_total=77 if at_m else 42,
            points=1000,
            voxels=200,
            pipe=pipe,
        )
        if not at_m:
            run.samples["train_per_frame"] = [0.0625]
            self.stream_runs[traj] = run
        else:
            run.samples = {"train_per_frame": [0.5, 0.25]}
        return run

    def idle_refinement(
        self, run: Any, steps: tuple[int, ...], decay_steps: int
    ) -> list[tuple[int, float, np.ndarray]]:
        self._rec("idle_refinement", steps, decay_steps)
        tags = [REF1, REF2]
        return [(k, 0.123 * (i + 1), _arr(tags[i])) for i, k in enumerate(steps)]

    def optimal_q(self, pipe: Any, cloud: np.ndarray, restore: bool = False) -> Any:
        name = pipe.name
        self._rec("optimal_q", name, restore)
        tag = {"paper-0": PAPER_OPT, "paper-1": PAPER2_OPT}.get(name, STREAM_OPT)
        return types.SimpleNamespace(elbo_before=-tag - 0.123456, elbo_after=-tag + 0.654321,
                                     sigma2_occ=_arr(tag))  # fmt: skip

    def steady_state_cycles(self, run: Any, frames: list[str], opts: Any, spf: int) -> None:
        self._rec("steady_state_cycles", self.traj_of(frames), spf)

    def svgp_thread_sweep(self, run: Any, threads: tuple[int, ...], repeats: int) -> dict[str, Any]:
        self._rec("svgp_thread_sweep", run.pipe.name, threads, repeats)
        return {"threads": list(threads)}

    def run_paper(self, core: Any, frames: list[str], cloud: np.ndarray, opts: Any) -> Any:
        traj = self.traj_of(frames)
        seed = core.svgp.seed
        self._rec("run_paper", traj, seed, core.svgp.num_inducing)
        assert cloud is self.cloud[traj]
        main = traj not in self.paper_results  # the first fit of a trajectory; then the reference's
        res = types.SimpleNamespace(sigma2_occ=_arr(PAPER if main else PAPER2), grasps=[0] * 6)
        if main:
            self.paper_results[traj] = res
        return res, 0.987654, 321, types.SimpleNamespace(name=f"paper-{0 if main else 1}")

    def spearman(self, a: np.ndarray, b: np.ndarray) -> float:
        return float(a[0] * b[0]) + 1e-6  # the rounding to 4 places shows

    def same_top_grasp(self, a: Any, b: Any) -> bool:
        # streaming vs the paper fit, and the paper fit vs its other seed (the reference's own
        # repeatability); any other pair (the run at the paper's M) is False
        return (a.sigma2_occ[0], b.sigma2_occ[0]) in {(STREAM, PAPER), (PAPER, PAPER2)}

    def topk_overlap(self, a: Any, b: Any) -> float:
        return 0.6 if a.sigma2_occ[0] == STREAM else float(a.sigma2_occ[0] * b.sigma2_occ[0]) / 1000.0

    def daemon_last_frame(
        self, cfg: Any, frames: list[str], opts: Any, write: Any, ref: Any
    ) -> dict[str, Any]:
        traj = self.traj_of(frames)
        self._rec("daemon_last_frame", traj, cfg.stereo.downsample, ref)
        if traj == self.daemon_error_on:
            raise ValueError(f"daemon {traj} broke")
        return {"dm": traj}

    def throughput_daemon(self, base: Any, feed: list[str], opts: Any, write: Any) -> dict[str, Any]:
        self._rec("throughput_daemon", list(feed))
        if self.throughput_error:
            raise RuntimeError("no port")
        return {"held_hz": 12.5}

    def replay_daemon(self, base: Any, feed: list[str], opts: Any, write: Any) -> dict[str, Any]:
        self._rec("replay_daemon", list(feed))
        return {"rss_growth_frac": 0.0123}

    def install(self, mp: pytest.MonkeyPatch) -> None:
        for name in ("render_sequences", "run_streaming", "idle_refinement", "optimal_q",
                     "steady_state_cycles", "svgp_thread_sweep", "run_paper", "spearman",
                     "same_top_grasp", "topk_overlap", "daemon_last_frame", "throughput_daemon",
                     "replay_daemon"):  # fmt: skip
            mp.setattr(measure, name, getattr(self, name))
        mp.setattr(measure, "summarize", _summ)
        mp.setattr(measure, "machine_info", lambda dev: {"device": dev})
        mp.setattr(measure, "peak_rss_mb", lambda: 123.456)
        mp.setattr(measure, "rss_mb", lambda: 100.04)


@pytest.fixture
def env(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """A deterministic clock, thread count, load average and target evaluation for run_bench."""
    clock = [0.0]

    def mono() -> float:
        clock[0] += 1.5
        return clock[0]

    threads: list[int] = []
    seen: list[dict[str, Any]] = []

    def targets(result: dict[str, Any]) -> list[str]:
        seen.append(result)
        return ["judged"]

    monkeypatch.setattr(run_mod, "time", types.SimpleNamespace(monotonic=mono))
    monkeypatch.setattr(run_mod, "evaluate_targets", targets)
    monkeypatch.setattr(torch, "set_num_threads", threads.append)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 7)
    monkeypatch.setattr(run_mod.os, "getloadavg", lambda: (0.126, 1.0, 2.004))
    return {"threads": threads, "targets_seen": seen}


def _opts(**kw: Any) -> BenchOptions:
    base: dict[str, Any] = {
        "n_frames": 3, "width": 320, "height": 240, "paper_reference_seed": 1, "streaming_at_paper_m": True,
        "refine_steps": (100, 400), "thread_sweep": (1, 2), "svgp_step_repeats": 4, "optimal_q": True,
    }  # fmt: skip
    base.update(kw)
    return BenchOptions.quick_preset().replace(**base)


def _bench(
    monkeypatch: pytest.MonkeyPatch, fakes: _Fakes, opts: BenchOptions, **kw: Any
) -> tuple[dict[str, Any], list[str]]:
    fakes.install(monkeypatch)
    lines: list[str] = []
    kw.setdefault("device", "cpu")
    res = run_bench(opts, write=lines.append, **kw)
    return res, lines


def _r4(x: float) -> float:
    return round(x + 1e-6, 4)


# ---------------------------------------------------------------- a whole run, pipeline and daemon


def test_a_full_run_derives_every_comparison_field_from_its_sources(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    f = _Fakes()
    ov = ["svgp.batch_size=64", "daemon.idle_train_steps=6", "daemon.ready_latch=false"]
    res, lines = _bench(monkeypatch, f, _opts(), overrides=ov, command="pugsd bench -q")
    cmp = res["paper_vs_streaming"]
    assert list(cmp) == ["complete", "partial"]
    c = cmp["complete"]
    daemon = c.pop("daemon")
    assert daemon == {"dm": "complete"}
    assert c == {
        "streaming_last_frame_to_grasps_s": 0.1235,
        "streaming_last_frame_to_cloud_s": 0.6543,
        "streaming_was_ready_before_last_frame": False,
        "paper_last_frame_to_grasps_s": 0.9877,
        "ratio_paper_over_streaming": 8.0,  # paper / streaming, not the inverse
        "spearman_sigma2_occ": _r4(STREAM * PAPER),
        "spearman_paper_vs_paper_other_seed": _r4(PAPER * PAPER2),
        # the reference's repeatability at the grasp level: the seed-0 fit against the seed-1 fit
        "top_grasp_same_paper_vs_paper_other_seed": True,
        "top5_overlap_paper_vs_paper_other_seed": PAPER * PAPER2 / 1000.0,
        "spearman_after_idle_steps": [
            {"steps": 100, "train_s": 0.12, "spearman": REF1 * PAPER + 1e-6},
            {"steps": 400, "train_s": 0.25, "spearman": REF2 * PAPER + 1e-6},
        ],
        "converged_reference": {
            "paper_elbo_per_point": round(-PAPER_OPT - 0.123456, 4),
            "paper_optimal_q_elbo_per_point": round(-PAPER_OPT + 0.654321, 4),
            "spearman_paper_vs_its_optimal_q": PAPER * PAPER_OPT + 1e-6,
            "spearman_streaming_vs_paper_optimal_q": STREAM * PAPER_OPT + 1e-6,
            # the refined model is the last refinement's
            "spearman_streaming_refined_vs_paper_optimal_q": REF2 * PAPER_OPT + 1e-6,
            "streaming_refined_elbo_per_point": round(-STREAM_OPT - 0.123456, 4),
            "streaming_optimal_q_elbo_per_point": round(-STREAM_OPT + 0.654321, 4),
            "spearman_streaming_refined_vs_its_optimal_q": REF2 * STREAM_OPT + 1e-6,
            "spearman_paper_optimal_q_vs_other_seed_optimal_q": PAPER_OPT * PAPER2_OPT + 1e-6,
        },
        "streaming_at_paper_num_inducing": {
            "num_inducing": 500,
            "last_frame_to_grasps_s": 0.75,
            "train_per_frame_median_ms": 375.0,
            "svgp_steps": 77,
            "spearman_sigma2_occ": AT_M * PAPER + 1e-6,
            "top_grasp_same": False,
        },
        "top_grasp_same": True,
        "top5_overlap": 0.6,
        "query_points": 7,
        "grasps_streaming": 4,
        "grasps_paper": 6,
        "streaming_ready": True,
        "streaming_idle_steps_after_last_frame": 3,
        "streaming_svgp_steps": 42,
        "paper_svgp_steps": 321,
        "paper_epochs": 3,
        "store_voxels": 200,
        "points_backprojected": 1000,
    }
    # the second trajectory ran with its sequence override; the first without
    rs = f.calls["run_streaming"]
    assert [(r[0], r[1], r[2], r[3]) for r in rs] == [
        ("complete", 0, 4, 64), ("complete", 500, 4, 64), ("partial", 0, 2, 64), ("partial", 500, 2, 64),
    ]  # fmt: skip
    assert all(r[4:] == (4, 6, False) for r in rs)  # the daemon's steps per frame, idle steps, latch
    assert f.calls["run_paper"] == [("complete", 0, 0), ("complete", 1, 0),
                                    ("partial", 0, 0), ("partial", 1, 0)]  # fmt: skip
    # at the daemon's idle rates (its default idle_rate_decay_steps: the overrides leave it)
    assert f.calls["idle_refinement"] == [((100, 400), 100)] * 2
    assert f.calls["steady_state_cycles"] == [("complete", 4), ("partial", 4)]
    # the thread sweep runs once, on the first trajectory's streaming model
    assert f.calls["svgp_thread_sweep"] == [("stream-complete", (1, 2), 4)]
    assert res["svgp_step_by_torch_threads"] == {"threads": [1, 2]}
    assert f.calls["optimal_q"] == [
        ("stream-complete", True), ("paper-0", False), ("paper-1", False),
        ("stream-partial", True), ("paper-0", False), ("paper-1", False),
    ]  # fmt: skip
    # the daemon gets each trajectory's config and its reference: the query cloud, the paper's fit
    dl = f.calls["daemon_last_frame"]
    assert [(d[0], d[1]) for d in dl] == [("complete", 4), ("partial", 2)]
    for traj, d in zip(("complete", "partial"), dl, strict=True):
        cloud, s2 = d[2]
        assert cloud is f.cloud[traj] and s2 is f.paper_results[traj].sigma2_occ
    assert cmp["partial"]["daemon"] == {"dm": "partial"}
    # throughput and replay are fed the first trajectory's frames
    assert f.calls["throughput_daemon"] == [(["c0", "c1", "c2"],)]
    assert f.calls["replay_daemon"] == [(["c0", "c1", "c2"],)]
    assert res["throughput"] == {"held_hz": 12.5} and res["replay"] == {"rss_growth_frac": 0.0123}
    assert "daemon_alone" not in res and res["errors"] == {}
    # stages: pooled over both trajectories, in STAGE_ORDER, unknown names left out of the pool
    assert list(res["stages"]) == ["stereo_depth", "svgp_step", "train_per_frame"]
    assert res["stages"]["svgp_step"] == {"n": 4, "median_ms": 375.0}
    assert res["stages"]["stereo_depth"] == {"n": 2, "median_ms": 125.0}
    assert res["stages"]["train_per_frame"] == {"n": 2, "median_ms": 62.5}  # the main runs' only
    assert res["stages_by_trajectory"]["partial"] == {
        "svgp_step": {"n": 2, "median_ms": 375.0}, "stereo_depth": {"n": 1, "median_ms": 125.0},
        "zzz_unlisted": {"n": 1, "median_ms": 1000.0}, "train_per_frame": {"n": 1, "median_ms": 62.5},
    }  # fmt: skip
    # head, memory, machine, timing, targets
    assert (res["schema"], res["quick"], res["command"]) == (SCHEMA, True, "pugsd bench -q")
    assert res["memory"] == {"peak_rss_mb": 123.5, "rss_end_mb": 100.0, "rss_growth_frac_replay": 0.0123}
    assert res["machine"] == {"device": "cpu", "load_average_at_end": [0.13, 1.0, 2.0]}
    assert res["render_s"] == 1.5 and res["wall_s"] == 4.5
    assert res["targets"] == ["judged"] and env["targets_seen"] == [res]
    assert dt.datetime.fromisoformat(res["started_utc"]).tzinfo is not None
    assert env["threads"] == [1]  # the config's [daemon] torch_threads
    assert lines[0] == (
        "pugsd bench --quick: 3 frames 320x240 per trajectory (complete, partial), device cpu, "
        "torch threads 7"
    )
    assert lines[1] == "rendered 5 stereo pairs in 1.5 s"
    assert "[complete] paper: 1.0 s, ratio 8.0, spearman 10.0, top grasp same True" in lines


def test_the_settings_record_the_resolved_configuration(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    opts = _opts().replace(quick=False, paper_epochs=None, trajectories=("partial",), use_daemon=False)
    res, lines = _bench(monkeypatch, _Fakes(), opts, overrides=["svgp.batch_size=64"])
    assert res["settings"] == {
        "object": "mug",
        "trajectories": ["partial"],
        "n_frames": 3,
        "resolution": [320, 240],
        "rate_hz": 10.0,
        "downsample": 4,  # the base config's, not a trajectory's override
        "train_steps_per_frame": 4,
        "idle_train_steps": 4,
        "paper_epochs": 100,  # None: the config's
        "num_inducing": 250,  # auto on the CPU
        "paper_num_inducing": 500,
        "batch_size": 64,
        "dtype": "float32",
        "overrides": ["svgp.batch_size=64"],
        "sections": {"pipeline": True, "daemon": False},
    }
    assert res["quick"] is False and lines[0].startswith("pugsd bench: 3 frames")
    assert res["paper_vs_streaming"]["partial"]["paper_epochs"] == 100


def test_optional_diagnostics_are_skipped_when_switched_off(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    f = _Fakes()
    opts = _opts(
        optimal_q=False, paper_reference_seed=None, streaming_at_paper_m=False, refine_steps=(),
        thread_sweep=(), trajectories=("partial", "complete"),
    )  # fmt: skip
    res, _ = _bench(monkeypatch, f, opts, torch_threads=0)
    c = res["paper_vs_streaming"]["partial"]
    assert c["converged_reference"] is None
    assert c["spearman_paper_vs_paper_other_seed"] is None
    assert c["top_grasp_same_paper_vs_paper_other_seed"] is None
    assert c["top5_overlap_paper_vs_paper_other_seed"] is None
    assert c["streaming_at_paper_num_inducing"] is None
    assert c["spearman_after_idle_steps"] == []
    assert "svgp_step_by_torch_threads" not in res and "svgp_thread_sweep" not in f.calls
    assert "optimal_q" not in f.calls
    assert f.calls["run_paper"] == [("partial", 0, 0), ("complete", 0, 0)]
    assert [r[1] for r in f.calls["run_streaming"]] == [0, 0]
    assert env["threads"] == []  # 0: torch's default, not set
    # the first trajectory named feeds throughput and replay
    assert f.calls["throughput_daemon"] == [(["p0", "p1"],)]


def test_without_refinement_the_refined_model_is_the_streaming_one(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    res, _ = _bench(monkeypatch, _Fakes(), _opts(refine_steps=()), torch_threads=3)
    conv = res["paper_vs_streaming"]["complete"]["converged_reference"]
    assert conv["spearman_streaming_refined_vs_paper_optimal_q"] == STREAM * PAPER_OPT + 1e-6
    assert conv["spearman_streaming_refined_vs_its_optimal_q"] == STREAM * STREAM_OPT + 1e-6
    assert env["threads"] == [3]


def test_reference_seed_zero_still_runs_the_second_paper_fit(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    f = _Fakes()
    res, _ = _bench(monkeypatch, f, _opts(paper_reference_seed=0, trajectories=("partial",)),
                    overrides=["svgp.seed=2"])  # fmt: skip
    assert [c[1] for c in f.calls["run_paper"]] == [2, 0]
    assert res["paper_vs_streaming"]["partial"]["spearman_paper_vs_paper_other_seed"] is not None


def test_the_streaming_run_at_the_paper_m_is_skipped_where_m_is_already_the_papers(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    f = _Fakes()
    res, _ = _bench(monkeypatch, f, _opts(), overrides=["svgp.num_inducing=500"])
    assert res["paper_vs_streaming"]["complete"]["streaming_at_paper_num_inducing"] is None
    assert [r[1] for r in f.calls["run_streaming"]] == [500, 500]
    assert res["settings"]["num_inducing"] == 500


def test_no_pipeline_runs_the_daemon_alone_without_references(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    f = _Fakes(throughput_error=True, daemon_error_on="partial")
    res, _ = _bench(monkeypatch, f, _opts(use_pipeline=False))
    assert "run_streaming" not in f.calls and "run_paper" not in f.calls
    assert "stages" not in res and "stages_by_trajectory" not in res
    assert res["paper_vs_streaming"] == {}
    assert res["daemon_alone"] == {"complete": {"dm": "complete"}}
    assert [d[2] for d in f.calls["daemon_last_frame"]] == [None, None]
    # a failing section is recorded as its exception's one-line message; the others still run
    assert res["errors"] == {
        "daemon_last_frame_partial": "ValueError: daemon partial broke",
        "throughput": "RuntimeError: no port",
    }
    assert "throughput" not in res and res["replay"] == {"rss_growth_frac": 0.0123}
    assert res["settings"]["sections"] == {"pipeline": False, "daemon": True}


def test_no_daemon_skips_the_daemon_sections(monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]) -> None:
    f = _Fakes()
    res, _ = _bench(monkeypatch, f, _opts(use_daemon=False))
    for name in ("daemon_last_frame", "throughput_daemon", "replay_daemon"):
        assert name not in f.calls
    assert "throughput" not in res and "replay" not in res
    assert "daemon" not in res["paper_vs_streaming"]["complete"]
    assert res["memory"]["rss_growth_frac_replay"] is None


@pytest.mark.parametrize("sections", [{}, {"use_daemon": False}, {"use_pipeline": False}])
def test_progress_reaches_the_total_once_per_section_failures_included(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any], sections: dict[str, bool]
) -> None:
    f = _Fakes(throughput_error=True, daemon_error_on="partial")
    seen: list[tuple[float, float]] = []
    opts = _opts(**sections)
    _bench(monkeypatch, f, opts, progress=lambda done, total: seen.append((done, total)))
    weights = section_weights(opts, int(opts.paper_epochs or 0), cuda=False)
    assert len(seen) == len(weights)  # one report per section, a failed one too
    assert {t for _, t in seen} == {sum(weights.values())}
    done = [d for d, _ in seen]
    assert done == sorted(done) and done[-1] == pytest.approx(sum(weights.values()))


def test_section_weights_follow_the_options() -> None:
    full = BenchOptions.full()
    w = section_weights(full, 100, cuda=False)
    assert set(w) == {"render", "pipeline complete", "pipeline partial", "daemon complete",
                      "daemon partial", "throughput", "replay"}  # fmt: skip
    assert "cuda" in section_weights(full, 100, cuda=True)
    # more frames render longer, more epochs fit longer, a longer replay paces longer
    assert section_weights(full.replace(n_frames=60), 100, False)["render"] > w["render"]
    assert section_weights(full, 200, False)["pipeline partial"] > w["pipeline partial"]
    assert section_weights(full.replace(replay_wall_s=480.0), 100, False)["replay"] > w["replay"]
    assert sum(section_weights(BenchOptions.quick_preset(), 3, False).values()) < sum(w.values())


def test_a_cuda_run_adds_the_cuda_section_and_records_its_failure(
    monkeypatch: pytest.MonkeyPatch, env: dict[str, Any]
) -> None:
    seen: list[tuple[Any, ...]] = []

    def fake_cuda(overrides: Any, frames: list[str], opts: BenchOptions) -> dict[str, Any]:
        seen.append((list(overrides), list(frames)))
        return {"speedup": 2.0}

    monkeypatch.setattr(run_mod, "_cuda_section", fake_cuda)
    f = _Fakes()
    res, lines = _bench(monkeypatch, f, _opts(use_daemon=False), device="cuda", overrides=["svgp.seed=0"])
    assert res["cuda"] == {"speedup": 2.0} and seen == [(["svgp.seed=0"], ["c0", "c1", "c2"])]
    assert res["settings"]["num_inducing"] == 500  # auto on CUDA: the paper's M, no extra run
    assert res["paper_vs_streaming"]["complete"]["streaming_at_paper_num_inducing"] is None
    assert res["machine"]["device"] == "cuda" and "device cuda" in lines[0]

    def broken(*a: Any) -> dict[str, Any]:
        raise MemoryError("CUDA out of memory")

    monkeypatch.setattr(run_mod, "_cuda_section", broken)
    res, _ = _bench(monkeypatch, _Fakes(), _opts(use_daemon=False), device="cuda")
    assert "cuda" not in res and res["errors"] == {"cuda": "MemoryError: CUDA out of memory"}
    res, _ = _bench(monkeypatch, _Fakes(), _opts(use_daemon=False), device="cpu")
    assert "cuda" not in res and res["errors"] == {}


# ---------------------------------------------------------------- _cuda_section on a fake pipeline


class _FakePipe:
    def __init__(self, core: Any, clock: list[float], log: list[tuple[Any, ...]]) -> None:
        self.dev = core.svgp.device
        self.m = core.svgp.num_inducing
        self.clock = clock
        self.log = log
        self.store = types.SimpleNamespace(mu_W=np.zeros((10, 3)))
        self.frames: list[Any] = []

    def add_stereo(self, f: Any) -> None:
        self.frames.append(f)

    def train_steps(self, n: int) -> None:
        # CPU: M / 1000 s per step; CUDA: 1/16 s at any M
        self.clock[0] += n * (self.m / 1000.0 if self.dev == "cpu" else 0.0625)
        self.log.append(("train", self.dev, self.m, len(self.frames)))

    def sigma2_occ(self, q: np.ndarray) -> tuple[None, np.ndarray]:
        self.clock[0] += 0.015625
        self.log.append(("sigma2", self.dev, self.m, q.shape))
        return None, np.zeros(len(q))


@pytest.mark.parametrize(("overrides", "m_cuda"), [([], 500), (["svgp.num_inducing=300"], 300)])
def test_cuda_section_compares_steps_per_second_at_each_m(
    monkeypatch: pytest.MonkeyPatch, overrides: list[str], m_cuda: int
) -> None:
    clock = [10.0]
    log: list[tuple[Any, ...]] = []
    syncs: list[int] = []
    monkeypatch.setattr(run_mod, "make_pipeline", lambda core, seed: _FakePipe(core, clock, log))
    monkeypatch.setattr(run_mod, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(torch.cuda, "synchronize", lambda: syncs.append(1))
    monkeypatch.setattr(measure, "summarize", _summ)
    opts = BenchOptions.quick_preset().replace(svgp_step_repeats=3)  # fewer than 5: 5 timed steps
    out = _cuda_section(overrides, ["f0", "f1"], opts)
    ms = sorted({250, 500, m_cuda})
    assert set(out) == {*(f"M{m}" for m in ms), "algorithm1_20k_cuda", "num_inducing_cuda",
                        "svgp_step_cpu", "svgp_step_cuda", "svgp_steps_per_s_cpu",
                        "svgp_steps_per_s_cuda", "speedup_steps_per_s"}  # fmt: skip
    for m in ms:
        per = out[f"M{m}"]
        assert per == {
            "svgp_step_cpu": {"n": 5, "median_ms": float(m)},
            "svgp_steps_per_s_cpu": round(1000.0 / m, 2),
            "svgp_step_cuda": {"n": 5, "median_ms": 62.5},
            "svgp_steps_per_s_cuda": 16.0,
            "speedup_steps_per_s": round(16.0 / round(1000.0 / m, 2), 2),
        }
    assert out["num_inducing_cuda"] == m_cuda
    assert out["algorithm1_20k_cuda"] == {"n": 5, "median_ms": 15.625}  # after one warm-up call
    for k in ("svgp_step_cpu", "svgp_step_cuda", "svgp_steps_per_s_cpu", "svgp_steps_per_s_cuda",
              "speedup_steps_per_s"):  # fmt: skip
        assert out[k] == out[f"M{m_cuda}"][k]
    # each pipeline: both frames added, one initialising step, then the timed ones
    trains = [e for e in log if e[0] == "train"]
    assert len(trains) == len(ms) * 2 * 6 and all(e[3] == 2 for e in trains)
    assert [e[1:3] for e in trains[::6]] == [(d, m) for m in ms for d in ("cpu", "cuda")]
    sig = [e for e in log if e[0] == "sigma2"]
    assert sig == [("sigma2", "cuda", m_cuda, (20000, 3))] * 6
    assert len(syncs) == len(ms) * 5 + 5  # every timed CUDA step and Algorithm 1 call, not the CPU's


def test_cuda_section_times_at_least_the_configured_repeats(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = [0.0]
    log: list[tuple[Any, ...]] = []
    monkeypatch.setattr(run_mod, "make_pipeline", lambda core, seed: _FakePipe(core, clock, log))
    monkeypatch.setattr(run_mod, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(torch.cuda, "synchronize", lambda: None)
    monkeypatch.setattr(measure, "summarize", _summ)
    out = _cuda_section([], ["f0"], BenchOptions.quick_preset().replace(svgp_step_repeats=8))
    assert out["svgp_step_cpu"]["n"] == 8 and out["svgp_step_cuda"] == {"n": 8, "median_ms": 62.5}


# ---------------------------------------------------------------- pure helpers


def test_resolve_device(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu"
    assert resolve_device("cuda") == "cuda" and resolve_device("cpu") == "cpu"


def test_build_config_sets_the_device_unless_an_override_names_it() -> None:
    c = build_config(["svgp.batch_size=64"], "cuda")
    assert (c.svgp.device, c.svgp.batch_size, c.daemon.log_level) == ("cuda", 64, "warning")
    assert build_config([" svgp.device = cpu"], "cuda").svgp.device == "cpu"
    ov = ["svgp.seed=3"]
    build_config(ov, "cuda")
    assert ov == ["svgp.seed=3"]  # the caller's list is not changed


def test_with_appends_typed_overrides_after_the_users() -> None:
    extra = {"stereo.downsample": 2, "svgp.dtype": "float64", "daemon.ready_latch": False}
    c = _with(["stereo.downsample=8", 'svgp.dtype="float32"'], extra, "cpu")
    assert (c.stereo.downsample, c.svgp.dtype, c.daemon.ready_latch, c.svgp.device) == (
        2, "float64", False, "cpu",
    )  # fmt: skip


@pytest.mark.parametrize(
    ("value", "text"),
    [(True, "true"), (False, "false"), ("mug", '"mug"'), (3, "3"), (0.25, "0.25"), ((1, 2), "(1, 2)")],
)
def test_toml_literals(value: Any, text: str) -> None:
    assert _toml(value) == text


def test_err_is_the_exceptions_one_line_message() -> None:
    assert _err(ValueError("bad value")) == "ValueError: bad value"
    assert _err(KeyError("k")) == "KeyError: 'k'"
    assert _err(RuntimeError()) == "RuntimeError"


def test_stage_order_names_each_stage_once() -> None:
    assert len(set(STAGE_ORDER)) == len(STAGE_ORDER) == 15
    assert STAGE_ORDER[0] == "stereo_depth" and STAGE_ORDER[-1] == "end_to_end"


# ---------------------------------------------------------------- options


def test_quick_preset_values() -> None:
    q = BenchOptions.quick_preset()
    assert q == BenchOptions(
        quick=True, n_frames=6, paper_epochs=3, paper_reference_seed=None, streaming_at_paper_m=False,
        svgp_step_repeats=3, compute_repeats=1, daemon_repeats=1, refine_steps=(4,), ready_timeout_s=5.0,
        thread_sweep=(), throughput_rates_hz=(10.0,), throughput_trial_s=2.0, throughput_min_frames=6,
        drain_timeout_s=3.0, replay_sim_min=1.0, replay_window_min=(0.25, 1.0), replay_wall_s=4.0,
        replay_wall_cap_s=10.0,
    )  # fmt: skip
    # the quick preset keeps the full run's picture and the sections
    assert (q.width, q.height, q.rate_hz, q.seed, q.object_name) == (640, 480, 10.0, 0, "mug")
    assert q.optimal_q and q.use_daemon and q.use_pipeline


def test_full_preset_remaining_values() -> None:
    f = BenchOptions.full()
    assert f == BenchOptions()
    assert (f.seed, f.svgp_step_repeats, f.compute_repeats, f.ready_timeout_s) == (0, 20, 5, 60.0)
    assert (f.drain_timeout_s, f.replay_wall_cap_s) == (15.0, 360.0)


def test_options_are_frozen_and_replace_rejects_unknown_fields() -> None:
    f = BenchOptions.full()
    with pytest.raises(AttributeError):
        f.n_frames = 3  # type: ignore[misc]
    with pytest.raises(TypeError):
        f.replace(no_such_field=1)
    fn: Callable[..., BenchOptions] = f.replace
    assert fn() == f and fn() is not f
