# SPDX-License-Identifier: Apache-2.0
"""What one benchmark run measures and how long it may take (full and ``--quick`` presets)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class BenchOptions:
    """Knobs of one run. ``full()`` is what ``make bench`` runs; ``quick()`` is a < 1 min smoke run
    whose numbers are *not* comparable with the targets (fewer frames, fewer paper epochs)."""

    quick: bool = False
    object_name: str = "mug"
    trajectories: tuple[str, ...] = ("complete", "partial")
    n_frames: int = 30
    width: int = 640
    height: int = 480
    rate_hz: float = 10.0  # the simulated camera rate (stamps are 1 / rate_hz apart)
    seed: int = 0
    paper_epochs: int | None = None  # None: the config's svgp.paper_epochs (paper: 100)
    paper_reference_seed: int | None = 1  # a second paper fit with this svgp.seed (None: skip)
    # the synchronous streaming run again with the paper's inducing-point count
    # (svgp.paper_num_inducing): how much of the gap to the paper's fit is the smaller M
    streaming_at_paper_m: bool = True
    svgp_step_repeats: int = 20  # dedicated single-step timings after each sequence
    compute_repeats: int = 5  # newest-frame -> grasps cycles after each sequence
    # extra SVGP steps after the first publish (cumulative), as the daemon's idle training
    # does: agreement with the paper's fit after each
    refine_steps: tuple[int, ...] = (100, 400)
    # the paper fit (and the streaming model) again with q(u) at its closed-form optimum
    optimal_q: bool = True
    ready_timeout_s: float = 60.0  # streaming: give up waiting for the readiness criterion
    # fresh daemons fed the same sequence for the daemon's last frame -> grasps (their median)
    daemon_repeats: int = 5
    thread_sweep: tuple[int, ...] = (1, 2)  # torch threads for the SVGP-step sweep (empty: skip)
    # sustained throughput through the daemon: input rates tried, highest first; the ladder
    # starts above the 10 Hz target so that the highest rate held is measured, not capped
    throughput_rates_hz: tuple[float, ...] = (30.0, 25.0, 20.0, 15.0, 10.0, 5.0, 2.5, 1.25)
    throughput_trial_s: float = 10.0  # each rate is offered for max(this, n_frames / rate) s
    throughput_min_frames: int = 30
    drain_timeout_s: float = 15.0
    # long replay: simulated minutes offered as fast as possible; RSS growth between two minutes
    replay_sim_min: float = 30.0
    replay_window_min: tuple[float, float] = (5.0, 30.0)
    replay_wall_s: float = 240.0  # offer pacing: the simulated minutes are spread over this
    replay_wall_cap_s: float = 360.0  # stop early (and say so) if the replay takes longer
    use_daemon: bool = True  # False: skip the daemon's last frame, throughput and long replay
    # False: skip the per-trajectory pipeline measurements (stage latencies, paper vs streaming),
    # e.g. to run the daemon sections alone where one command has a time limit
    use_pipeline: bool = True

    @classmethod
    def full(cls) -> BenchOptions:
        return cls()

    @classmethod
    def quick_preset(cls) -> BenchOptions:
        return cls(
            quick=True,
            n_frames=6,
            paper_epochs=3,
            paper_reference_seed=None,
            streaming_at_paper_m=False,
            svgp_step_repeats=3,
            compute_repeats=1,
            daemon_repeats=1,
            refine_steps=(4,),
            ready_timeout_s=5.0,
            thread_sweep=(),
            throughput_rates_hz=(10.0,),
            throughput_trial_s=2.0,
            throughput_min_frames=6,
            drain_timeout_s=3.0,
            replay_sim_min=1.0,
            replay_window_min=(0.25, 1.0),
            replay_wall_s=4.0,
            replay_wall_cap_s=10.0,
        )

    def replace(self, **changes: object) -> BenchOptions:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]
