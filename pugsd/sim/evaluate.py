# SPDX-License-Identifier: Apache-2.0
"""The Table I evaluation: rendered stereo -> PUGS pipeline -> top grasp -> MuJoCo trial.

For every object x reconstruction type x trial seed, one sequence is rendered and run once through
:class:`pugsd.core.pipeline.PugsPipeline`; the proposer's own top grasp (``baseline``) and the top
grasp after Eq. 13 (``pugs``) then each go through the physics trial (:mod:`pugsd.sim.physics`).
Success rates carry 95 % Wilson score intervals.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pugsd.sim.objects import ObjectSpec, get_object, load_object_mesh

if TYPE_CHECKING:
    from pugsd.sim.sequence import SyntheticSequence

log = logging.getLogger(__name__)

METRICS = ("traversal", "closed", "lifted")
METRIC_TITLES = {
    "traversal": "Grasp Traversal Success",
    "closed": "Gripper Closed Onto Object",
    "lifted": "Goal Pose Reached",
}
METHODS = ("baseline", "pugs")
RECONS = ("partial", "noisy_partial", "complete")
METHOD_TITLES = {"baseline": "Baseline (antipodal proposer)", "pugs": "PUGS"}
RECON_TITLES = {"partial": "Partial", "noisy_partial": "Noisy Partial", "complete": "Complete"}

# the paper's Table I (percent, N = 5): method -> recon -> metric -> (kettlebell, mug)
PAPER_TABLE: dict[str, dict[str, dict[str, tuple[int, int]]]] = {
    "baseline": {
        "partial": {"traversal": (0, 40), "closed": (0, 0), "lifted": (0, 0)},
        "noisy_partial": {"traversal": (0, 0), "closed": (0, 0), "lifted": (0, 0)},
        "complete": {"traversal": (100, 60), "closed": (100, 80), "lifted": (100, 60)},
    },
    "pugs": {
        "partial": {"traversal": (60, 60), "closed": (60, 40), "lifted": (60, 40)},
        "noisy_partial": {"traversal": (40, 80), "closed": (0, 60), "lifted": (0, 60)},
        "complete": {"traversal": (100, 80), "closed": (60, 60), "lifted": (60, 20)},
    },
}


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion k / n (0, 1 for n = 0)."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def mcnemar_exact_p(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar p-value from the discordant pairs of a paired comparison.

    Baseline and PUGS are tried on the same sequences, so their outcomes are paired; only the
    sequences where exactly one succeeded carry information (``only_a``, ``only_b``).
    """
    n = only_a + only_b
    if n == 0:
        return 1.0
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def paired_tests(
    trials: Sequence[dict[str, Any]], names: Sequence[str], recons: Sequence[str]
) -> list[dict[str, Any]]:
    """Per object x recon x metric: baseline-only and PUGS-only successes on the same sequences
    and the exact McNemar p-value (empty unless both methods were evaluated)."""
    out: list[dict[str, Any]] = []
    for n in names:
        for rc in recons:
            rows = [t for t in trials if t["object"] == n and t["recon"] == rc]
            if not rows or not all({"baseline", "pugs"} <= set(t["methods"]) for t in rows):
                continue
            for k in METRICS:
                b = sum(1 for t in rows if t["methods"]["baseline"][k] and not t["methods"]["pugs"][k])
                p = sum(1 for t in rows if t["methods"]["pugs"][k] and not t["methods"]["baseline"][k])
                out.append(
                    {"object": n, "recon": rc, "metric": k, "n": len(rows), "baseline_only": b,
                     "pugs_only": p, "mcnemar_p": mcnemar_exact_p(b, p)}
                )  # fmt: skip
    return out


@dataclass
class EvalOptions:
    """What to evaluate and how (the CLI maps one-to-one onto these)."""

    objects: list[str] = field(default_factory=lambda: ["kettlebell", "mug"])
    recons: list[str] = field(default_factory=lambda: list(RECONS))
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    trials: int = 20
    seed: int = 0
    mode: str = "streaming"  # "paper": 100-epoch batch SVGP; "streaming": the daemon's settings
    pose: str = "upright"
    width: int = 320
    height: int = 240
    n_frames: int | None = None
    object_mesh: str | None = None
    mass_kg: float | None = None
    underwater: bool = False
    config_path: str | None = None
    overrides: list[str] = field(default_factory=list)
    workers: int = 1
    figures_dir: str | None = None
    figures_per_cell: int = 1


@dataclass
class Job:
    object_name: str
    recon: str
    seed: int
    index: int


