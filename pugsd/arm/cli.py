# SPDX-License-Identifier: Apache-2.0
"""``pugsd arm sim|status|execute|stop|safe`` and ``pugsd bpl encode|decode``."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import re
import signal
import sys
import time
from typing import Any

import numpy as np

from pugsd.daemon.client import query_daemon
from pugsd.errors import ArmError, PortInUseError

log = logging.getLogger(__name__)


# ---------------------------------------------------------------- shared


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="TOML config file (default: built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a key")


def _load(args: argparse.Namespace) -> Any:
    from pugsd.config import load_config

    return load_config(args.config, args.set or ())


def _out(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _run(coro: Any) -> Any:
    return asyncio.run(coro)


# ---------------------------------------------------------------- bpl encode / decode


def _parse_value(text: str, kind: str, packet_id: int) -> float | int:
    from pugsd.arm.protocol import PacketID, parse_mode, parse_packet_id

    if kind == "f32":
        try:
            return float(text)
        except ValueError:
            raise ArmError(f"{text!r} is not a number") from None
    if packet_id == PacketID.MODE:
        return parse_mode(text)
    if packet_id in (PacketID.REQUEST, PacketID.HEARTBEAT_SET):
        return parse_packet_id(text)
    return _parse_byte(text)


def _parse_byte(text: str) -> int:
    try:
        v = int(text, 0)
    except ValueError:
        raise ArmError(f"{text!r} is not a byte value (0-255, decimal or 0x..)") from None
    if not 0 <= v <= 0xFF:
        raise ArmError(f"byte value {v} out of range 0-255")
    return v


def _bpl_encode(args: argparse.Namespace) -> int:
    from pugsd.arm.protocol import (
        PACKET_SPECS,
        Packet,
        encode_frame,
        make_packet,
        parse_device_id,
        parse_packet_id,
    )

    dev = parse_device_id(args.device)
    pid = parse_packet_id(args.packet)
    spec = PACKET_SPECS.get(pid)
    if spec is None:  # an id without a known layout: raw bytes
        pk = Packet(dev, pid, bytes(_parse_byte(v) for v in args.values))
    elif spec.kind == "ascii":
        pk = make_packet(dev, pid, " ".join(args.values))
    else:
        pk = make_packet(dev, pid, [_parse_value(v, spec.kind, pid) for v in args.values])
    _out(encode_frame(pk).hex(" ").upper())
    return 0


def _bpl_decode(args: argparse.Namespace) -> int:
    from pugsd.arm.protocol import StreamDecoder, packet_to_json

    # "09 9E ..", "0x09 0x9E ..", "09:9E", "099E..." (a 0x prefix is allowed on every token)
    tokens = re.split(r"[\s,:]+", " ".join(args.hex).strip())
    text = "".join(t[2:] if t[:2].lower() == "0x" else t for t in tokens if t)
    try:
        data = bytes.fromhex(text)
    except ValueError as exc:
        raise ArmError(f"not hex: {exc}") from None
    dec = StreamDecoder()
    pk = dec.feed(data)
    if data and not data.endswith(b"\x00"):
        pk += dec.feed(b"\x00")  # accept a single frame given without its terminator
    out = {"packets": [packet_to_json(p) for p in pk], "decoder": dec.stats.as_dict()}
    _out(json.dumps(out, indent=2))
    return 0 if pk else 1


# ---------------------------------------------------------------- arm sim


async def _sim_main(
    cfg: Any, transport: str, duration: float | None, port: int | None, object_mm: float | None = None
) -> None:
    from pugsd.arm.sim import close_pty, make_pty_pair, sim_from_config
    from pugsd.arm.transport import CanTransport, FdStreamTransport, UdpTransport, can_mapping

    master: int | None = None
    if transport == "serial":
        master, path = make_pty_pair()
        tr: Any = FdStreamTransport(master)
        where = f"serial pty {path}  (use --set arm.serial.port={path})"
    elif transport == "udp":
        tr = UdpTransport(None, (cfg.sim.udp_host, cfg.sim.udp_port if port is None else port))
        await tr.open()
        host, p = tr.local_address
        # everything a client needs: the default arm.transport is serial, and the default
        # arm.udp.local_host binds every interface, which a simulator on loopback does not need
        local = " --set arm.udp.local_host=127.0.0.1" if host == "127.0.0.1" else ""
        where = (
            f"udp {host}:{p}  (use --set arm.transport=udp --set arm.udp.host={host} "
            f"--set arm.udp.port={p}{local})"
        )
    else:
        c = cfg.can
        if c.interface == "virtual":
            log.warning("the virtual CAN interface only reaches buses in the same process")
        tr = CanTransport(
            interface=c.interface,
            channel=c.channel,
            bitrate=c.bitrate,
            mapping=can_mapping(c),
            role="arm",
            reassembly_timeout_s=c.reassembly_timeout_s,
        )
        where = f"can {c.interface}:{c.channel}"
    sim = sim_from_config(cfg, tr)
    sim.jaw_block_mm = object_mm
    await sim.start()
    held = "" if object_mm is None else f"; an object stops the jaw at {object_mm} mm"
    _out(f"simulated Bravo 7 listening on {where}{held}")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    try:
        if duration is None:
            await stop.wait()
        else:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(duration):  # not wait_for: it can swallow a cancel
                    await stop.wait()
    finally:
        await sim.close()
        if master is not None:
            close_pty(master)


def _arm_sim(args: argparse.Namespace) -> int:
    cfg = _load(args).arm
    if args.object_mm is not None:
        lo, hi = sorted((cfg.motion.jaw_closed_mm, cfg.motion.jaw_open_mm))
        if not lo <= args.object_mm <= hi:
            raise ArmError(f"--object-mm {args.object_mm} is outside the jaw's range [{lo}, {hi}] mm")
        if cfg.motion.jaw_open_mm < cfg.motion.jaw_closed_mm:
            raise ArmError("--object-mm needs a jaw numbered open > closed (the simulator's jaw is)")
    _run(_sim_main(cfg, args.transport or cfg.transport, args.duration, args.port, args.object_mm))
    return 0


# ---------------------------------------------------------------- arm status / stop / execute


async def _status_main(cfg: Any, wait: float) -> dict[str, Any]:
    from pugsd.arm.controller import ArmController

    ctl = ArmController(cfg)
    await ctl.link.start()  # no watchdog: status only listens and polls, it never commands
    try:
        t_end = time.monotonic() + wait
        while time.monotonic() < t_end and not ctl.link.have_feedback():  # noqa: ASYNC110
            await asyncio.sleep(0.02)
        from pugsd.arm.protocol import JOINT_DEVICES, PacketID

        for d in JOINT_DEVICES:  # one device at a time (RS-485 safe)
            await ctl.link.request(d, [PacketID.POSITION_LIMITS], within_s=0.1)
        # the first poll also requested HARDWARE_STATUS_FLAGS (per device on RS-485)
        await asyncio.sleep(min(0.2, wait))
        return ctl.status()
    finally:
        await ctl.link.close()


def _format_status(st: dict[str, Any]) -> str:
    # arm.enabled gates pugsd's motion commands; "DISABLED" alone read like the arm's DISABLE mode
    gate = "motion enabled" if st["enabled"] else "motion disabled in pugsd (arm.enabled = false)"
    lines = [f"arm: {gate}, over {st['transport']}, state {st['state']}"]
    lk = st["link"]
    age = lk["feedback_age_s"]
    # before any reply the age counts from the connection: say that nothing came back instead
    fb = f"oldest feedback {age * 1000:.0f} ms" if lk["rx_packets"] else "NO REPLY from the arm"
    lines.append(
        f"link: rx {lk['rx_packets']} packets, {lk['rx_crc_errors']} CRC errors, "
        f"{lk['rx_framing_errors']} framing errors, tx {lk['tx_packets']}, "
        f"{fb}" + (f", error: {lk['error']}" if lk["error"] else "")
    )
    for j in st["joints"]:
        pos = "   --   " if j["position"] is None else f"{j['position']:8.4f} {j['unit']}"
        if j.get("invalid"):
            pos = f"INVALID ({j['invalid']} not finite)"
        flags = ",".join(j["flags"]) or "-"
        lim = j.get("device_limits")
        lims = f"  limits [{lim[0]:.3f}, {lim[1]:.3f}]" if lim else ""
        lines.append(f"  0x{j['device_id']:02X} {j['name']:<15} {pos}  mode {j['mode']}  flags {flags}{lims}")
    if st["tcp_base"]:
        x, y, z = st["tcp_base"]["xyz_m"]
        lines.append(f"TCP (base frame, our FK): {x:.4f} {y:.4f} {z:.4f} m")
    if st["watchdog"]["tripped"]:
        lines.append(f"watchdog: TRIPPED ({st['watchdog']['tripped']})")
    return "\n".join(lines)


def _arm_status(args: argparse.Namespace) -> int:
    cfg = _load(args).arm
    st = _run(_status_main(cfg, args.wait))
    _out(json.dumps(st, indent=2, default=float) if args.json else _format_status(st))
    return 0 if st["link"]["rx_packets"] else 1


async def _stop_main(cfg: Any) -> None:
    from pugsd.arm.controller import ArmController

    ctl = ArmController(cfg)
    await ctl.link.start()
    try:
        # no latch: it would die with this process (the daemon's arm/stop latches its own)
        await ctl.stop(reason="pugsd arm stop", latch=False)
        await asyncio.sleep(0.05)
        await ctl.stop(reason="pugsd arm stop (repeat)", latch=False)
        with contextlib.suppress(Exception):
            flush = getattr(ctl.link.transport, "flush", None)
            if flush is not None:
                await flush(0.5)
    finally:
        await ctl.link.close()


def _stop_via_daemon(full_cfg: Any, timeout: float) -> str:
    """The daemon's ``<prefix>/arm/stop``: it aborts its motion, stops the arm and latches."""
    key = f"{full_cfg.daemon.prefix}/arm/stop"
    data, errors = query_daemon(full_cfg, "arm/stop", timeout)
    if data is None:
        detail = (
            f": {'; '.join(errors)}"
            if errors
            else " (is the daemon running, with [arm] enabled = true, on these zenoh endpoints?)"
        )
        raise ArmError(f"no reply from {key}{detail}")
    return data.decode("utf-8", "replace")


