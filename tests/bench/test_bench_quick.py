# SPDX-License-Identifier: Apache-2.0
"""Smoke tests of ``pugsd bench --quick``: a well-formed JSON with the expected keys and sane
values. No wall-clock assertions: the benchmark measures, the tests only check the plumbing."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.bench import measure
from pugsd.bench.measure import match_points
from pugsd.bench.options import BenchOptions
from pugsd.bench.run import SCHEMA
from pugsd.bench.targets import evaluate_targets, format_table
from pugsd.cli import main
from pugsd.config import PugsdConfig
from pugsd.core.types import ScoredGrasps
from pugsd.wire.codec import CloudMsg

STAGES = (
    "stereo_depth",
    "backproject",
    "fof_update",
    "ingest",
    "svgp_step",
    "grasp_proposal",
    "algorithm1",
    "eq13",
    "end_to_end",
)


_QUICK = BenchOptions.quick_preset()


def _tiny() -> BenchOptions:
    """The quick preset, smaller still (tests share the machine)."""
    return _QUICK.replace(
        n_frames=3,
        width=320,
        height=240,
        ready_timeout_s=0.5,
        svgp_step_repeats=2,
        drain_timeout_s=2.0,
        throughput_min_frames=3,
        throughput_trial_s=0.5,
        replay_sim_min=0.2,
        replay_window_min=(0.05, 0.2),
        replay_wall_s=1.0,
        # the full run's diagnostic (off in --quick), exercised here at this small size
        streaming_at_paper_m=True,
    )


@pytest.fixture(scope="module")
def quick_json(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    path = tmp_path_factory.mktemp("bench") / "out" / "bench.json"
    mp = pytest.MonkeyPatch()
    mp.setattr(BenchOptions, "quick_preset", classmethod(lambda cls: _tiny()))
    try:
        rc = main(["bench", "--quick", "--json", str(path)])
    finally:
        mp.undo()
    assert rc == 0
    return dict(json.loads(path.read_text()))


def _finite_nonneg(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x >= 0


def test_quick_json_is_well_formed(quick_json: dict[str, Any]) -> None:
    r = quick_json
    assert r["schema"] == SCHEMA
    assert r["quick"] is True
    assert r["errors"] == {}
    m = r["machine"]
    assert m["logical_cores"] >= 1 and m["torch_threads"] >= 1
    assert m["device"] in ("cpu", "cuda") and isinstance(m["cpu_model"], str)
    from importlib import metadata

    assert m["packages"]["gpytorch"] == metadata.version("gpytorch")  # read from the environment
    assert r["settings"]["downsample"] >= 1 and r["settings"]["n_frames"] == 3


def test_quick_stage_latencies_are_sane(quick_json: dict[str, Any]) -> None:
    stages = quick_json["stages"]
    for k in STAGES:
        s = stages[k]
        assert s["n"] >= 1, k
        assert _finite_nonneg(s["median_ms"]) and _finite_nonneg(s["p95_ms"]), k
        assert s["p95_ms"] >= s["median_ms"] - 1e-9, k
        assert s["max_ms"] >= s["p95_ms"] - 1e-9, k


def test_quick_paper_vs_streaming(quick_json: dict[str, Any]) -> None:
    cmp = quick_json["paper_vs_streaming"]
    assert set(cmp) == {"complete", "partial"}
    for c in cmp.values():
        assert _finite_nonneg(c["streaming_last_frame_to_grasps_s"])
        assert _finite_nonneg(c["paper_last_frame_to_grasps_s"])
        ratio = c["paper_last_frame_to_grasps_s"] / c["streaming_last_frame_to_grasps_s"]
        assert c["ratio_paper_over_streaming"] == pytest.approx(ratio, rel=0.01, abs=0.01)
        rho = c["spearman_sigma2_occ"]
        assert rho is None or -1.0 <= rho <= 1.0
        assert c["top_grasp_same"] in (True, False, None)
        assert c["query_points"] > 0 and c["paper_epochs"] == 3
        assert c["paper_svgp_steps"] >= 3
        refined = c["spearman_after_idle_steps"]
        assert [x["steps"] for x in refined] == [4]
        assert _finite_nonneg(refined[0]["train_s"])
        assert refined[0]["spearman"] is None or -1.0 <= refined[0]["spearman"] <= 1.0
        # the converged reference: q(u) at its closed-form optimum can only raise the ELBO
        cv = c["converged_reference"]
        assert cv["paper_optimal_q_elbo_per_point"] >= cv["paper_elbo_per_point"] - 1e-4
        assert cv["streaming_optimal_q_elbo_per_point"] >= cv["streaming_refined_elbo_per_point"] - 1e-4
        for k in ("spearman_streaming_vs_paper_optimal_q", "spearman_paper_vs_its_optimal_q"):
            assert cv[k] is None or -1.0 <= cv[k] <= 1.0
        # the streaming run again with the paper's inducing-point count, on the same cloud; not
        # run where the streaming model already has it (on CUDA, M auto = 500 = the paper's)
        pm = c["streaming_at_paper_num_inducing"]
        if quick_json["settings"]["num_inducing"] == quick_json["settings"]["paper_num_inducing"]:
            assert pm is None
        else:
            assert pm["num_inducing"] == quick_json["settings"]["paper_num_inducing"]
            assert _finite_nonneg(pm["last_frame_to_grasps_s"]) and pm["svgp_steps"] >= 3 * 4
            assert pm["spearman_sigma2_occ"] is None or -1.0 <= pm["spearman_sigma2_occ"] <= 1.0
        dm = c["daemon"]
        # the daemon's own counters are kept, and no frame goes missing without a count
        assert dm["status_counts"]["integrated"] == dm["integrated"] <= dm["frames"]
        assert dm["integrated"] == dm["frames"] or any(dm["drops"].values()), dm
        assert "lost" in dm["upstream"]
        ag = dm["agreement_with_paper"]
        assert ag["cloud_received"] in (True, False)
        if ag["cloud_received"]:
            assert 0.0 <= ag["shared_fraction"] <= 1.0
    assert any("then idle training: +4 steps" in line for line in quick_json["table"])
    at_paper_m = any("streaming with the paper's M = 500" in line for line in quick_json["table"])
    assert at_paper_m == (quick_json["settings"]["num_inducing"] != 500)
    assert any("paper fit with q(u) at its optimum" in line for line in quick_json["table"])


def test_quick_throughput_replay_memory(quick_json: dict[str, Any]) -> None:
    tp = quick_json["throughput"]
    assert tp["source"] == "daemon" and len(tp["trials"]) >= 1
    for t in tp["trials"]:
        assert 0 <= t["integrated"] <= t["offered"]
        in_operation = t["fed_after_first_grasps_s"] >= _tiny().throughput_trial_s
        assert t["held"] == (t["integrated"] == t["offered"] and not any(t["drops"].values())
                             and in_operation)  # fmt: skip
    rp = quick_json["replay"]
    assert rp["frames_offered"] > 0 and rp["simulated_min"] > 0
    assert rp["rss_growth_frac"] is None or math.isfinite(rp["rss_growth_frac"])
    mem = quick_json["memory"]
    assert mem["peak_rss_mb"] > 0 and mem["peak_rss_mb"] >= mem["rss_end_mb"] - 1.0


def test_quick_targets_and_table(quick_json: dict[str, Any]) -> None:
    names = [t["target"] for t in quick_json["targets"]]
    assert any("paper / streaming" in n for n in names)
    assert any("sustained input" in n for n in names)
    assert any("RSS growth" in n for n in names)
    assert all(t["pass"] in (True, False, None) for t in quick_json["targets"])
    assert any(line.startswith("target") for line in quick_json["table"])


def test_targets_on_a_synthetic_result() -> None:
    """The judge itself, without running anything."""
    r: dict[str, Any] = {
        "quick": False,
        "wall_s": 600.0,
        "machine": {"cuda_available": False, "cpu_model": "x", "logical_cores": 2,
                    "torch": "t", "torch_threads": 1, "device": "cpu",
                    "load_average_at_start": [0.0]},
        "settings": {"object": "mug", "n_frames": 30, "resolution": [640, 480], "rate_hz": 10.0,
                     "downsample": 4, "num_inducing": 500, "batch_size": 1024,
                     "train_steps_per_frame": 4, "paper_epochs": 100},
        "stages": {"ingest": {"n": 30, "median_ms": 40.0, "p95_ms": 60.0, "max_ms": 70.0}},
        "paper_vs_streaming": {
            "complete": {
                "streaming_last_frame_to_grasps_s": 0.4, "paper_last_frame_to_grasps_s": 60.0,
                "ratio_paper_over_streaming": 75.0, "spearman_sigma2_occ": 0.95,
                "daemon": {"last_frame_to_grasps_s": 0.45, "train_steps_at_grasps": 44,
                           "agreement_with_paper": {
                               "cloud_received": True, "spearman_sigma2_occ": 0.85,
                               "last_frame_to_cloud_s": 1.2, "shared_fraction": 1.0}},
                "top_grasp_same": True, "top5_overlap": 1.0, "query_points": 100,
                "streaming_ready": True, "streaming_idle_steps_after_last_frame": 0,
            },
            "partial": {
                "streaming_last_frame_to_grasps_s": 0.5, "paper_last_frame_to_grasps_s": 40.0,
                "ratio_paper_over_streaming": 80.0, "spearman_sigma2_occ": 0.7,
                "spearman_paper_vs_paper_other_seed": 0.84,
                "top_grasp_same_paper_vs_paper_other_seed": False,
                "top5_overlap_paper_vs_paper_other_seed": 0.6,
                "streaming_at_paper_num_inducing": {
                    "num_inducing": 500, "last_frame_to_grasps_s": 1.25,
                    "train_per_frame_median_ms": 300.0, "svgp_steps": 120,
                    "spearman_sigma2_occ": 0.85, "top_grasp_same": False},
                "top_grasp_same": False, "top5_overlap": 0.4, "query_points": 100,
                "streaming_ready": True, "streaming_idle_steps_after_last_frame": 0,
            },
        },
        "throughput": {"source": "daemon", "sustained_hz": 5.0, "trials": [
            {"rate_hz": 20.0, "offered": 200, "integrated": 150, "drops": {"a": 50},
             "held": False, "latency": {}},
            {"rate_hz": 10.0, "offered": 100, "integrated": 90, "drops": {"a": 10},
             "held": False, "latency": {}},
            {"rate_hz": 5.0, "offered": 50, "integrated": 50, "drops": {"a": 0},
             "held": True, "latency": {}}]},
        "replay": {"source": "daemon", "rss_growth_frac": 0.02, "window_min": [5.0, 30.0],
                   "simulated_min": 30.0, "target_simulated_min": 30.0, "feed_wall_s": 1.0,
                   "speedup_vs_real_time": 7.5, "integrated": 10, "rss_window_start_mb": 1.0,
                   "rss_window_end_mb": 1.02},
        "memory": {"peak_rss_mb": 10.0},
    }
    targets = evaluate_targets(r)
    rows = {t["target"]: t["pass"] for t in targets}
    assert rows["streaming last frame -> grasps (complete)"] is True
    # the Spearman rows are information only, at any figure
    assert rows["Spearman streaming sigma2_occ vs paper (partial)"] is None
    name = "Spearman streaming sigma2_occ vs paper (partial)"
    note = next(t["note"] for t in targets if t["target"] == name)
    assert "paper vs paper, other seed: 0.840" in note
    assert "streaming with the paper's M = 500: 0.850 (synchronous, 1.25 s)" in note
    assert rows["paper / streaming time (complete)"] is True
    assert rows["Spearman streaming sigma2_occ vs paper (complete)"] is None
    assert rows["daemon last frame -> its grasps (complete)"] is True
    assert rows["Spearman daemon's sigma2_occ vs paper (complete)"] is None
    assert all(t["required"] == "info" for t in targets if t["target"].startswith("Spearman"))
    assert "Spearman daemon's sigma2_occ vs paper (partial)" not in rows
    assert rows["sustained input without drops (daemon)"] is False
    assert rows["median ingest (depth + back-projection + FOF)"] is True
    assert rows["RSS growth, minute 5 -> 30 of replay"] is True
    assert rows["CUDA SVGP steps/s vs CPU"] is None
    assert rows["whole benchmark wall time"] is True
    r["targets"] = evaluate_targets(r)
    table = format_table(r)
    assert any("FAIL" in line for line in table) and any("PASS" in line for line in table)
    assert any("the daemon itself (10 Hz, its own schedule; 44 SVGP steps at the grasps): last "
               "frame -> grasps 0.45 s, its cloud 1.20 s, spearman of that cloud's sigma2_occ 0.850"
               in line for line in table)  # fmt: skip
    assert any("streaming with the paper's M = 500 (synchronous): last frame -> grasps 1.25 s, "
               "training 300 ms per frame" in line for line in table)  # fmt: skip
    # the reference's own repeatability, at the grasp level too; only where the second fit ran
    seed_lines = [line for line in table if "the paper fit against itself" in line]
    assert seed_lines == [
        f"{'':<11} the paper fit against itself with another svgp.seed: spearman 0.840, "
        "top grasp same no, top5 0.6"
    ]
    # a ladder that starts above 10 Hz: the highest rate held is what counts
    r["throughput"]["trials"][1]["held"] = True
    r["throughput"]["sustained_hz"] = 10.0
    rows = {t["target"]: t["pass"] for t in evaluate_targets(r)}
    assert rows["sustained input without drops (daemon)"] is True


def test_the_cuda_target_is_judged_at_the_daemons_m_on_cuda() -> None:
    """The CUDA section times both automatic M; the row is judged at CUDA's and names the other."""

    def step(cpu: float, cuda: float) -> dict[str, Any]:
        return {"svgp_steps_per_s_cpu": cpu, "svgp_steps_per_s_cuda": cuda,
                "speedup_steps_per_s": round(cuda / cpu, 2),
                "svgp_step_cpu": {}, "svgp_step_cuda": {}}  # fmt: skip

    cu: dict[str, Any] = {"M250": step(20.0, 80.0), "M500": step(5.0, 75.0), "num_inducing_cuda": 500,
                          "algorithm1_20k_cuda": {"median_ms": 45.0}}  # fmt: skip
    cu.update({k: cu["M500"][k] for k in cu["M500"]})
    r: dict[str, Any] = {"quick": False, "machine": {"cuda_available": True}, "cuda": cu}
    row = next(t for t in evaluate_targets(r) if t["target"] == "CUDA SVGP steps/s vs CPU")
    assert row["measured"] == 15.0 and row["pass"] is True
    assert row["note"] == "at M = 500, the daemon's on CUDA; M = 250: 4.0x"
    cu["num_inducing_cuda"] = 250
    cu.update({k: cu["M250"][k] for k in cu["M250"]})
    row = next(t for t in evaluate_targets(r) if t["target"] == "CUDA SVGP steps/s vs CPU")
    assert row["measured"] == 4.0 and row["pass"] is False and "M = 500: 15.0x" in row["note"]


