# SPDX-License-Identifier: Apache-2.0
"""The daemon's outputs: a grasp round (started on the loop when the schedule says grasps are
due, computed on the grasp thread), a proposal made before the model is ready, their publication
on the loop (grasps, markers, the cloud), the latest results served on ``grasps/latest``, and the
cleared outputs after a reset."""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pugsd.core.types import ScoredGrasps
from pugsd.errors import EmptyCloudError, Preempted
from pugsd.stream.assembler import log_nth
from pugsd.wire import codec
from pugsd.wire.publisher import Publisher

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

log = logging.getLogger(__name__)

GRASPS_LOG_S = 60.0  # published grasps are logged at most this often (the first ones at once)


@dataclass(frozen=True)
class Prepared:
    """A proposal made before the model was ready, on the map of ``map_version``."""

    proposal: Any
    stamp_ns: int
    map_version: int


class Outputs:
    """The publishers of the daemon ``d`` and what it last published; ``clock`` is the daemon's
    monotonic clock."""

    def __init__(self, d: Daemon, clock: Callable[[], float]) -> None:
        self.d = d
        self.clock = clock
        self.publishers: dict[str, Publisher] = {}
        self.latest_grasps: bytes | None = None
        self.latest_result: Any = None  # the last PipelineResult
        # the last PipelineResult whose cloud went out: sigma^2_occ over the whole query cloud
        # (the demo draws it; latest_result may be a newer round's, its cloud not computed)
        self.latest_cloud_result: Any = None
        self.model_version: int | None = None
        self.grasps_published = 0
        self.grasps_logged_s = -math.inf  # when grasps were last logged
        self.grasps_logged_n = 0  # grasps_published then
        # a proposal made while the model was not ready (``prepare``) and the map version it was
        # made on (set before it is made: a failed one is not retried on the same map)
        self.prepared: Prepared | None = None
        self.prepared_for: int | None = None

    def clear(self) -> None:
        """A reset: no grasps of the cleared map are served any more; the new map's first grasps
        are logged."""
        self.latest_grasps = self.latest_result = self.latest_cloud_result = self.model_version = None
        self.grasps_logged_s = -math.inf
        self.prepared = self.prepared_for = None

    async def grasp_round(self, loop: asyncio.AbstractEventLoop) -> None:
        """On the loop: one grasp computation (``compute_and_encode`` on the grasp thread) if
        the schedule says grasps are due; else wait until they are, or the model changes. While
        the input has paused and the newest frame's grasps wait (for its training steps, or the
        rate limit), the proposal for its map is ``prepare``d meanwhile: it needs no model."""
        d = self.d
        s, now, queued = d.schedule, self.clock(), d.frames_in_flight()
        due_in = s.grasps_due_in(now, s.grasps_started_s, queued)
        if due_in > 0.0:
            if s.frame_unpublished and s.paused_in(now, queued) == 0.0 and self.prepared_for != d.map_version:
                await self.prepare_now()
            else:
                await d.model_changes.take_within(due_in)
            return
        with_cloud = s.start_grasps(now, queued)
        newest_recv = d._newest_recv_s
        generation = d._generation

        def hand_over(result: Any, payloads: dict[str, bytes], newest: float | None = newest_recv,
                      gen: int = generation) -> None:  # fmt: skip
            loop.call_soon_threadsafe(self.publish, result, payloads, newest, gen)

        try:
            args = (d.frames.frame_id, generation, hand_over, with_cloud)
            outcome = await d._guard("grasps", d._offload("grasps", self.compute_and_encode, *args))
        finally:
            s.grasps_urgent = False
        if outcome == "discarded":
            d.health.count("grasps_discarded")
            log.info("grasp computation discarded: the map was reset while it ran")
        elif outcome == "preempted":
            d.health.count("clouds_preempted")
        elif outcome == "cloud discarded":
            d.health.count("clouds_discarded")
        if outcome == "proposal preempted":
            d.health.count("proposals_preempted")
            s.grasps_preempted()
        else:  # computed (or failed: a failure is not a reason to hold the next one)
            s.grasps_completed()
        await asyncio.sleep(0)  # let the hand-over callbacks run before the next round

    async def propose_early(self, changes: Any) -> None:
        """The model is not ready yet: once the input pauses, ``prepare`` a proposal on the map
        as it is (it needs no model), so that the first grasps need only Algorithm 1 at the
        contacts when the model becomes ready. Until the pause, wait on ``changes``."""
        d = self.d
        paused_in = d.schedule.paused_in(self.clock(), d.frames_in_flight())
        if paused_in == 0.0:
            await self.prepare_now()
        elif paused_in < math.inf:
            await changes.take_within(paused_in)
        else:
            await changes.take()

    def prepare(self) -> bool:
        """On the grasp thread, while grasps cannot be computed yet (the model is not ready, or
        the newest frame's training steps are not done): the snapshot and the proposal (the
        grasp candidates and their swept volumes' unknown shares need only the map), kept for
        the next grasp computation, which uses it if the map is still the same (no frame
        integrated, no reset: both bump ``map_version``). It gives way like a computation's
        proposal when a frame came since and the input paused: then it returns False. A map
        with no surface yet (after a first frame) has nothing to propose on: no proposal, and
        not a rejected input."""
        d = self.d
        with d._model_lock:
            self.prepared, self.prepared_for = None, d.map_version
            try:
                inp = d.pipeline.grasp_input()
            except EmptyCloudError:
                return True
            stamp_ns = d._newest_stamp_ns
            version = d.map_version
        try:
            proposal = d.pipeline.propose(inp, should_stop=lambda: d._proposal_gives_way(version))
        except Preempted:
            return False
        self.prepared = Prepared(proposal, stamp_ns, version)
        return True

    async def prepare_now(self) -> None:
        """On the loop: ``prepare`` on the grasp thread; one that gave way is counted."""
        d = self.d
        if await d._guard("grasps", d._offload("grasps", self.prepare)) is False:
            d.health.count("proposals_preempted")

    def compute_and_encode(
        self,
        frame_id: str,
        generation: int,
        on_grasps: Callable[[Any, dict[str, bytes]], None],
        with_cloud: bool,
    ) -> str:
        """On the grasp thread. Under the model lock: a snapshot of the query cloud. Without it:
        the grasp proposal (frames are integrated and the SVGP trains meanwhile); the one
        ``prepare`` made instead, when no frame was integrated since. Under the lock
        again: Algorithm 1 at the contacts and Eq. 13 with the model as it is now, handed to
        ``on_grasps`` at once; then, if ``with_cloud``, still under that lock, the fused
        covariances of the rest of the query cloud and a frozen copy of the same model, through
        which Algorithm 1 for the PointCloud2 runs without the lock, in chunks: it gives way (the
        cloud is not published) as soon as grasps for a newer frame are due, unless clouds are
        overdue (``_cloud_gives_way``).
        The outputs are stamped with the newest frame in the snapshot (read with it).
        The proposal gives way when a frame came since the snapshot and the input has paused
        (``_proposal_gives_way``): the next computation then starts at once on the newest map.
        Returns "discarded" if a reset while this ran discarded the result ("cloud discarded" if
        it came after the grasps), "proposal preempted" if the proposal gave way, "preempted" if
        the cloud did, else "published"."""
        d = self.d
        prep, self.prepared = self.prepared, None
        with d._model_lock:
            if prep is not None and prep.map_version == d.map_version:
                inp, proposal, stamp_ns = None, prep.proposal, prep.stamp_ns
            else:
                inp, stamp_ns = d.pipeline.grasp_input(), d._newest_stamp_ns
            version = d.map_version
        if inp is not None:
            try:
                proposal = d.pipeline.propose(inp, should_stop=lambda: d._proposal_gives_way(version))
            except Preempted:
                return "proposal preempted"
        with d._model_lock, d._svgp_lock:
            if generation != d._generation:
                return "discarded"
            result = d.pipeline.score(proposal)
            g = result.grasps
            out = {"grasps": codec.encode_grasp_array(g, frame_id, stamp_ns)}
            out["markers"] = codec.encode_grasp_markers(
                g, frame_id, stamp_ns, top_k=d.cfg.daemon.markers_top_k
            )
            on_grasps(result, out)
            job = d.pipeline.cloud_job(result) if with_cloud else None
        if job is not None:
            result = d.pipeline.finish_cloud(job, d._cloud_gives_way)
            if result is None:
                return "preempted"
            if generation != d._generation:
                return "cloud discarded"  # the map was reset meanwhile: not the current map
            cloud = codec.encode_cloud(
                result.cloud_W,
                stamp_ns,
                frame_id,
                sigma2_occ=result.sigma2_occ,
                pugs_confidence=result.pugs_conf_points,
            )
            on_grasps(result, {"cloud": cloud})  # the round's result, its sigma^2_occ now whole
        return "published"

    def publish(
        self, result: Any, payloads: dict[str, bytes], newest_recv: float | None, generation: int
    ) -> None:
        """On the loop: publish what ``compute_and_encode`` handed over (grasps, then the cloud),
        unless a reset began since it was computed: the grasp thread checks the generation
        before scoring, but a reset can bump it (here, on the loop) while the scoring runs."""
        d = self.d
        if generation != d._generation:
            d.health.count("grasps_discarded" if "grasps" in payloads else "clouds_discarded")
            log.info("grasp results discarded: the map was reset while they were computed")
            return
        for role, data in payloads.items():
            self.put(role, data)
        if "cloud" in payloads:
            d.schedule.last_cloud_published_s = self.clock()
            if result is not None:
                self.latest_cloud_result = result
        if "grasps" not in payloads:
            # the cloud of the latest grasps' round: the same grasps, with sigma^2_occ over the
            # whole query cloud (the demo draws it); a cloud of another round changes nothing
            latest = self.latest_result
            if result is not None and latest is not None and result.grasps is latest.grasps:
                self.latest_result = result
            return
        d.schedule.grasps_urgent = False  # the grasps are out: idle training need not wait for the cloud
        self.latest_grasps = payloads["grasps"]
        self.latest_result = result
        self.model_version = int(result.model_version)
        self.grasps_published += 1
        d.health.count("grasps_published")
        if newest_recv is not None:
            d.health.observe("newest_frame_to_grasps", self.clock() - newest_recv)
        g = result.grasps
        now = self.clock()
        # not one line per publication: the first grasps (since the start or a reset), then at
        # most one line per GRASPS_LOG_S with the updates published meanwhile
        if len(g) and now - self.grasps_logged_s >= GRASPS_LOG_S:
            log.info(
                "grasps v%s: %d, top PUGS %.3f (baseline %.3f, sigma2 %.3g); %d update(s) published "
                "since the last such line",
                self.model_version,
                len(g),
                float(g.pugs_confidence[0]),
                float(g.baseline_confidence[0]),
                float(g.sigma2_occ[0]),
                self.grasps_published - self.grasps_logged_n,
            )
            self.grasps_logged_s, self.grasps_logged_n = now, self.grasps_published

    def put(self, role: str, data: bytes) -> bool:
        """Publish one output; a failed put (zenoh refusing it: a closed or broken session) is
        logged and counted (``publish_failed``, per role in ``publish_failed.<role>``) instead of
        escaping into the event loop's exception handler. The results stay queryable
        (``grasps/latest``). ``daemon.max_consecutive_failures`` failed puts in a row, of any
        role, make the daemon unhealthy, so systemd restarts it with a fresh session; one role
        that keeps failing while the others go out does not (a restart would not mend it)."""
        d = self.d
        try:
            self.publishers[role].put(data)
        except Exception as exc:
            d.health.count("publish_failed")
            d.health.count(f"publish_failed.{role}")
            n = d.health.failed("publish")
            of_role = d.health.counts[f"publish_failed.{role}"]
            if log_nth(of_role, first=10):  # the first ten of a role, then every 100th
                log.warning("publishing %s failed (%d so far, %d puts in a row): %s", role, of_role, n, exc)
            return False
        d.health.succeeded("publish")
        return True

    def publish_cleared(self, stamp_ns: int) -> None:
        """After a reset: an empty GraspArray, a MarkerArray holding only its DELETEALL and an
        empty PointCloud2, so that viewers and subscribers drop the old object's grasps (markers
        live until deleted) instead of showing them until the new model is ready."""
        d = self.d
        z = np.zeros(0)
        empty = ScoredGrasps(np.zeros((0, 4, 4)), np.zeros((0, 3)), z, z, z, z, np.zeros(0, np.int64))
        payloads = {
            "grasps": codec.encode_grasp_array(empty, d.frames.frame_id, stamp_ns),
            "markers": codec.encode_grasp_markers(empty, d.frames.frame_id, stamp_ns, top_k=0),
        }
        if d.cfg.daemon.publish_cloud:
            payloads["cloud"] = codec.encode_cloud(np.zeros((0, 3)), stamp_ns, d.frames.frame_id)
        for role, data in payloads.items():
            if role in self.publishers:  # a failed put is counted and does not fail the reset
                self.put(role, data)


def output_stamp_ns(newest_ns: int, stamp_ns: int, max_gap_ns: int) -> int:
    """The stamp for outputs after integrating a frame stamped ``stamp_ns`` when the newest was
    ``newest_ns``: the newest frame stamp, never going back by a frame integrated out of order,
    but following the source when its stamps go back by more than ``max_gap_ns``
    (``daemon.pose_max_gap_s``: a restarted source, a looped recording, a stepped clock, the same
    test the pose buffer restarts on); a reset starts afresh."""
    if stamp_ns >= newest_ns or newest_ns - stamp_ns > max_gap_ns:
        return stamp_ns
    return newest_ns
