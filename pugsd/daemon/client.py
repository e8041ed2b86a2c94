# SPDX-License-Identifier: Apache-2.0
"""Clients of a running daemon: ``pugsd status``, ``pugsd grasps``, ``pugsd reset``.

Each opens a zenoh peer that connects to the daemon's listen endpoints (the config's ``[zenoh]``;
with no fixed listen port, its connect endpoints: a router; multicast scouting and gossip off,
under the daemon's own loopback policy), asks one query on ``<prefix>/...`` and prints the answer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from typing import Any

from pugsd import exit_codes
from pugsd.config import load_config


def exit_codes_epilog(example: str, *codes: str) -> str:
    """A client command's epilog: its example, then its exit codes one a line."""
    return f"example:\n  {example}\n\nexit codes:\n" + "".join(f"  {c}\n" for c in codes)


FAILED = "1  failure (the daemon answered with an error)"
NO_REPLY = "4  no reply (no daemon on these endpoints)"


def query_daemon(full_cfg: Any, suffix: str, timeout: float = 2.0) -> tuple[bytes | None, list[str]]:
    """One query on the daemon's ``<prefix>/<suffix>``: the first ok reply's payload (None if
    none came within ``timeout``) and the text of the error replies."""
    from pugsd.wire.session import close_session, open_session, tool_config

    key = f"{full_cfg.daemon.prefix}/{suffix}"
    # a peer that connects to the daemon's listen endpoints (multicast scouting and gossip off),
    # under the same loopback policy as the daemon itself
    session = open_session(
        tool_config(full_cfg.zenoh), require_loopback=not full_cfg.daemon.allow_non_loopback
    )
    try:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:  # let the connection to the daemon come up first
            with contextlib.suppress(Exception):
                if list(session.info.peers_zid()) or list(session.info.routers_zid()):
                    break
            time.sleep(0.01)
        errors: list[str] = []
        for reply in session.get(key, timeout=max(0.1, t_end - time.monotonic())):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes(), errors
            err = reply.err
            if err is not None:
                with contextlib.suppress(Exception):
                    errors.append(err.payload.to_string())
        return None, errors
    finally:
        close_session(session)


def _ask(args: argparse.Namespace, suffix: str) -> tuple[bytes | None, int]:
    """The reply's payload and exit_codes.OK; with no ok reply, None and why, printed: NO_PEER
    (nothing answered), NOT_READY (the daemon has no grasps yet) or FAILURE (another error reply)."""
    from pugsd.daemon.queries import NO_GRASPS

    cfg = load_config(args.config, args.set or ())
    data, errors = query_daemon(cfg, suffix, args.timeout)
    code = exit_codes.OK
    if data is None:
        key = f"{cfg.daemon.prefix}/{suffix}"
        if errors:
            not_ready = all(e.startswith(NO_GRASPS) for e in errors)
            code = exit_codes.NOT_READY if not_ready else exit_codes.FAILURE
        else:
            code = exit_codes.NO_PEER
            from pugsd.wire.session import tool_config

            asked = ", ".join(tool_config(cfg.zenoh)["connect"]["endpoints"]) or "none"
            errors = [
                f"no reply within {args.timeout:g} s from {asked} (is the daemon running, on these "
                "zenoh endpoints? give its --config, or "
                "--set 'zenoh.listen.endpoints=[\"tcp/127.0.0.1:PORT\"]')"
            ]
        detail = "; ".join(errors)
        sys.stderr.write(f"pugsd: {key}: {detail}\n")
    return data, code


