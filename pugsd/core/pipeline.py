# SPDX-License-Identifier: Apache-2.0
"""PugsPipeline: frames in, ranked grasps out (synchronous; the daemon drives it from workers).

Stages, with the equations they implement:
  StereoDepth (depth + sigma) -> Observation (Eq. 1-3) -> FofStore (Eq. 4-6 targets)
  -> OccupancySVGP (Eq. 7-8) ; Reconstruction (TSDF cloud) -> proposer -> Algorithm 1
  (Eq. 9-12 on the cloud) -> Eq. 13 ranking; FreeSpaceMap (seen free / surface / unknown) ->
  the swept-volume uncertainty of each grasp (``grasp.uncertainty = "swept"``).

One verb family per stage: ingest (``depth_from_stereo``, ``integrate``; ``add_stereo`` does
both), train (``train_steps`` streaming, ``fit_paper`` the paper's batch fit), grasps
(``grasp_input`` -> ``propose`` -> ``score``; ``compute`` does all three) and the rest of the
query cloud (``cloud_job`` -> ``finish_cloud``; ``complete_cloud`` does both).

Thread model: ``depth_from_stereo`` and ``propose`` are stateless. ``integrate``,
``train_steps``, ``fit_paper``, ``grasp_input``, ``score``, ``cloud_job``, ``complete_cloud``
and ``compute`` share state and must be called from one thread at a time (the daemon holds a lock
for each call, and runs ``propose`` and ``finish_cloud``, the costliest parts, without it).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pugsd.core.config import CoreConfig, CubatureConfig
from pugsd.core.cubature import algorithm1
from pugsd.core.fof import FofStore, resolve_query_device, resolve_query_workers
from pugsd.core.freespace import FreeSpaceMap
from pugsd.core.grasp.proposer import GraspProposer, GraspSet, make_proposer
from pugsd.core.grasp.scoring import rank_grasps, reweight
from pugsd.core.grasp.swept import grasp_sigma2, swept_samples, unknown_share
from pugsd.core.observation import Observation
from pugsd.core.predictive import OccupancySVGP, SvgpSnapshot, TrainStats
from pugsd.core.reconstruction import Reconstruction
from pugsd.core.stereo import StereoDepth
from pugsd.core.types import DepthFrame, ScoredGrasps, StereoFrame
from pugsd.errors import EmptyCloudError, ModelNotReadyError, Preempted


@dataclass(frozen=True)
class PipelineResult:
    """Grasps and the per-point uncertainty of the query cloud."""

    grasps: ScoredGrasps  # ranked by PUGS confidence (Eq. 13)
    baseline_grasps: ScoredGrasps  # the same candidates ranked by the proposer's confidence
    cloud_W: np.ndarray  # (Q, 3) query cloud
    mu_occ: np.ndarray  # (Q,) Algorithm 1 mean
    sigma2_occ: np.ndarray  # (Q,) Algorithm 1 variance
    occupancy_confidence: np.ndarray  # (Q,) 1 / (1 + gamma sigma2_occ)
    pugs_conf_points: np.ndarray  # (Q,) Eq. 13 where a valid grasp exists, else 0
    candidates: GraspSet
    model_version: int
    timings_s: dict[str, float] = field(default_factory=dict)
    # grasp.uncertainty = swept, per candidate (aligned with ``candidates``; NaN where invalid):
    # the never-observed share of the swept volume and the unit-free sigma^2 of Eq. 13
    unknown_share: np.ndarray | None = None
    sigma2_grasp: np.ndarray | None = None
    # sigma^2_occ of the contacts is divided by this in the swept form (1 for contact)
    sigma2_ref: float = 1.0


@dataclass(frozen=True)
class GraspInput:
    """What the grasp proposer reads, copied out of the pipeline (``PugsPipeline.grasp_input``)."""

    cloud_W: np.ndarray  # (Q, 3) query cloud
    views_W: np.ndarray  # (V, 3) camera centres seen so far
    timings_s: dict[str, float] = field(default_factory=dict)
    # grasp.uncertainty = swept: the free-space map around the cloud, far enough for every
    # candidate's swept volume (``FreeSpaceMap.crop``)
    free: FreeSpaceMap | None = None


@dataclass(frozen=True)
class Proposal:
    """Grasp candidates on a ``GraspInput`` snapshot (``PugsPipeline.propose``)."""

    cloud_W: np.ndarray
    candidates: GraspSet
    timings_s: dict[str, float] = field(default_factory=dict)
    # with ``GraspInput.free``: the never-observed share of each candidate's swept volume
    # (aligned with ``candidates``; NaN where invalid)
    unknown_share: np.ndarray | None = None


@dataclass(frozen=True)
class CubatureJob:
    """Algorithm 1 with lines 1-2 done: the fused Gaussians (Eq. 5-6) of the query points and the
    SVGP to push their sigma points through: a frozen copy (``PugsPipeline.cubature_job``) or the
    live model (``sigma2_occ``). ``run`` does lines 3-6."""

    mean_W: np.ndarray  # (Q, 3)
    cov_W: np.ndarray  # (Q, 3, 3)
    model: SvgpSnapshot | OccupancySVGP
    scale: float  # normalised -> output units (svgp.output_units)
    cfg: CubatureConfig

    def run(self) -> tuple[np.ndarray, np.ndarray]:
        """Lines 3-6: sigma points through the SVGP (Eq. 7-8): (mu_occ, sigma2_occ)."""
        c = self.cfg

        def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            mu, _, var_pred = self.model.predict(p, self.scale)  # Eq. 7-8
            return mu, var_pred

        return algorithm1(self.mean_W, self.cov_W, predict, c.alpha, c.beta, c.kappa, c.variance_form)

    def run_chunked(
        self, chunk: int, should_stop: Callable[[], bool]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``run`` over ``chunk`` query points at a time (each point's result depends on that point
        alone, so the values are the same), asking ``should_stop`` before each chunk: None if it
        said yes."""
        n = len(self.mean_W)
        mu, s2 = np.empty(n), np.empty(n)
        for i in range(0, n, chunk):
            if should_stop():
                return None
            part = dataclasses.replace(
                self, mean_W=self.mean_W[i : i + chunk], cov_W=self.cov_W[i : i + chunk]
            )
            mu[i : i + chunk], s2[i : i + chunk] = part.run()
        return mu, s2


