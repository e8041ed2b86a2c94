# SPDX-License-Identifier: Apache-2.0
"""The benchmark's targets (2-core CPU, no GPU; ratios from one run) judged on a result dict,
and the printed table.

The Spearman rows (streaming's and the daemon's sigma2_occ against the paper fit) are information
only, with no verdict: their agreement with one 100-epoch batch fit measures that fit's optimiser
state. Whether streaming picks grasps as well as the paper fit is measured by
``pugsd evaluate --mode streaming,paper`` (paired McNemar per cell)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

Writer = Callable[[str], None]


def _row(name: str, required: str, measured: Any, ok: bool | None, note: str = "") -> dict[str, Any]:
    return {"target": name, "required": required, "measured": measured, "pass": ok, "note": note}


LATENCY_S = 0.5  # last frame -> grasps, streaming and the daemon
INFO = "info"  # the required column of a row reported without a verdict


def _rho_note(rho: Any, note: str) -> str:
    """A Spearman row's note: a NaN (undefined correlation, e.g. a non-finite sigma2_occ) says
    so."""
    if isinstance(rho, float) and math.isnan(rho):
        nan_note = "Spearman undefined (NaN): non-finite or constant sigma2_occ"
        return "; ".join(n for n in (nan_note, note) if n)
    return note


def _later_cloud(later: dict[str, Any]) -> str:
    rho = later.get("spearman_sigma2_occ")
    return (
        f"the next cloud for that frame ({later.get('train_steps_at_cloud')} SVGP steps, "
        f"{_fmt(later.get('last_frame_to_cloud_s'), 2)} s): spearman {_fmt(rho, 3)}"
    )


def _daemon_cloud_note(ag: dict[str, Any]) -> str:
    """Why the daemon's agreement row has no figure."""
    if not ag["cloud_received"] and ag.get("later_cloud"):
        return "the first grasps for the last frame came without a cloud; " + _later_cloud(
            ag["later_cloud"]
        )
    if not ag["cloud_received"]:
        return "no cloud for the last frame"
    return f"query clouds share {ag.get('shared_fraction', 0):.0%} of points"


def _skipped_sections(r: dict[str, Any]) -> list[str]:
    """The halves of the benchmark a run skipped (``settings.sections``; for results written
    before it was recorded, inferred from what the result holds)."""
    sec = (r.get("settings") or {}).get("sections")
    if sec is None:
        err = r.get("errors") or {}
        sec = {
            "pipeline": bool(r.get("stages") or r.get("paper_vs_streaming")),
            "daemon": any(k in r for k in ("throughput", "replay", "daemon_alone"))
            or any(k.startswith(("throughput", "replay", "daemon")) for k in err),
        }
    return [f"the {k} sections" for k in ("pipeline", "daemon") if not sec.get(k, True)]


def _daemon_note(dm: dict[str, Any], quick_note: str) -> str:
    """The daemon latency row's note: each fresh daemon's latency when there were several."""
    runs = dm.get("last_frame_to_grasps_runs_s") or []
    each = ", ".join("none" if x is None else f"{x:.2f}" for x in runs)
    note = f"median of {len(runs)} fresh daemons: {each} s" if len(runs) > 1 else ""
    if dm.get("last_frame_to_grasps_s") is None:
        note = "grasps not received" + (f" ({note})" if note else "")
    return quick_note or note