def status_lines(st: dict[str, Any]) -> list[str]:
    """A daemon status (the JSON of ``<prefix>/status``) in a few lines for an operator."""
    c = st.get("counts", {})
    frames = c.get("frames.stereo", 0) + c.get("frames.depth", 0)
    verdict = "healthy" if st.get("healthy", True) else "UNHEALTHY: " + "; ".join(st.get("problems", []))
    # every drop: the counted reasons (counts.dropped) and the queues' own counters
    dropped = st.get("dropped_total", c.get("dropped", 0))
    skipped = c.get("frames.skipped_rate", 0)
    lines = [
        f"{st.get('node', '?')}: {verdict}; up {st.get('uptime_s', 0):.0f} s; "
        f"ready {st.get('ready')}; model version {st.get('model_version')}",
        f"frames {frames}, integrated {c.get('integrated', 0)}, grasps published "
        f"{st.get('grasps_published', 0)}, rejected {c.get('rejected', 0)}, dropped {dropped}"
        + (f", skipped {skipped} (daemon.max_frame_rate_hz)" if skipped else ""),
    ]
    inputs = st.get("inputs", {})
    ages = ", ".join(f"{k} {v:.1f} s" for k, v in inputs.get("age_s", {}).items()) or "none yet"
    lines.append(f"inputs (time since last): {ages}")
    if inputs.get("stale"):
        lines.append(f"stale inputs: {' '.join(inputs['stale'])}")
    crowded = st.get("upstream", {}).get("concurrent_publishers", {})
    if crowded:
        lines.append(
            "several publishers sending on one input at the same time (a node launched twice?): "
            + ", ".join(f"{k} {n}" for k, n in sorted(crowded.items()))
        )
    skew = inputs.get("frame_minus_newest_pose_s", {})
    if skew.get("n"):
        lines.append(
            f"frame stamp - newest pose stamp: median {skew['p50']:+.3f} s (min {skew['min']:+.3f}, "
            f"max {skew['max']:+.3f}, last {skew['n']} frames)"
        )
    drops = dict(st.get("dropped", {}))
    for name in ("stereo", "depth"):  # the frame queues (what dropped_total counts)
        box = st.get("mailboxes", {}).get(name, {})
        pushed = int(box.get("overflowed", 0))
        cleared = int(box.get("dropped", 0)) - pushed
        if pushed > 0:
            drops[f"{name} queue: pushed out by newer frames (input faster than the daemon)"] = pushed
        if cleared > 0:
            drops[f"{name} queue: cleared (reset)"] = cleared
    for what, n in (
        ("ingress bound: messages faster than the loop took them", st.get("ingress", {}).get("dropped")),
        ("unpaired stereo halves", st.get("waiting", {}).get("unpaired_dropped")),
    ):
        if n:
            drops[what] = int(n)
    for title, reasons in (("rejected", st.get("rejected", {})), ("dropped", drops)):
        for reason, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:10]:
            lines.append(f"  {title} {n:>8}  {reason}")
    lat = st.get("latency", {})
    if lat:
        parts = [f"{k} {v['p50_ms']:.0f}/{v['p95_ms']:.0f}" for k, v in lat.items() if "p50_ms" in v]
        lines.append("latency p50/p95 ms: " + ", ".join(parts))
    return lines


def _status(args: argparse.Namespace) -> int:
    data, code = _ask(args, "status")
    if data is None:
        return code
    st = json.loads(data)
    if args.json:
        sys.stdout.write(json.dumps(st, indent=2) + "\n")
    else:
        sys.stdout.write("\n".join(status_lines(st)) + "\n")
    return exit_codes.OK if st.get("healthy", True) else exit_codes.UNHEALTHY


def _grasps(args: argparse.Namespace) -> int:
    from pugsd.grasp_text import grasp_lines
    from pugsd.record.replay import grasps_to_json
    from pugsd.wire.codec import decode_grasp_array, grasp_array_frame_id

    data, code = _ask(args, "grasps/latest")
    if data is None:
        return code
    g = decode_grasp_array(data)
    n = min(len(g), args.top) if args.top > 0 else len(g)
    if args.json:  # the form `pugsd replay` writes
        rows = grasps_to_json(g)[:n]
        sys.stdout.write(json.dumps({"stamp_ns": int(g.stamp_ns), "grasps": rows}, indent=2) + "\n")
        return 0
    sys.stdout.write(f"{len(g)} grasps, stamp {int(g.stamp_ns)} ns, best first (PUGS confidence)\n")
    for line in grasp_lines(g, n, grasp_array_frame_id(data)):
        sys.stdout.write(line + "\n")
    return 0


def _reset(args: argparse.Namespace) -> int:
    data, code = _ask(args, "reset")
    if data is None:
        return code
    sys.stdout.write(f"reset: {data.decode('utf-8', 'replace')}\n")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--config",
            default=None,
            help="the daemon's TOML config ([daemon] prefix; the client connects to its "
            "[zenoh] listen endpoints, default tcp/127.0.0.1:7447, or with none to its connect "
            "endpoints, e.g. a router)",
        )
        p.add_argument(
            "--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)"
        )
        p.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the reply")

    p = sub.add_parser(
        "status",
        help="ask a running daemon for its status (exit 0 healthy, 3 unhealthy, 4 no reply)",
        epilog=exit_codes_epilog(
            "pugsd status --config /etc/pugsd/pugsd.toml", "0  healthy", FAILED, "3  unhealthy", NO_REPLY
        ),
    )
    common(p)
    p.add_argument("--json", action="store_true", help="print the status JSON as the daemon sent it")
    p.set_defaults(func=_status)
    p = sub.add_parser(
        "grasps",
        help="ask a running daemon for its latest grasps (best first)",
        epilog=exit_codes_epilog(
            "pugsd grasps --top 3",
            "0  ok",
            FAILED,
            NO_REPLY,
            "5  not ready (no grasps yet: the model is not ready, or a reset is clearing the map)",
        ),
    )
    common(p)
    p.add_argument("--top", type=int, default=10, help="grasps to print (0: all)")
    p.add_argument("--json", action="store_true", help="print them as JSON")
    p.set_defaults(func=_grasps)
    p = sub.add_parser(
        "reset",
        help="ask a running daemon to clear its map and model",
        epilog=exit_codes_epilog("pugsd reset", "0  accepted", FAILED, NO_REPLY),
    )
    common(p)
    p.set_defaults(func=_reset)