def _arm_stop(args: argparse.Namespace) -> int:
    full = _load(args)
    cfg = full.arm
    if args.via != "daemon":
        try:
            _run(_stop_main(cfg))  # stopping is always allowed, even with arm.enabled = false
        except PortInUseError as exc:
            if args.via == "link":
                raise
            # the daemon holds the serial port: it is the one that can stop the arm
            sys.stderr.write(f"pugsd arm stop: {exc}\npugsd arm stop: stopping through the daemon\n")
        else:
            _out(f"sent zero velocity and {cfg.safety.safe_mode} to all devices")
            return 0
    _out(f"daemon: {_stop_via_daemon(full, args.timeout)}")
    return 0


def _arm_safe(args: argparse.Namespace) -> int:
    from pugsd.arm.safe import run_safe

    return run_safe(_load(args).arm)  # always allowed, even with arm.enabled = false


def fetch_latest_grasps(full_cfg: Any, timeout: float = 2.0) -> Any:
    """The daemon's latest grasps from its zenoh queryable ``<prefix>/grasps/latest``."""
    from pugsd.wire.codec import decode_grasp_array as decode

    data, errors = query_daemon(full_cfg, "grasps/latest", timeout)
    if data is None:
        detail = f": {'; '.join(errors)}" if errors else " (is the daemon running?)"
        raise ArmError(f"no grasps from {full_cfg.daemon.prefix}/grasps/latest{detail}")
    return decode(data)


