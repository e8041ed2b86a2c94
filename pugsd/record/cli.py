# SPDX-License-Identifier: Apache-2.0
"""Subcommands: ``record``, ``play``, ``replay``, ``mcap recover|info|synth``."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from pugsd import exit_codes
from pugsd.config import PugsdConfig, dump_config, load_config
from pugsd.errors import ConfigError, PugsdError
from pugsd.progress import progress_bar


def _load(args: argparse.Namespace) -> PugsdConfig:
    return load_config(getattr(args, "config", None), getattr(args, "set", None) or ())


def _open_tool_session(args: argparse.Namespace, cfg: PugsdConfig) -> Any:
    from pugsd.wire.session import open_session, tool_config

    zc = tool_config(cfg.zenoh, args.connect, args.listen)
    return open_session(zc, require_loopback=True)


def _open_record_session(
    args: argparse.Namespace, cfg: PugsdConfig, stop: threading.Event, deadline: float | None
) -> Any:
    """The recorder's session: a zenoh client of the daemon (it hears what every session linked to
    the daemon publishes), waiting until something listens there; None if stopped first."""
    from pugsd.wire.session import open_session, open_session_waiting, tool_config

    zc = tool_config(cfg.zenoh, args.connect, args.listen, client=True)
    if zc["mode"] != "client":  # it listens: a peer, which cannot wait for anyone
        return open_session(zc, require_loopback=True)

    def waiting(error: str) -> None:
        asked = ", ".join(zc["connect"]["endpoints"])
        sys.stderr.write(f"pugsd record: nothing listens at {asked} yet; waiting\n")
        sys.stderr.flush()

    return open_session_waiting(zc, stop, deadline=deadline, on_wait=waiting)


def _stop_on_signals() -> threading.Event:
    ev = threading.Event()

    def handler(signum: int, frame: Any) -> None:
        ev.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    return ev


# ------------------------------------------------------------------------------ record


def _record(args: argparse.Namespace) -> int:
    import dataclasses

    from pugsd.record.recorder import Recorder, default_record_keys, watched_topics
    from pugsd.wire.session import close_session
    from pugsd.wire.topics import topic_types

    cfg = _load(args)
    rc = cfg.record
    if args.prefix:
        rc = dataclasses.replace(rc, name_prefix=args.prefix)
    keys = list(args.key) if args.key else default_record_keys(cfg)
    t = cfg.topics
    stop = _stop_on_signals()
    t_end = None if args.duration is None else time.monotonic() + args.duration
    session = _open_record_session(args, cfg, stop, t_end)  # None: stopped before a daemon came
    inputs, outputs = watched_topics(cfg, keys)
    rec = Recorder(
        rc,
        directory=args.out or rc.directory,
        queue_size=cfg.queues.record,
        topic_types=topic_types(t),
        metadata={"pugsd.config": {"toml": dump_config(cfg), "keys": json.dumps(keys)}},
        input_topics=inputs,
        output_topics=outputs,
    )
    rec.start()
    try:  # the session is closed and the recorder stopped whatever happens from here
        if rec.stats.error:
            raise ConfigError(str(rec.stats.error))
        if session is not None:
            rec.subscribe(session, keys)  # ConfigError naming a key zenoh refuses
            sys.stderr.write(f"pugsd record: {len(keys)} key expressions -> {rec.directory}\n")
            sys.stderr.flush()
        tick = min(1.0, args.status_interval) if args.status_interval > 0 else 1.0
        next_status = time.monotonic() + args.status_interval
        while not stop.is_set():
            timeout = tick if t_end is None else min(tick, t_end - time.monotonic())
            if timeout <= 0:
                break
            stop.wait(timeout)
            if args.status_interval > 0 and time.monotonic() >= next_status:
                next_status += args.status_interval
                s = rec.stats
                sys.stderr.write(
                    f"pugsd record: status received={s.received} written={s.written} "
                    f"buffered={s.buffered} dropped={s.dropped_queue + s.dropped_error} "
                    f"files={s.files_finished} inputs={s.inputs_received} outputs={s.outputs_received} "
                    f"error={s.error or '-'}\n"
                )
                sys.stderr.flush()
    finally:
        rec.unsubscribe()
        files = rec.stop()
        if session is not None:
            close_session(session)
    s = rec.stats
    sys.stderr.write(
        f"pugsd record: {s.written} written, {s.dropped_queue} dropped (slow disk), "
        f"{s.dropped_error} dropped (disk error), {s.dropped_invalid} dropped (time or sequence out of "
        f"range), {s.unknown_type} of unknown type, {s.deletes} zenoh deletes skipped, "
        f"{s.callback_errors} lost to callback errors\n"
    )
    if s.received == 0:  # nothing came: nobody publishing, or not where it asked
        from pugsd.wire.session import tool_config

        asked = ", ".join(tool_config(cfg.zenoh, args.connect, args.listen)["connect"]["endpoints"])
        sys.stderr.write(
            f"pugsd record: no message received (is anything publishing on these keys, reachable at "
            f"{asked or 'the listen endpoints'}?)\n"
        )
    if s.missing_inputs:
        sys.stderr.write(
            f"pugsd record: warning: {s.outputs_received} messages on the daemon's outputs and none on "
            "its inputs: this recording cannot be replayed (no camera or pose reached this recorder, "
            "or none was sent while it ran)\n"
        )
    for f in files:
        sys.stdout.write(f"{f}\n")
    if s.error:
        sys.stderr.write(f"pugsd record: error: {s.error}\n")
        return exit_codes.FAILURE
    if s.missing_inputs and args.require_inputs:
        sys.stderr.write("pugsd record: error: --require-inputs: no input recorded\n")
        return exit_codes.FAILURE
    return exit_codes.NO_PEER if s.received == 0 else exit_codes.OK


# ------------------------------------------------------------------------------ play


def _play(args: argparse.Namespace) -> int:
    from pugsd.record.player import Player, PlayOptions, PlayProgress, parse_remap
    from pugsd.wire.session import close_session, tool_config
    from pugsd.wire.topics import INPUT_ROLES, OUTPUT_ROLES

    cfg = _load(args)
    topics = tuple(args.topic) if args.topic else None
    if args.inputs_only:
        if topics is not None:
            raise ConfigError("--inputs-only and --topic exclude each other")
        topics = tuple(getattr(cfg.topics, r) for r in INPUT_ROLES)
    opts = PlayOptions(
        rate=args.rate,
        start_s=args.start,
        end_s=args.end,
        topics=topics,
        remap=parse_remap(args.remap or ()),
        loop=args.loop,
        key_style=args.key_style,
        domain_id=args.domain,
        hash_mode=cfg.topics.hash_mode,
    )
    for f in args.files:
        if not Path(f).is_file():
            raise ConfigError(f"no such file {f}")
    bars: list[Any] = []  # drawn from the first progress on, below the warnings said before

    def progress(p: PlayProgress) -> None:
        if not bars:  # seconds of the recording
            bars.append(progress_bar(round(p.duration_s, 1), "play", unit="s", quiet=args.quiet))
        bars[0].n = round(p.position_s, 1)
        bars[0].set_postfix_str(f"{p.published} msgs" + (f", loop {p.loop}" if args.loop else ""))

    stop = _stop_on_signals()
    session = _open_tool_session(args, cfg)
    try:
        player = Player(
            session, args.files, opts, progress=progress, stop_event=stop,
            wait_for_subscribers_s=args.wait_subscribers,
        )  # fmt: skip
        unknown = sorted(set(opts.remap) - player.selected_topics())
        if unknown:  # a typo, or a topic the files do not have: nothing is renamed
            sys.stderr.write(
                f"pugsd play: warning: --remap {', '.join(unknown)}: not among the topics played\n"
            )
        outputs = player.played_topics(getattr(cfg.topics, r) for r in OUTPUT_ROLES)
        if outputs:  # a daemon's recording played whole into a running daemon: its old grasps go out
            sys.stderr.write(
                f"pugsd play: warning: playing pugsd's outputs too ({', '.join(outputs)}): next to a "
                "running daemon they mix with its own; --inputs-only plays its inputs alone\n"
            )
        n = player.run()
    finally:
        for bar in bars:
            bar.close()
        close_session(session)
    if n and player.unheard == n:
        asked = ", ".join(tool_config(cfg.zenoh, args.connect, args.listen)["connect"]["endpoints"])
        sys.stderr.write(
            f"pugsd play: {n} messages published, none of them to a subscriber (is anything "
            f"listening on {asked or 'the listen endpoints'}? --wait-subscribers S waits for one)\n"
        )
    elif player.unheard:
        sys.stderr.write(
            f"pugsd play: {n} messages published ({player.unheard} of them while nothing "
            "subscribed to their key)\n"
        )
    else:
        sys.stderr.write(f"pugsd play: {n} messages published\n")
    return exit_codes.NO_PEER if n == 0 or player.unheard == n else exit_codes.OK


# ------------------------------------------------------------------------------ replay


def _replay(args: argparse.Namespace) -> int:
    from pugsd.grasp_text import grasp_lines
    from pugsd.progress import ticking
    from pugsd.record.replay import count_left_images, replay

    cfg = _load(args)
    for f in args.files:
        if not Path(f).is_file():
            raise ConfigError(f"no such file {f}")
    total = count_left_images(args.files, cfg.topics) if sys.stderr.isatty() else None
    with ticking(progress_bar(total, f"replay ({args.mode})", unit="frame")) as bar:
        res = replay(args.files, cfg, out_dir=args.out, mode=args.mode, seed=args.seed,
                     on_frame=lambda: bar.update(1))  # fmt: skip
    sys.stdout.write(f"pugsd replay: {res.frames} frames, {len(res.grasps)} grasps\n")
    for line in grasp_lines(res.grasps, 5):
        sys.stdout.write(line + "\n")
    if res.json_path:
        sys.stdout.write(f"{res.json_path}\n{res.mcap_path}\n")
    return 0


# ------------------------------------------------------------------------------ mcap tools


def _recover(args: argparse.Namespace) -> int:
    from pugsd.record.mcapio import recover

    r = recover(args.input, args.output)
    sys.stdout.write(
        f"recovered {r.messages} messages on {r.channels} channels ({r.schemas} schemas, "
        f"{r.metadata} metadata) -> {args.output}\n"
        f"reading stopped: {r.error or 'input was complete'}\n"
    )
    return 0


def _info(args: argparse.Namespace) -> int:
    from pugsd.record.mcapio import scan

    infos, rc = [], 0
    for f in args.files:
        try:
            infos.append(scan(f))
        except PugsdError as exc:  # not an MCAP, unreadable: said, and the other files go on
            sys.stderr.write(f"pugsd mcap info: error: {exc}\n")
            rc = 1
    if args.json:
        sys.stdout.write(json.dumps([i.to_dict() for i in infos], indent=1) + "\n")
        return rc
    for i in infos:
        state = "complete" if i.complete else f"INCOMPLETE ({i.error})"
        sys.stdout.write(
            f"{i.path}: {i.size_bytes / 1e6:.2f} MB, {state}\n"
            f"  profile {i.profile!r}, library {i.library!r}\n"
            f"  {i.message_count} messages, {i.duration_s:.3f} s, {i.chunk_count} chunks\n"
        )
        for c in i.channels:
            sys.stdout.write(f"  {c.count:8d}  {c.topic}  [{c.typename}]\n")
        for name, enc in sorted(i.schemas.items()):
            sys.stdout.write(f"  schema {name} ({enc})\n")
        for name in sorted(i.metadata):
            sys.stdout.write(f"  metadata {name}: {', '.join(sorted(i.metadata[name]))}\n")
    return rc


def _synth(args: argparse.Namespace) -> int:
    from pugsd.record.synth import generate

    cfg = _load(args)
    n = generate(args.output, args.kind, args.object, args.frames, args.width, args.height,
                 args.seed, cfg.topics)  # fmt: skip
    sys.stdout.write(f"{args.output}: {n} messages ({args.kind}, {args.object})\n")
    return 0


def _add_cfg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None, help="pugsd TOML config (default: the built-in defaults)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config key (repeatable)")


def _add_net(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to (default: the config's listen endpoints)",
    )
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help="zenoh endpoint to listen on (default: none)")  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "record",
        help="record zenoh traffic (ROS 2 CDR) to MCAP",
        epilog="example:\n  pugsd record --out recordings --duration 60\n\n"
        "exit codes: 0 ok; 1 failure; 4 nothing received",
    )
    _add_cfg(p)
    _add_net(p)
    p.add_argument("--out", default=None, help="output directory (default: [record] directory)")
    p.add_argument("--key", action="append", help="key expression (default: [record] keys or "
                   "every [topics] input and output)")  # fmt: skip
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: at Ctrl-C or SIGTERM)")
    p.add_argument("--prefix", default=None, help="file name prefix (default: [record] name_prefix)")
    p.add_argument("--status-interval", type=float, default=10.0,
                   help="print counters to stderr this often [s]; 0: never")  # fmt: skip
    p.add_argument("--require-inputs", action="store_true",
                   help="exit 1 when the daemon's outputs were recorded but none of its inputs")  # fmt: skip
    p.set_defaults(func=_record)

    p = sub.add_parser(
        "play",
        help="publish MCAP recordings on zenoh",
        epilog="example:\n  pugsd play --inputs-only --rate 0.5 recordings/pugsd-0001.mcap\n\n"
        "exit codes: 0 ok; 1 failure; 4 nothing delivered (no message published, or none to a "
        "subscriber)",
    )
    _add_cfg(p)
    _add_net(p)
    p.add_argument("files", nargs="+", help="MCAP files, played one after the other")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor; 0 = as fast as possible")
    p.add_argument("--start", type=float, default=0.0, help="start offset [s]")
    p.add_argument("--end", type=float, default=None, help="end offset [s] (default: the end)")
    p.add_argument("--topic", action="append", help="only this ROS topic (repeatable)")
    p.add_argument("--inputs-only", action="store_true",
                   help="only the config's [topics] inputs (not a recorded daemon's outputs)")  # fmt: skip
    p.add_argument("--remap", action="append", metavar="OLD:=NEW", help="topic remap")
    p.add_argument("--loop", action="store_true", help="play the files again and again until stopped")
    p.add_argument("--key-style", choices=("rmw_zenoh", "ros2dds"), default=None,
                   help="rebuild keys in this style (default: the recorded keys)")  # fmt: skip
    p.add_argument("--domain", type=int, default=None,
                   help="ROS domain for rebuilt keys (default: the recorded keys' own)")
    p.add_argument("--wait-subscribers", type=float, default=0.0,
                   help="wait up to this long for a subscriber on each new key")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_play)

    p = sub.add_parser(
        "replay",
        help="run the pipeline on a recording (no zenoh)",
        epilog="example:\n  pugsd replay --out replayed recordings/pugsd-0001.mcap",
    )
    _add_cfg(p)
    p.add_argument("files", nargs="+", help="MCAP files, read as one recording")
    p.add_argument("--out", default=None,
                   help="write grasps.json and grasps.mcap here (default: print only)")
    p.add_argument("--mode", choices=("streaming", "paper"), default="streaming",
                   help="streaming: the daemon's SVGP updates after every frame; paper: the batch fit "
                   "on all frames")
    p.add_argument("--seed", type=int, default=0, help="seed of the model")
    p.set_defaults(func=_replay)

    p = sub.add_parser("mcap", help="MCAP tools: recover, info, synth")
    msub = p.add_subparsers(dest="mcap_command", required=True, metavar="TOOL")
    q = msub.add_parser(
        "recover",
        help="rebuild a file whose writer died",
        epilog="example:\n  pugsd mcap recover pugsd-0001.mcap.part pugsd-0001.mcap",
    )
    q.add_argument("input", help="the damaged MCAP (a .part left by a crash)")
    q.add_argument("output", help="the rebuilt MCAP to write")
    q.set_defaults(func=_recover)
    q = msub.add_parser(
        "info",
        help="topics, counts, duration, schemas",
        epilog="example:\n  pugsd mcap info recordings/*.mcap",
    )
    q.add_argument("files", nargs="+", help="MCAP files")
    q.add_argument("--json", action="store_true", help="print the summaries as JSON")
    q.set_defaults(func=_info)
    q = msub.add_parser(
        "synth",
        help="write a synthetic recording",
        epilog="example:\n  pugsd mcap synth mug.mcap --kind complete --object mug",
    )
    _add_cfg(q)
    q.add_argument("output", help="the MCAP file to write")
    q.add_argument("--kind", choices=("complete", "partial", "noisy_partial"), default="partial",
                   help="camera path around the object")
    q.add_argument("--object", default="mug", help="synthetic object (mug, kettlebell, box, bottle, mallet)")
    q.add_argument("--frames", type=int, default=None,
                   help="number of stereo frames (default: the trajectory's own)")
    q.add_argument("--width", type=int, default=160, help="image width [px]")
    q.add_argument("--height", type=int, default=120, help="image height [px]")
    q.add_argument("--seed", type=int, default=0, help="seed of the scene")
    q.set_defaults(func=_synth)
