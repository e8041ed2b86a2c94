# SPDX-License-Identifier: Apache-2.0
"""The evaluation: Wilson intervals, the Table I layout, and the CI variant end to end; the per-cell
numbers of the results file (what Table I is read from), on hand-made trials: successes, rates,
Wilson intervals, seeds, trials without a grasp, shared grasps."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pugsd.cli import main
from pugsd.sim.evaluate import METRICS, aggregate_cells, markdown_table, rescore, wilson_interval


def test_wilson_interval_reference_values() -> None:
    lo, hi = wilson_interval(0, 5)
    assert lo == 0.0 and hi == pytest.approx(0.4345, abs=1e-4)
    lo, hi = wilson_interval(5, 5)
    assert lo == pytest.approx(0.5655, abs=1e-4) and hi == 1.0
    lo, hi = wilson_interval(10, 20)
    assert lo == pytest.approx(0.2993, abs=1e-4) and hi == pytest.approx(0.7007, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_mcnemar_exact_reference_values() -> None:
    from pugsd.sim.evaluate import mcnemar_exact_p, paired_tests

    assert mcnemar_exact_p(0, 0) == 1.0
    assert mcnemar_exact_p(0, 4) == pytest.approx(0.125)  # 2 * 0.5^4
    assert mcnemar_exact_p(1, 5) == pytest.approx(0.21875)  # 2 * 7 / 64
    assert mcnemar_exact_p(0, 6) == pytest.approx(0.03125)
    assert mcnemar_exact_p(3, 3) == 1.0
    # paired on the same sequences: only the discordant ones count
    trials = [
        {"object": "mug", "recon": "partial", "seed": i,
         "methods": {"baseline": dict.fromkeys(METRICS, i < 2), "pugs": dict.fromkeys(METRICS, i < 7)}}
        for i in range(10)
    ]  # fmt: skip
    rows = paired_tests(trials, ["mug"], ["partial"])
    assert [(r["metric"], r["a"], r["b"], r["a_only"], r["b_only"]) for r in rows] == [
        (m, "pugs", "baseline", 5, 0) for m in METRICS
    ]
    assert rows[0]["mcnemar_p"] == pytest.approx(0.0625)


def _fake_results() -> dict:
    cells = []
    for obj in ("kettlebell", "mug"):
        for rc in ("partial",):
            for me in ("baseline", "pugs"):
                k = 3 if me == "pugs" else 1
                cells.append({
                    "object": obj, "recon": rc, "mode": "streaming", "method": me, "n": 5,
                    "successes": dict.fromkeys(METRICS, k), "seeds": [0, 1, 2, 3, 4],
                    "failures": {"no_grasp": 0, "traversal": 5 - k, "close": 0, "lift_hold": 0},
                    "from_behind": 4 - k, "candidates_min": 7, "candidates_median": 12.0,
                })
    paired = [
        {"object": o, "recon": "partial", "mode": "streaming", "metric": "lifted", "a": "pugs",
         "b": "baseline", "n": 5, "a_only": 2, "b_only": 0, "mcnemar_p": 0.5}
        for o in ("kettlebell", "mug")
    ]
    return {
        "settings": {"objects": ["kettlebell", "mug"], "recons": ["partial"],
                     "methods": ["baseline", "pugs"], "trials": 5, "seed": 0,
                     "modes": ["streaming"], "pose": "upright"},
        "cells": cells,
        "paired": paired,
        "auc": [{"recon": "partial", "mode": "streaming", "n": 40, "traversal_rate": 0.5,
                 "confidence": 0.4, "pugs": 0.9, "pugs_contact": 0.6, "neg_unknown_share": 0.95,
                 "neg_sigma2_occ": None}],
    }


def test_table_layout() -> None:
    t = markdown_table(_fake_results())
    lines = t.splitlines()
    assert lines[0].startswith("| Mode | Method | Reconstruction | Grasp Traversal Success: kettlebell")
    assert "| streaming | PUGS (swept volume) | Partial | 60% (3/5) [23-88]" in t
    assert "| streaming | Baseline (single-contact, visibility-naive) | Partial | 20% (1/5) [4-62]" in t
    # failures no grasp / traversal / close / lift-hold, picks from behind, candidates, McNemar
    assert "| streaming | mug | Partial | 0/4/0/0 / 3 / 7-12 | 0/2/0/0 / 1 / 7-12 | 2:0 p=0.5 |" in t
    assert "| streaming | Partial | 40 | 0.50 | 0.40 | 0.90 | 0.60 | 0.95 | - |" in t
    assert "Paper Table I" in t  # shown next to ours when both paper objects are evaluated


def test_evaluate_ci_variant(tmp_path: Path) -> None:
    """One object, one reconstruction type, N = 2, through the real pipeline and MuJoCo."""
    out = tmp_path / "results.json"
    figs = tmp_path / "figures"
    rc = main([
        "evaluate", "--objects", "mug", "--recon", "partial", "--trials", "2", "--frames", "6",
        "--json", str(out), "--figures", str(figs), "--quiet",
    ])
    assert rc == 0
    res = json.loads(out.read_text())
    cells = {c["method"]: c for c in res["cells"]}
    assert set(cells) == {"baseline", "antipodal", "pugs", "pugs_contact"}
    for name, c in cells.items():
        assert c["n"] == 2 and c["seeds"] == [0, 1] and c["mode"] == "streaming"
        assert set(c["successes"]) == set(METRICS)
        s = c["successes"]
        assert 0 <= s["lifted"] <= s["closed"] <= s["traversal"] <= 2  # cumulative metrics
        # every failure is counted once, at the first stage the pick did not pass
        assert sum(c["failures"].values()) == 2 - s["lifted"]
        if name != "antipodal":
            assert c["no_grasp"] == 0 and c["candidates_min"] >= 1  # single-contact proposals
    for t in res["trials"]:
        assert "error" not in t, t.get("error")
        for name, m in t["methods"].items():
            if name == "antipodal" and m["grasp"] is None:
                continue  # the antipodal proposer may find no observed pair on a partial scan
            assert m["grasp"] is not None
            assert len(m["grasp"]["pose_W"]) == 4
            assert "traversal_max_penetration_m" in m["details"]
            assert 0.0 <= m["grasp"]["approach_view_angle_deg"] <= 180.0
        assert 0 < len(t["auc_samples"]) <= 8
        assert all(0.0 <= a["unknown_share"] <= 1.0 for a in t["auc_samples"])
    g = res["trials"][0]["methods"]["pugs"]["grasp"]
    assert 0.0 <= g["pugs_confidence"] <= g["baseline_confidence"] <= 1.0  # readable, Eq. 13
    pngs = sorted(figs.glob("*.png"))
    assert [p.name for p in pngs] == ["mug_partial_seed0_streaming.png"]
    assert pngs[0].stat().st_size > 20_000
    assert "| streaming | PUGS (swept volume) | Partial |" in res["table_markdown"]
    # the physics is deterministic: re-scoring the stored grasps reproduces every outcome
    again = rescore(res)
    assert [c["successes"] for c in again["cells"]] == [c["successes"] for c in res["cells"]]
    # the paired tests of PUGS against the other three on the same sequences, one row per metric
    assert [(p["b"], p["metric"]) for p in res["paired"]] == [
        (b, m) for b in ("baseline", "antipodal", "pugs_contact") for m in METRICS
    ]
    assert again["paired"] == res["paired"]
    assert [a["recon"] for a in res["auc"]] == ["partial", "all"]


def test_evaluate_rejects_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", "--objects", "teapot", "--trials", "1"]) == 1
    assert "teapot" in capsys.readouterr().err
    assert main(["evaluate", "--object-mesh", "x.stl", "--trials", "1"]) == 1  # needs --mass


@pytest.mark.parametrize("width", [160, 320, 640])
def test_disparity_search_reaches_the_nearest_surface(width: int) -> None:
    """At every --resolution the matcher's disparity range covers the object's nearest surface.

    With the old fixed default of 64 px (16 levels at the 160-px matching resolution) the search
    reached only 0.40 m at 640 x 480, while the cameras see the object from 0.35 m: 20-40 % of
    its pixels were matched at a wrong (aliased) disparity and still marked valid. The default
    search is now sized from the rig to reach ``stereo.min_depth_m``.
    """
    from pugsd.core.stereo import StereoDepth, disparity_levels
    from pugsd.core.stereo import reach_m as stereo_reach_m
    from pugsd.sim import make_sequence
    from pugsd.sim.evaluate import EvalOptions, _core_config

    opts = EvalOptions(objects=["mug"], recons=["partial"], width=width, height=width * 3 // 4)
    seq = make_sequence("mug", "partial", n_frames=2, width=opts.width, height=opts.height, seed=0)
    cfg = _core_config(opts, seq.core_overrides)
    z_near = min(float(np.nanmin(d[m])) for d, m in zip(seq.depth_gt_m, seq.masks))
    assert z_near < 0.4  # the case that needed more than 64 px at 640 x 480
    assert stereo_reach_m(cfg.stereo, seq.rig) < 0.8 * z_near
    if width == 320:  # the recorded Table I ran at 320 x 240 with 64 px: the same 32 levels
        assert cfg.stereo.downsample == 2 and disparity_levels(cfg.stereo, seq.rig) == 32
    # the nearest part of the object is measured, not aliased
    ds = cfg.stereo.downsample
    errs = []
    for f, d, m in zip(seq.frames, seq.depth_gt_m, seq.masks):
        z = StereoDepth(cfg.stereo).estimate(f).depth_m
        gt, mm = d[ds // 2 :: ds, ds // 2 :: ds], m[ds // 2 :: ds, ds // 2 :: ds]
        near = mm & (gt < 0.4)
        errs.append(np.abs(z - gt)[near])
    err = np.concatenate(errs)
    assert err.size > 20 and np.mean(np.isfinite(err)) > 0.8
    assert np.nanmedian(err) < 0.008  # measured 3 mm at 640 (15 mm with 64 px), 4-8 mm at 160-320


def test_explicit_disparity_override_wins() -> None:
    from pugsd.core.stereo import disparity_levels
    from pugsd.sim.evaluate import EvalOptions, _core_config
    from pugsd.sim.render import default_rig

    opts = EvalOptions(width=640, height=480, overrides=["stereo.num_disparities=48"])
    cfg = _core_config(opts, {})
    assert cfg.stereo.num_disparities == 48 and cfg.stereo.downsample == 4
    assert disparity_levels(cfg.stereo, default_rig(640, 480)) == 16


def test_user_meshes_with_the_same_name_get_their_own_physics(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two user meshes called thing.stl evaluated in one process are each trialled on themselves
    (the MuJoCo model cache was keyed by file stem and pose only)."""
    from types import SimpleNamespace

    import trimesh

    from pugsd.sim import evaluate
    from pugsd.sim.physics import GraspTrial, TrialResult

    paths = []
    for sub, ext in (("a", (0.04, 0.04, 0.04)), ("b", (0.08, 0.05, 0.03))):
        (tmp_path / sub).mkdir()
        p = tmp_path / sub / "thing.stl"
        trimesh.creation.box(extents=ext).export(p)
        paths.append((str(p), np.array(ext)))

    class Grasps(SimpleNamespace):
        def __len__(self) -> int:
            return len(self.pose_W)

    def one(n: int) -> Grasps:
        return Grasps(
            pose_W=np.eye(4)[None].repeat(n, 0), contact_W=np.zeros((n, 3)), width_m=np.full(n, 0.03),
            baseline_confidence=np.ones(n), sigma2_occ=np.ones(n), pugs_confidence=np.ones(n),
            grasp_id=np.arange(n), unknown_share=None, sigma2_grasp=None,
        )  # fmt: skip

    fake = SimpleNamespace(
        grasps=one(1), baseline_grasps=one(1), cloud_W=np.zeros((5, 3)),
        candidates=SimpleNamespace(valid=np.ones(1, bool)),
    )  # fmt: skip
    scored = {"streaming": {"swept": fake, "contact": fake, "antipodal": fake}}
    monkeypatch.setattr(evaluate, "_scored", lambda *a, **k: (np.zeros((1, 3)), scored, {}))
    seen: list[np.ndarray] = []

    def run(self: GraspTrial, pose_W: np.ndarray, traversal_only: bool = False) -> TrialResult:
        seen.append(np.sort(self.obj.extents_m))
        return TrialResult(False, False, False, {})

    monkeypatch.setattr(GraspTrial, "run", run)
    monkeypatch.setattr(evaluate, "_TRIALS", {})
    for path, ext in paths:
        opts = evaluate.EvalOptions(
            recons=["partial"], methods=["pugs"], trials=1, width=160, height=120, n_frames=1,
            object_mesh=path, mass_kg=0.3, auc_candidates=0,
        )  # fmt: skip
        evaluate._run_job(opts, evaluate.Job("thing", "partial", 0, 0))
        np.testing.assert_allclose(seen[-1], np.sort(ext), atol=1e-6)


