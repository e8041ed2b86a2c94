# SPDX-License-Identifier: Apache-2.0
"""The config subcommands: ``check-config`` (validate a file as ``pugsd run`` would) and
``dump-config`` (the documented TOML of the effective config)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from pugsd.config import PugsdConfig, config_warnings, dump_config, load_config
from pugsd.errors import ConfigError


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
        from pugsd.pipeline_factory import model_path_problem

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


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "check-config",
        help="validate a TOML config (exit 1 on any error)",
        epilog="example:\n  pugsd check-config /etc/pugsd/pugsd.toml",
    )
    p.add_argument("file", help="the TOML config to check")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key (repeatable)")
    p.set_defaults(func=_check_config)
    p = sub.add_parser(
        "dump-config",
        help="print the effective config as documented TOML",
        epilog="example:\n  pugsd dump-config > pugsd.toml",
    )
    p.add_argument(
        "--config", default=None, help="TOML config to start from (default: the built-in defaults)"
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key (repeatable)")
    p.set_defaults(func=_dump_config)
