# SPDX-License-Identifier: Apache-2.0
"""The Table I evaluation: rendered stereo -> PUGS pipeline -> top grasp -> MuJoCo trial.

For every object x reconstruction type x trial seed, one sequence is rendered and ingested once
through :class:`pugsd.core.pipeline.PugsPipeline`; both proposers run once on its cloud, and for
each training mode (``streaming``: the daemon's incremental SVGP; ``paper``: the 100-epoch batch
fit on the same store) the candidates are ranked by each method:

- ``baseline``: the single-contact proposer ranked by its own geometric confidence, collisions
  checked against observed points only: the visibility-naive stand-in for TSGrasp
  (``docs/sim.md``);
- ``antipodal``: the antipodal proposer (both contacts observed) ranked by its confidence;
- ``pugs``: the single-contact candidates ranked by Eq. 13 with the swept-volume uncertainty;
- ``pugs_contact``: the same candidates ranked by the paper-literal Eq. 13 (sigma^2_occ at the
  contact).

Each method's top grasp goes through the physics trial (:mod:`pugsd.sim.physics`). A few more
single-contact candidates per sequence get the traversal check only, so that each score's power
to predict traversal success (AUC) is measured on more than the picks. Success rates carry 95 %
Wilson score intervals; methods and modes are compared on the same sequences by the exact
McNemar test.
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
METHODS = ("baseline", "antipodal", "pugs", "pugs_contact")
MODES = ("streaming", "paper")
RECONS = ("partial", "noisy_partial", "complete")
METHOD_TITLES = {
    "baseline": "Baseline (single-contact, visibility-naive)",
    "antipodal": "Antipodal proposer",
    "pugs": "PUGS (swept volume)",
    "pugs_contact": "PUGS (contact point, paper)",
}
RECON_TITLES = {"partial": "Partial", "noisy_partial": "Noisy Partial", "complete": "Complete"}
# why a method's pick failed: the first stage it did not pass
FAILURES = ("no_grasp", "traversal", "close", "lift_hold")
# scores whose power to predict traversal success is measured (higher = predicted better)
AUC_SCORES = ("confidence", "pugs", "pugs_contact", "neg_unknown_share", "neg_sigma2_occ")
# pairs compared by McNemar within a mode (first the method under test)
METHOD_PAIRS = (("pugs", "baseline"), ("pugs", "antipodal"), ("pugs", "pugs_contact"))

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


def auc(scores: Sequence[float] | np.ndarray, labels: Sequence[bool] | np.ndarray) -> float | None:
    """Area under the ROC curve of ``scores`` for ``labels`` (the Mann-Whitney U statistic over
    n_pos n_neg, ties counted half); None without both a positive and a negative."""
    x = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    keep = np.isfinite(x)
    x, y = x[keep], y[keep]
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    pos, neg = x[y], x[~y]
    greater = (pos[:, None] > neg[None, :]).sum()
    ties = (pos[:, None] == neg[None, :]).sum()
    return float((greater + 0.5 * ties) / (n_pos * n_neg))


def _mode_of(t: dict[str, Any]) -> str:
    return str(t.get("mode", "streaming"))


def paired_tests(
    trials: Sequence[dict[str, Any]], names: Sequence[str], recons: Sequence[str]
) -> list[dict[str, Any]]:
    """Exact McNemar per object x recon x metric on the same sequences: each of
    ``METHOD_PAIRS`` within a mode (where both were evaluated), and streaming against paper for
    every method (where both modes were run)."""
    out: list[dict[str, Any]] = []
    modes = sorted({_mode_of(t) for t in trials}, key=lambda m: MODES.index(m) if m in MODES else 9)
    for n in names:
        for rc in recons:
            cell = [t for t in trials if t["object"] == n and t["recon"] == rc]
            for mode in modes:
                rows = [t for t in cell if _mode_of(t) == mode]
                for ma, mb in METHOD_PAIRS:
                    if not rows or not all({ma, mb} <= set(t["methods"]) for t in rows):
                        continue
                    for k in METRICS:
                        a = sum(1 for t in rows if t["methods"][ma][k] and not t["methods"][mb][k])
                        b = sum(1 for t in rows if t["methods"][mb][k] and not t["methods"][ma][k])
                        out.append(
                            {"object": n, "recon": rc, "mode": mode, "metric": k, "a": ma, "b": mb,
                             "n": len(rows), "a_only": a, "b_only": b, "mcnemar_p": mcnemar_exact_p(a, b)}
                        )  # fmt: skip
            if {"streaming", "paper"} <= set(modes):
                by_seed: dict[int, dict[str, dict[str, Any]]] = {}
                for t in cell:
                    by_seed.setdefault(t["seed"], {})[_mode_of(t)] = t
                pairs = [v for v in by_seed.values() if {"streaming", "paper"} <= set(v)]
                methods = sorted(
                    set.intersection(*(set(v[m]["methods"]) for v in pairs for m in v)) if pairs else set()
                )
                for me in methods:
                    for k in METRICS:
                        s_ok = [v["streaming"]["methods"][me][k] for v in pairs]
                        p_ok = [v["paper"]["methods"][me][k] for v in pairs]
                        a = sum(1 for x, y in zip(s_ok, p_ok) if x and not y)
                        b = sum(1 for x, y in zip(s_ok, p_ok) if y and not x)
                        out.append(
                            {"object": n, "recon": rc, "mode": "streaming-vs-paper", "metric": k,
                             "a": f"{me}/streaming", "b": f"{me}/paper", "n": len(pairs), "a_only": a,
                             "b_only": b, "mcnemar_p": mcnemar_exact_p(a, b)}
                        )  # fmt: skip
    return out


@dataclass
class EvalOptions:
    """What to evaluate and how (the CLI maps one-to-one onto these)."""

    objects: list[str] = field(default_factory=lambda: ["kettlebell", "mug"])
    recons: list[str] = field(default_factory=lambda: list(RECONS))
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    trials: int = 40
    seed: int = 0
    # "streaming": the daemon's incremental SVGP; "paper": the 100-epoch batch fit; both: side by
    # side on the same sequences
    modes: list[str] = field(default_factory=lambda: ["streaming"])
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
    auc_candidates: int = 8  # extra single-contact candidates per sequence, traversal only


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


def _approach_view_angle_deg(pose_W: np.ndarray, contact_W: np.ndarray, views_W: np.ndarray) -> float:
    """Angle between the hand's travel direction reversed (-a) and the direction from the contact
    to its nearest camera: 0 deg comes from the camera, 180 deg from straight behind the object."""
    a = np.asarray(pose_W)[:3, 2]
    cam = views_W[np.argmin(((views_W - contact_W) ** 2).sum(1))]
    v = cam - contact_W
    c = float(-a @ v / max(np.linalg.norm(v), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def failure_of(row: dict[str, Any]) -> str | None:
    """The first stage a method's pick did not pass (``FAILURES``), None for a success."""
    if row.get("grasp") is None:
        return "no_grasp"
    if not row["traversal"]:
        return "traversal"
    if not row["closed"]:
        return "close"
    if not row["lifted"]:
        return "lift_hold"
    return None


