# SPDX-License-Identifier: Apache-2.0
"""The benchmark's pure helpers (``pugsd.bench.measure``) on hand-made inputs whose answers are
worked out by hand: latency summaries, agreement figures, the RSS trace's windows, point matching,
which published cloud belongs to which grasps, and the daemon's drop and queue counts. No daemon
runs and nothing is rendered."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from pugsd.bench import measure
from pugsd.core.types import PinholeCamera, ScoredGrasps, StereoFrame, StereoRig
from pugsd.wire.codec import CloudMsg


def test_summarize_gives_milliseconds_of_the_finite_durations() -> None:
    # 1, 2, 3, 4 and 123.4567 ms, with a NaN and an infinity that are left out
    s = measure.summarize([0.003, 0.001, float("nan"), 0.1234567, 0.004, float("inf"), 0.002])
    # median of 5: the 3rd (not the mean, 26.69); p95 interpolates between 4 and 123.4567 at 0.8
    assert s == {"n": 5, "median_ms": 3.0, "p95_ms": pytest.approx(99.565, abs=1e-3),
                 "max_ms": 123.457}  # fmt: skip
    assert measure.summarize([0.5])["p95_ms"] == 500.0
    for empty in ([], [float("nan")], [float("inf"), float("-inf")]):
        assert measure.summarize(empty) == {"n": 0, "median_ms": None, "p95_ms": None, "max_ms": None}


def test_spearman_is_a_rank_correlation_with_no_figure_where_it_is_undefined() -> None:
    a = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert measure.spearman(a, np.array([1.0, 2.0, 3.0, 4.0, 1e6])) == pytest.approx(1.0)  # ranks only
    assert measure.spearman(a, -np.exp(a)) == pytest.approx(-1.0)
    # one swapped pair among 5: 1 - 6 * 2 / (5 * 24) = 0.9
    assert measure.spearman(a, np.array([2.0, 1.0, 3.0, 4.0, 5.0])) == pytest.approx(0.9)
    # fewer than 3 points, or a constant side: no figure (not NaN, not +-1)
    assert measure.spearman(a[:2], a[:2][::-1]) is None
    assert measure.spearman(a[:3], a[:3]) == pytest.approx(1.0)
    assert measure.spearman(a, np.full(5, 0.25)) is None
    assert measure.spearman(np.full(5, 0.25), a) is None


def _grasps(contacts: np.ndarray, widths: np.ndarray | None = None, shift: float = 0.0) -> Any:
    n = len(contacts)
    pose = np.tile(np.eye(4), (n, 1, 1))
    pose[:, :3, 3] = contacts + shift
    g = ScoredGrasps(
        pose_W=pose, contact_W=np.asarray(contacts, dtype=np.float64),
        width_m=np.full(n, 0.05) if widths is None else widths, baseline_confidence=np.full(n, 0.5),
        sigma2_occ=np.full(n, 0.1), pugs_confidence=np.full(n, 0.4),
        grasp_id=np.arange(n, dtype=np.int64),
    )  # fmt: skip
    return SimpleNamespace(grasps=g)  # a PipelineResult as far as these helpers look


def test_same_top_grasp_compares_the_best_grasps_pose_and_width_only() -> None:
    c = np.arange(12, dtype=np.float64).reshape(4, 3) * 0.01
    a = _grasps(c)
    assert measure.same_top_grasp(a, _grasps(c)) is True
    # the rest of the ranking does not matter
    other_rest = np.concatenate([c[:1], c[1:] + 0.5])
    assert measure.same_top_grasp(a, _grasps(other_rest)) is True
    # the best grasp moved by 1 mm, or opened 1 cm wider
    assert measure.same_top_grasp(a, _grasps(np.concatenate([c[:1] + 1e-3, c[1:]]))) is False
    wider = np.array([0.06, 0.05, 0.05, 0.05])
    assert measure.same_top_grasp(a, _grasps(c, widths=wider)) is False
    # no grasps on either side: no answer
    none = _grasps(np.zeros((0, 3)))
    assert measure.same_top_grasp(a, none) is None and measure.same_top_grasp(none, a) is None


def test_topk_overlap_is_the_share_of_the_top_k_contacts_found_in_the_others_top_k() -> None:
    c = np.arange(24, dtype=np.float64).reshape(8, 3) * 0.01
    a = _grasps(c)
    assert measure.topk_overlap(a, _grasps(c)) == 1.0
    # the same top 5 in another order, the rest different: only the top 5 count
    b = np.concatenate([c[[4, 2, 0, 3, 1]], c[5:] + 1.0])
    assert measure.topk_overlap(a, _grasps(b)) == 1.0
    # two of the top 5 replaced, one of them by a contact 1 mm away (a different point)
    b = np.concatenate([c[:3], c[3:4] + 1e-3, c[7:8] + 1.0, c[5:]])
    assert measure.topk_overlap(a, _grasps(b)) == pytest.approx(3 / 5)
    # a contact ranked 6th in b is not in its top 5
    b = np.concatenate([c[:4], c[6:7], c[4:5], c[7:]])
    assert measure.topk_overlap(a, _grasps(b)) == pytest.approx(4 / 5)
    assert measure.topk_overlap(a, _grasps(b), k=6) == pytest.approx(5 / 6)
    # fewer grasps than k: over the shorter list
    assert measure.topk_overlap(_grasps(c[:2]), a) == 1.0
    assert measure.topk_overlap(a, _grasps(np.zeros((0, 3)))) is None


def test_the_rss_trace_floor_and_peak_windows(monkeypatch: pytest.MonkeyPatch) -> None:
    readings = iter([5.0, 4.0, 6.0, 1.0, 9.0])
    monkeypatch.setattr(measure, "rss_mb", lambda: next(readings))  # the current RSS, sampled
    tr = measure._RssTrace()
    for sim_s in (0.0, 10.0, 20.0, 30.0, 40.0):
        tr.add(sim_s)
    assert tr.points == [(0.0, 5.0), (10.0, 4.0), (20.0, 6.0), (30.0, 1.0), (40.0, 9.0)]
    # the lowest RSS over [sim_s - window_s, sim_s], both ends included
    assert tr.floor(20.0, 10.0) == 4.0
    assert tr.floor(20.0, 0.0) == 6.0
    assert tr.floor(30.0, 10.0) == 1.0
    assert tr.floor(40.0, 9.0) == 9.0
    assert tr.floor(5.0, 4.0) is None
    # the highest over [t0_s, t1_s], both ends included
    assert tr.peak(10.0, 30.0) == 6.0
    assert tr.peak(30.0, 30.0) == 1.0
    assert tr.peak(0.0, 10.0) == 5.0
    assert tr.peak(41.0, 50.0) is None


def test_match_points_keeps_one_pair_per_reference_point_within_the_tolerance() -> None:
    ref = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    other = np.array([
        [0.1, 0.0, 5e-5],  # ref 1, 0.05 mm off: the same point
        [0.0, 0.1, 5e-4],  # ref 2, 0.5 mm off: not
        [0.0, 0.0, 0.0],  # ref 0
        [0.0, 0.0, 1e-6],  # ref 0 again: its first match is kept
    ])  # fmt: skip
    ia, ib = measure.match_points(other, ref)
    assert sorted(zip(ia.tolist(), ib.tolist(), strict=True)) == [(0, 1), (2, 0)]
    ia, ib = measure.match_points(other, ref, tol_m=1e-3)
    assert sorted(zip(ia.tolist(), ib.tolist(), strict=True)) == [(0, 1), (1, 2), (2, 0)]
    for a, b in ((other, ref[:0]), (other[:0], ref)):
        ia, ib = measure.match_points(a, b)
        assert len(ia) == len(ib) == 0 and ia.dtype == ib.dtype == np.int64


def _scored(ids: list[int], s2: list[float], stamp: int = 7) -> ScoredGrasps:
    n = len(ids)
    return ScoredGrasps(
        pose_W=np.tile(np.eye(4), (n, 1, 1)), contact_W=np.zeros((n, 3)), width_m=np.full(n, 0.05),
        baseline_confidence=np.full(n, 0.5), sigma2_occ=np.asarray(s2, dtype=np.float64),
        pugs_confidence=np.full(n, 0.4), grasp_id=np.asarray(ids, dtype=np.int64), stamp_ns=stamp,
    )  # fmt: skip


def _cloud(s2: list[float] | None, stamp: int = 7) -> CloudMsg:
    n = 4 if s2 is None else len(s2)
    f = {k: np.zeros(n, dtype=np.float32) for k in "xyz"}
    if s2 is not None:
        f["sigma2_occ"] = np.asarray(s2, dtype=np.float32)
    return CloudMsg(stamp, "world", f)


def test_cloud_scored_grasps_edge_cases() -> None:
    cloud = _cloud([0.1, 0.2, 0.3, 0.4])
    assert measure.cloud_scored_grasps(_scored([3, 1], [0.4, 0.2]), cloud) is True
    # float64 values as the grasps carry them, float32 in the cloud: the same to float32 rounding
    assert measure.cloud_scored_grasps(_scored([0], [0.1 + 1e-12]), cloud) is True
    # 0.1 % off: another model's value
    assert measure.cloud_scored_grasps(_scored([3, 1], [0.4, 0.2 * 1.001]), cloud) is False
    # cannot tell: an id outside the cloud (either side), no sigma2_occ field, no grasps
    assert measure.cloud_scored_grasps(_scored([-1], [0.4]), cloud) is None
    assert measure.cloud_scored_grasps(_scored([4], [0.4]), cloud) is None
    assert measure.cloud_scored_grasps(_scored([0], [0.1]), _cloud(None)) is None
    assert measure.cloud_scored_grasps(_scored([], []), cloud) is None


def test_a_cloud_is_not_the_first_grasps_when_it_came_before_them() -> None:
    """Rounds without grasps are told apart by order: a cloud received before the first grasps for
    the frame is not theirs, even with no GraspArray in between."""
    g_empty = _scored([], [], stamp=100)
    cl = _cloud([0.1, 0.2, 0.3, 0.4], stamp=100)
    out = measure.last_frame_outputs([(5.0, g_empty, 20)], [(4.5, cl, 18)], t_last=4.0, stamp_last=100)
    assert out["cloud_scored_first_grasps"] is False
    assert out["last_frame_cloud"] is None and out["later_cloud"]["train_steps"] == 18
    assert out["later_cloud"]["to_cloud_s"] == pytest.approx(0.5)
    # received after them: theirs
    out = measure.last_frame_outputs([(5.0, g_empty, 20)], [(5.5, cl, 22)], t_last=4.0, stamp_last=100)
    assert out["cloud_scored_first_grasps"] is True and out["last_frame_cloud"] is cl


def test_a_cloud_for_the_last_frame_without_its_grasps_is_still_the_last_frames_cloud() -> None:
    """No GraspArray for the last frame (only older ones): the cloud cannot be compared with the
    first grasps, and is reported as the frame's cloud, not as a later round's."""
    old = _scored([0], [0.1], stamp=90)
    cl = _cloud([0.1, 0.2, 0.3, 0.4], stamp=100)
    out = measure.last_frame_outputs([(3.0, old, 10)], [(4.7, cl, 30)], t_last=4.0, stamp_last=100)
    assert out["last_frame_to_grasps_s"] is None and out["train_steps_at_grasps"] is None
    assert out["cloud_scored_first_grasps"] is None and out["later_cloud"] is None
    assert out["last_frame_cloud"] is cl and out["train_steps_at_cloud"] == 30
    assert out["last_frame_to_cloud_s"] == pytest.approx(0.7)
    # and nothing at all for the frame
    out = measure.last_frame_outputs([(3.0, old, 10)], [], t_last=4.0, stamp_last=100)
    assert all(v is None for v in out.values()), out


def _status() -> dict[str, Any]:
    """A daemon status with a different count in every place a drop is counted."""
    return {
        "counts": {"integrated": 50, "dropped": 7, "rejected": 8},
        "mailboxes": {"stereo": {"dropped": 1, "queued": 11}, "depth": {"dropped": 2, "queued": 12}},
        "ingress": {"dropped": 3, "pending": 13},
        "waiting": {"unpaired_dropped": 4, "unpaired": 5},
        "upstream": {"lost": {"left_image": 6, "right_image": 10},
                     "before_first": {"left_image": 20, "pose": 9}},
    }  # fmt: skip


def test_drop_counts_name_each_place_a_frame_can_be_lost() -> None:
    assert measure._drop_counts(_status()) == {
        "stereo_mailbox": 1, "depth_mailbox": 2, "ingress": 3, "unpaired": 4,
        "unpaired_waiting": 5, "lost_before_daemon": 16, "lost_before_first_seen": 29,
        "pose_wait_and_other": 7, "rejected": 8,
    }  # fmt: skip
    # a status from before these were counted
    st = _status()
    del st["counts"]["dropped"], st["counts"]["rejected"], st["upstream"]["before_first"]
    d = measure._drop_counts(st)
    assert (d["pose_wait_and_other"], d["rejected"], d["lost_before_first_seen"]) == (0, 0, 0)


def test_drain_queued_counts_both_mailboxes_and_the_ingress_queue() -> None:
    assert measure.drain_queued(_status()) == 11 + 12 + 13


def test_restamp_gives_a_copy_with_the_new_stamp() -> None:
    cam = PinholeCamera(100.0, 100.0, 15.5, 11.5, 32, 24)
    img = np.zeros((24, 32), dtype=np.uint8)
    f = StereoFrame(stamp_ns=5, left=img, right=img, rig=StereoRig(cam, 0.1), T_W_C=np.eye(4))
    g = measure.restamp(f, 1_000_000_123)
    assert g.stamp_ns == 1_000_000_123 and f.stamp_ns == 5
    assert g.left is f.left and g.right is f.right and g.rig is f.rig  # the rest is the frame's
    np.testing.assert_array_equal(g.T_W_C, f.T_W_C)


class _IdlePipe:
    """Records each ``train_steps`` call's rate scale and when sigma2_occ was asked for."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, float]] = []
        self.asked_after: list[int] = []

    def train_steps(self, steps: int, rate_scale: float = 1.0) -> None:
        self.calls.append((steps, rate_scale))

    def sigma2_occ(self, cloud: np.ndarray) -> tuple[None, np.ndarray]:
        self.asked_after.append(len(self.calls))
        return None, np.full(len(cloud), float(len(self.calls)))