def _object(opts: EvalOptions, name: str) -> ObjectSpec:
    if opts.object_mesh:
        return load_object_mesh(opts.object_mesh, opts.mass_kg or 0.5, name=name)
    return get_object(name)


def _nearest_object_depth_m(seq: SyntheticSequence) -> float:
    """The smallest true z-depth of the object over a sequence's left views (inf if never seen)."""
    near = [float(np.nanmin(d[m])) for d, m in zip(seq.depth_gt_m, seq.masks) if m.any()]
    return min(near, default=math.inf)


def _core_config(opts: EvalOptions, seq_overrides: dict[str, Any]) -> Any:
    """The pipeline configuration of one trial: the paper's 160-px matching resolution, the
    sequence's own overrides, then ``--set`` (which wins). The disparity search is sized from the
    rig by default (``stereo.num_disparities = 0``: it reaches ``stereo.min_depth_m``, 0.2 m,
    nearer than any surface the evaluation's cameras see)."""
    from pugsd.config import core_of, load_config

    ds = max(1, round(opts.width / 160))  # the paper's input resolution after downsampling
    over = [f"stereo.downsample={ds}"]
    over += [f"{k}={v}" for k, v in seq_overrides.items()]
    return core_of(load_config(opts.config_path, over + list(opts.overrides)))


# one MuJoCo model per object, pose and gripper in each process; a user mesh is keyed by its path
# and mass too, so two meshes with the same file name never share a model
_TRIALS: dict[tuple[str, str | None, float | None, str, Any], Any] = {}


def _run_job(opts: EvalOptions, job: Job) -> dict[str, Any]:
    """Render, run the pipeline, and trial each method's top grasp (one worker's unit of work)."""
    from pugsd.core.pipeline import PugsPipeline
    from pugsd.core.stereo import reach_m as stereo_reach_m
    from pugsd.sim.physics import GraspTrial, TrialConfig
    from pugsd.sim.sequence import make_sequence

    t0 = time.perf_counter()
    obj = _object(opts, job.object_name)
    seq = make_sequence(
        job.object_name,
        job.recon,
        n_frames=opts.n_frames,
        width=opts.width,
        height=opts.height,
        seed=job.seed,
        pose=opts.pose,
        obj=obj,
        underwater=opts.underwater,
    )
    t1 = time.perf_counter()
    cfg = _core_config(opts, seq.core_overrides)
    z_near, z_reach = _nearest_object_depth_m(seq), stereo_reach_m(cfg.stereo, seq.rig)
    if z_near < z_reach:
        log.warning(
            "%s/%s seed %d: the object comes to %.3f m, nearer than the disparity search reaches "
            "(%.3f m); lower stereo.min_depth_m (with stereo.num_disparities = 0) or raise "
            "stereo.num_disparities",
            job.object_name, job.recon, job.seed, z_near, z_reach,
        )  # fmt: skip
    out: dict[str, Any] = {"object": job.object_name, "recon": job.recon, "seed": job.seed}
    try:
        res = PugsPipeline.run(seq.frames, cfg, mode=opts.mode, seed=job.seed)
    except Exception as exc:  # the pipeline failing on a trial is a failed trial, not a crash
        log.warning("pipeline failed on %s/%s seed %d: %s", job.object_name, job.recon, job.seed, exc)
        out["error"] = f"{type(exc).__name__}: {exc}"
        res = None
    t2 = time.perf_counter()
    # the physics simulates the jaws the proposer placed its grasps for
    gripper = cfg.grasp.gripper
    key = (job.object_name, opts.object_mesh, opts.mass_kg, opts.pose, gripper)
    if key not in _TRIALS:
        _TRIALS[key] = GraspTrial(obj, seq.T_W_O, TrialConfig(gripper=gripper))
    trial = _TRIALS[key]
    methods: dict[str, Any] = {}
    for method in opts.methods:
        grasps = None if res is None else (res.grasps if method == "pugs" else res.baseline_grasps)
        if grasps is None or len(grasps) == 0:
            methods[method] = {"grasp": None, **dict.fromkeys(METRICS, False)}
            continue
        r = trial.run(grasps.pose_W[0])
        methods[method] = {
            "grasp": {
                "pose_W": np.round(grasps.pose_W[0], 6).tolist(),
                "contact_W": np.round(grasps.contact_W[0], 6).tolist(),
                "width_m": float(grasps.width_m[0]),
                "baseline_confidence": float(grasps.baseline_confidence[0]),
                "sigma2_occ": float(grasps.sigma2_occ[0]),
                "pugs_confidence": float(grasps.pugs_confidence[0]),
                "grasp_id": int(grasps.grasp_id[0]),
            },
            **{m: bool(getattr(r, m)) for m in METRICS},
            "details": _jsonable(r.details),
        }
    t3 = time.perf_counter()
    if res is not None and "baseline" in methods and "pugs" in methods:
        gb, gp = methods["baseline"]["grasp"], methods["pugs"]["grasp"]
        out["same_grasp"] = bool(gb and gp and gb["grasp_id"] == gp["grasp_id"])
    out["methods"] = methods
    out["timings_s"] = {"render": t1 - t0, "pipeline": t2 - t1, "physics": t3 - t2}
    if res is not None:
        out["cloud_points"] = len(res.cloud_W)
        out["candidates"] = int(np.count_nonzero(res.candidates.valid))
    if opts.figures_dir and res is not None and job.index < opts.figures_per_cell:
        from pugsd.sim.figures import grasp_figure

        path = Path(opts.figures_dir) / f"{job.object_name}_{job.recon}_seed{job.seed}.png"
        title = f"{job.object_name}, {RECON_TITLES.get(job.recon, job.recon)}, seed {job.seed}"
        grasp_figure(res, seq, path, title=title, gripper=cfg.grasp.gripper)
        out["figure"] = str(path)
    log.info(
        "%s/%s seed %d: %s (%.1f s)",
        job.object_name,
        job.recon,
        job.seed,
        " ".join(f"{m}={''.join('1' if methods[m][k] else '0' for k in METRICS)}" for m in methods),
        t3 - t0,
    )
    return out


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, np.generic):
            out[k] = v.item()
        elif isinstance(v, float):
            out[k] = round(v, 6)
        else:
            out[k] = v
    return out