def _pick(grasps: Any, views_W: np.ndarray) -> dict[str, Any] | None:
    """The top grasp of a ranking as the trial record keeps it (None for no grasp)."""
    if grasps is None or len(grasps) == 0:
        return None
    out = {
        "pose_W": np.round(grasps.pose_W[0], 6).tolist(),
        "contact_W": np.round(grasps.contact_W[0], 6).tolist(),
        "width_m": float(grasps.width_m[0]),
        "baseline_confidence": float(grasps.baseline_confidence[0]),
        "sigma2_occ": float(grasps.sigma2_occ[0]),
        "pugs_confidence": float(grasps.pugs_confidence[0]),
        "grasp_id": int(grasps.grasp_id[0]),
        "approach_view_angle_deg": round(
            _approach_view_angle_deg(grasps.pose_W[0], grasps.contact_W[0], views_W), 2
        ),
    }
    if grasps.unknown_share is not None:
        out["unknown_share"] = float(grasps.unknown_share[0])
        out["sigma2_grasp"] = float(grasps.sigma2_grasp[0]) if grasps.sigma2_grasp is not None else None
    return out


def _scored(
    opts: EvalOptions, job: Job, cfg: Any, seq: SyntheticSequence, whole_cloud: bool = False
) -> tuple[np.ndarray, dict[str, dict[str, Any] | str], dict[str, int]]:
    """Ingest the sequence once, propose with both proposers, and per mode score them: (camera
    centres, mode -> {"swept", "contact", "antipodal": PipelineResult} or the error text,
    valid candidates per proposer). ``whole_cloud``: Algorithm 1 on the whole query cloud of
    the swept result too (for the figures)."""
    from pugsd.core.grasp.proposer import make_proposer
    from pugsd.core.pipeline import PugsPipeline

    views = np.zeros((1, 3))
    out: dict[str, dict[str, Any] | str] = {}
    try:
        pipe = PugsPipeline(cfg, seed=job.seed)
        for f in seq.frames:
            pipe.add_stereo(f)
            if "streaming" in opts.modes:
                pipe.train_steps()
        inp = pipe.grasp_input()
        views = inp.views_W
        props = {  # the antipodal candidates are scored at their contacts: no swept volume
            kind: pipe.propose(i, make_proposer(cfg.grasp, job.seed, kind=kind))
            for kind, i in (("single_contact", inp), ("antipodal", dataclasses.replace(inp, free=None)))
        }
    except Exception as exc:  # the pipeline failing on a trial is a failed trial, not a crash
        log.warning("pipeline failed on %s/%s seed %d: %s", job.object_name, job.recon, job.seed, exc)
        return views, dict.fromkeys(opts.modes, f"{type(exc).__name__}: {exc}"), {}
    counts = {k: int(np.count_nonzero(p.candidates.valid)) for k, p in props.items()}
    for mode in opts.modes:  # streaming first: the paper fit replaces the streamed model
        try:
            if mode == "paper":
                pipe.fit_paper()
            swept = pipe.score(props["single_contact"], uncertainty="swept")
            out[mode] = {
                "swept": pipe.complete_cloud(swept) if whole_cloud else swept,
                "contact": pipe.score(props["single_contact"], uncertainty="contact"),
                "antipodal": pipe.score(props["antipodal"], uncertainty="contact"),
            }
        except Exception as exc:
            log.warning("scoring failed on %s/%s seed %d (%s): %s", job.object_name, job.recon,
                        job.seed, mode, exc)  # fmt: skip
            out[mode] = f"{type(exc).__name__}: {exc}"
    return views, out, counts


