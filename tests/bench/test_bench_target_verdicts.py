# SPDX-License-Identifier: Apache-2.0
"""The judge of the benchmark's targets (``pugsd.bench.targets``) on hand-made results: each target's
threshold on both sides of its edge, which figure of the result is the one judged, the rows that
get no verdict (n/a) and say why, the Spearman rows reported for information only, ``--quick``
rows marked as not comparable, half runs, and the printed table's result column. Nothing is run
or rendered."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest

from pugsd.bench.targets import evaluate_targets, format_table

STREAM = "streaming last frame -> grasps (partial)"
DAEMON = "daemon last frame -> its grasps (partial)"
DAEMON_RHO = "Spearman daemon's sigma2_occ vs paper (partial)"
RATIO = "paper / streaming time (partial)"
RHO = "Spearman streaming sigma2_occ vs paper (partial)"
SUSTAINED = "sustained input without drops (daemon)"
INGEST = "median ingest (depth + back-projection + FOF)"
RSS = "RSS growth, minute 5 -> 30 of replay"
RSS_UNMEASURED = "RSS growth over the long replay"
CUDA_STEPS = "CUDA SVGP steps/s vs CPU"
CUDA_ALG1 = "CUDA Algorithm 1, 20k query points"
WALL = "whole benchmark wall time"
DAEMON_ALONE = "daemon last frame -> its grasps (complete)"
QUICK_NOTE = "quick run: reduced frames/epochs, not comparable"
INFO_ROWS = (RHO, DAEMON_RHO)  # reported, never judged


def _trajectory(**extra: Any) -> dict[str, Any]:
    """One trajectory's paper-vs-streaming figures, every judged one passing its target."""
    c: dict[str, Any] = {
        "streaming_last_frame_to_grasps_s": 0.5, "paper_last_frame_to_grasps_s": 40.0,
        "ratio_paper_over_streaming": 80.0, "spearman_sigma2_occ": 0.95,
        "daemon": {"last_frame_to_grasps_s": 0.45, "train_steps_at_grasps": 40,
                   "agreement_with_paper": {"cloud_received": True, "spearman_sigma2_occ": 0.93,
                                            "last_frame_to_cloud_s": 0.9, "shared_fraction": 1.0}},
        "top_grasp_same": True, "top5_overlap": 1.0, "query_points": 100,
        "streaming_ready": True, "streaming_idle_steps_after_last_frame": 0,
    }  # fmt: skip
    c.update(extra)
    return c


def _result(**extra: Any) -> dict[str, Any]:
    """A whole (not --quick) run on a CUDA machine in which every judged target passes."""
    r: dict[str, Any] = {
        "quick": False, "wall_s": 600.0, "render_s": 5.0,
        "machine": {"cuda_available": True, "cpu_model": "x", "logical_cores": 2, "torch": "t",
                    "torch_threads": 1, "device": "cpu", "load_average_at_start": [0.0]},
        "settings": {"object": "mug", "n_frames": 30, "resolution": [640, 480], "rate_hz": 10.0,
                     "downsample": 4, "num_inducing": 250, "batch_size": 1024,
                     "train_steps_per_frame": 4, "paper_epochs": 100,
                     "sections": {"pipeline": True, "daemon": True}},
        "stages": {"ingest": {"n": 30, "median_ms": 20.0, "p95_ms": 30.0, "max_ms": 35.0}},
        "paper_vs_streaming": {"partial": _trajectory()},
        "throughput": {"source": "daemon", "sustained_hz": 20.0, "trials": [
            {"rate_hz": 20.0, "offered": 200, "integrated": 200, "drops": {"ingress": 0},
             "held": True, "latency": {}}]},
        "replay": {"source": "daemon", "rss_growth_frac": 0.02, "window_min": [5.0, 30.0],
                   "simulated_min": 30.0, "target_simulated_min": 30.0, "feed_wall_s": 200.0,
                   "speedup_vs_real_time": 9.0, "integrated": 9000, "rss_window_start_mb": 1000.0,
                   "rss_window_end_mb": 1020.0},
        "memory": {"peak_rss_mb": 1500.0},
        "cuda": {"speedup_steps_per_s": 8.0, "num_inducing_cuda": 500,
                 "svgp_steps_per_s_cuda": 80.0, "svgp_steps_per_s_cpu": 10.0,
                 "algorithm1_20k_cuda": {"median_ms": 40.0}},
        "errors": {},
    }  # fmt: skip
    r.update(extra)
    return r