def _pose_matrix(vals: list[float]) -> np.ndarray:
    from pugsd.arm.kinematics import pose_from_xyz_quat

    q = np.asarray(vals[3:7], dtype=float)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or abs(n - 1.0) > 1e-3:
        raise ArmError(f"--pose quaternion must be unit length (norm {n:.4f})")
    return pose_from_xyz_quat(vals[:3], q / n)


async def _execute_main(cfg: Any, T: np.ndarray, frame: str, width: float, grasp_id: int) -> dict[str, Any]:
    from pugsd.arm.controller import ArmController
    from pugsd.arm.safe import ArmGuard

    # before the link opens: if this process ends without its own stop (SIGKILL, the OOM
    # killer), the guard sends it
    guard = ArmGuard.start(cfg)
    safe = True  # nothing has been sent that could move the arm
    try:
        ctl = ArmController(cfg)
        await ctl.start()
        safe = False
        try:
            await ctl.wait_for_feedback(3.0)
            if frame == "world":
                rep = await ctl.execute_grasp(T_W_G=T, width_m=width, grasp_id=grasp_id)
            else:
                rep = await ctl.execute_grasp(T_B_G=T, width_m=width, grasp_id=grasp_id)
            return rep.to_dict()
        finally:
            # zero velocity and the safe mode; if they were not written (a congested link, a
            # cancel while stopping), the guard sends them
            safe = await ctl.close()
    finally:
        if safe:
            guard.release()
        else:
            guard.trigger()