@pytest.mark.parametrize("decay", [0, 2])
def test_idle_refinement_trains_at_the_daemons_idle_rates(decay: int) -> None:
    """The bench's 'after +N idle steps' figures follow the daemon's idle schedule: the i-th extra
    step at rate scale 1 / (1 + i / daemon.idle_rate_decay_steps), counted across checkpoints."""
    pipe = _IdlePipe()
    run = SimpleNamespace(pipe=pipe, result=SimpleNamespace(cloud_W=np.zeros((4, 3))))
    out = measure.idle_refinement(run, (5, 3), decay)  # type: ignore[arg-type]
    expected = [1.0 / (1.0 + i / decay) if decay else 1.0 for i in range(5)]
    assert [n for n, _ in pipe.calls] == [1] * 5
    assert [s for _, s in pipe.calls] == pytest.approx(expected, abs=1e-12)
    assert pipe.asked_after == [3, 5]  # checkpoints sorted, cumulative
    assert [k for k, _, _ in out] == [3, 5] and out[1][2][0] == 5.0


def test_median_latency_counts_a_missing_run_as_the_slowest() -> None:
    assert measure.median_latency([0.5, 0.3, 0.4]) == 0.4
    assert measure.median_latency([0.3, 0.5]) == 0.4
    assert measure.median_latency([None, 0.3, 0.6]) == 0.6  # the missing run is above the median
    assert measure.median_latency([None, None, 0.3]) is None  # the median run got nothing
    assert measure.median_latency([None]) is None and measure.median_latency([]) is None