def _rows(r: dict[str, Any]) -> dict[str, dict[str, Any]]:
    rows = evaluate_targets(r)
    names = [t["target"] for t in rows]
    assert len(names) == len(set(names)), names
    return {t["target"]: t for t in rows}


def test_the_all_passing_result_passes_every_judged_target() -> None:
    rows = _rows(_result())
    assert set(rows) == {STREAM, DAEMON, DAEMON_RHO, RATIO, RHO, SUSTAINED, INGEST, RSS,
                         CUDA_STEPS, CUDA_ALG1, WALL}  # fmt: skip
    assert {k: t["pass"] for k, t in rows.items() if t["pass"] is not True} == {
        RHO: None, DAEMON_RHO: None}  # fmt: skip


_AGREEMENT = ("paper_vs_streaming", "partial", "daemon", "agreement_with_paper")
# each case: (row, where the judged figure sits in the result, its value, the expected verdict)
_EDGES = [
    # "<= 0.5 s": 0.5 itself passes
    (STREAM, ("paper_vs_streaming", "partial", "streaming_last_frame_to_grasps_s"), 0.5, True),
    (STREAM, ("paper_vs_streaming", "partial", "streaming_last_frame_to_grasps_s"), 0.5001, False),
    (DAEMON, ("paper_vs_streaming", "partial", "daemon", "last_frame_to_grasps_s"), 0.5, True),
    (DAEMON, ("paper_vs_streaming", "partial", "daemon", "last_frame_to_grasps_s"), 0.5001, False),
    # ">= 50x"
    (RATIO, ("paper_vs_streaming", "partial", "ratio_paper_over_streaming"), 50.0, True),
    (RATIO, ("paper_vs_streaming", "partial", "ratio_paper_over_streaming"), 49.99, False),
    # --no-pipeline: the daemon's own row, the same target
    (DAEMON_ALONE, ("daemon_alone", "complete", "last_frame_to_grasps_s"), 0.5, True),
    (DAEMON_ALONE, ("daemon_alone", "complete", "last_frame_to_grasps_s"), 0.5001, False),
    # "<= 50 ms"
    (INGEST, ("stages", "ingest", "median_ms"), 50.0, True),
    (INGEST, ("stages", "ingest", "median_ms"), 50.01, False),
    # "< 10%": 10 % itself fails
    (RSS, ("replay", "rss_growth_frac"), 0.0999, True),
    (RSS, ("replay", "rss_growth_frac"), 0.10, False),
    # ">= 5x"
    (CUDA_STEPS, ("cuda", "speedup_steps_per_s"), 5.0, True),
    (CUDA_STEPS, ("cuda", "speedup_steps_per_s"), 4.99, False),
    # "< 100 ms": 100 ms itself fails
    (CUDA_ALG1, ("cuda", "algorithm1_20k_cuda", "median_ms"), 99.9, True),
    (CUDA_ALG1, ("cuda", "algorithm1_20k_cuda", "median_ms"), 100.0, False),
    # "< 15 min": 900 s itself fails
    (WALL, ("wall_s",), 899.9, True),
    (WALL, ("wall_s",), 900.0, False),
]


@pytest.mark.parametrize(("name", "path", "value", "verdict"), _EDGES)
def test_each_target_at_the_edge_of_its_threshold(
    name: str, path: tuple[str, ...], value: float, verdict: bool
) -> None:
    r = _result(daemon_alone={"complete": {"last_frame_to_grasps_s": 0.25}})
    d: Any = r
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value
    rows = _rows(r)
    assert rows[name]["pass"] is verdict, rows[name]
    # the one figure moved only that row
    judged = {k: t for k, t in rows.items() if k not in INFO_ROWS}
    assert [k for k, t in judged.items() if t["pass"] is not True] == ([] if verdict else [name])


_NOTE = "paper vs paper, other seed: 0.840"


