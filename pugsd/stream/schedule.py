# SPDX-License-Identifier: Apache-2.0
"""The streaming schedule: when the model trains (steps per frame, idle rounds and their rate
decay) and when grasps and clouds are due.

Pure and synchronous: every decision takes the time ``now`` (seconds, one monotonic clock) and
the number of frames waiting to be integrated from the caller.
"""

from __future__ import annotations

import math
from typing import Any


def idle_rate_scale(idle_steps: int, decay_steps: int) -> float:
    """The learning-rate scale of an idle step after ``idle_steps`` idle steps since the last
    frame: 1 / (1 + idle_steps / ``decay_steps``) (``daemon.idle_rate_decay_steps``; 0: no
    decay)."""
    return 1.0 / (1.0 + idle_steps / decay_steps) if decay_steps > 0 else 1.0


class StreamingSchedule:
    """The training and publishing schedule of ``[daemon]`` (``d``), and the state it keeps.

    After each integrated frame the model takes ``train_steps_per_frame`` steps; while no frame
    waits and the last one came less than ``idle_train_s`` ago, idle rounds of
    ``idle_train_steps`` follow. Ingest has priority: a step waits while a frame is queued, unless
    the last step is older than ``min_train_interval_s`` (sustained overload cannot starve the
    model). Idle rounds also wait while grasps for a newly integrated frame are being computed.
    Idle steps of a ready model run at learning rates that decay with the number of such steps
    since the last frame (:func:`idle_rate_scale`), so that what is published settles; steps
    after a frame, and idle steps before the model is ready, run at the configured rates."""

    def __init__(self, d: Any) -> None:  # pugsd.config.DaemonConfig
        self.d = d
        self.last_frame_s: float | None = None  # when the last integrated frame came
        self.steps_since_frame = 0  # training steps since the newest frame was integrated
        self.idle_steps = 0  # idle steps of a ready model since then (their learning rates decay)
        self.changed = False  # the model changed since the last grasp computation started
        self.frame_unpublished = False  # a frame was integrated since the last computation started
        self.grasps_urgent = False  # computing grasps for a newly integrated frame
        self.last_train_s = 0.0  # when the last training step started
        self.retry_train_at = 0.0  # a failing model's next idle round (backoff)
        self.last_cloud_published_s = -math.inf
        self.gave_way = False  # the last computation's proposal gave way (none completed since)
        self.grasps_started_s = -math.inf  # when the last grasp computation started
        self.cloud_started_s = -math.inf  # when the last computation with a cloud started
        self._before_start = (-math.inf, -math.inf)  # the two above before the last start

    # --- training ---------------------------------------------------------------------------

    def frame_integrated(self, now: float, came_s: float | None = None) -> None:
        """A frame was integrated at ``now``; it came (was received) at ``came_s`` (default
        ``now``): the pause before early grasps counts from then."""
        self.last_frame_s = now if came_s is None else came_s
        self.changed = True
        self.frame_unpublished = True
        self.steps_since_frame = 0
        self.idle_steps = 0

    def idle(self, now: float) -> bool:
        """Idle rounds are on: within ``idle_train_s`` of the last frame."""
        d, last = self.d, self.last_frame_s
        return last is not None and d.idle_train_steps > 0 and now - last < d.idle_train_s

    def idle_round_due(self, now: float) -> bool:
        """An idle round may start: no grasps for a new frame in the making, no backoff."""
        return not self.grasps_urgent and now >= self.retry_train_at

    def may_step(self, now: float, frames_queued: int, idle: bool) -> bool:
        """Whether the next step of a round runs: not while a frame waits (unless steps are
        overdue), and in an idle round not while grasps for a new frame are computed."""
        overdue = now - self.last_train_s > self.d.min_train_interval_s
        if frames_queued > 0 and not overdue:
            return False
        return not (idle and self.grasps_urgent)

    def decaying(self, idle: bool, ready: bool) -> bool:
        """Whether an idle step's rates decay: idle, the model ready, the decay on."""
        return idle and self.d.idle_rate_decay_steps > 0 and ready

    def rate_scale(self, decaying: bool) -> float:
        return idle_rate_scale(self.idle_steps, self.d.idle_rate_decay_steps) if decaying else 1.0

    def stepped(self, decaying: bool) -> None:
        self.changed = True
        self.steps_since_frame += 1
        if decaying:
            self.idle_steps += 1

    def round_ended(self, now: float, failures: int) -> None:
        """After an idle round: a model failing ``failures`` times in a row is retried with
        exponential backoff (0.1 s .. 5 s)."""
        self.retry_train_at = now + (min(0.1 * 2 ** (failures - 1), 5.0) if failures else 0.0)

    # --- publishing -------------------------------------------------------------------------

    def streaming(self, now: float, frames_queued: int) -> bool:
        """Frames are coming: one is queued, or the last came less than ``pause_publish_s`` ago."""
        return frames_queued > 0 or (
            self.last_frame_s is not None and now - self.last_frame_s < self.d.pause_publish_s
        )

    def paused_in(self, now: float, frames_queued: int) -> float:
        """Seconds from ``now`` until the input counts as paused (no frame queued and none for
        ``pause_publish_s``): 0.0 once it has, inf while a frame waits or none came yet."""
        if frames_queued > 0 or self.last_frame_s is None:
            return math.inf
        return max(self.d.pause_publish_s - (now - self.last_frame_s), 0.0)

    def grasps_due(self, now: float, last_start: float, frames_queued: int) -> bool:
        """Every 1 / grasp_rate_hz while the model changes; and at once when the input pauses:
        the newest frame has had its training steps and no frame came for ``pause_publish_s``
        (then at most twice the configured rate)."""
        return self.grasps_due_in(now, last_start, frames_queued) == 0.0

    def grasps_due_in(self, now: float, last_start: float, frames_queued: int) -> float:
        """Seconds from ``now`` until grasps are due (:meth:`grasps_due`; 0.0: they are due now)
        if nothing else happens meanwhile. A frame integrated or queued and a training step change
        the answer: ask again after each."""
        d = self.d
        period = 1.0 / d.grasp_rate_hz
        since_start = now - last_start
        due_in = max(period - since_start, 0.0)
        if (
            d.pause_publish_s > 0
            and self.frame_unpublished
            and self.steps_since_frame >= d.train_steps_per_frame
        ):  # early once the input has paused, but not before half a period
            paused_in = self.paused_in(now, frames_queued)
            due_in = min(due_in, max(paused_in, 0.5 * period - since_start, 0.0))
        return due_in

    def start_grasps(self, now: float, frames_queued: int) -> bool:
        """A grasp computation starts now; returns whether it publishes the cloud too. The whole
        cloud's Algorithm 1 costs about as much as the grasps and occupies the grasp thread:
        while frames stream, at most every ``cloud_interval_s`` (the first one too)."""
        d = self.d
        self._before_start = (self.grasps_started_s, self.cloud_started_s)
        self.grasps_started_s = now
        self.changed = False
        # grasps for a frame not yet published: idle training waits for them (less contention)
        self.grasps_urgent = self.frame_unpublished
        self.frame_unpublished = False
        streaming = self.streaming(now, frames_queued)
        if streaming and self.cloud_started_s == -math.inf:
            self.cloud_started_s = now
        cloud_due = not streaming or now - self.cloud_started_s >= d.cloud_interval_s
        with_cloud = bool(d.publish_cloud) and cloud_due
        if with_cloud:
            self.cloud_started_s = now
        return with_cloud

    def cloud_gives_way(self, now: float, frames_queued: int) -> bool:
        """A frame was integrated since the running grasp computation began and the input has
        paused: fresh grasps now matter more than that computation's cloud, as long as a cloud
        was published within ``cloud_interval_s``. (Without that bound a camera slower than
        1 / pause_publish_s, whose every gap looks like a pause, would never let a cloud
        finish.)"""
        return (
            self.frame_unpublished
            and not self.streaming(now, frames_queued)
            and now - self.last_cloud_published_s < self.d.cloud_interval_s
        )

    def proposal_gives_way(self, now: float, frames_queued: int) -> bool:
        """A frame was integrated since the running grasp computation began and the input has
        paused: its proposal, on the older map, gives way to one on the newest, unless the
        computation before it gave way too (else a camera whose every gap looks like a pause
        could keep every proposal from finishing: at most every other one gives way)."""
        return self.frame_unpublished and not self.streaming(now, frames_queued) and not self.gave_way

    def grasps_preempted(self) -> None:
        """The computation started last gave way before publishing anything: the rate limits
        count from the one before it (the next computation may start at once), and the next
        one does not give way."""
        self.grasps_started_s, self.cloud_started_s = self._before_start
        self.gave_way = True

    def grasps_completed(self) -> None:
        """The computation started last computed its grasps (its proposal did not give way)."""
        self.gave_way = False

    def reset(self) -> None:
        """A map reset: nothing to publish until a new frame."""
        self.changed = False
        self.frame_unpublished = False
        self.last_frame_s = None