def _run_job(opts: EvalOptions, job: Job) -> list[dict[str, Any]]:
    """Render, ingest, propose with both proposers, then per mode rank and trial each method's
    top grasp (one worker's unit of work): one record per mode."""
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
    base: dict[str, Any] = {"object": job.object_name, "recon": job.recon, "seed": job.seed}
    # the physics simulates the jaws the proposer placed its grasps for
    gripper = cfg.grasp.gripper
    key = (job.object_name, opts.object_mesh, opts.mass_kg, opts.pose, gripper)
    if key not in _TRIALS:
        _TRIALS[key] = GraspTrial(obj, seq.T_W_O, TrialConfig(gripper=gripper))
    trial = _TRIALS[key]
    cache: dict[tuple[bytes, bool], Any] = {}

    def run_trial(pose_W: np.ndarray, traversal_only: bool = False) -> Any:
        k = (np.round(np.asarray(pose_W), 6).tobytes(), traversal_only)
        if k not in cache:
            cache[k] = trial.run(pose_W, traversal_only=traversal_only)
        return cache[k]

    want_figures = bool(opts.figures_dir) and job.index < opts.figures_per_cell
    views, scored, counts = _scored(opts, job, cfg, seq, want_figures)
    records: list[dict[str, Any]] = []
    t2 = time.perf_counter()
    rng = np.random.default_rng(job.seed)
    sample = np.zeros(0, dtype=np.int64)
    first = next((r for r in scored.values() if isinstance(r, dict)), None)
    if first is not None and opts.auc_candidates > 0:
        valid = np.flatnonzero(first["swept"].candidates.valid)
        sample = np.sort(rng.choice(valid, min(opts.auc_candidates, len(valid)), replace=False))
    for mode in opts.modes:
        tm0 = time.perf_counter()
        out: dict[str, Any] = {**base, "mode": mode}
        got = scored.get(mode)
        results: dict[str, Any] = got if isinstance(got, dict) else {}
        if isinstance(got, str):
            out["error"] = got
        ranking = {
            "baseline": ("swept", "baseline_grasps"),
            "antipodal": ("antipodal", "baseline_grasps"),
            "pugs": ("swept", "grasps"),
            "pugs_contact": ("contact", "grasps"),
        }
        methods: dict[str, Any] = {}
        for method in opts.methods:
            which, attr = ranking[method]
            res = results.get(which)
            pick = _pick(None if res is None else getattr(res, attr), views)
            if pick is None:
                methods[method] = {"grasp": None, **dict.fromkeys(METRICS, False), "failure": "no_grasp"}
                continue
            r = run_trial(np.asarray(pick["pose_W"]))
            row = {"grasp": pick, **{m: bool(getattr(r, m)) for m in METRICS}}
            row["details"] = _jsonable(r.details)
            row["failure"] = failure_of(row)
            methods[method] = row
        out["methods"] = methods
        if "swept" in results:
            out["candidates"] = dict(counts)
            out["cloud_points"] = len(results["swept"].cloud_W)
            out["auc_samples"] = _auc_samples(results, sample, run_trial)
        if "baseline" in methods and "pugs" in methods:
            gb, gp = methods["baseline"]["grasp"], methods["pugs"]["grasp"]
            out["same_grasp"] = bool(gb and gp and gb["grasp_id"] == gp["grasp_id"])
        out["timings_s"] = {
            "render": t1 - t0, "pipeline": t2 - t1, "trials": time.perf_counter() - tm0
        }  # fmt: skip
        if want_figures and "swept" in results:
            from pugsd.sim.figures import grasp_figure

            path = Path(opts.figures_dir or ".") / f"{job.object_name}_{job.recon}_seed{job.seed}_{mode}.png"
            title = f"{job.object_name}, {RECON_TITLES.get(job.recon, job.recon)}, seed {job.seed}, {mode}"
            grasp_figure(results["swept"], seq, path, title=title, gripper=cfg.grasp.gripper)
            out["figure"] = str(path)
        log.info(
            "%s/%s seed %d %s: %s",
            job.object_name, job.recon, job.seed, mode,
            " ".join(f"{m}={''.join('1' if methods[m][k] else '0' for k in METRICS)}" for m in methods),
        )  # fmt: skip
        records.append(out)
    return records