@pytest.mark.parametrize("rho", [-1.0, 0.0, 0.5, 0.8999, 0.9, 0.95, 1.0, float("nan"), None])
@pytest.mark.parametrize("quick", [False, True])
def test_the_spearman_rows_are_information_only_whatever_the_figure(
    rho: float | None, quick: bool
) -> None:
    """The agreement of sigma2_occ with one 100-epoch paper fit gets no verdict at any figure
    (``pugsd evaluate --mode streaming,paper`` judges the grasps); the figure and the row's note
    are reported as they are, and no other row moves."""
    r = _result(quick=quick)
    c = r["paper_vs_streaming"]["partial"]
    c.update(spearman_sigma2_occ=rho, spearman_paper_vs_paper_other_seed=0.84)
    c["daemon"]["agreement_with_paper"]["spearman_sigma2_occ"] = rho
    if rho is None:  # no daemon figure: the daemon row says why
        c["daemon"]["agreement_with_paper"]["cloud_received"] = False
    rows = _rows(r)
    nan = "Spearman undefined (NaN): non-finite or constant sigma2_occ"
    base = QUICK_NOTE if quick else ""
    daemon_base = base or ("no cloud for the last frame" if rho is None else "")
    want_note = {RHO: QUICK_NOTE if quick else _NOTE, DAEMON_RHO: daemon_base}
    for name in INFO_ROWS:
        row = rows[name]
        assert row["pass"] is None and row["required"] == "info", row
        if rho is not None and math.isnan(rho):
            assert math.isnan(row["measured"])
            assert row["note"] == "; ".join(n for n in (nan, want_note[name]) if n), row
        else:
            assert row["measured"] == rho and row["note"] == want_note[name], row
    assert all(t["pass"] is True for k, t in rows.items() if k not in INFO_ROWS)


def test_each_row_reports_the_figure_it_judges() -> None:
    r = _result()
    r["paper_vs_streaming"]["partial"].update(
        streaming_last_frame_to_grasps_s=0.25, paper_last_frame_to_grasps_s=99.0,
        ratio_paper_over_streaming=396.0, spearman_sigma2_occ=0.91,
    )  # fmt: skip
    r["paper_vs_streaming"]["partial"]["daemon"]["last_frame_to_grasps_s"] = 0.75
    r["paper_vs_streaming"]["partial"]["daemon"]["agreement_with_paper"]["spearman_sigma2_occ"] = 0.92
    r["replay"]["rss_growth_frac"] = 0.0234
    rows = _rows(r)
    measured = {k: t["measured"] for k, t in rows.items()}
    assert measured == {
        STREAM: 0.25, DAEMON: 0.75, DAEMON_RHO: 0.92, RATIO: 396.0, RHO: 0.91,
        SUSTAINED: "20 Hz", INGEST: 20.0, RSS: "2.3%", CUDA_STEPS: 8.0, CUDA_ALG1: 40.0,
        WALL: "10.0 min",
    }  # fmt: skip
    required = {k: t["required"] for k, t in rows.items()}
    assert required == {
        STREAM: "<= 0.5 s", DAEMON: "<= 0.5 s", DAEMON_RHO: "info", RATIO: ">= 50x",
        RHO: "info", SUSTAINED: ">= 10 Hz", INGEST: "<= 50 ms", RSS: "< 10%",
        CUDA_STEPS: ">= 5x", CUDA_ALG1: "< 100 ms", WALL: "< 15 min",
    }  # fmt: skip
    # the paper's own time is not a target: a slow paper fit fails nothing but the ratio
    r["paper_vs_streaming"]["partial"]["paper_last_frame_to_grasps_s"] = 5.0
    assert _rows(r)[RATIO]["pass"] is True


def test_the_window_of_the_rss_row_is_named_from_the_result() -> None:
    r = _result()
    r["replay"].update(window_min=[0.25, 1.0], simulated_min=1.0, target_simulated_min=1.0)
    assert "RSS growth, minute 0.25 -> 1 of replay" in _rows(r)


def test_the_sustained_rate_counts_trials_at_10_hz_or_more_only() -> None:
    def trials(*held: tuple[float, bool]) -> dict[str, Any]:
        ts = [{"rate_hz": hz, "offered": 10, "integrated": 10, "drops": {}, "held": h}
              for hz, h in held]  # fmt: skip
        sus = next((hz for hz, h in held if h), None)
        return {"source": "daemon", "sustained_hz": sus, "trials": ts}

    row = _rows(_result(throughput=trials((10.0, True))))[SUSTAINED]
    assert (row["pass"], row["measured"]) == (True, "10 Hz")  # exactly 10 Hz counts
    row = _rows(_result(throughput=trials((15.0, False), (10.0, False), (5.0, True))))[SUSTAINED]
    assert (row["pass"], row["measured"]) == (False, "5 Hz")
    # a ladder that held nothing: the lowest rate tried is named
    row = _rows(_result(throughput=trials((20.0, False), (10.0, False), (2.5, False))))[SUSTAINED]
    assert (row["pass"], row["measured"]) == (False, "< 2.5 Hz (none held)")
    # a ladder that never offered 10 Hz cannot tell: no verdict (not a FAIL)
    row = _rows(_result(throughput=trials((5.0, True), (2.5, True))))[SUSTAINED]
    assert row["pass"] is None and row["measured"] == "5 Hz"


