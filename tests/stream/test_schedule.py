# SPDX-License-Identifier: Apache-2.0
"""StreamingSchedule: the idle rate decay, when a step or an idle round may run, when grasps and
clouds are due and when a cloud gives way, all on times the test passes in."""

from __future__ import annotations

import math

import pytest

from pugsd.config import load_config_dict
from pugsd.stream.schedule import StreamingSchedule, idle_rate_scale


def _schedule(**daemon: object) -> StreamingSchedule:
    return StreamingSchedule(load_config_dict({"daemon": daemon}).daemon)


def test_idle_rates_decay_as_one_over_one_plus_steps_over_tau() -> None:
    assert idle_rate_scale(0, 100) == 1.0
    assert idle_rate_scale(100, 100) == pytest.approx(0.5)
    assert idle_rate_scale(300, 100) == pytest.approx(0.25)
    assert idle_rate_scale(10_000, 0) == 1.0  # tau = 0: no decay


def test_only_idle_steps_of_a_ready_model_decay_and_a_frame_restores_full_rates() -> None:
    s = _schedule(idle_rate_decay_steps=2)
    s.frame_integrated(10.0)
    assert not s.decaying(idle=False, ready=True) and not s.decaying(idle=True, ready=False)
    scales = []
    for _ in range(4):
        decaying = s.decaying(idle=True, ready=True)
        scales.append(s.rate_scale(decaying))
        s.stepped(decaying)
    assert scales == pytest.approx([1.0, 2 / 3, 0.5, 0.4])
    assert s.idle_steps == 4 and s.steps_since_frame == 4 and s.changed
    s.frame_integrated(11.0)
    assert s.idle_steps == 0 and s.rate_scale(s.decaying(True, True)) == 1.0
    off = _schedule(idle_rate_decay_steps=0)
    assert not off.decaying(idle=True, ready=True)


def test_idle_rounds_run_within_idle_train_s_of_the_last_frame() -> None:
    s = _schedule(idle_train_steps=4, idle_train_s=5.0)
    assert not s.idle(0.0)  # no frame yet
    s.frame_integrated(100.0)
    assert s.idle(104.9) and not s.idle(105.0)
    assert not _schedule(idle_train_steps=0).idle(0.0)


def test_a_step_waits_for_a_queued_frame_unless_training_is_overdue() -> None:
    s = _schedule(min_train_interval_s=0.5)
    s.last_train_s = 100.0
    assert s.may_step(100.1, frames_queued=0, idle=False)
    assert not s.may_step(100.5, frames_queued=1, idle=False)  # exactly the interval: not overdue
    assert s.may_step(100.51, frames_queued=1, idle=False)
    s.grasps_urgent = True  # an idle round gives way to grasps for a new frame; frame steps do not
    assert not s.may_step(100.1, frames_queued=0, idle=True) and s.may_step(100.1, 0, idle=False)


def test_a_failing_model_is_retried_with_exponential_backoff() -> None:
    s = _schedule()
    waits = []
    for k in range(9):
        s.round_ended(10.0, k)
        waits.append(round(s.retry_train_at - 10.0, 3))
    assert waits == [0.0, 0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 5.0, 5.0]
    assert not s.idle_round_due(14.9) and s.idle_round_due(15.0)
    s.grasps_urgent = True
    assert not s.idle_round_due(20.0)


def test_grasps_are_due_each_period_and_early_once_a_trained_frame_is_followed_by_a_pause() -> None:
    s = _schedule(grasp_rate_hz=2.0, pause_publish_s=0.1, train_steps_per_frame=2)
    assert s.grasps_due(100.5, 100.0, 0) and not s.grasps_due(100.49, 100.0, 0)
    s.frame_integrated(100.1)
    s.stepped(False)
    assert not s.grasps_due(100.3, 100.0, 0)  # its training steps are not done
    s.stepped(False)
    assert s.grasps_due(100.25, 100.0, 0)
    assert not s.grasps_due(100.25, 100.0, 1)  # a frame is queued: still streaming


def test_grasps_are_due_in_the_rest_of_the_period_or_once_the_input_pauses_after_half_of_it() -> None:
    s = _schedule(grasp_rate_hz=1.0, pause_publish_s=0.125, train_steps_per_frame=2)
    assert s.grasps_due_in(100.0, -math.inf, 0) == 0.0  # no computation yet
    assert s.grasps_due_in(100.25, 100.0, 0) == 0.75 and s.grasps_due_in(101.5, 100.0, 0) == 0.0
    s.frame_integrated(100.5625)
    s.stepped(False)
    assert s.grasps_due_in(100.5625, 100.0, 0) == 0.4375  # its training steps are not done
    s.stepped(False)
    assert s.grasps_due_in(100.5625, 100.0, 0) == 0.125  # at the pause
    assert s.grasps_due_in(100.5625, 100.0, 1) == 0.4375  # a frame is queued: streaming
    s.frame_integrated(100.0625)
    s.stepped(False)
    s.stepped(False)
    assert s.grasps_due_in(100.125, 100.0, 0) == 0.375  # paused at 100.1875, but half a period first
    s.frame_unpublished = False  # its grasps were computed: the period again
    assert s.grasps_due_in(100.125, 100.0, 0) == 0.875
    off = _schedule(grasp_rate_hz=1.0, pause_publish_s=0.0, train_steps_per_frame=0)
    off.frame_integrated(100.0)
    assert off.grasps_due_in(100.75, 100.0, 0) == 0.25