def test_the_full_throughput_ladder_starts_above_the_target() -> None:
    rates = BenchOptions.full().throughput_rates_hz
    assert max(rates) > 10.0 and 10.0 in rates
    assert BenchOptions.full().streaming_at_paper_m and not _QUICK.streaming_at_paper_m


def test_match_points_pairs_coinciding_points_only() -> None:
    rng = np.random.default_rng(0)
    ref_W = rng.uniform(-0.1, 0.1, size=(200, 3))
    perm = rng.permutation(200)
    # the same points in another order, float32-rounded as a PointCloud2 carries them, plus
    # three points that are not in the reference and one that is 1 mm off
    other_W = np.concatenate([ref_W[perm].astype(np.float32).astype(np.float64),
                              rng.uniform(0.5, 0.6, size=(3, 3)), ref_W[:1] + 1e-3])  # fmt: skip
    ia, ib = match_points(other_W, ref_W)
    assert len(ia) == 200
    np.testing.assert_array_equal(ib, perm[ia])
    assert not set(ia.tolist()) & {200, 201, 202, 203}


def _fake_feed(cloud: CloudMsg | None) -> Any:
    def feed(*args: Any, **kwargs: Any) -> dict[str, Any]:
        assert kwargs["cloud_timeout_s"] > 0  # a reference asks for the cloud
        st = {"counts": {"integrated": 3, "train_steps": 12}, "ready": True,
              "mailboxes": {"stereo": {"dropped": 0}, "depth": {"dropped": 0}},
              "ingress": {"dropped": 0}, "waiting": {"unpaired_dropped": 0, "unpaired": 0},
              "upstream": {"lost": {}}}  # fmt: skip
        return {"status": st, "sent": 3, "last_frame_to_grasps_s": 0.4, "grasps_received": 1,
                "train_steps_at_grasps": 9, "last_frame_cloud": cloud,
                "last_frame_to_cloud_s": None if cloud is None else 0.9}  # fmt: skip
    return feed


