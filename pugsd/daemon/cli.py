# SPDX-License-Identifier: Apache-2.0
"""``pugsd run`` (the service) and ``pugsd demo`` (everything in one process on loopback)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import signal
import sys

from pugsd.config import PugsdConfig, core_of, load_config
from pugsd.daemon.app import Daemon
from pugsd.daemon.logs import setup_logging
from pugsd.daemon.process import apply_malloc_arena_max, apply_thread_limits

log = logging.getLogger(__name__)


async def serve(daemon: Daemon, stop: asyncio.Event | None = None) -> None:
    """Run ``daemon`` until SIGTERM or SIGINT (or ``stop``)."""
    stop = stop if stop is not None else asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    try:
        await daemon.run(stop)
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)


def exit_after(daemon: Daemon) -> int:
    """Exit 0 once the daemon has stopped (its recording finished, its session closed): the logs
    are flushed and the interpreter's teardown is skipped (``os._exit``), as the finalisers of
    torch and the other extension modules take seconds and the threads of abandoned calls cannot
    be joined. Returns 0 only where ``os._exit`` is a test's stand-in."""
    if daemon.abandoned_work():
        log.warning("exiting with %d abandoned in-flight call(s)", daemon.abandoned_work())
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
    return 0


def run_log_level(args: argparse.Namespace, cfg: PugsdConfig) -> str:
    """``pugsd --log-level X run``: X wins over ``[daemon] log_level`` (it used to be ignored)."""
    given = getattr(args, "log_level", None)
    return str(given) if given else cfg.daemon.log_level


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config, args.set or ())
    apply_malloc_arena_max(cfg.daemon.malloc_arena_max)  # before torch and zenoh start threads
    setup_logging(run_log_level(args, cfg), cfg.daemon.log_json)
    from pugsd.pipeline_factory import make_pipeline  # torch import: only when serving

    daemon = Daemon(cfg, make_pipeline(core_of(cfg)))
    apply_thread_limits(cfg)
    asyncio.run(serve(daemon))
    return exit_after(daemon)


def _demo(args: argparse.Namespace) -> int:
    from pugsd.daemon.demo import run_demo

    setup_logging(getattr(args, "log_level", None) or "warning", False)  # pugsd --log-level X demo

    def write(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    return run_demo(
        duration_s=args.duration,
        out_dir=args.out,
        listen=args.listen,
        overrides=args.set or (),
        write=write,
    )


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "run",
        help="run the streaming daemon (systemd: Type=notify)",
        epilog="example:\n  pugsd run --config /etc/pugsd/pugsd.toml --set daemon.grasp_rate_hz=2",
    )
    p.add_argument("--config", default=None, help="TOML config (default: built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    p.set_defaults(func=_run)
    p = sub.add_parser(
        "demo",
        help="daemon + synthetic stereo camera + grasp printer on a loopback zenoh peer",
        epilog="example:\n  pugsd demo --duration 90 --listen tcp/127.0.0.1:7448",
    )
    p.add_argument("--duration", type=float, default=60.0, help="seconds to run")
    p.add_argument("--out", default="pugsd-demo", help="directory for the MCAP and PNG")
    p.add_argument("--listen", default="tcp/127.0.0.1:7447", help="loopback endpoint other nodes can join")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")
    p.set_defaults(func=_demo)