def test_rows_that_could_not_be_measured_get_no_verdict_and_say_why() -> None:
    r = _result()
    # the daemon published no grasps for the last frame (in either kind of run)
    r["paper_vs_streaming"]["partial"]["daemon"]["last_frame_to_grasps_s"] = None
    r["daemon_alone"] = {"complete": {"last_frame_to_grasps_s": None}}
    # streaming agreement not computable
    r["paper_vs_streaming"]["partial"]["spearman_sigma2_occ"] = None
    del r["throughput"], r["stages"], r["cuda"]
    r["replay"]["rss_growth_frac"] = None
    r["wall_s"] = None
    r["errors"] = {"throughput": "RuntimeError: no daemon"}
    rows = _rows(r)
    for name in (DAEMON, "daemon last frame -> its grasps (complete)"):
        assert rows[name]["pass"] is None and rows[name]["note"] == "grasps not received", name
    assert rows[RHO]["pass"] is None
    assert rows[SUSTAINED]["pass"] is None and rows[SUSTAINED]["note"] == "RuntimeError: no daemon"
    assert rows[INGEST]["pass"] is None and rows[INGEST]["note"] == "not measured"
    assert RSS not in rows
    assert rows[RSS_UNMEASURED]["pass"] is None and rows[RSS_UNMEASURED]["note"] == "not measured"
    for name in (CUDA_STEPS, CUDA_ALG1):  # a CUDA machine on which the section did not run
        assert rows[name]["pass"] is None and rows[name]["note"] == "not run", name
    assert rows[WALL]["pass"] is None and rows[WALL]["measured"] is None
    # the other way round: the replay's error is named, throughput is "not measured"
    r["errors"] = {"replay": "TimeoutError: replay"}
    del r["replay"]
    rows = _rows(r)
    assert rows[RSS_UNMEASURED]["note"] == "TimeoutError: replay"
    assert rows[SUSTAINED]["note"] == "not measured"
    # no GPU at all
    r["machine"]["cuda_available"] = False
    rows = _rows(r)
    assert rows[CUDA_STEPS]["note"] == rows[CUDA_ALG1]["note"] == "no GPU on this machine"
    # a daemon record without the figure at all (an older result): no daemon row
    del r["paper_vs_streaming"]["partial"]["daemon"]["last_frame_to_grasps_s"]
    assert DAEMON not in _rows(r)


def test_a_replay_that_stopped_short_fails_whatever_its_growth() -> None:
    r = _result()
    r["replay"].update(simulated_min=12.5, rss_growth_frac=0.01)
    row = _rows(r)[RSS]
    assert row["pass"] is False and row["note"] == "replay stopped at 12.5 simulated min"
    r["replay"]["simulated_min"] = 29.9  # a few seconds short is short
    assert _rows(r)[RSS]["pass"] is False
    r["replay"]["simulated_min"] = 30.0 - 1e-12  # rounding, not a short replay
    row = _rows(r)[RSS]
    assert row["pass"] is True and row["note"] == ""


def test_an_undefined_daemon_spearman_keeps_the_reason_it_was_given() -> None:
    """A NaN is reported as such, and a note the row already had is kept after it."""
    r = _result(quick=True)
    r["paper_vs_streaming"]["partial"]["daemon"]["agreement_with_paper"]["spearman_sigma2_occ"] = float("nan")
    row = _rows(r)[DAEMON_RHO]
    assert row["pass"] is None
    assert row["note"] == "Spearman undefined (NaN): non-finite or constant sigma2_occ; " + QUICK_NOTE