def _cloud(points_W: np.ndarray, sigma2: np.ndarray) -> CloudMsg:
    f = {k: points_W[:, i].astype(np.float32) for i, k in enumerate("xyz")}
    f["sigma2_occ"] = sigma2.astype(np.float32)
    return CloudMsg(1, "world", f)


def test_the_daemon_agreement_is_taken_on_the_shared_points(monkeypatch: pytest.MonkeyPatch) -> None:
    """The daemon's published cloud against the reference: point order does not matter, a
    monotone transform of the reference agrees perfectly, reversed ranks give -1, and a cloud
    that shares too few points gives no figure (and the target says why)."""
    rng = np.random.default_rng(1)
    ref_W = rng.uniform(-0.1, 0.1, size=(300, 3))
    ref_s2 = rng.uniform(0.0, 1.0, size=300)
    perm = rng.permutation(300)
    opts = _tiny()
    cases = [
        (_cloud(ref_W[perm], np.exp(3.0 * ref_s2[perm])), 1.0, 1.0),
        (_cloud(ref_W[perm], -ref_s2[perm]), -1.0, 1.0),
        (_cloud(ref_W[perm[:150]], ref_s2[perm[:150]]), None, 0.5),
    ]
    for cloud, want, share in cases:
        monkeypatch.setattr(measure, "daemon_feed", _fake_feed(cloud))
        out = measure.daemon_last_frame(PugsdConfig(), [], opts, lambda s: None, (ref_W, ref_s2))
        ag = out["agreement_with_paper"]
        assert ag["cloud_received"] and ag["shared_fraction"] == pytest.approx(share)
        if want is None:
            assert ag["spearman_sigma2_occ"] is None
        else:
            assert ag["spearman_sigma2_occ"] == pytest.approx(want, abs=1e-9)
        assert out["train_steps_at_grasps"] == 9
    r: dict[str, Any] = {"quick": False, "machine": {}, "paper_vs_streaming": {"partial": {
        "streaming_last_frame_to_grasps_s": 0.2, "ratio_paper_over_streaming": 200.0,
        "spearman_sigma2_occ": 0.95, "daemon": out}}}  # fmt: skip
    row = next(t for t in evaluate_targets(r) if t["target"].startswith("Spearman daemon"))
    assert row["pass"] is None and "share 50% of points" in row["note"]
    monkeypatch.setattr(measure, "daemon_feed", _fake_feed(None))
    out = measure.daemon_last_frame(PugsdConfig(), [], opts, lambda s: None, (ref_W, ref_s2))
    assert out["agreement_with_paper"] == {"cloud_received": False, "spearman_sigma2_occ": None}
    r["paper_vs_streaming"]["partial"]["daemon"] = out
    row = next(t for t in evaluate_targets(r) if t["target"].startswith("Spearman daemon"))
    assert row["pass"] is None and row["note"] == "no cloud for the last frame"


