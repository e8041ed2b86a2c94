# SPDX-License-Identifier: Apache-2.0
"""The ``pugsd`` command line: subcommands registered by each subsystem (explicit list)."""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from collections.abc import Sequence

from pugsd import __version__
from pugsd.errors import PugsdError

# Each module defines ``register(subparsers)``; a subcommand sets ``func(args) -> int``.
_COMMAND_MODULES = (
    "pugsd.config_cli",
    "pugsd.offline_cli",
    "pugsd.arm.cli",
    "pugsd.sim.cli",
    "pugsd.record.cli",
    "pugsd.daemon.cli",
    "pugsd.daemon.client",
    "pugsd.bench.cli",
)


def _version(args: argparse.Namespace) -> int:
    sys.stdout.write(f"pugsd {__version__}\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pugsd", description=__doc__)
    parser.add_argument(
        "--log-level",
        default=None,
        choices=("debug", "info", "warning", "error"),
        help="log level (default warning; for `run`, [daemon] log_level, which this overrides)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sub.add_parser("version", help="print the version").set_defaults(func=_version)
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C before the command runs (its imports take seconds)
        sys.stderr.write("pugsd: interrupted\n")
        return 130


def _build_and_parse(argv: Sequence[str] | None) -> argparse.Namespace:
    """``build_parser().parse_args(argv)``, with a Ctrl-C during the subcommand modules' imports
    (open3d, torch, mujoco: seconds) noted and turned into KeyboardInterrupt afterwards: raised
    inside an import, a library's catch-all import guard swallowed it and the command ran on."""
    if threading.current_thread() is not threading.main_thread():
        return build_parser().parse_args(argv)
    before = signal.getsignal(signal.SIGINT)
    if before is not signal.default_int_handler:  # ignored (a background job) or the caller's own
        return build_parser().parse_args(argv)
    hit = threading.Event()
    signal.signal(signal.SIGINT, lambda signum, frame: hit.set())
    try:
        args = build_parser().parse_args(argv)
    finally:
        signal.signal(signal.SIGINT, before)
    if hit.is_set():
        raise KeyboardInterrupt
    return args


def _main(argv: Sequence[str] | None) -> int:
    args = _build_and_parse(argv)
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
