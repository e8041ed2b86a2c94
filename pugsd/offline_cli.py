# SPDX-License-Identifier: Apache-2.0
"""The ``offline`` subcommand: the PUGS pipeline on a synthetic scene, its top grasps printed."""

from __future__ import annotations

import argparse
import sys
import time

from pugsd.config import core_of, load_config
from pugsd.core.types import ScoredGrasps
from pugsd.grasp_text import grasp_lines


def format_grasps(grasps: ScoredGrasps, n: int = 10) -> str:
    """The top ``n`` grasps, one line each."""
    return "".join(line + "\n" for line in grasp_lines(grasps, n))


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
    p = sub.add_parser(
        "offline",
        help="run the PUGS pipeline on a synthetic scene, print grasps",
        epilog="example:\n  pugsd offline --object kettlebell --trajectory noisy_partial",
    )
    p.add_argument("--object", default="mug", help="synthetic object (mug, kettlebell, box, bottle, mallet)")
    p.add_argument(
        "--trajectory",
        default="partial",
        choices=("complete", "partial", "noisy_partial"),
        help="camera path around the object",
    )
    p.add_argument(
        "--frames", type=int, default=None, help="number of stereo frames (default: the trajectory's own)"
    )
    p.add_argument("--width", type=int, default=640, help="rendered image width [px]")
    p.add_argument("--height", type=int, default=480, help="rendered image height [px]")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and the model")
    p.add_argument(
        "--mode",
        default="streaming",
        choices=("streaming", "paper"),
        help="streaming SVGP updates (the daemon's), or the paper's batch fit (100 epochs)",
    )
    p.add_argument(
        "--epochs", type=int, default=None, help="paper mode: the epochs (default: the config's)"
    )
    p.add_argument(
        "--final-steps", type=int, default=60, help="streaming: steps after the last frame"
    )
    p.add_argument("--top", type=int, default=5, help="grasps to print")
    p.add_argument("--config", default=None, help="pugsd TOML config (default: the built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    p.set_defaults(func=_offline)
