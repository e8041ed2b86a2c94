# SPDX-License-Identifier: Apache-2.0
"""Core subcommands: version, check-config, dump-config, offline."""

from __future__ import annotations

import argparse
import sys

from pugsd import __version__
from pugsd.config import dump_config, load_config


def _version(args: argparse.Namespace) -> int:
    sys.stdout.write(f"pugsd {__version__}\n")
    return 0


def _check_config(args: argparse.Namespace) -> int:
    load_config(args.file, args.set or ())
    sys.stdout.write(f"{args.file}: ok\n")
    return 0


def _dump_config(args: argparse.Namespace) -> int:
    cfg = load_config(args.config, args.set or ()) if args.config or args.set else None
    sys.stdout.write(dump_config(cfg))
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