def test_tools_bench_is_executable() -> None:
    p = Path(__file__).resolve().parents[2] / "tools" / "bench"
    assert p.is_file() and p.stat().st_mode & 0o111


def test_no_pipeline_runs_the_daemon_sections_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--no-pipeline`` (for machines with a per-command time limit): no stage latencies and no
    paper fit, but the daemon's last-frame latency, throughput and replay are measured and judged."""
    path = tmp_path / "bench.json"
    mp = pytest.MonkeyPatch()
    mp.setattr(
        BenchOptions, "quick_preset", classmethod(lambda cls: _tiny().replace(trajectories=("partial",)))
    )
    try:
        rc = main(["bench", "--quick", "--no-pipeline", "--json", str(path)])
    finally:
        mp.undo()
    assert rc == 0
    r = json.loads(path.read_text())
    assert "stages" not in r and r["paper_vs_streaming"] == {}
    dm = r["daemon_alone"]["partial"]
    # the synthetic camera publishes as a camera does (zenoh congestion control DROP), so on a
    # loaded machine a message can be lost before it reaches the daemon: at least one frame in
    assert dm["frames"] == 3 and 1 <= dm["integrated"] <= 3, dm
    assert dm["agreement_with_paper"] is None
    assert r["throughput"]["trials"] and r["replay"]["frames_offered"] > 0
    names = [t["target"] for t in r["targets"]]
    assert "daemon last frame -> its grasps (partial)" in names
    assert not any("Spearman" in n or "paper / streaming" in n for n in names)
    assert any(line.startswith("the daemon alone") for line in r["table"])
    assert not any(line.startswith(("stage", "paper mode")) for line in r["table"])
    capsys.readouterr()
    assert main(["bench", "--quick", "--no-pipeline", "--no-daemon"]) == 2
    assert "leave nothing to measure" in capsys.readouterr().err


