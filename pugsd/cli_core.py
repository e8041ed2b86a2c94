# SPDX-License-Identifier: Apache-2.0
"""Core subcommands: version, check-config, dump-config, offline."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from pugsd import __version__
from pugsd.config import PugsdConfig, config_warnings, core_of, dump_config, load_config
from pugsd.core.types import ScoredGrasps
from pugsd.errors import ConfigError


def _version(args: argparse.Namespace) -> int:
    sys.stdout.write(f"pugsd {__version__}\n")
    return 0


def _check_config(args: argparse.Namespace) -> int:
    from pugsd.wire.session import check_loopback_safe, zenoh_config

    cfg = load_config(args.file, args.set or ())
    # what `pugsd run` checks when it opens its session: the unit's ExecStartPre relies on it
    if not cfg.daemon.allow_non_loopback:
        try:
            check_loopback_safe(cfg.zenoh)
        except ConfigError as exc:
            raise ConfigError(
                f"{exc} (`pugsd run` refuses it unless [daemon] allow_non_loopback = true)"
            ) from None
    zenoh_config(cfg.zenoh)  # zenoh's own parser: unknown keys and bad values
    problems = cuda_problems(cfg)
    if cfg.grasp.proposer == "torchscript":  # `pugsd run` loads it at start and refuses a missing one
        from pugsd.models import model_path_problem

        problem = model_path_problem(cfg.grasp.model_path)
        if problem:
            problems.append(problem)
    if problems:
        raise ConfigError("; ".join(problems))
    for w in [*config_warnings(cfg), *record_directory_warnings(cfg)]:
        sys.stderr.write(f"{args.file}: warning: {w}\n")
    sys.stdout.write(f"{args.file}: ok\n")
    return 0


def record_directory_warnings(cfg: PugsdConfig) -> list[str]:
    """With ``[record] enabled``: a ``directory`` this user cannot create or write (the daemon
    then serves without recording, its status says why). A warning, not an error: systemd's
    StateDirectory may create it only when the unit starts."""
    if not cfg.record.enabled:
        return []
    path = Path(cfg.record.directory).expanduser().absolute()
    probe = path
    while not probe.exists() and probe != probe.parent:  # the nearest existing ancestor
        probe = probe.parent
    if not probe.is_dir():
        return [f"record.directory = {str(path)!r}: {str(probe)!r} is not a directory; the daemon will run "
                "without recording"]  # fmt: skip
    if not os.access(probe, os.W_OK | os.X_OK):
        what = "cannot write" if probe == path else f"cannot create it ({str(probe)!r} is not writable)"
        return [f"record.directory = {str(path)!r}: this user {what}; the daemon will run without "
                "recording"]  # fmt: skip
    return []


def cuda_problems(cfg: PugsdConfig) -> list[str]:
    """Settings that need a CUDA device this machine's torch does not see: ``pugsd run`` refuses
    them when it builds the model, so check-config (the unit's ExecStartPre) refuses them too.
    torch is imported only when a setting asks for CUDA."""
    fof_device = cfg.fof.query_device
    if "cuda" not in (cfg.svgp.device, fof_device):
        return []
    import torch

    if torch.cuda.is_available():
        return []
    return [
        f"{key} = cuda, but torch sees no CUDA device on this machine (use cpu or auto)"
        for key, value in (("svgp.device", cfg.svgp.device), ("fof.query_device", fof_device))
        if value == "cuda"
    ]


def _dump_config(args: argparse.Namespace) -> int:
    cfg = load_config(args.config, args.set or ()) if args.config or args.set else None
    sys.stdout.write(dump_config(cfg))
    return 0


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
    from pugsd.models import make_pipeline
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
    p = sub.add_parser("version", help="print the version")
    p.set_defaults(func=_version)
    p = sub.add_parser("check-config", help="validate a TOML config (exit 1 on any error)")
    p.add_argument("file")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key")
    p.set_defaults(func=_check_config)
    p = sub.add_parser("dump-config", help="print the effective config as documented TOML")
    p.add_argument("--config", default=None)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key")
    p.set_defaults(func=_dump_config)
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