def evaluate_targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per target: pass True/False, or None where it could not be measured here or the
    row is information only (required "info")."""
    rows: list[dict[str, Any]] = []
    quick_note = "quick run: reduced frames/epochs, not comparable" if r.get("quick") else ""
    for traj, c in (r.get("paper_vs_streaming") or {}).items():
        s = c["streaming_last_frame_to_grasps_s"]
        rows.append(_row(f"streaming last frame -> grasps ({traj})", f"<= {LATENCY_S} s", s,
                         s <= LATENCY_S, quick_note))  # fmt: skip
        dl = (c.get("daemon") or {}).get("last_frame_to_grasps_s", "absent")
        if dl != "absent":
            rows.append(_row(f"daemon last frame -> its grasps ({traj})", f"<= {LATENCY_S} s", dl,
                             None if dl is None else dl <= LATENCY_S,
                             _daemon_note(c["daemon"], quick_note)))  # fmt: skip
        ag = (c.get("daemon") or {}).get("agreement_with_paper")
        if ag is not None:
            drho = ag["spearman_sigma2_occ"]
            dnote = quick_note
            if drho is None:
                dnote = dnote or _daemon_cloud_note(ag)
            rows.append(_row(f"Spearman daemon's sigma2_occ vs paper ({traj})", INFO, drho,
                             None, _rho_note(drho, dnote)))  # fmt: skip
        ratio = c["ratio_paper_over_streaming"]
        rows.append(_row(f"paper / streaming time ({traj})", ">= 50x", ratio, ratio >= 50.0,
                         quick_note))  # fmt: skip
        rho = c["spearman_sigma2_occ"]
        floor = c.get("spearman_paper_vs_paper_other_seed")
        fnote = "" if floor is None else f"paper vs paper, other seed: {floor:.3f}"
        refined = [x for x in c.get("spearman_after_idle_steps") or [] if x["spearman"] is not None]
        if refined:
            x = refined[-1]
            fnote += f"; after +{x['steps']} idle steps ({x['train_s']:.0f} s): {x['spearman']:.3f}"
        cv = c.get("converged_reference") or {}
        if cv.get("spearman_paper_optimal_q_vs_other_seed_optimal_q") is not None:
            fnote += (
                "; paper fits at optimal q(u), seed vs seed: "
                f"{cv['spearman_paper_optimal_q_vs_other_seed_optimal_q']:.3f}"
            )
        pm = c.get("streaming_at_paper_num_inducing") or {}
        if pm.get("spearman_sigma2_occ") is not None:
            fnote += (
                f"; streaming with the paper's M = {pm['num_inducing']}: "
                f"{pm['spearman_sigma2_occ']:.3f} (synchronous, "
                f"{pm['last_frame_to_grasps_s']:.2f} s)"
            )
        rows.append(_row(f"Spearman streaming sigma2_occ vs paper ({traj})", INFO, rho, None,
                         _rho_note(rho, quick_note or fnote)))  # fmt: skip
    for traj, dm in (r.get("daemon_alone") or {}).items():  # --no-pipeline
        dl = dm.get("last_frame_to_grasps_s")
        rows.append(_row(f"daemon last frame -> its grasps ({traj})", f"<= {LATENCY_S} s", dl,
                         None if dl is None else dl <= LATENCY_S, _daemon_note(dm, quick_note)))  # fmt: skip
    tp = r.get("throughput")
    if tp is not None:
        at10 = [t for t in tp["trials"] if t["rate_hz"] >= 10.0]
        held10 = any(t["held"] for t in at10) if at10 else None
        sus = tp.get("sustained_hz")
        lowest = min((t["rate_hz"] for t in tp["trials"]), default=None)
        meas = f"{sus:g} Hz" if sus is not None else f"< {lowest:g} Hz (none held)"
        rows.append(_row("sustained input without drops (daemon)", ">= 10 Hz", meas, held10,
                         quick_note))  # fmt: skip
    else:
        rows.append(_row("sustained input without drops (daemon)", ">= 10 Hz", None, None,
                         (r.get("errors") or {}).get("throughput", "not measured")))  # fmt: skip
    ing = (r.get("stages") or {}).get("ingest", {}).get("median_ms")
    rows.append(_row("median ingest (depth + back-projection + FOF)", "<= 50 ms", ing,
                     None if ing is None else ing <= 50.0,
                     quick_note if ing is not None else "not measured"))  # fmt: skip
    rp = r.get("replay")
    if rp is not None and rp.get("rss_growth_frac") is not None:
        g = rp["rss_growth_frac"]
        w0, w1 = rp["window_min"]
        enough = rp["simulated_min"] >= rp["target_simulated_min"] - 1e-9
        note = "" if enough else f"replay stopped at {rp['simulated_min']} simulated min"
        rows.append(_row(f"RSS growth, minute {w0:g} -> {w1:g} of replay", "< 10%",
                         f"{100 * g:.1f}%", (g < 0.10) and enough, note or quick_note))  # fmt: skip
    else:
        rows.append(_row("RSS growth over the long replay", "< 10%", None, None,
                         (r.get("errors") or {}).get("replay", "not measured")))  # fmt: skip
    cu = r.get("cuda")
    if cu is not None:
        sp = cu["speedup_steps_per_s"]
        m_cuda = cu.get("num_inducing_cuda")
        others = ", ".join(
            f"M = {k[1:]}: {v['speedup_steps_per_s']}x"
            for k, v in cu.items()
            if k.startswith("M") and isinstance(v, dict) and k != f"M{m_cuda}"
        )
        note = f"at M = {m_cuda}, the daemon's on CUDA" + (f"; {others}" if others else "")
        note = note if m_cuda else ""
        rows.append(_row("CUDA SVGP steps/s vs CPU", ">= 5x", sp, sp >= 5.0,
                         "; ".join(n for n in (quick_note, note) if n)))  # fmt: skip
        a = cu["algorithm1_20k_cuda"]["median_ms"]
        rows.append(_row("CUDA Algorithm 1, 20k query points", "< 100 ms", a, a < 100.0,
                         quick_note))  # fmt: skip
    else:
        note = "no GPU on this machine" if not r["machine"].get("cuda_available") else "not run"
        rows.append(_row("CUDA SVGP steps/s vs CPU", ">= 5x", None, None, note))
        rows.append(_row("CUDA Algorithm 1, 20k query points", "< 100 ms", None, None, note))
    if not r.get("quick"):
        w = r.get("wall_s")
        skipped = _skipped_sections(r)
        wnote = f"not the whole benchmark: {' and '.join(skipped)} skipped" if skipped else ""
        rows.append(_row("whole benchmark wall time", "< 15 min", None if w is None else
                         f"{w / 60:.1f} min", None if w is None or skipped else w < 900.0,
                         wnote))  # fmt: skip
    return rows


def _fmt(v: Any, nd: int = 1) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


STAGE_LABELS = {
    "stereo_depth": "stereo depth (SGBM, downsampled)",
    "backproject": "back-projection with covariance",
    "fof_update": "FOF store update (Eq. 4-6 targets)",
    "tsdf": "TSDF integration",
    "ingest": "ingest = depth + back-proj. + FOF",
    "ingest_with_tsdf": "ingest incl. TSDF",
    "svgp_step": "one SVGP training step",
    "train_per_frame": "SVGP steps per frame (daemon K)",
    "query_cloud": "query cloud (TSDF extraction)",
    "grasp_proposal": "grasp proposal",
    "algorithm1": "Algorithm 1 (grasp contacts)",
    "eq13": "Eq. 13 ranking",
    "algorithm1_cloud": "Algorithm 1 (rest of the cloud)",
    "algorithm1_query_cloud": "Algorithm 1 (whole query cloud)",
    "end_to_end": "end-to-end newest frame -> grasps",
}


def format_table(r: dict[str, Any]) -> list[str]:
    """The printed summary (also pasted into docs/performance.md)."""
    mi = r["machine"]
    st = r["settings"]
    out = [
        f"pugsd bench{' (QUICK: not comparable with targets)' if r.get('quick') else ''}"
        f" -- {mi['cpu_model']}, {mi['logical_cores']} cores, torch {mi['torch']} "
        f"({mi['torch_threads']} threads), device {mi['device']}",
        f"{st['object']}, {st['n_frames']} frames {st['resolution'][0]}x{st['resolution'][1]} "
        f"at {st['rate_hz']:g} Hz, downsample {st['downsample']}, M={st['num_inducing']}, "
        f"B={st['batch_size']}, {st['train_steps_per_frame']} SVGP steps/frame, "
        f"paper epochs {st['paper_epochs']}; load avg {mi['load_average_at_start']} -> "
        f"{mi.get('load_average_at_end')}",
    ]
    if r.get("stages"):
        out += ["", f"{'stage':<40} {'median ms':>10} {'p95 ms':>10} {'n':>5}"]
    for k, label in STAGE_LABELS.items():
        s = (r.get("stages") or {}).get(k)
        if s is None:
            continue
        out.append(f"{label:<40} {_fmt(s['median_ms']):>10} {_fmt(s['p95_ms']):>10} {s['n']:>5}")
    sweep = r.get("svgp_step_by_torch_threads")
    if sweep:
        out.append(
            "one SVGP step by torch threads (median ms): "
            + ", ".join(f"{t}: {_fmt(v['median_ms'])}" for t, v in sweep.items())
        )
    if r.get("paper_vs_streaming"):
        out += [
            "",
            "paper mode vs streaming (same frames; last frame -> scored grasps)",
            f"{'trajectory':<11} {'stream s':>9} {'paper s':>9} {'ratio':>7} {'spearman':>9} "
            f"{'top same':>9} {'top5':>5} {'Q':>6} {'ready':>6} {'idle st':>7} {'cloud s':>8}",
        ]
    for traj, c in (r.get("paper_vs_streaming") or {}).items():
        out.append(
            f"{traj:<11} {_fmt(c['streaming_last_frame_to_grasps_s'], 2):>9} "
            f"{_fmt(c['paper_last_frame_to_grasps_s'], 1):>9} "
            f"{_fmt(c['ratio_paper_over_streaming'], 1):>7} {_fmt(c['spearman_sigma2_occ'], 3):>9} "
            f"{_fmt(c['top_grasp_same']):>9} {_fmt(c['top5_overlap'], 1):>5} "
            f"{c['query_points']:>6} {_fmt(c['streaming_ready']):>6} "
            f"{c['streaming_idle_steps_after_last_frame']:>7} "
            f"{_fmt(c.get('streaming_last_frame_to_cloud_s'), 2):>8}"
        )
        dm = c.get("daemon") or {}
        ag = dm.get("agreement_with_paper")
        if dm and ag is not None:
            out.append(
                f"{'':<11} the daemon itself ({_fmt((r.get('settings') or {}).get('rate_hz'), 0)} Hz, "
                f"its own schedule; "
                f"{dm.get('train_steps_at_grasps')} SVGP steps at the grasps): last frame -> grasps "
                f"{_fmt(dm.get('last_frame_to_grasps_s'), 2)} s, "
                + (
                    f"its cloud {_fmt(ag.get('last_frame_to_cloud_s'), 2)} s, spearman of that "
                    f"cloud's sigma2_occ {_fmt(ag['spearman_sigma2_occ'], 3)} "
                    f"(on {_fmt(ag.get('shared_fraction'), 3)} of the query cloud)"
                    if ag.get("cloud_received") or not ag.get("later_cloud")
                    else f"no cloud with those grasps; {_later_cloud(ag['later_cloud'])}"
                )
            )
        refined = c.get("spearman_after_idle_steps") or []
        if refined:
            out.append(
                f"{'':<11} then idle training: "
                + ", ".join(
                    f"+{x['steps']} steps ({_fmt(x['train_s'], 1)} s) spearman {_fmt(x['spearman'], 3)}"
                    for x in refined
                )
            )
        if c.get("spearman_paper_vs_paper_other_seed") is not None:
            out.append(
                f"{'':<11} the paper fit against itself with another svgp.seed: spearman "
                f"{_fmt(c['spearman_paper_vs_paper_other_seed'], 3)}, top grasp same "
                f"{_fmt(c.get('top_grasp_same_paper_vs_paper_other_seed'))}, top5 "
                f"{_fmt(c.get('top5_overlap_paper_vs_paper_other_seed'), 1)}"
            )
        pm = c.get("streaming_at_paper_num_inducing")
        if pm:
            out.append(
                f"{'':<11} streaming with the paper's M = {pm['num_inducing']} (synchronous): "
                f"last frame -> grasps {_fmt(pm['last_frame_to_grasps_s'], 2)} s, training "
                f"{_fmt(pm['train_per_frame_median_ms'], 0)} ms per frame (median), spearman "
                f"{_fmt(pm['spearman_sigma2_occ'], 3)}, top grasp same {_fmt(pm['top_grasp_same'])}"
            )
        cv = c.get("converged_reference")
        if cv:
            out.append(
                f"{'':<11} paper fit with q(u) at its optimum (ELBO/point "
                f"{_fmt(cv['paper_elbo_per_point'], 2)} -> {_fmt(cv['paper_optimal_q_elbo_per_point'], 2)}): "
                f"spearman vs streaming {_fmt(cv['spearman_streaming_vs_paper_optimal_q'], 3)} "
                f"(after idle training {_fmt(cv['spearman_streaming_refined_vs_paper_optimal_q'], 3)}), "
                f"vs the other seed's optimum "
                f"{_fmt(cv.get('spearman_paper_optimal_q_vs_other_seed_optimal_q'), 3)}, "
                f"vs the paper fit {_fmt(cv['spearman_paper_vs_its_optimal_q'], 3)}"
            )
            if "streaming_optimal_q_elbo_per_point" in cv:
                out.append(
                    f"{'':<11} streaming model after idle training vs its own optimum: ELBO/point "
                    f"{_fmt(cv['streaming_refined_elbo_per_point'], 2)} -> "
                    f"{_fmt(cv['streaming_optimal_q_elbo_per_point'], 2)}, spearman "
                    f"{_fmt(cv['spearman_streaming_refined_vs_its_optimal_q'], 3)}"
                )
    if r.get("daemon_alone"):  # --no-pipeline
        out += ["", "the daemon alone (no paper fit in this run; last frame -> its grasps)"]
    for traj, dm in (r.get("daemon_alone") or {}).items():
        out.append(
            f"{traj:<11} {_fmt(dm.get('last_frame_to_grasps_s'), 2)} s ({_fmt(st.get('rate_hz'), 0)} "
            f"Hz, its own schedule; {dm.get('train_steps_at_grasps')} SVGP steps at the grasps, "
            f"{dm.get('integrated')} of {dm.get('frames')} frames integrated)"
        )
    tp = r.get("throughput")
    if tp is not None:
        sus = tp["sustained_hz"]
        held = f"{sus:g} Hz" if sus is not None else "none of the rates tried"
        out += ["", f"sustained throughput ({tp['source']}): highest rate held {held}"]
        for t in tp["trials"]:
            lat = t.get("latency", {})
            e2e = lat.get("newest_frame_to_grasps", {})
            age = lat.get("frame_age_at_integrate", {})
            out.append(
                f"  {t['rate_hz']:>5g} Hz: offered {t['offered']:>4}, integrated "
                f"{t['integrated']:>4}, dropped {sum(t['drops'].values()):>4} "
                f"({'held' if t['held'] else 'NOT held'}); frame age at integrate p50 "
                f"{_fmt(age.get('p50_ms'))} ms; newest frame -> grasps p50 "
                f"{_fmt(e2e.get('p50_ms'))} ms"
            )
    rp = r.get("replay")
    mem = r.get("memory") or {}
    out += ["", f"memory: peak RSS {_fmt(mem.get('peak_rss_mb'))} MiB"]
    if rp is not None:
        out.append(
            f"  long replay ({rp['source']}): {rp['simulated_min']} simulated min offered in "
            f"{rp['feed_wall_s']} s ({rp['speedup_vs_real_time']}x real time), integrated "
            f"{rp['integrated']}, RSS min {rp['window_min'][0]:g} {_fmt(rp['rss_window_start_mb'])} "
            f"MiB -> min {rp['window_min'][1]:g} {_fmt(rp['rss_window_end_mb'])} MiB "
            f"(growth {_fmt(None if rp['rss_growth_frac'] is None else 100 * rp['rss_growth_frac'])}%,"
            f" lowest RSS over {_fmt(rp.get('rss_window_s'))} simulated s; peaks "
            f"{_fmt(rp.get('rss_window_start_peak_mb'))} -> {_fmt(rp.get('rss_window_end_peak_mb'))} "
            f"MiB); {rp.get('grasps_published', '-')} grasp updates published"
        )
    cu = r.get("cuda")
    if cu is not None:
        per_m = [(k, v) for k, v in cu.items() if k.startswith("M") and isinstance(v, dict)]
        for k, v in per_m or [("", cu)]:
            out.append(
                f"CUDA{f' (M = {k[1:]})' if k else ''}: SVGP steps/s {v['svgp_steps_per_s_cuda']} vs "
                f"CPU {v['svgp_steps_per_s_cpu']} ({v['speedup_steps_per_s']}x)"
            )
        out.append(
            f"CUDA: Algorithm 1 at 20k points {_fmt(cu['algorithm1_20k_cuda']['median_ms'])} ms"
            + (f" (M = {cu['num_inducing_cuda']})" if cu.get("num_inducing_cuda") else "")
        )
    for k, v in (r.get("errors") or {}).items():
        out.append(f"ERROR in {k}: {v}")
    out += ["", f"{'target':<52} {'required':>9} {'measured':>20} {'result':>6}"]
    for t in r.get("targets", []):
        res = "n/a" if t["pass"] is None else ("PASS" if t["pass"] else "FAIL")
        meas = _fmt(t["measured"], 3) if isinstance(t["measured"], float) else _fmt(t["measured"])
        line = f"{t['target']:<52} {t['required']:>9} {meas:>20} {res:>6}"
        if t.get("note"):
            line += f"  ({t['note']})"
        out.append(line)
    out.append(f"wall time {r.get('wall_s')} s (rendering {r.get('render_s')} s)")
    return out