def _arm_execute(args: argparse.Namespace) -> int:
    full = _load(args)
    cfg = full.arm
    if not cfg.enabled:
        raise ArmError("the arm is disabled in the config (arm.enabled = false); nothing was sent")
    if args.pose is not None:
        T = _pose_matrix(args.pose)
        width = args.width if args.width is not None else 0.05
        gid = -1
    else:
        grasps = fetch_latest_grasps(full, args.timeout)
        ids = [int(g) for g in np.asarray(grasps.grasp_id)]
        if args.grasp_id not in ids:
            raise ArmError(f"grasp id {args.grasp_id} is not among the latest grasps {ids}")
        k = ids.index(args.grasp_id)
        T = np.asarray(grasps.pose_W[k], dtype=float)
        width = float(grasps.width_m[k]) if args.width is None else args.width
        gid = args.grasp_id
        if args.frame != "world":
            raise ArmError("--grasp-id poses are in the world frame; --frame base applies to --pose")
    # Ctrl-C (or kill -INT) must stop the arm even when this process was started with SIGINT
    # ignored (a job in the background of a non-interactive shell): Python then installs no
    # KeyboardInterrupt handler, and the motion would run on to its end
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    rep = _run(_execute_main(cfg, T, args.frame, width, gid))
    if args.json:
        _out(json.dumps(rep, indent=2, default=float))
    else:
        _out(
            f"grasp {gid}: {'OK' if rep['ok'] else 'FAILED'} in {rep['duration_s']:.2f} s"
            + (f" ({rep['reason']})" if rep["reason"] else "")
        )
        for ph in rep["phases"]:
            _out(f"  {ph['name']:<9} {ph['duration_s']:.2f} s  converged={ph['converged']}")
        if rep["grip"]:
            at = f" (the close stopped it at {rep['grip_mm']:.2f} mm)" if rep["grip_mm"] is not None else ""
            _out(f"  jaw: {_GRIP_TEXT.get(rep['grip'], rep['grip'])}{at}")
        if rep["grasp_pose_error_mm"] is not None:
            _out(
                f"  grasp pose error {rep['grasp_pose_error_mm']:.2f} mm / "
                f"{rep['grasp_pose_error_deg']:.2f} deg (convergence tolerance allows "
                f"{rep['grasp_pose_error_bound_mm']:.2f} mm / {rep['grasp_pose_error_bound_deg']:.2f} deg)"
            )
    if not rep["ok"]:
        return 2
    return 3 if rep["holding"] is False else 0


_GRIP_TEXT = {
    "held": "holding the object",
    "empty": "holds nothing: it closed fully (missed, or the object slipped out in the close)",
    "dropped": "holds nothing: it gripped, then closed fully during the lift (object lost)",
    "unknown": "no jaw position reported: whether it holds the object is unknown",
}