def _grasps(ids: np.ndarray, sigma2_cloud: np.ndarray, stamp_ns: int) -> ScoredGrasps:
    """Grasps at query-cloud points ``ids`` (their ids, as ``rank_grasps`` sets them), scored
    with the cloud's ``sigma2_cloud``; the contacts lie off the cloud points, as the proposer's do."""
    n = len(ids)
    return ScoredGrasps(
        pose_W=np.tile(np.eye(4), (n, 1, 1)), contact_W=np.full((n, 3), 0.5),
        width_m=np.full(n, 0.05), baseline_confidence=np.full(n, 0.5),
        sigma2_occ=sigma2_cloud[ids], pugs_confidence=np.full(n, 0.4),
        grasp_id=np.asarray(ids, dtype=np.int64), stamp_ns=stamp_ns,
    )  # fmt: skip


def test_the_daemons_cloud_must_come_from_the_computation_that_scored_the_first_grasps() -> None:
    """While frames stream the daemon publishes grasps without the cloud; then the first cloud
    stamped with the last frame comes from a later grasp round on a further-trained model. Its
    sigma2_occ is not that of the model that scored the first grasps (whose latency and step
    count the bench reports), so it is kept apart (``later_cloud``) instead of being taken as the
    last frame's cloud."""
    rng = np.random.default_rng(2)
    cloud_W = rng.uniform(-0.1, 0.1, size=(200, 3))
    s2_first = rng.uniform(0.0, 1.0, size=200)  # the model that scored the first grasps
    s2_later = s2_first + rng.normal(0.0, 0.05, size=200)  # a few dozen SVGP steps later
    contacts = np.array([5, 17, 80])
    stamp = 1_000
    g_first = _grasps(contacts, s2_first, stamp)
    g_later = _grasps(contacts, s2_later, stamp)
    old = _grasps(contacts, s2_first * 0.5, stamp - 100)  # the frame before
    assert measure.cloud_scored_grasps(g_first, _cloud(cloud_W, s2_first)) is True
    assert measure.cloud_scored_grasps(g_first, _cloud(cloud_W, s2_later)) is False
    assert measure.cloud_scored_grasps(g_first, _cloud(cloud_W[:50], s2_first[:50])) is None

    # the first grasps for the last frame came with their cloud
    grasps_rx = [(10.0, old, 30), (10.4, g_first, 44), (11.5, g_later, 80)]
    first_cloud = dataclasses.replace(_cloud(cloud_W, s2_first), stamp_ns=stamp)
    later_cloud = dataclasses.replace(_cloud(cloud_W, s2_later), stamp_ns=stamp)
    clouds_rx = [(10.8, first_cloud, 52), (11.9, later_cloud, 90)]
    out = measure.last_frame_outputs(grasps_rx, clouds_rx, t_last=10.1, stamp_last=stamp)
    assert out["last_frame_to_grasps_s"] == pytest.approx(0.3)
    assert out["train_steps_at_grasps"] == 44 and out["cloud_scored_first_grasps"] is True
    assert out["last_frame_to_cloud_s"] == pytest.approx(0.7) and out["train_steps_at_cloud"] == 52
    assert out["later_cloud"] is None
    # they came without one: the first cloud for the frame is the later round's
    out = measure.last_frame_outputs(grasps_rx, clouds_rx[1:], t_last=10.1, stamp_last=stamp)
    assert out["train_steps_at_grasps"] == 44 and out["cloud_scored_first_grasps"] is False
    assert out["last_frame_cloud"] is None and out["last_frame_to_cloud_s"] is None
    assert out["later_cloud"]["train_steps"] == 90
    assert out["later_cloud"]["to_cloud_s"] == pytest.approx(1.8)
    # rounds that proposed no grasps cannot tell by their values: the order of receipt does
    # (each round's grasps, then its cloud, then the next round's grasps)
    none = np.zeros(0, dtype=np.int64)
    empty_rx = [(10.0, old, 30), (10.4, _grasps(none, s2_first, stamp), 44),
                (11.5, _grasps(none, s2_later, stamp), 80)]  # fmt: skip
    out = measure.last_frame_outputs(empty_rx, clouds_rx, t_last=10.1, stamp_last=stamp)
    assert out["cloud_scored_first_grasps"] is True and out["train_steps_at_cloud"] == 52
    out = measure.last_frame_outputs(empty_rx, clouds_rx[1:], t_last=10.1, stamp_last=stamp)
    assert out["cloud_scored_first_grasps"] is False and out["last_frame_cloud"] is None
    assert out["later_cloud"]["train_steps"] == 90

    # what daemon_last_frame and the targets make of it: no figure for the first grasps' model
    def feed(*args: Any, **kwargs: Any) -> dict[str, Any]:
        st = {"counts": {"integrated": 3, "train_steps": 95}, "ready": True,
              "mailboxes": {"stereo": {"dropped": 0}, "depth": {"dropped": 0}},
              "ingress": {"dropped": 0}, "waiting": {"unpaired_dropped": 0, "unpaired": 0},
              "upstream": {"lost": {}}}  # fmt: skip
        return {"status": st, "sent": 3, "grasps_received": 3, **out}

    mp = pytest.MonkeyPatch()
    mp.setattr(measure, "daemon_feed", feed)
    try:
        dm = measure.daemon_last_frame(PugsdConfig(), [], _tiny(), lambda s: None, (cloud_W, s2_first))
    finally:
        mp.undo()
    ag = dm["agreement_with_paper"]
    assert ag["cloud_received"] is False and ag["spearman_sigma2_occ"] is None
    assert ag["cloud_scored_first_grasps"] is False
    assert ag["later_cloud"]["train_steps_at_cloud"] == 90
    assert 0.9 < ag["later_cloud"]["spearman_sigma2_occ"] < 1.0
    r: dict[str, Any] = {"quick": False, "machine": {}, "paper_vs_streaming": {"partial": {
        "streaming_last_frame_to_grasps_s": 0.2, "ratio_paper_over_streaming": 200.0,
        "spearman_sigma2_occ": 0.95, "daemon": dm}}}  # fmt: skip
    row = next(t for t in evaluate_targets(r) if t["target"].startswith("Spearman daemon"))
    assert row["pass"] is None
    assert row["note"].startswith("the first grasps for the last frame came without a cloud; the "
                                  "next cloud for that frame (90 SVGP steps, 1.80 s): spearman 0.9")
    r["machine"] = {"cpu_model": "x", "logical_cores": 2, "torch": "t", "torch_threads": 1,
                    "device": "cpu", "load_average_at_start": [0.0]}
    r["settings"] = {"object": "mug", "n_frames": 3, "resolution": [320, 240], "rate_hz": 10.0,
                     "downsample": 4, "num_inducing": 250, "batch_size": 1024,
                     "train_steps_per_frame": 4, "paper_epochs": 3}
    r["paper_vs_streaming"]["partial"].update(
        paper_last_frame_to_grasps_s=40.0, top_grasp_same=None, top5_overlap=None,
        query_points=200, streaming_ready=True, streaming_idle_steps_after_last_frame=0)
    line = next(x for x in format_table(r) if "the daemon itself" in x)
    assert "44 SVGP steps at the grasps): last frame -> grasps 0.30 s, no cloud with those grasps; " \
        "the next cloud for that frame (90 SVGP steps, 1.80 s): spearman 0.9" in line


