# SPDX-License-Identifier: Apache-2.0
"""The ``pugsd`` command line: subcommands registered by each subsystem (explicit list)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from pugsd.errors import PugsdError

# Each module defines ``register(subparsers)``; a subcommand sets ``func(args) -> int``.
_COMMAND_MODULES = (
    "pugsd.cli_core",
    "pugsd.arm.cli",
    "pugsd.sim.cli",
    "pugsd.record.cli",
    "pugsd.daemon.cli",
    "pugsd.daemon.client",
    "pugsd.bench.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pugsd", description=__doc__)
    parser.add_argument(
        "--log-level",
        default=None,
        choices=("debug", "info", "warning", "error"),
        help="log level (default warning; for `run`, [daemon] log_level, which this overrides)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, str(args.log_level or "warning").upper(), logging.WARNING),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        rc = args.func(args)
    except PugsdError as exc:
        sys.stderr.write(f"pugsd {args.command}: error: {exc}\n")
        return 1
    except KeyboardInterrupt:
        return 130
    return int(rc or 0)