def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)


def run_evaluation(
    opts: EvalOptions, progress: Callable[[dict[str, Any]], None] | None = None
) -> dict[str, Any]:
    """Run every cell; return the results dictionary (also what ``--json`` writes)."""
    if opts.object_mesh:
        names = [Path(opts.object_mesh).stem]
    else:
        names = list(opts.objects)
        for n in names:
            get_object(n)  # validate early
    jobs = [
        Job(n, rc, opts.seed + i, i) for n in names for rc in opts.recons for i in range(opts.trials)
    ]
    if opts.figures_dir:
        Path(opts.figures_dir).mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    trials: list[dict[str, Any]] = []
    if opts.workers > 1:
        import multiprocessing as mp

        with ProcessPoolExecutor(
            opts.workers, mp_context=mp.get_context("spawn"), initializer=_worker_init
        ) as ex:
            for r in ex.map(_run_job, [opts] * len(jobs), jobs):
                trials.append(r)
                if progress:
                    progress(r)
    else:
        for j in jobs:
            r = _run_job(opts, j)
            trials.append(r)
            if progress:
                progress(r)
    cells = aggregate_cells(trials, names, opts.recons, opts.methods)
    return {
        "settings": {
            "objects": names,
            "recons": list(opts.recons),
            "methods": list(opts.methods),
            "trials": opts.trials,
            "seed": opts.seed,
            "mode": opts.mode,
            "pose": opts.pose,
            "resolution": [opts.width, opts.height],
            "n_frames": opts.n_frames,
            "object_mesh": opts.object_mesh,
            "mass_kg": opts.mass_kg,
            "underwater": opts.underwater,
            "overrides": list(opts.overrides),
            "gripper": dataclasses.asdict(_core_config(opts, {}).grasp.gripper),
        },
        "wall_time_s": time.perf_counter() - t0,
        "cells": cells,
        "paired": paired_tests(trials, names, opts.recons),
        "trials": trials,
    }


def aggregate_cells(
    trials: Sequence[dict[str, Any]],
    names: Sequence[str],
    recons: Sequence[str],
    methods: Sequence[str],
) -> list[dict[str, Any]]:
    """Per object x recon x method: n, successes per metric, rates, Wilson intervals, seeds."""
    cells = []
    for n in names:
        for rc in recons:
            rows = [t for t in trials if t["object"] == n and t["recon"] == rc]
            for m in methods:
                succ = {k: sum(1 for t in rows if t["methods"][m][k]) for k in METRICS}
                nn = len(rows)
                cells.append(
                    {
                        "object": n,
                        "recon": rc,
                        "method": m,
                        "n": nn,
                        "successes": succ,
                        "rates": {k: (succ[k] / nn if nn else 0.0) for k in METRICS},
                        "wilson95": {k: list(wilson_interval(succ[k], nn)) for k in METRICS},
                        "seeds": [t["seed"] for t in rows],
                        "no_grasp": sum(1 for t in rows if t["methods"][m]["grasp"] is None),
                        "same_grasp_as_other_method": sum(1 for t in rows if t.get("same_grasp")),
                    }
                )
    return cells