def test_figures_draw_the_configured_gripper() -> None:
    """The figure's gripper is the proposer's (``grasp.gripper``), not a fixed size."""
    from pugsd.config import GripperConfig
    from pugsd.sim.figures import gripper_lines

    T_W_G = np.eye(4)
    T_W_G[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # approach a = +x
    T_W_G[:3, 3] = [1.0, 2.0, 3.0]
    g = GripperConfig(depth_m=0.12, finger_length_m=0.06, palm_depth_m=0.02)
    fingers, palm = gripper_lines(T_W_G, 0.05, g)
    # fingertips at depth + L/2 along the approach, 0.05 m apart along the closing axis b (= -z)
    np.testing.assert_allclose(fingers, [[1.15, 2.0, 3.025], [1.09, 2.0, 3.025],
                                         [1.09, 2.0, 2.975], [1.15, 2.0, 2.975]], atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(palm, [[1.09, 2.0, 3.0], [1.07, 2.0, 3.0]], atol=1e-12)
    default = gripper_lines(T_W_G, 0.05)[0]
    assert default[0, 0] == pytest.approx(1.0 + 0.09 + 0.0225)  # the Bravo 7 defaults


def _method(traversal: bool, closed: bool, lifted: bool, grasp: bool = True) -> dict[str, Any]:
    return {
        "traversal": traversal, "closed": closed, "lifted": lifted,
        "grasp": {"grasp_id": 1} if grasp else None,
    }  # fmt: skip


def test_cells_count_rates_and_missing_grasps() -> None:
    T, F = True, False
    rows = [  # seed: (baseline, pugs)
        (0, _method(T, T, T), _method(T, T, T)),
        (1, _method(T, F, F), _method(T, T, F)),
        (2, _method(F, F, F, grasp=False), _method(T, T, T)),
        (3, _method(F, F, F, grasp=False), _method(F, F, F, grasp=False)),
        (4, _method(T, T, F), _method(T, T, T)),
    ]
    trials = [
        {"object": "mug", "recon": "partial", "seed": s, "methods": {"baseline": b, "pugs": p},
         "same_grasp": s == 0}
        for s, b, p in rows
    ]  # fmt: skip
    trials.append({"object": "kettlebell", "recon": "partial", "seed": 0, "methods": {
        "baseline": _method(T, T, T), "pugs": _method(T, T, T)}})  # fmt: skip
    cells = aggregate_cells(trials, ["mug", "kettlebell"], ["partial", "complete"], ["baseline", "pugs"])
    by = {(c["object"], c["recon"], c["method"]): c for c in cells}
    assert len(cells) == 8
    base, pugs = by[("mug", "partial", "baseline")], by[("mug", "partial", "pugs")]
    assert base["n"] == pugs["n"] == 5 and base["seeds"] == [0, 1, 2, 3, 4]
    assert base["successes"] == {"traversal": 3, "closed": 2, "lifted": 1}
    assert pugs["successes"] == {"traversal": 4, "closed": 4, "lifted": 3}
    assert base["rates"] == {"traversal": 0.6, "closed": 0.4, "lifted": 0.2}
    assert pugs["rates"] == {"traversal": 0.8, "closed": 0.8, "lifted": 0.6}
    for k in METRICS:
        assert base["wilson95"][k] == list(wilson_interval(base["successes"][k], 5))
    assert base["wilson95"]["lifted"] == pytest.approx([0.0362, 0.6245], abs=1e-4)
    assert base["no_grasp"] == 2 and pugs["no_grasp"] == 1
    assert base["same_grasp_as_other_method"] == pugs["same_grasp_as_other_method"] == 1
    kb = by[("kettlebell", "partial", "pugs")]
    assert kb["n"] == 1 and kb["rates"] == dict.fromkeys(METRICS, 1.0) and kb["no_grasp"] == 0
    empty = by[("mug", "complete", "baseline")]  # no trials: no rate, the widest interval
    assert empty["n"] == 0 and empty["rates"] == dict.fromkeys(METRICS, 0.0)
    assert empty["wilson95"] == {k: [0.0, 1.0] for k in METRICS} and empty["no_grasp"] == 0
