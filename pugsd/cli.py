# SPDX-License-Identifier: Apache-2.0
"""The ``pugsd`` command line: subcommands registered by each subsystem (explicit list), parsed
by :class:`PugsdParser` (suggestions for misspelled commands and options, the default beside every
option's help)."""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import os
import re
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Any, NoReturn

from pugsd import __version__, exit_codes
from pugsd.errors import PugsdError

DESCRIPTION = """\
pugsd finds grasps on an object seen by a stereo camera and scores each by how sure the
reconstruction is where the fingers go (PUGS): live from ROS 2 topics over zenoh, or offline
from recordings."""
EPILOG = """examples:
  pugsd demo                      daemon, synthetic camera and grasp printer on loopback
  pugsd run --config pugsd.toml   the streaming daemon (systemd: Type=notify)
  pugsd grasps                    the running daemon's latest grasps
  pugsd replay rec.mcap           the pipeline on a recording, without zenoh

exit codes: 0 ok; 1 failure; 2 usage error; 3 daemon unhealthy (status); 4 no reply, or nothing
received or delivered (record, play); 5 not ready (grasps: no model yet); 130 interrupted.
`pugsd COMMAND --help` describes each command."""
# the simulation extras (`pip install 'pugsd[sim]'`): the commands that render or simulate need them
SIM_MODULES = frozenset({"mujoco", "trimesh", "manifold3d", "matplotlib"})


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs as written (their examples keep their lines), and each option's
    default after its help unless the help names it already (or it is an on/off flag)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            "default" in text
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        return text + " (default: %(default)s)"


class PugsdParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors suggest the closest command, choice or option of the
    command typed, and whose subcommands are parsed by the same class (and formatter)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        ns, extras = super().parse_known_args(args, namespace)
        if extras and not hasattr(ns, "_pugsd_parser"):  # the innermost parser with leftovers
            ns._pugsd_parser = self
        return ns, extras

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        ns, extras = self.parse_known_args(args, namespace)
        parser = vars(ns).pop("_pugsd_parser", self)
        if extras:  # said by the command they were given to, with its usage and options
            parser.error(f"unrecognized arguments: {' '.join(extras)}")
        return ns

    def error(self, message: str) -> NoReturn:
        hint = self._suggestion(message)
        super().error(message + (f"; did you mean {hint}?" if hint else ""))

    def _suggestion(self, message: str) -> str:
        """The closest known word to the one an argparse error names, or ""."""
        m = re.search(r"invalid choice: '([^']*)'", message)
        if m:
            typed = m.group(1)
            known = [str(c) for a in self._actions if a.choices for c in a.choices]
        else:
            m = re.search(r"unrecognized arguments: (\S+)", message)
            if not m:
                return ""
            typed = m.group(1).split("=", 1)[0]
            known = [o for a in self._actions for o in a.option_strings]
        close = difflib.get_close_matches(typed, known, n=1, cutoff=0.6)
        return repr(close[0]) if close else ""

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
    parser = PugsdParser(prog="pugsd", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=f"pugsd {__version__}")
    parser.add_argument(
        "--log-level",
        default=None,
        choices=("debug", "info", "warning", "error"),
        help="log level (default warning; for `run`, [daemon] log_level, which this overrides)",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sub.add_parser("version", help="print the version", epilog="example:\n  pugsd version").set_defaults(
        func=_version
    )
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:  # Ctrl-C before the command runs (its imports take seconds)
        sys.stderr.write("pugsd: interrupted\n")
        return exit_codes.INTERRUPTED


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
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
    except PugsdError as exc:
        sys.stderr.write(f"pugsd {args.command}: error: {exc}\n")
        return exit_codes.FAILURE
    except ModuleNotFoundError as exc:
        if exc.name not in SIM_MODULES:
            raise
        sys.stderr.write(
            f"pugsd {args.command}: error: this command needs the simulation (no module named "
            f"{exc.name!r}): pip install 'pugsd[sim]'\n"
        )
        return exit_codes.FAILURE
    except KeyboardInterrupt:
        return exit_codes.INTERRUPTED
    except BrokenPipeError:  # `pugsd mcap info x.mcap | head`: the reader has gone, end quietly
        _drop_stdout()
        return exit_codes.BROKEN_PIPE
    return int(rc or 0)


def _drop_stdout() -> None:
    """Point stdout at /dev/null, so that the interpreter's last flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no file descriptor (a replaced sys.stdout)
        pass