@dataclass(frozen=True)
class TrainingBatch:
    """One streaming update's data (Eq. 7), copied out of the store: inputs [m, world] (N, 3),
    Eq. 4 targets over the target scale (N,), and the indices of the points changed since the
    previous batch."""

    x_W: np.ndarray
    target: np.ndarray
    new_idx: np.ndarray


@dataclass(frozen=True)
class CloudJob:
    """What ``finish_cloud`` needs to fill in the query cloud of a ``compute(full_cloud=False)``
    result (``PugsPipeline.cloud_job``)."""

    result: PipelineResult
    todo: np.ndarray  # indices into result.cloud_W still NaN
    cubature: CubatureJob | None
    prepare_s: float


class PugsPipeline:
    """The complete PUGS method as a synchronous library."""

    def __init__(
        self, cfg: CoreConfig | None = None, seed: int = 0, grasp_model: Any = None
    ) -> None:
        """``grasp_model``: the loaded network for ``grasp.proposer = "torchscript"`` (the core
        reads no files; ``pugsd.pipeline_factory.make_pipeline`` loads it)."""
        self.cfg = cfg if cfg is not None else CoreConfig()
        self.seed = seed
        self.stereo = StereoDepth(self.cfg.stereo)
        self.observation = Observation(self.cfg.observation, self.cfg.stereo.sigma_d2_m2, seed)
        self.svgp = OccupancySVGP(self.cfg.svgp)
        dev = self.svgp.device.type
        fof = self.cfg.fof
        self.store = FofStore(
            dataclasses.replace(
                fof,
                query_workers=resolve_query_workers(fof.query_workers, dev),
                query_device=resolve_query_device(fof.query_device, dev),
            )
        )
        self.recon = Reconstruction(self.cfg.reconstruction)
        self.free = FreeSpaceMap(self.cfg.freespace)
        self.proposer = make_proposer(self.cfg.grasp, seed, grasp_model)
        g = self.cfg.grasp
        self._swept_G = swept_samples(g.gripper, g.approach_check_m, g.swept_step_m)
        # how far from its contact a candidate's swept samples reach: the samples from the wrist,
        # plus the wrist from the contact (the depth along the approach, half the width across)
        self._swept_reach_m = (
            float(np.linalg.norm(np.vstack(self._swept_G), axis=1).max())
            + float(np.hypot(g.gripper.depth_m, 0.5 * g.gripper.max_width_m))
        )
        self._pending: list[np.ndarray] = []
        self._scale: float | None = None
        self.frames = 0
        self.points = 0
        self.last_stamp_ns = 0
        self.last_train: TrainStats | None = None
        self.timings_s: dict[str, float] = {}

    # ------------------------------------------------------------------ ingest
    def depth_from_stereo(self, frame: StereoFrame) -> DepthFrame:
        """Stage 1 (stateless)."""
        return self.stereo.estimate(frame)

    def integrate(self, depth: DepthFrame) -> int:
        """Eq. 1-6 for one depth frame: back-project, fuse into the store, refresh dirty targets,
        and integrate the frame into the TSDF. Returns the number of points added."""
        t0 = time.perf_counter()
        batch = self.observation.backproject(depth)
        # everything that can refuse the frame runs before the store and the grid change: a frame
        # the TSDF cannot take must not leave the map half-updated
        tsdf = self.recon.prepare(depth)
        t1 = time.perf_counter()
        evicted = self.store.evicted
        touched = self.store.insert(batch.points_W, batch.cov_W)
        if self.store.evicted != evicted:  # the store compacted: the pending indices moved
            remap = self.store.last_remap
            self._pending = [r[r >= 0] for r in (remap[p] for p in self._pending)]
        self.store.update_targets()
        t2 = time.perf_counter()
        if tsdf is not None:
            self.recon.commit(tsdf)
        t3 = time.perf_counter()
        self.free.integrate(depth)
        t4 = time.perf_counter()
        self._pending.append(touched)
        self.frames += 1
        self.points += len(batch)
        self.last_stamp_ns = max(self.last_stamp_ns, depth.stamp_ns)
        self.timings_s.update(backproject=t1 - t0, fof=t2 - t1, tsdf=t3 - t2, freespace=t4 - t3)
        return len(batch)

    def add_stereo(self, frame: StereoFrame) -> DepthFrame:
        t0 = time.perf_counter()
        depth = self.depth_from_stereo(frame)
        self.timings_s["depth"] = time.perf_counter() - t0
        self.integrate(depth)
        return depth

    # ------------------------------------------------------------------ training
    def _targets(self) -> tuple[np.ndarray, np.ndarray]:
        """Training inputs and targets; the target scale is kept unless it drifts by > 25 %.

        The SVGP is deliberately not rescaled when the scale changes: the scale follows the
        field, which grows (Eq. 4's weights are counts) where views overlap, so the model's
        normalised predictions stay close to the new normalised targets, and its
        hyperparameters stay of order 1. Rescaling the model to keep its old density-unit field
        shrank the output scale and the noise by the squared ratio (67x at frame 2 of the bench
        orbit), and training never recovered (full-data ELBO per point -125 against +0.2)."""
        s = self.store.compute_scale()
        if self._scale is None or abs(s / self._scale - 1.0) > 0.25:
            self._scale = s
        return self.store.training_data(self._scale)

    def train_steps(self, steps: int | None = None, rate_scale: float = 1.0) -> TrainStats:
        """Streaming SVGP update (warm start, NGD + Adam, replay) on what changed since last call,
        with the learning rates multiplied by ``rate_scale`` in (0, 1] (``OccupancySVGP.set_rate_scale``;
        the daemon's idle training lowers it): :meth:`train_on` the :meth:`training_batch`."""
        return self.train_on(self.training_batch(), steps, rate_scale)

    def training_batch(self) -> TrainingBatch:
        """What the next streaming update trains on: copies of the store's inputs and Eq. 4
        targets (Eq. 7) and the points changed since the last batch. It reads the store and
        nothing else; :meth:`train_on` reads nothing but the batch and the SVGP, so the daemon
        takes it under the map's lock and trains without holding that lock."""
        x, y = self._targets()
        if len(x) == 0:
            raise EmptyCloudError("no training points")
        new = np.unique(np.concatenate(self._pending)) if self._pending else np.zeros(0, np.int64)
        self._pending.clear()
        return TrainingBatch(x, y, new[new < len(x)])

    def train_on(
        self, batch: TrainingBatch, steps: int | None = None, rate_scale: float = 1.0
    ) -> TrainStats:
        """Streaming SVGP update on ``batch`` (see :meth:`train_steps`)."""
        t0 = time.perf_counter()
        self.svgp.set_rate_scale(rate_scale)
        self.last_train = self.svgp.update(batch.x_W, batch.target, batch.new_idx, steps)
        self.timings_s["train"] = time.perf_counter() - t0
        return self.last_train

    def fit_paper(self, epochs: int | None = None) -> TrainStats:
        """The paper's batch fit on all current points (fresh model, Adam 1e-3, 100 epochs)."""
        t0 = time.perf_counter()
        self.store.update_targets(full=True)
        self._scale = None
        x, y = self._targets()
        self._pending.clear()
        self.last_train = self.svgp.fit_paper(x, y, epochs)
        self.timings_s["train"] = time.perf_counter() - t0
        return self.last_train

    def set_optimal_q(self) -> tuple[float, float]:
        """Set the SVGP's q(u) to its closed-form optimum on all current points, keeping its
        hyperparameters and inducing points (``OccupancySVGP.set_optimal_q``): a converged
        reference for the benchmark. Returns the full-data ELBO per point (before, after)."""
        x, y = self._targets()
        before = self.svgp.elbo_per_point(x, y)
        return before, self.svgp.set_optimal_q(x, y)

    @property
    def ready(self) -> bool:
        if self.last_train is None:
            return False
        return self.last_train.ready

    # ------------------------------------------------------------------ query
    def sigma2_occ(self, points_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Algorithm 1 at query points, with the live model: (mu_occ, sigma2_occ)."""
        return self._cubature(points_W, frozen=False).run()

    def cubature_job(self, points_W: np.ndarray) -> CubatureJob:
        """Algorithm 1 lines 1-2 (Eq. 5-6: the fused Gaussian of each query point, read from the
        store) now, and a frozen copy of the SVGP, so that lines 3-6 (``CubatureJob.run``) can run
        later, on another thread, with the model as it is now."""
        return self._cubature(points_W, frozen=True)

    def _cubature(self, points_W: np.ndarray, frozen: bool) -> CubatureJob:
        if not self.svgp.initialised:
            raise ModelNotReadyError("the SVGP has not been trained")
        cov, mean = self.store.fused_covariance(points_W)  # lines 1-2, Eq. 5-6
        units = self.cfg.svgp.output_units
        scale = float(self._scale or 1.0) if units == "density" else 1.0
        model = self.svgp.snapshot() if frozen else self.svgp
        return CubatureJob(mean, cov, model, scale, self.cfg.cubature)

    def query_cloud(self) -> np.ndarray:
        cloud = self.recon.cloud(self.seed)
        cap = self.cfg.cubature.max_query_points
        if len(cloud) > cap:
            rng = np.random.default_rng(self.seed)
            cloud = cloud[np.sort(rng.choice(len(cloud), cap, replace=False))]
        return cloud

    def grasp_input(self, cloud_W: np.ndarray | None = None) -> GraspInput:
        """Phase 1 of ``compute``: a snapshot of what the proposer needs (the query cloud, the
        camera centres and, for the swept uncertainty, the free-space map around the cloud).
        Reads the reconstruction: call it under the same lock as ``integrate``."""
        if len(self.store) == 0:
            raise EmptyCloudError("no observations")
        t0 = time.perf_counter()
        cloud = self.query_cloud() if cloud_W is None else np.asarray(cloud_W, dtype=np.float64)
        views = (
            np.array(self.recon.camera_centers_W, dtype=np.float64)
            if self.recon.camera_centers_W
            else np.zeros((1, 3))
        )
        free = None
        if self.cfg.grasp.uncertainty == "swept" and len(cloud):
            r = self._swept_reach_m
            free = self.free.crop(cloud.min(0) - r, cloud.max(0) + r)
        return GraspInput(
            cloud_W=cloud, views_W=views, timings_s={"cloud": time.perf_counter() - t0}, free=free
        )

    def propose(
        self,
        inp: GraspInput,
        proposer: GraspProposer | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> Proposal:
        """Phase 2 of ``compute``: grasp candidates on the snapshot (by ``proposer``, default the
        configured one) and, where the snapshot holds the free-space map, the never-observed
        share of each one's swept volume (``pugsd.core.grasp.swept``). Touches no pipeline state
        (the proposer is stateless), so the daemon runs it without the model lock while frames
        are integrated and the SVGP trains. ``should_stop`` is asked during the proposal and
        before the swept volumes: once it says True, :class:`pugsd.errors.Preempted` is raised."""
        t0 = time.perf_counter()
        cands = (proposer or self.proposer).propose(inp.cloud_W, None, inp.views_W, should_stop)
        if should_stop is not None and should_stop():
            raise Preempted("the grasp proposal gave way")
        t1 = time.perf_counter()
        unk = None if inp.free is None else self._unknown_share(inp.free, inp.cloud_W, cands)
        timings = {**inp.timings_s, "propose": t1 - t0}
        if unk is not None:
            timings["swept"] = time.perf_counter() - t1
        return Proposal(cloud_W=inp.cloud_W, candidates=cands, timings_s=timings, unknown_share=unk)

    def _unknown_share(self, free: FreeSpaceMap, cloud_W: np.ndarray, cands: GraspSet) -> np.ndarray:
        """U of each valid candidate (NaN for the others) against the free-space map ``free``."""
        g = self.cfg.grasp
        unk = np.full(len(cands), np.nan)
        v = cands.valid
        if v.any():
            unk[v] = unknown_share(
                free, cands.pose[v], *self._swept_G, cKDTree(cloud_W), g.unknown_decay_m, g.threads
            )
        return unk

    def score(self, proposal: Proposal, uncertainty: str | None = None) -> PipelineResult:
        """Phase 3 of ``compute``: Algorithm 1 (Eq. 9-12) at the contact points of the valid
        candidates with the current store and SVGP, then the Eq. 13 ranking. The query cloud's
        other entries of ``mu_occ`` and ``sigma2_occ`` are NaN (``complete_cloud`` fills them).
        Reads the store and the model: call it under the same lock as ``integrate``.
        ``uncertainty`` overrides ``grasp.uncertainty`` (swept or contact) for this call."""
        cloud, cands = proposal.cloud_W, proposal.candidates
        t2 = time.perf_counter()
        mu_occ = np.full(len(cloud), np.nan)
        s2 = np.full(len(cloud), np.nan)
        v = cands.valid
        need = np.unique(cands.src_index[v])
        if len(need):
            mu_occ[need], s2[need] = self.sigma2_occ(cloud[need])
        t3 = time.perf_counter()
        g = self.cfg.grasp
        ref, unk, s2g = 1.0, None, None
        if (uncertainty or g.uncertainty) == "swept":
            # unit-free: the contacts' sigma^2_occ over their median on this scan, plus the
            # never-observed share of each grasp's swept volume (pugsd.core.grasp.swept)
            contact_s2 = s2[cands.src_index[v]]
            finite = contact_s2[np.isfinite(contact_s2) & (contact_s2 > 0)]
            ref = float(np.median(finite)) if len(finite) else 1.0
            unk = proposal.unknown_share
            if unk is None:  # proposed without the free-space map: read the live one
                unk = self._unknown_share(self.free, cloud, cands)
            s2g = np.full(len(cands), np.nan)
            if v.any():
                s2g[v] = grasp_sigma2(contact_s2, ref, unk[v], g.unknown_weight)
        t4 = time.perf_counter()
        ranked = rank_grasps(
            cands, s2, g.gamma, g.top_k, g.thin_distance_m, "pugs", self.last_stamp_ns, s2g, unk
        )
        base = rank_grasps(
            cands, s2, g.gamma, g.top_k, g.thin_distance_m, "baseline", self.last_stamp_ns, s2g, unk
        )
        t5 = time.perf_counter()
        pc = np.zeros(len(cloud))
        per_grasp = s2[cands.src_index[v]] if s2g is None else s2g[v]
        pc[cands.src_index[v]] = reweight(cands.confidence[v], per_grasp, g.gamma)
        timings = {"swept": t4 - t3, **proposal.timings_s, "algorithm1": t3 - t2, "eq13": t5 - t4}
        self.timings_s.update(timings)
        return PipelineResult(
            grasps=ranked,
            baseline_grasps=base,
            cloud_W=cloud,
            mu_occ=mu_occ,
            sigma2_occ=s2,
            occupancy_confidence=1.0 / (1.0 + g.gamma * s2 / ref),
            pugs_conf_points=pc,
            candidates=cands,
            model_version=self.svgp.version,
            timings_s=timings,
            unknown_share=unk,
            sigma2_grasp=s2g,
            sigma2_ref=ref,
        )

    def compute(self, cloud_W: np.ndarray | None = None, *, full_cloud: bool = True) -> PipelineResult:
        """Reconstruction -> grasp candidates -> Algorithm 1 -> Eq. 13 ranking, in one call:
        ``score(propose(grasp_input(cloud_W)))``.

        Eq. 13 needs sigma^2_occ only at the contact points of valid candidates, so Algorithm 1 runs
        there first and the grasps are ranked from it. With ``full_cloud`` (default) the rest of
        the query cloud follows (``complete_cloud``); without it those entries of ``mu_occ`` and
        ``sigma2_occ`` are NaN, and ``complete_cloud(result)`` fills them in later, so a caller
        can publish grasps before the per-point cloud is done. Values are per point: the order
        does not change them."""
        result = self.score(self.propose(self.grasp_input(cloud_W)))
        return self.complete_cloud(result) if full_cloud else result

    def complete_cloud(self, result: PipelineResult) -> PipelineResult:
        """Algorithm 1 for the query points ``compute(full_cloud=False)`` left out (NaN), with the
        current model; call it before the next training step to stay with ``result``'s model."""
        done = self.finish_cloud(self.cloud_job(result))
        assert done is not None
        return done

    def cloud_job(self, result: PipelineResult) -> CloudJob:
        """Phase 1 of ``complete_cloud`` (reads the store and copies the model: under the lock):
        call it before the next training step to stay with ``result``'s model."""
        todo = np.flatnonzero(np.isnan(result.sigma2_occ))
        t0 = time.perf_counter()
        job = self.cubature_job(result.cloud_W[todo]) if len(todo) else None
        return CloudJob(result, todo, job, time.perf_counter() - t0)

    def finish_cloud(
        self, job: CloudJob, should_stop: Callable[[], bool] | None = None, chunk: int = 1024
    ) -> PipelineResult | None:
        """Phase 2 of ``complete_cloud``: Algorithm 1 lines 3-6 through the frozen model. Touches
        no pipeline state: the daemon runs it without the model lock. With ``should_stop`` it
        works through ``chunk`` query points at a time and gives up (None) once that says so."""
        result = job.result
        t0 = time.perf_counter()
        mu_occ, s2 = result.mu_occ.copy(), result.sigma2_occ.copy()
        if job.cubature is not None:
            if should_stop is None:
                out: tuple[np.ndarray, np.ndarray] | None = job.cubature.run()
            else:
                out = job.cubature.run_chunked(chunk, should_stop)
            if out is None:
                return None
            mu_occ[job.todo], s2[job.todo] = out
        dt = job.prepare_s + time.perf_counter() - t0
        timings = {**result.timings_s, "algorithm1_cloud": dt}
        return dataclasses.replace(
            result,
            mu_occ=mu_occ,
            sigma2_occ=s2,
            occupancy_confidence=1.0 / (1.0 + self.cfg.grasp.gamma * s2 / result.sigma2_ref),
            timings_s=timings,
        )

    # ------------------------------------------------------------------ helpers
    def warm_up(self) -> None:
        """Pay first-call costs before frames arrive: torch's optimizers import their compiler
        machinery lazily (seconds on the first SVGP step, enough to drop a second of 10 Hz
        frames), and the single-contact proposer's search is compiled (or loaded from numba's
        cache) on first use. Trains and queries a throwaway 8-point SVGP and compiles the
        search; the pipeline's own state is not touched."""
        compile_search = getattr(self.proposer, "compile_search", None)
        if compile_search is not None:
            compile_search()
        cfg = dataclasses.replace(self.cfg.svgp, num_inducing=8, batch_size=16)
        svgp = OccupancySVGP(cfg)
        rng = np.random.default_rng(0)
        x = rng.uniform(-0.05, 0.05, (64, 3))
        svgp.update(x, np.ones(len(x)), np.arange(len(x)), steps=2)
        svgp.predict(x[:4])

    def reset(self) -> None:
        self.store.reset()
        self.svgp.reset()
        self.recon.reset()
        self.free.reset()
        self._pending.clear()
        self._scale = None
        self.frames = 0
        self.points = 0
        self.last_train = None

    def stats(self) -> dict[str, float | int | bool]:
        t = self.last_train
        return {
            "frames": self.frames,
            "points": self.points,
            "voxels": len(self.store),
            "evicted": self.store.evicted,
            "tsdf_blocks": self.recon.blocks,
            "tsdf_blocks_evicted": self.recon.blocks_evicted,
            "freespace_blocks": len(self.free),
            "model_version": self.svgp.version,
            "svgp_steps": self.svgp.total_steps,
            "elbo": float(t.elbo) if t is not None else float("nan"),
            "ready": self.ready,
        }
