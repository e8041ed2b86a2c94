# SPDX-License-Identifier: Apache-2.0
"""The daemon's training: SVGP steps on their own thread beside the ingest, as the streaming
schedule allows (``train_steps_per_frame`` after each integrated frame, then idle rounds), and
what each step tells the daemon (step count, ELBO, readiness)."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from pugsd.errors import EmptyCloudError

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

log = logging.getLogger(__name__)


class Training:
    """The training worker of daemon ``d`` and its steps."""

    def __init__(self, d: Daemon) -> None:
        self.d = d

    def step_locked(self, rate_scale: float = 1.0) -> Any:
        """On the training thread: one SVGP step. The batch is taken under the model lock, which
        is handed over to the SVGP lock (taken before it is released: no reset comes between the
        batch and the step), so that frames are integrated during the step. None when the map is
        empty: a reset between two steps of a round emptied it, which ends the round and is not a
        rejected input."""
        d = self.d
        with d._model_lock:
            try:
                batch = d.pipeline.training_batch()
            except EmptyCloudError:
                return None
            d._svgp_lock.acquire()
        try:
            return d.pipeline.train_on(batch, 1, rate_scale=rate_scale)
        finally:
            d._svgp_lock.release()

    async def train(self, steps: int, idle: bool = False) -> None:
        """Up to ``steps`` SVGP steps, one per offload, as the schedule allows each."""
        d = self.d
        s = d.schedule
        for _ in range(steps):
            if d._stopping or not s.may_step(time.monotonic(), len(d.depth_box), idle):
                break
            s.last_train_s = time.monotonic()
            decaying = s.decaying(idle, d.ready)
            step = d._offload("train", self.step_locked, s.rate_scale(decaying))
            stats = await d._guard("train", step)
            if stats is None:
                break
            self.note(stats, 1)
            s.stepped(decaying)
            d.model_changes.offer("step")

    async def worker(self) -> None:
        """Trains beside the ingest: ``train_steps_per_frame`` steps after each integrated frame;
        while no frame comes, idle rounds of ``idle_train_steps`` (within ``idle_train_s`` of the
        last frame, every 20 ms at most, with backoff after failures)."""
        d = self.d
        cfg, s = d.cfg.daemon, d.schedule
        while not d._stopping:
            idle = s.idle(time.monotonic())
            frame = await d.integrated.take_within(0.02 if idle else 0.5)
            if d._stopping:
                break
            if frame is not None:
                if cfg.train_steps_per_frame > 0:
                    await self.train(cfg.train_steps_per_frame)
            elif idle and s.idle_round_due(time.monotonic()):
                await self.train(cfg.idle_train_steps, idle=True)
                s.round_ended(time.monotonic(), d.health.failures.get("train", 0))

    def note(self, stats: Any, steps: int) -> None:
        """A step's result: counted, its ELBO kept, readiness updated (logged when it begins)."""
        d = self.d
        d.health.count("train_steps", steps)
        elbo = float(stats.elbo)
        d.elbo = elbo if np.isfinite(elbo) else None
        was = d.ready
        d.ready = bool(stats.ready)
        d.was_ready = d.was_ready or d.ready
        if d.ready and not was:
            log.info("model ready (ELBO %.4g)", elbo)