@pytest.mark.parametrize("frame_s", [None, 100.03, 100.2, 100.45])
@pytest.mark.parametrize("steps", [0, 3])
@pytest.mark.parametrize("queued", [0, 1])
def test_grasps_are_due_exactly_when_due_in_is_zero_and_due_once_that_wait_has_passed(
    frame_s: float | None, steps: int, queued: int
) -> None:
    s = _schedule(grasp_rate_hz=3.0, pause_publish_s=0.1, train_steps_per_frame=2)
    if frame_s is not None:
        s.frame_integrated(frame_s)
    for _ in range(steps):
        s.stepped(False)
    last = 100.0
    for k in range(60):
        now = frame_s if frame_s is not None and k == 0 else 100.0 + k * 0.007
        due_in = s.grasps_due_in(now, last, queued)
        assert due_in >= 0.0 and s.grasps_due(now, last, queued) == (due_in == 0.0)
        assert s.grasps_due_in(now + due_in, last, queued) == pytest.approx(0.0, abs=1e-12)
        assert due_in == 0.0 or not s.grasps_due(now + 0.999 * due_in, last, queued)


def test_a_computation_while_streaming_takes_the_cloud_every_cloud_interval() -> None:
    s = _schedule(cloud_interval_s=2.0, pause_publish_s=0.5, publish_cloud=True)
    s.frame_integrated(10.0)
    assert s.start_grasps(10.1, 0) is False  # streaming: the first cloud waits an interval too
    assert s.grasps_urgent and not s.frame_unpublished and not s.changed
    assert s.start_grasps(11.0, 1) is False
    assert s.start_grasps(12.1, 1) is True
    assert s.start_grasps(12.2, 0) is True  # the input paused: the cloud goes at once
    assert _schedule(publish_cloud=False).start_grasps(0.0, 0) is False


def test_a_cloud_gives_way_to_a_newer_frame_after_a_pause_while_clouds_are_recent() -> None:
    s = _schedule(pause_publish_s=0.1, cloud_interval_s=5.0)
    s.last_frame_s, s.last_cloud_published_s = 90.0, 99.0
    assert not s.cloud_gives_way(100.0, 0)  # no newer frame
    s.frame_unpublished = True
    assert s.cloud_gives_way(100.0, 0)
    assert not s.cloud_gives_way(100.0, 1)  # a frame is queued: streaming
    s.last_cloud_published_s = -math.inf  # clouds overdue: this one finishes
    assert not s.cloud_gives_way(100.0, 0)


def test_a_reset_leaves_nothing_to_publish_until_a_new_frame() -> None:
    s = _schedule()
    s.frame_integrated(1.0)
    s.reset()
    assert (s.changed, s.frame_unpublished, s.last_frame_s) == (False, False, None)


def test_the_input_counts_as_paused_pause_publish_s_after_the_last_frame_with_none_queued() -> None:
    s = StreamingSchedule(load_config_dict({"daemon": {"pause_publish_s": 0.5}}).daemon)
    assert s.paused_in(100.0, 0) == math.inf  # no frame yet
    s.frame_integrated(100.0)
    assert s.paused_in(100.2, 0) == pytest.approx(0.3)
    assert s.paused_in(100.2, 1) == math.inf  # a frame waits: still streaming
    assert s.paused_in(100.5, 0) == 0.0 and s.paused_in(107.0, 0) == 0.0


def test_a_proposal_gives_way_to_a_newer_frame_after_a_pause_but_not_twice_in_a_row() -> None:
    s = _schedule(pause_publish_s=0.1)
    s.last_frame_s = 90.0
    assert not s.proposal_gives_way(100.0, 0)  # no newer frame
    s.frame_unpublished = True
    assert s.proposal_gives_way(100.0, 0)
    assert not s.proposal_gives_way(100.0, 1)  # a frame is in flight: streaming
    s.last_frame_s = 99.95
    assert not s.proposal_gives_way(100.0, 0)  # the input has not paused yet
    s.last_frame_s = 90.0
    s.grasps_preempted()
    assert not s.proposal_gives_way(100.0, 0)  # the one before gave way: this one finishes
    s.grasps_completed()
    assert s.proposal_gives_way(100.0, 0)


def test_after_a_preempted_computation_the_rate_limits_count_from_the_one_before() -> None:
    s = _schedule(grasp_rate_hz=1.0, pause_publish_s=0.1, cloud_interval_s=2.0, publish_cloud=True)
    s.frame_integrated(10.0)
    s.start_grasps(10.05, 1)  # streaming: the cloud's interval starts
    s.frame_integrated(10.1)
    s.steps_since_frame = s.d.train_steps_per_frame
    s.start_grasps(10.3, 0)
    assert (s.grasps_started_s, s.cloud_started_s) == (10.3, 10.3)
    s.grasps_preempted()
    assert (s.grasps_started_s, s.cloud_started_s) == (10.05, 10.05)
    s.frame_integrated(10.6)
    s.steps_since_frame = s.d.train_steps_per_frame
    # the next may start at the pause, half a period after the computation before the preempted one
    assert s.grasps_due_in(10.6, s.grasps_started_s, 0) == pytest.approx(0.1)