def _result(**extra: Any) -> dict[str, Any]:
    r: dict[str, Any] = {
        "quick": False, "wall_s": 420.0, "machine": {"cuda_available": False},
        "stages": {"ingest": {"n": 70, "median_ms": 20.0}},
        "paper_vs_streaming": {},
        "throughput": {"source": "daemon", "sustained_hz": 10.0, "trials": [
            {"rate_hz": 10.0, "offered": 100, "integrated": 100, "drops": {}, "held": True}]},
        "replay": {"rss_growth_frac": 0.01, "window_min": [5.0, 30.0], "simulated_min": 30.0,
                   "target_simulated_min": 30.0},
    }  # fmt: skip
    r.update(extra)
    return r


def _row(r: dict[str, Any], name: str) -> dict[str, Any]:
    return next(t for t in evaluate_targets(r) if t["target"].startswith(name))


def test_the_wall_time_target_is_judged_on_a_whole_run_only() -> None:
    """``--no-daemon`` / ``--no-pipeline`` runs are halves of the benchmark: their wall time says
    nothing about the 15-minute target (the recorded 2.4 min --no-daemon run passed it)."""
    assert _row(_result(), "whole benchmark wall time")["pass"] is True
    for skip in ("pipeline", "daemon"):
        sections = {"pipeline": True, "daemon": True, skip: False}
        row = _row(_result(settings={"sections": sections}), "whole benchmark wall time")
        assert row["pass"] is None and row["measured"] == "7.0 min", skip
        assert row["note"] == f"not the whole benchmark: the {skip} sections skipped"
    # results written before the sections were recorded: told from what they hold
    no_daemon = {k: v for k, v in _result().items() if k not in ("throughput", "replay")}
    assert _row(no_daemon, "whole benchmark wall time")["pass"] is None
    no_pipeline = _result(daemon_alone={"partial": {}})
    del no_pipeline["stages"]
    assert _row(no_pipeline, "whole benchmark wall time")["pass"] is None