# ---------------------------------------------------------------- registration


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    arm = sub.add_parser("arm", help="Reach Bravo 7 arm: sim, status, execute, stop, safe")
    arm_sub = arm.add_subparsers(dest="arm_command", required=True, metavar="ARM_COMMAND")

    p = arm_sub.add_parser(
        "sim",
        help="run the simulated Bravo 7 (pty, UDP or CAN)",
        epilog="example:\n  pugsd arm sim --transport udp --duration 60",
    )
    _add_config_args(p)
    p.add_argument(
        "--transport",
        choices=("serial", "udp", "can"),
        default=None,
        help="default: arm.transport (serial creates a pseudo-terminal)",
    )
    p.add_argument("--port", type=int, default=None, help="UDP port (default arm.sim.udp_port)")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        help="exit after this many seconds (default: run until stopped)",
    )
    p.add_argument(
        "--object-mm",
        type=float,
        default=None,
        help="an object between the fingers stops the closing jaw at this position (mm); "
        "default: nothing to grip",
    )
    p.set_defaults(func=_arm_sim)

    p = arm_sub.add_parser(
        "status",
        help="joint positions, modes, flags and link health",
        epilog="example:\n  pugsd arm status --config /etc/pugsd/pugsd.toml",
    )
    _add_config_args(p)
    p.add_argument("--json", action="store_true", help="print the status as JSON")
    p.add_argument("--wait", type=float, default=1.0, help="seconds to wait for feedback")
    p.set_defaults(func=_arm_status)

    p = arm_sub.add_parser(
        "execute",
        help="execute one grasp (needs arm.enabled = true)",
        epilog="example:\n  pugsd arm execute --grasp-id 3",
    )
    _add_config_args(p)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--grasp-id", type=int, help="a grasp id from the daemon's latest grasps")
    g.add_argument(
        "--pose",
        type=float,
        nargs=7,
        metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
        help="grasp pose (Contact-GraspNet convention: z approach, x baseline)",
    )
    p.add_argument(
        "--width",
        type=float,
        default=None,
        help="grasp width in m (default: the grasp's own width with --grasp-id, 0.05 with --pose)",
    )
    p.add_argument(
        "--frame",
        choices=("world", "base"),
        default="world",
        help="frame of --pose (world is mapped with arm.kinematics.T_B_W)",
    )
    p.add_argument("--timeout", type=float, default=2.0, help="daemon query timeout (s)")
    p.add_argument("--json", action="store_true", help="print the outcome as JSON")
    p.set_defaults(func=_arm_execute)

    p = arm_sub.add_parser(
        "stop",
        help="zero velocity and the safe mode to all devices",
        description="Stop the arm: zero velocity and the safe mode to every device, sent over the "
        "configured link. When the serial port is held by a running daemon, the stop goes "
        "through the daemon's <prefix>/arm/stop instead (it aborts its motion and latches the "
        "stop until <prefix>/arm/release).",
        epilog="example:\n  pugsd arm stop",
    )
    _add_config_args(p)
    p.add_argument(
        "--via",
        choices=("auto", "link", "daemon"),
        default="auto",
        help="auto: the link, or the daemon when it holds the serial port; link: the link only; "
        "daemon: the daemon's <prefix>/arm/stop only",
    )
    p.add_argument("--timeout", type=float, default=2.0, help="daemon query timeout (s)")
    p.set_defaults(func=_arm_stop)

    p = arm_sub.add_parser(
        "safe",
        help="zero velocity and the safe mode to all devices over the link; wait for them to report it",
        description="Send zero velocity and the safe mode (arm.safety.safe_mode) to every device "
        "over the configured link only, retrying for up to 2 s while the serial port is still "
        "locked by a process that just ended, then ask every axis for its mode for up to 0.5 s. "
        "Exit 0 when every axis reports the safe mode, 2 when the stop was sent but not every "
        "axis confirmed it, 1 when the link could not be opened. The systemd arm drop-in runs it "
        "(as python -m pugsd.arm.safe, which starts faster) after every end of pugsd run.",
        epilog="example:\n  pugsd arm safe --config /etc/pugsd/pugsd.toml",
    )
    _add_config_args(p)
    p.set_defaults(func=_arm_safe)

    bpl = sub.add_parser("bpl", help="Reach BPL packet tools: encode, decode")
    bpl_sub = bpl.add_subparsers(dest="bpl_command", required=True, metavar="BPL_COMMAND")
    p = bpl_sub.add_parser(
        "encode",
        help="print the wire bytes of one packet in hex",
        epilog="example:\n  pugsd bpl encode jaw position 5.0",
    )
    p.add_argument("device", help="device id or name (0x01, jaw, G, broadcast, compute)")
    p.add_argument("packet", help="packet id or name (0x03, position, request)")
    p.add_argument(
        "values",
        nargs="*",
        help="floats for float packets; bytes (or mode/packet names) for byte packets",
    )
    p.set_defaults(func=_bpl_encode)
    p = bpl_sub.add_parser(
        "decode",
        help="decode wire bytes (hex) to JSON",
        epilog="example:\n  pugsd bpl decode 01 01 07 A0 40 03 01 08 3F 00",
    )
    p.add_argument("hex", nargs="+", help="hex bytes, spaces allowed")
    p.set_defaults(func=_bpl_decode)


__all__ = ["fetch_latest_grasps", "query_daemon", "register"]
