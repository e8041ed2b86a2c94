# SPDX-License-Identifier: Apache-2.0
"""``pugsd evaluate``: the paper's Table I experiment in simulation."""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from pugsd.errors import InputError

log = logging.getLogger(__name__)


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _rescore(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from pugsd.sim.evaluate import markdown_table, rescore, write_json

    path = Path(args.rescore)
    if not path.is_file():
        raise InputError(f"--rescore: no such file {path}")
    res = rescore(json.loads(path.read_text()))
    table = markdown_table(res)
    sys.stdout.write(table)
    if args.json:
        res["table_markdown"] = table
        write_json(res, args.json)
        sys.stdout.write(f"results: {args.json}\n")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from pugsd.sim.evaluate import (
        METHODS,
        MODES,
        RECONS,
        EvalOptions,
        markdown_table,
        run_evaluation,
        write_json,
    )

    if args.rescore:
        return _rescore(args)
    from pugsd.sim.objects import BUILTIN_OBJECTS
    from pugsd.sim.sequence import POSES

    objects = _csv(args.objects)
    recons = _csv(args.recon)
    methods = _csv(args.methods)
    modes = _csv(args.mode)
    for name, vals, known in (
        ("--objects", objects, tuple(BUILTIN_OBJECTS)),
        ("--recon", recons, RECONS),
        ("--methods", methods, METHODS),
        ("--mode", modes, MODES),
    ):
        bad = [v for v in vals if v not in known]
        if bad and not (name == "--objects" and args.object_mesh):
            raise InputError(f"{name}: unknown {', '.join(bad)}; known: {', '.join(known)}")
        if not vals:
            raise InputError(f"{name}: empty")
    if args.pose not in POSES:
        raise InputError(f"--pose: unknown {args.pose}; known: {', '.join(POSES)}")
    if args.trials < 1:
        raise InputError("--trials must be >= 1")
    if args.auc_candidates < 0:
        raise InputError("--auc-candidates must be >= 0")
    if args.object_mesh and args.mass is None:
        raise InputError("--object-mesh needs --mass KG")
    if args.resolution not in ("160x120", "320x240", "640x480"):
        raise InputError("--resolution: one of 160x120, 320x240, 640x480")
    w, h = (int(v) for v in args.resolution.split("x"))
    opts = EvalOptions(
        objects=objects,
        recons=recons,
        methods=methods,
        trials=args.trials,
        seed=args.seed,
        modes=modes,
        pose=args.pose,
        width=w,
        height=h,
        n_frames=args.frames,
        object_mesh=args.object_mesh,
        mass_kg=args.mass,
        underwater=args.underwater,
        config_path=args.config,
        overrides=list(args.set or ()),
        workers=args.workers,
        figures_dir=args.figures,
        figures_per_cell=args.figures_per_cell,
        auc_candidates=args.auc_candidates,
    )
    total = len(recons) * args.trials * (1 if args.object_mesh else len(objects)) * len(modes)
    done = [0]

    partial_path = None
    if args.json:
        from pathlib import Path

        partial_path = Path(args.json).with_suffix(".trials.jsonl")
        partial_path.parent.mkdir(parents=True, exist_ok=True)
        partial_path.write_text("")

    from pugsd.progress import progress_bar, ticking

    bar = progress_bar(total, "evaluate", unit="trial", quiet=args.quiet)

    def progress(r: dict[str, Any]) -> None:
        done[0] += 1
        bar.update(1)
        if partial_path is not None:  # survives an interrupted run
            import json

            with partial_path.open("a") as fh:
                fh.write(json.dumps(r, default=float) + "\n")
        if not args.quiet:
            marks = " ".join(
                f"{m}={''.join('1' if v[k] else '0' for k in ('traversal', 'closed', 'lifted'))}"
                for m, v in r["methods"].items()
            )
            bar.write(  # above the bar (a plain line when stderr is not a terminal)
                f"[{done[0]}/{total}] {r['object']} {r['recon']} seed {r['seed']} "
                f"{r.get('mode', '')}: {marks}",
                file=sys.stderr,
            )

    with ticking(bar):
        results = run_evaluation(opts, progress)
    table = markdown_table(results)
    sys.stdout.write(table)
    sys.stdout.write(f"\nwall time {results['wall_time_s']:.0f} s\n")
    if args.json:
        results["table_markdown"] = table
        write_json(results, args.json)
        sys.stdout.write(f"results: {args.json}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "evaluate",
        help="simulated grasp evaluation (the paper's Table I): baselines vs PUGS",
        description="Render stereo sequences of synthetic objects, run the PUGS pipeline, and test "
        "each method's top grasp in MuJoCo (traversal, closed, lifted).",
        epilog="example:\n  pugsd evaluate --objects mug --recon partial --trials 5 --json results.json",
    )
    p.add_argument("--objects", default="kettlebell,mug",
                   help="comma list of kettlebell, mug, box, bottle, mallet")
    p.add_argument("--recon", default="complete,partial,noisy_partial",
                   help="comma list of complete, partial, noisy_partial")
    p.add_argument("--methods", default="baseline,antipodal,pugs,pugs_contact",
                   help="comma list of baseline, antipodal, pugs, pugs_contact (default: all)")
    p.add_argument("--trials", type=int, default=40, help="trials (seeds) per cell (default: 40)")
    p.add_argument("--seed", type=int, default=0, help="first seed; trial i uses seed + i")
    p.add_argument("--mode", default="streaming",
                   help="SVGP training, comma list: streaming (the daemon's incremental steps), "
                   "paper (the 100-epoch batch fit); both run side by side on the same sequences "
                   "(default: streaming)")
    p.add_argument("--auc-candidates", type=int, default=8,
                   help="single-contact candidates per sequence given the traversal check only, "
                   "for the AUC of each score (default: 8)")
    p.add_argument("--pose", default="upright", help="upright, lying, tilted or sideways")
    p.add_argument("--resolution", default="320x240",
                   help="rendered size (downsampled to 160x120 before matching, as in the paper)")
    p.add_argument("--frames", type=int, default=None,
                   help="frames per sequence (default 16 complete, 8 partial)")
    p.add_argument("--object-mesh", default=None, metavar="PATH",
                   help="evaluate a user mesh (PLY, OBJ or STL, metres) instead of --objects "
                   "(default: none)")
    p.add_argument("--mass", type=float, default=None, metavar="KG",
                   help="mass of --object-mesh (default: none; needed with it)")
    p.add_argument("--underwater", action="store_true", help="apply the underwater image model")
    p.add_argument("--config", default=None,
                   help="pugsd TOML config for the pipeline (default: the built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    p.add_argument("--json", default=None, metavar="PATH",
                   help="write results.json here (and each trial as it finishes to *.trials.jsonl; "
                   "default: not written)")
    p.add_argument("--figures", default=None, metavar="DIR",
                   help="write PNG figures here (default: none)")
    p.add_argument("--figures-per-cell", type=int, default=1,
                   help="figures per object x reconstruction (first trials)")
    p.add_argument("--rescore", default=None, metavar="RESULTS_JSON",
                   help="re-run only the physics on the grasps stored in a results.json (default: "
                   "a full evaluation)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or per-trial lines on stderr")
    p.set_defaults(func=_evaluate)