def rescore(results: dict[str, Any], cfg: Any = None) -> dict[str, Any]:
    """Re-run only the physics on the grasps stored in ``results`` (e.g. after changing a
    decision threshold); built-in objects only, with the gripper recorded in the settings (the
    defaults for older files). Returns a new results dictionary."""
    import copy

    from pugsd.config import GripperConfig
    from pugsd.sim.physics import GraspTrial, TrialConfig
    from pugsd.sim.sequence import object_pose

    out = copy.deepcopy(results)
    st = out["settings"]
    if st.get("object_mesh"):
        raise ValueError("rescoring a user mesh needs the mesh: rerun the evaluation")
    trials_by_obj: dict[str, GraspTrial] = {}
    trial_cfg = cfg or TrialConfig(gripper=GripperConfig(**st.get("gripper", {})))
    for t in out["trials"]:
        name = t["object"]
        if name not in trials_by_obj:
            obj = get_object(name)
            trials_by_obj[name] = GraspTrial(obj, object_pose(obj, st["pose"]), trial_cfg)
        for m in t["methods"].values():
            if m["grasp"] is None:
                continue
            r = trials_by_obj[name].run(np.asarray(m["grasp"]["pose_W"], dtype=np.float64))
            for k in METRICS:
                m[k] = bool(getattr(r, k))
            m["details"] = _jsonable(r.details)
    out["cells"] = aggregate_cells(out["trials"], st["objects"], st["recons"], st["methods"])
    out["paired"] = paired_tests(out["trials"], st["objects"], st["recons"])
    out["rescored"] = True
    return out


def _cell(results: dict[str, Any], obj: str, recon: str, method: str) -> dict[str, Any] | None:
    for c in results["cells"]:
        if c["object"] == obj and c["recon"] == recon and c["method"] == method:
            return dict(c)
    return None


def markdown_table(results: dict[str, Any], with_paper: bool = True) -> str:
    """Table I layout: rows method x reconstruction, columns metric x object, with Wilson CIs."""
    objs: Sequence[str] = results["settings"]["objects"]
    recons: Sequence[str] = results["settings"]["recons"]
    methods: Sequence[str] = results["settings"]["methods"]
    head = ["Method", "Reconstruction"] + [
        f"{METRIC_TITLES[m]}: {o}" for m in METRICS for o in objs
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for rc in recons:
        for me in methods:
            row = [METHOD_TITLES.get(me, me), RECON_TITLES.get(rc, rc)]
            for m in METRICS:
                for o in objs:
                    c = _cell(results, o, rc, me)
                    if c is None:
                        row.append("-")
                        continue
                    k, n = c["successes"][m], c["n"]
                    lo, hi = wilson_interval(k, n)
                    row.append(f"{100 * k / max(n, 1):.0f}% ({k}/{n}) [{100 * lo:.0f}-{100 * hi:.0f}]")
            lines.append("| " + " | ".join(row) + " |")
    s = results["settings"]
    lines.append("")
    lines.append(
        f"N = {results['settings']['trials']} trials per cell (seeds {s['seed']}..."
        f"{s['seed'] + s['trials'] - 1}), mode {s['mode']}, pose {s['pose']}; "
        "cells: rate (successes/n) [95% Wilson interval, %]."
    )
    if with_paper and set(objs) >= {"kettlebell", "mug"}:
        lines += ["", "Paper Table I (TSGrasp / PUGS, N = 5, percent):", ""]
        ph = ["Method", "Reconstruction"] + [
            f"{METRIC_TITLES[m]}: {o}" for m in METRICS for o in ("kettlebell", "mug")
        ]
        lines += ["| " + " | ".join(ph) + " |", "|" + "---|" * len(ph)]
        for rc in RECONS:
            for me in METHODS:
                vals = PAPER_TABLE[me][rc]
                cells = [f"{vals[m][i]}%" for m in METRICS for i in range(2)]
                name = "TSGrasp" if me == "baseline" else "PUGS"
                lines.append("| " + " | ".join([name, RECON_TITLES[rc], *cells]) + " |")
    return "\n".join(lines) + "\n"


def write_json(results: dict[str, Any], path: str | Path) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(results, indent=1, default=float))
