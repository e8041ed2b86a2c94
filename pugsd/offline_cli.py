# SPDX-License-Identifier: Apache-2.0
"""The ``offline`` subcommand: the PUGS pipeline on a synthetic scene, its top grasps printed."""

from __future__ import annotations

import argparse
import sys
import time

from pugsd.config import core_of, load_config
from pugsd.core.types import ScoredGrasps


def format_grasps(grasps: ScoredGrasps, n: int = 10) -> str:
    """A plain-text table of the top grasps."""
    rows = [
        f"{'rank':>4} {'id':>6} {'x_m':>8} {'y_m':>8} {'z_m':>8} {'width_m':>8} "
        f"{'baseline':>9} {'sigma2_occ':>11} {'pugs':>10}"
    ]
    for i in range(min(n, len(grasps))):
        t = grasps.pose_W[i, :3, 3]
        rows.append(
            f"{i + 1:>4} {int(grasps.grasp_id[i]):>6} {t[0]:>8.3f} {t[1]:>8.3f} {t[2]:>8.3f} "
            f"{grasps.width_m[i]:>8.3f} {grasps.baseline_confidence[i]:>9.3f} "
            f"{grasps.sigma2_occ[i]:>11.4g} {grasps.pugs_confidence[i]:>10.4g}"
        )
    return "\n".join(rows) + "\n"


def _offline(args: argparse.Namespace) -> int:
    from pugsd.pipeline_factory import make_pipeline
    from pugsd.sim import make_sequence

    seq = make_sequence(
        args.object,
        args.trajectory,
        n_frames=args.frames,
        width=args.width,
        height=args.height,
        seed=args.seed,
    )
    # the sequence's own overrides (noisy_partial: sigma_d^2 = 0.01), then --set, which wins
    overrides = [
        f"{k}={v!r}" if isinstance(v, str) else f"{k}={v}" for k, v in seq.core_overrides.items()
    ]
    cfg = load_config(args.config, overrides + list(args.set or ()))
    pipe = make_pipeline(core_of(cfg), seed=args.seed)
    t0 = time.perf_counter()
    for frame in seq.frames:
        pipe.add_stereo(frame)
        if args.mode == "streaming":
            pipe.train_steps()
    if args.mode == "paper":
        pipe.fit_paper(args.epochs)
    else:
        pipe.train_steps(args.final_steps)
    result = pipe.compute()
    dt = time.perf_counter() - t0
    out = sys.stdout
    out.write(
        f"pugsd offline: {seq.object_name}, {seq.trajectory}, {len(seq.frames)} frames "
        f"{args.width}x{args.height}, mode {args.mode}: {pipe.stats()['voxels']} Gaussians, "
        f"{len(result.cloud_W)} query points, {int(result.candidates.valid.sum())} candidates, "
        f"{dt:.1f} s\n\nTop grasps by PUGS confidence (Eq. 13):\n"
    )
    out.write(format_grasps(result.grasps, args.top))
    out.write("\nTop grasps by the proposer's own confidence (baseline):\n")
    out.write(format_grasps(result.baseline_grasps, args.top))
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("offline", help="run the PUGS pipeline on a synthetic scene, print grasps")
    p.add_argument("--object", default="mug", help="synthetic object (mug, kettlebell, box, ...)")
    p.add_argument(
        "--trajectory", default="partial", choices=("complete", "partial", "noisy_partial")
    )
    p.add_argument("--frames", type=int, default=None, help="number of stereo frames")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--mode",
        default="streaming",
        choices=("streaming", "paper"),
        help="streaming SVGP updates, or the paper's batch fit (100 epochs)",
    )
    p.add_argument("--epochs", type=int, default=None, help="paper mode: override the epochs")
    p.add_argument(
        "--final-steps", type=int, default=60, help="streaming: steps after the last frame"
    )
    p.add_argument("--top", type=int, default=5)
    p.add_argument("--config", default=None)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key")
    p.set_defaults(func=_offline)