def test_a_quick_run_says_so_on_every_row_it_judges() -> None:
    cu = {"speedup_steps_per_s": 6.0, "num_inducing_cuda": 500, "algorithm1_20k_cuda": {"median_ms": 40.0}}
    r = _result(quick=True, cuda=cu, machine={"cuda_available": True})
    for t in evaluate_targets(r):
        if t["pass"] is not None:
            assert "quick run" in t["note"], t


def test_an_undefined_spearman_gets_no_verdict_and_says_why() -> None:
    """A NaN Spearman (information only, like every Spearman row) says why it has no figure."""
    pvs = {"streaming_last_frame_to_grasps_s": 0.5, "paper_last_frame_to_grasps_s": 40.0,
           "ratio_paper_over_streaming": 80.0, "spearman_sigma2_occ": float("nan"),
           "spearman_paper_vs_paper_other_seed": 0.9,
           "daemon": {"last_frame_to_grasps_s": 0.6, "agreement_with_paper": {
               "cloud_received": True, "spearman_sigma2_occ": float("nan"),
               "shared_fraction": 1.0}}}  # fmt: skip
    r = _result(paper_vs_streaming={"partial": pvs})
    for name in ("Spearman streaming sigma2_occ vs paper", "Spearman daemon's sigma2_occ vs paper"):
        row = _row(r, name)
        assert row["pass"] is None, name
        assert row["note"].startswith("Spearman undefined (NaN)"), row
    assert "paper vs paper, other seed: 0.900" in _row(r, "Spearman streaming")["note"]
    pvs["spearman_sigma2_occ"] = 0.95
    row = _row(r, "Spearman streaming sigma2_occ vs paper")
    assert row["pass"] is None and row["note"] == "paper vs paper, other seed: 0.900"


def test_the_drain_waits_for_messages_still_in_the_ingress_queue() -> None:
    """A message zenoh handed over but the loop has not taken yet is not drained: before, the
    throughput trial's drain looked at the mailboxes only and could judge a rate while the last
    frames sat in the ingress queue."""
    st = {"ingress": {"pending": 3, "dropped": 0},
          "mailboxes": {"stereo": {"queued": 0}, "depth": {"queued": 0}}}  # fmt: skip
    assert measure.drain_queued(st) == 3
    st["ingress"]["pending"] = 0
    st["mailboxes"]["depth"]["queued"] = 1
    assert measure.drain_queued(st) == 1