def test_the_daemon_latency_is_the_median_of_fresh_daemons(monkeypatch: pytest.MonkeyPatch) -> None:
    from pugsd.bench.options import BenchOptions

    lat = iter([0.7, 0.3, None, 0.4, 0.45])
    calls: list[float] = []

    def feed(*a: Any, grasps_timeout_s: float = 0.0, **k: Any) -> dict[str, Any]:
        calls.append(grasps_timeout_s)
        return {"status": {"counts": {}}, "sent": 30, "last_frame_to_grasps_s": next(lat)}

    monkeypatch.setattr(measure, "daemon_feed", feed)
    monkeypatch.setattr(measure, "_drop_counts", lambda st: {})
    lines: list[str] = []
    out = measure.daemon_last_frame(None, [], BenchOptions(daemon_repeats=5), lines.append, None)  # type: ignore[arg-type]
    assert out["last_frame_to_grasps_runs_s"] == [0.7, 0.3, None, 0.4, 0.45]
    assert out["last_frame_to_grasps_s"] == 0.45  # the median, the missing run the slowest
    assert calls == [60.0] * 5 and "median of 5 fresh daemons: 0.70, 0.30, -, 0.40, 0.45 s" in lines[-1]


class _FirstFrame(Exception):
    pass


@pytest.mark.parametrize("run", ["streaming", "paper"])
def test_the_synchronous_runs_warm_the_pipeline_up_before_the_first_frame(
    run: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As the daemon does before it serves: first-call costs (torch's optimizer, the proposer's
    compiled search) are not timed as the last frame's latency."""
    from pugsd.bench.options import BenchOptions

    seen: list[str] = []

    class Pipe:
        def __init__(self, core: Any, seed: int = 0) -> None:
            pass

        def warm_up(self) -> None:
            seen.append("warm_up")

        def depth_from_stereo(self, frame: Any) -> None:
            seen.append("frame")
            raise _FirstFrame

        add_stereo = depth_from_stereo

    monkeypatch.setattr(measure, "PugsPipeline", Pipe)
    with pytest.raises(_FirstFrame):
        if run == "streaming":
            measure.run_streaming(None, [None, None], BenchOptions(), 4, 8)  # type: ignore[arg-type]
        else:
            measure.run_paper(None, [None, None], np.zeros((1, 3)), BenchOptions())  # type: ignore[arg-type]
    assert seen == ["warm_up", "frame"]