def _auc_samples(
    results: dict[str, Any], sample: np.ndarray, run_trial: Callable[..., Any]
) -> list[dict[str, Any]]:
    """The scores of the sampled single-contact candidates (indices into the candidates) and
    whether each traverses: the population for the AUC of each score."""
    sw = results["swept"]
    cands = sw.candidates
    out = []
    for i in sample:
        s2 = float(sw.sigma2_occ[cands.src_index[i]])
        unk = float(sw.unknown_share[i]) if sw.unknown_share is not None else float("nan")
        s2g = float(sw.sigma2_grasp[i]) if sw.sigma2_grasp is not None else float("nan")
        r = run_trial(cands.pose[i], traversal_only=True)
        out.append(
            {
                "confidence": round(float(cands.confidence[i]), 6),
                "sigma2_occ": s2,
                "unknown_share": round(unk, 6),
                "sigma2_grasp": s2g,
                "traversal": bool(r.traversal),
            }
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
    """Run every cell; return the results dictionary (also what ``--json`` writes).
    ``progress`` is called with each record (one per sequence and mode) as it completes."""
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

    def take(records: list[dict[str, Any]]) -> None:
        for r in records:
            trials.append(r)
            if progress:
                progress(r)

    if opts.workers > 1:
        import multiprocessing as mp

        with ProcessPoolExecutor(
            opts.workers, mp_context=mp.get_context("spawn"), initializer=_worker_init
        ) as ex:
            for recs in ex.map(_run_job, [opts] * len(jobs), jobs):
                take(recs)
    else:
        for j in jobs:
            take(_run_job(opts, j))
    core = _core_config(opts, {})
    results = {
        "settings": {
            "objects": names,
            "recons": list(opts.recons),
            "methods": list(opts.methods),
            "modes": list(opts.modes),
            "trials": opts.trials,
            "seed": opts.seed,
            "pose": opts.pose,
            "resolution": [opts.width, opts.height],
            "n_frames": opts.n_frames,
            "object_mesh": opts.object_mesh,
            "mass_kg": opts.mass_kg,
            "underwater": opts.underwater,
            "overrides": list(opts.overrides),
            "gripper": dataclasses.asdict(core.grasp.gripper),
            "gamma": core.grasp.gamma,
            "unknown_weight": core.grasp.unknown_weight,
            "auc_candidates": opts.auc_candidates,
        },
        "wall_time_s": time.perf_counter() - t0,
        "trials": trials,
    }
    return summarise(results)


def summarise(results: dict[str, Any]) -> dict[str, Any]:
    """(Re)compute the cells, paired tests and AUCs of ``results`` from its trials."""
    st = results["settings"]
    trials = results["trials"]
    modes = st.get("modes") or [st.get("mode", "streaming")]
    results["cells"] = aggregate_cells(trials, st["objects"], st["recons"], st["methods"], modes)
    results["paired"] = paired_tests(trials, st["objects"], st["recons"])
    results["auc"] = auc_table(trials, st["recons"], modes, float(st.get("gamma", 5.0)))
    return results


def auc_table(
    trials: Sequence[dict[str, Any]], recons: Sequence[str], modes: Sequence[str], gamma: float
) -> list[dict[str, Any]]:
    """Per recon x mode (objects pooled) and over all recons: the AUC of each score in
    ``AUC_SCORES`` for traversal success, over the sampled single-contact candidates."""
    out = []
    for mode in modes:
        for rc in [*recons, "all"]:
            rows = [
                s for t in trials if _mode_of(t) == mode and (rc == "all" or t["recon"] == rc)
                for s in t.get("auc_samples", ())
            ]  # fmt: skip
            if not rows:
                continue
            y = [bool(r["traversal"]) for r in rows]
            conf = np.array([r["confidence"] for r in rows], dtype=np.float64)
            s2g = np.array([r["sigma2_grasp"] for r in rows], dtype=np.float64)
            s2 = np.array([r["sigma2_occ"] for r in rows], dtype=np.float64)
            unk = np.array([r["unknown_share"] for r in rows], dtype=np.float64)
            scores = {
                "confidence": conf,
                "pugs": conf / (1.0 + gamma * s2g),
                "pugs_contact": conf / (1.0 + gamma * s2),
                "neg_unknown_share": -unk,
                "neg_sigma2_occ": -s2,
            }
            out.append(
                {"recon": rc, "mode": mode, "n": len(rows), "traversal_rate": float(np.mean(y)),
                 **{k: auc(v, y) for k, v in scores.items()}}
            )  # fmt: skip
    return out


def aggregate_cells(
    trials: Sequence[dict[str, Any]],
    names: Sequence[str],
    recons: Sequence[str],
    methods: Sequence[str],
    modes: Sequence[str] = ("streaming",),
) -> list[dict[str, Any]]:
    """Per object x recon x mode x method: n, successes per metric, rates, Wilson intervals,
    the failure taxonomy, picks approaching from behind the object, and candidates per
    sequence."""
    cells = []
    for n in names:
        for rc in recons:
            for mode in modes:
                rows = [
                    t for t in trials
                    if t["object"] == n and t["recon"] == rc and _mode_of(t) == mode
                ]  # fmt: skip
                for m in methods:
                    rows_m = [t for t in rows if m in t["methods"]]
                    succ = {k: sum(1 for t in rows_m if t["methods"][m][k]) for k in METRICS}
                    nn = len(rows_m)
                    fails = [failure_of(t["methods"][m]) for t in rows_m]
                    angles = [
                        t["methods"][m]["grasp"].get("approach_view_angle_deg")
                        for t in rows_m if t["methods"][m]["grasp"] is not None
                    ]  # fmt: skip
                    kind = "antipodal" if m == "antipodal" else "single_contact"
                    counts = [t["candidates"][kind] for t in rows_m if "candidates" in t]
                    cells.append(
                        {
                            "object": n,
                            "recon": rc,
                            "mode": mode,
                            "method": m,
                            "n": nn,
                            "successes": succ,
                            "rates": {k: (succ[k] / nn if nn else 0.0) for k in METRICS},
                            "wilson95": {k: list(wilson_interval(succ[k], nn)) for k in METRICS},
                            "seeds": [t["seed"] for t in rows_m],
                            "no_grasp": sum(1 for t in rows_m if t["methods"][m]["grasp"] is None),
                            "failures": {f: fails.count(f) for f in FAILURES},
                            "from_behind": sum(1 for a in angles if a is not None and a > 90.0),
                            "candidates_min": min(counts) if counts else 0,
                            "candidates_median": float(np.median(counts)) if counts else 0.0,
                            "same_grasp_as_other_method": sum(1 for t in rows_m if t.get("same_grasp")),
                        }
                    )
    return cells


def rescore(results: dict[str, Any], cfg: Any = None) -> dict[str, Any]:
    """Re-run only the physics on the grasps stored in ``results`` (e.g. after changing a
    decision threshold); built-in objects only, with the gripper recorded in the settings.
    Returns a new results dictionary."""
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
            m["failure"] = failure_of(m)
    summarise(out)
    out["rescored"] = True
    return out


def _cell(
    results: dict[str, Any], obj: str, recon: str, method: str, mode: str | None = None
) -> dict[str, Any] | None:
    for c in results["cells"]:
        same = c["object"] == obj and c["recon"] == recon and c["method"] == method
        if same and (mode is None or c.get("mode", "streaming") == mode):
            return dict(c)
    return None


def _paired(results: dict[str, Any], obj: str, recon: str, mode: str, a: str, b: str,
            metric: str = "lifted") -> dict[str, Any] | None:  # fmt: skip
    for r in results.get("paired", ()):
        if (r["object"], r["recon"], r.get("mode"), r.get("a"), r.get("b"), r["metric"]) == (
            obj, recon, mode, a, b, metric
        ):
            return r
    return None


def _pair_text(r: dict[str, Any] | None) -> str:
    return "-" if r is None else f"{r['a_only']}:{r['b_only']} p={r['mcnemar_p']:.3g}"


def markdown_table(results: dict[str, Any], with_paper: bool = True) -> str:
    """Table I layout (rows mode x method x reconstruction, columns metric x object, with Wilson
    CIs), then per cell the failure taxonomy and the paired tests, then the AUCs."""
    st = results["settings"]
    objs: Sequence[str] = st["objects"]
    recons: Sequence[str] = st["recons"]
    methods: Sequence[str] = st["methods"]
    modes: Sequence[str] = st.get("modes") or [st.get("mode", "streaming")]
    head = ["Mode", "Method", "Reconstruction"] + [
        f"{METRIC_TITLES[m]}: {o}" for m in METRICS for o in objs
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for mode in modes:
        for rc in recons:
            for me in methods:
                row = [mode, METHOD_TITLES.get(me, me), RECON_TITLES.get(rc, rc)]
                for m in METRICS:
                    for o in objs:
                        c = _cell(results, o, rc, me, mode)
                        if c is None:
                            row.append("-")
                            continue
                        k, n = c["successes"][m], c["n"]
                        lo, hi = wilson_interval(k, n)
                        row.append(f"{100 * k / max(n, 1):.0f}% ({k}/{n}) [{100 * lo:.0f}-{100 * hi:.0f}]")
                lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append(
        f"N = {st['trials']} trials per cell (seeds {st['seed']}...{st['seed'] + st['trials'] - 1}), "
        f"pose {st['pose']}; cells: rate (successes/n) [95% Wilson interval, %]."
    )
    # failures and paired tests (Goal Pose Reached)
    lines += [
        "",
        "Failures of each method's pick (no grasp / traversal / close / lift-hold), picks "
        "approaching from behind the object (> 90 deg from the camera), candidates per sequence "
        "(min-median), and exact McNemar on Goal Pose Reached (PUGS-only:other-only p; "
        "streaming against paper for PUGS):",
        "",
    ]
    fh = ["Mode", "Object", "Reconstruction"] + [f"{me}: fail / behind / cand." for me in methods]
    fh += [f"p pugs vs {b}" for a, b in METHOD_PAIRS if a in methods and b in methods]
    if len(modes) > 1:
        fh.append("p pugs streaming vs paper")
    lines += ["| " + " | ".join(fh) + " |", "|" + "---|" * len(fh)]
    for mode in modes:
        for o in objs:
            for rc in recons:
                row = [mode, o, RECON_TITLES.get(rc, rc)]
                for me in methods:
                    c = _cell(results, o, rc, me, mode)
                    if c is None or "failures" not in c:
                        row.append("-")
                        continue
                    f = c["failures"]
                    row.append(
                        f"{'/'.join(str(f[k]) for k in FAILURES)} / {c['from_behind']} / "
                        f"{c['candidates_min']}-{c['candidates_median']:.0f}"
                    )
                for a, b in METHOD_PAIRS:
                    if a in methods and b in methods:
                        r = _paired(results, o, rc, mode, a, b)
                        row.append(_pair_text(r))
                if len(modes) > 1:
                    r = _paired(results, o, rc, "streaming-vs-paper", "pugs/streaming", "pugs/paper")
                    row.append(_pair_text(r))
                lines.append("| " + " | ".join(row) + " |")
    if results.get("auc"):
        lines += ["", "AUC for traversal success over sampled single-contact candidates "
                  "(objects pooled):", ""]  # fmt: skip
        ah = ["Mode", "Reconstruction", "n", "traversal rate", *AUC_SCORES]
        lines += ["| " + " | ".join(ah) + " |", "|" + "---|" * len(ah)]
        for r in results["auc"]:
            vals = ["-" if r[k] is None else f"{r[k]:.2f}" for k in AUC_SCORES]
            lines.append(
                "| " + " | ".join([r["mode"], RECON_TITLES.get(r["recon"], r["recon"]), str(r["n"]),
                                   f"{r['traversal_rate']:.2f}", *vals]) + " |"
            )  # fmt: skip
    if with_paper and set(objs) >= {"kettlebell", "mug"}:
        lines += ["", "Paper Table I (TSGrasp / PUGS, N = 5, percent):", ""]
        ph = ["Method", "Reconstruction"] + [
            f"{METRIC_TITLES[m]}: {o}" for m in METRICS for o in ("kettlebell", "mug")
        ]
        lines += ["| " + " | ".join(ph) + " |", "|" + "---|" * len(ph)]
        for rc in RECONS:
            for me in ("baseline", "pugs"):
                paper = PAPER_TABLE[me][rc]
                pct = [f"{paper[m][i]}%" for m in METRICS for i in range(2)]
                name = "TSGrasp" if me == "baseline" else "PUGS"
                lines.append("| " + " | ".join([name, RECON_TITLES[rc], *pct]) + " |")
    return "\n".join(lines) + "\n"


def write_json(results: dict[str, Any], path: str | Path) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(results, indent=1, default=float))