def test_the_streaming_rows_note_tells_what_the_agreement_could_reach() -> None:
    """The streaming Spearman's note: the paper's own seed-to-seed floor, the last idle-training
    figure that was computed, the seed-to-seed figure at the optimal q(u), and the streaming run
    at the paper's M; in that order."""
    c = _trajectory(
        spearman_sigma2_occ=0.7, spearman_paper_vs_paper_other_seed=0.84,
        spearman_after_idle_steps=[{"steps": 100, "train_s": 12.2, "spearman": 0.75},
                                   {"steps": 400, "train_s": 48.7, "spearman": 0.8},
                                   {"steps": 800, "train_s": 97.0, "spearman": None}],
        converged_reference={"spearman_paper_optimal_q_vs_other_seed_optimal_q": 0.881},
        streaming_at_paper_num_inducing={"num_inducing": 500, "spearman_sigma2_occ": 0.85,
                                         "last_frame_to_grasps_s": 1.25},
    )  # fmt: skip
    row = _rows(_result(paper_vs_streaming={"partial": c}))[RHO]
    assert row["pass"] is None
    assert row["note"] == (
        "paper vs paper, other seed: 0.840; after +400 idle steps (49 s): 0.800; paper fits at "
        "optimal q(u), seed vs seed: 0.881; streaming with the paper's M = 500: 0.850 "
        "(synchronous, 1.25 s)"
    )
    # the parts that were not computed are left out
    c["converged_reference"] = {"spearman_paper_optimal_q_vs_other_seed_optimal_q": None}
    c["streaming_at_paper_num_inducing"]["spearman_sigma2_occ"] = None
    c["spearman_after_idle_steps"] = [{"steps": 100, "train_s": 1.0, "spearman": None}]
    row = _rows(_result(paper_vs_streaming={"partial": c}))[RHO]
    assert row["note"] == "paper vs paper, other seed: 0.840"


def test_a_quick_run_marks_every_judged_row_and_has_no_wall_time_target() -> None:
    """--quick: fewer frames and epochs, so every verdict carries the not-comparable note (the
    per-trajectory rows and the daemon-alone rows too), and the whole-run wall time (15 min) is not
    a target at all."""
    r = _result(quick=True, daemon_alone={"complete": {"last_frame_to_grasps_s": 0.4}})
    r["paper_vs_streaming"]["partial"]["daemon"]["agreement_with_paper"] = {
        "cloud_received": False, "spearman_sigma2_occ": None}  # fmt: skip
    r["paper_vs_streaming"]["partial"].update(spearman_paper_vs_paper_other_seed=0.8)
    rows = _rows(r)
    assert WALL not in rows
    judged = [k for k, t in rows.items() if t["pass"] is not None]
    assert set(judged) == {STREAM, DAEMON, RATIO, SUSTAINED, INGEST, RSS, CUDA_STEPS,
                           CUDA_ALG1, "daemon last frame -> its grasps (complete)"}  # fmt: skip
    for k in judged:
        assert QUICK_NOTE in rows[k]["note"], k
    # the rows' own notes give way to the quick note where they would explain a full run's figure
    assert rows[RHO]["pass"] is None and rows[RHO]["note"] == QUICK_NOTE
    assert rows[DAEMON_RHO]["pass"] is None and rows[DAEMON_RHO]["note"] == QUICK_NOTE
    table = format_table({**r, "targets": evaluate_targets(r)})
    assert table[0].startswith("pugsd bench (QUICK: not comparable with targets) -- x, 2 cores")
    full = _result()
    assert format_table({**full, "targets": evaluate_targets(full)})[0].startswith("pugsd bench -- x")


def test_half_runs_are_told_from_their_errors_too() -> None:
    """A result without ``settings.sections`` (written before it was recorded): sections that ran
    and failed (an error under their name) were not skipped, so the wall time is judged."""
    r = _result()
    del r["settings"]["sections"], r["throughput"], r["replay"]
    r["errors"] = {"throughput": "RuntimeError: x", "replay": "RuntimeError: y"}
    assert _rows(r)[WALL]["pass"] is True
    r["errors"] = {}
    row = _rows(r)[WALL]
    assert row["pass"] is None and row["note"] == "not the whole benchmark: the daemon sections skipped"
    # a pipeline half with only the paper-vs-streaming figures (no stage table) still ran the pipeline
    r = _result()
    del r["settings"]["sections"], r["stages"]
    assert _rows(r)[WALL]["pass"] is True
    # both halves skipped
    r = _result()
    r["settings"]["sections"] = {"pipeline": False, "daemon": False}
    assert _rows(r)[WALL]["note"] == (
        "not the whole benchmark: the pipeline sections and the daemon sections skipped"
    )
    # a section the record does not mention ran
    r["settings"]["sections"] = {"pipeline": True}
    assert _rows(r)[WALL]["pass"] is True


def _target_lines(r: dict[str, Any]) -> dict[str, str]:
    r = copy.deepcopy(r)
    r["targets"] = evaluate_targets(r)
    table = format_table(r)
    head = table.index(next(x for x in table if x.startswith("target ")))
    out = {}
    for line in table[head + 1 : -1]:
        name = next(t["target"] for t in r["targets"] if line.startswith(t["target"]))
        out[name] = line
    assert len(out) == len(r["targets"])
    assert table[-1] == f"wall time {r['wall_s']} s (rendering {r['render_s']} s)"
    return out


def test_the_cuda_note_names_m_only_where_the_result_records_it() -> None:
    r = _result()
    assert _rows(r)[CUDA_STEPS]["note"] == "at M = 500, the daemon's on CUDA"
    del r["cuda"]["num_inducing_cuda"]  # a result from before both M were timed
    assert _rows(r)[CUDA_STEPS]["note"] == ""
    r["quick"] = True
    assert _rows(r)[CUDA_STEPS]["note"] == QUICK_NOTE


def test_the_table_shows_each_verdict_as_pass_fail_or_n_a() -> None:
    r = _result()
    r["paper_vs_streaming"]["partial"]["ratio_paper_over_streaming"] = 12.5
    del r["cuda"]
    r["machine"]["cuda_available"] = False
    r["errors"] = {"cuda": "RuntimeError: no device"}
    lines = _target_lines(r)
    result_col = {k: v[52 + 1 + 9 + 1 + 20 + 1 :][:6].strip() for k, v in lines.items()}
    assert result_col[STREAM] == "PASS" and result_col[RATIO] == "FAIL"
    assert result_col[CUDA_STEPS] == result_col[CUDA_ALG1] == "n/a"
    # the Spearman rows: "info" in the required column, no verdict
    for name in INFO_ROWS:
        assert lines[name][52:].split()[0] == "info" and result_col[name] == "n/a", lines[name]
    # the measured figure: floats to 3 decimals, strings as they are, a missing one as "-"
    assert lines[STREAM].split()[-2:] == ["0.500", "PASS"]
    assert lines[RATIO].split()[-2:] == ["12.500", "FAIL"]
    assert lines[RSS].split()[-2:] == ["2.0%", "PASS"]
    assert lines[CUDA_STEPS].endswith("-    n/a  (no GPU on this machine)")
    assert lines[STREAM].endswith("PASS")  # no note, no parentheses after the verdict
    table = format_table({**r, "targets": evaluate_targets(r)})
    assert "ERROR in cuda: RuntimeError: no device" in table


def test_the_table_lists_each_throughput_trial() -> None:
    r = _result()
    r["throughput"] = {"source": "daemon", "sustained_hz": 10.0, "trials": [
        {"rate_hz": 20.0, "offered": 200, "integrated": 150, "drops": {"a": 30, "b": 20},
         "held": False, "latency": {"newest_frame_to_grasps": {"p50_ms": 512.34},
                                    "frame_age_at_integrate": {"p50_ms": 72.0}}},
        {"rate_hz": 10.0, "offered": 100, "integrated": 100, "drops": {"a": 0}, "held": True,
         "latency": {}}]}  # fmt: skip
    table = format_table({**r, "targets": evaluate_targets(r)})
    assert "sustained throughput (daemon): highest rate held 10 Hz" in table
    assert ("     20 Hz: offered  200, integrated  150, dropped   50 (NOT held); frame age at "
            "integrate p50 72.0 ms; newest frame -> grasps p50 512.3 ms") in table  # fmt: skip
    assert ("     10 Hz: offered  100, integrated  100, dropped    0 (held); frame age at "
            "integrate p50 - ms; newest frame -> grasps p50 - ms") in table  # fmt: skip
    r["throughput"]["sustained_hz"] = None
    table = format_table({**r, "targets": evaluate_targets(r)})
    assert "sustained throughput (daemon): highest rate held none of the rates tried" in table


def test_the_table_says_yes_or_no_for_the_top_grasp() -> None:
    r = _result()
    r["paper_vs_streaming"]["partial"]["top_grasp_same"] = False
    line = next(x for x in format_table({**r, "targets": []}) if x.startswith("partial "))
    assert line.split()[:8] == ["partial", "0.50", "40.0", "80.0", "0.950", "no", "1.0", "100"]
    r["paper_vs_streaming"]["partial"]["top_grasp_same"] = True
    line = next(x for x in format_table({**r, "targets": []}) if x.startswith("partial "))
    assert line.split()[5:9] == ["yes", "1.0", "100", "yes"]
