# SPDX-License-Identifier: Apache-2.0
"""The MCAP player: publishes recorded payloads verbatim on their zenoh keys (or remapped ones)
with fresh rmw_zenoh attachments, paced by ``log_time``."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from pugsd.errors import ConfigError, DecodeError
from pugsd.record.mcapio import RecordedMessage, iter_recording, scan, time_range
from pugsd.wire.keys import dds_type_name, parse_key, strip_topic, topic_key
from pugsd.wire.publisher import Publisher

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlayOptions:
    """``rate``: 1 real time, 0.5 half speed, 0 as fast as possible. ``start_s``/``end_s`` are
    offsets from the first message of the recording. ``topics``: only these ROS topics.
    ``remap``: ROS topic -> new ROS topic (topic names are normalised to one leading '/').
    ``key_style``/``domain_id``: when either is set (or a topic is remapped), keys are rebuilt
    from topic and type instead of the recorded keys; a recorded rmw_zenoh type hash is kept,
    ``hash_mode`` applies to keys rebuilt without one."""

    rate: float = 1.0
    start_s: float = 0.0
    end_s: float | None = None
    topics: tuple[str, ...] | None = None
    remap: Mapping[str, str] = field(default_factory=dict)
    loop: bool = False
    key_style: str | None = None
    domain_id: int | None = None
    hash_mode: str = "rihs01"

    def __post_init__(self) -> None:
        if not self.rate >= 0:
            raise ConfigError(f"--rate must be >= 0, got {self.rate}")
        if self.start_s < 0 or (self.end_s is not None and self.end_s <= self.start_s):
            raise ConfigError(f"bad start/end offsets {self.start_s} .. {self.end_s}")
        # frozen: normalise in place (`--topic camera_pose` is `/camera_pose`, as for --remap)
        if self.topics is not None:
            object.__setattr__(self, "topics", tuple("/" + strip_topic(t) for t in self.topics))
        remap = {"/" + strip_topic(a): "/" + strip_topic(b) for a, b in self.remap.items()}
        object.__setattr__(self, "remap", remap)


@dataclass
class PlayProgress:
    published: int
    position_s: float  # log time of the last message since the recording's start
    duration_s: float
    loop: int


def parse_remap(items: Iterable[str]) -> dict[str, str]:
    """``/a:=/b`` pairs (as ``ros2 bag play --remap``)."""
    out = {}
    for it in items:
        if ":=" not in it:
            raise ConfigError(f"remap {it!r}: expected OLD:=NEW")
        a, b = it.split(":=", 1)
        out["/" + strip_topic(a)] = "/" + strip_topic(b)
    return out


def output_key(msg: RecordedMessage, opts: PlayOptions) -> str:
    """The key to publish a recorded message on: the recorded key unless the topic is remapped
    or ``key_style``/``domain_id`` is set; a rebuilt rmw_zenoh key keeps the recorded type hash
    (e.g. Humble's ``TypeHashNotSupported``) when the recorded key has one for the same type."""
    topic = opts.remap.get(msg.topic, msg.topic)
    if opts.key_style is None and opts.domain_id is None and topic == msg.topic and msg.key:
        return msg.key
    style, domain = opts.key_style, opts.domain_id
    recorded_hash = None
    if msg.key:
        try:
            info = parse_key(msg.key)
            style = style or "rmw_zenoh"
            domain = info.domain_id if domain is None else domain
            if info.typename == msg.typename:
                recorded_hash = info.type_hash
        except DecodeError:
            style = style or "ros2dds"
    style = style or "rmw_zenoh"
    if style == "rmw_zenoh" and recorded_hash is not None:
        return f"{domain or 0}/{strip_topic(topic)}/{dds_type_name(msg.typename)}/{recorded_hash}"
    return topic_key(topic, msg.typename, domain_id=domain or 0, key_style=style,
                     hash_mode=opts.hash_mode)  # fmt: skip


class Player:
    """Publish the messages of one or more MCAP files (merged by log time) on zenoh."""

    def __init__(
        self,
        session: Any,
        files: Sequence[str | Path],
        options: PlayOptions | None = None,
        *,
        progress: Callable[[PlayProgress], None] | None = None,
        progress_interval_s: float = 1.0,
        stop_event: threading.Event | None = None,
        wait_for_subscribers_s: float = 0.0,
    ) -> None:
        if not files:
            raise ConfigError("play: no files")
        self.session = session
        self.files = [Path(f) for f in files]
        self.opts = options or PlayOptions()
        self.progress = progress
        self.progress_interval_s = progress_interval_s
        self.stop_event = stop_event or threading.Event()
        self.wait_for_subscribers_s = wait_for_subscribers_s
        self._pubs: dict[str, Publisher] = {}
        self.published = 0
        self.unheard = 0  # of those, published while no subscriber matched their key

    def _publisher(self, key: str) -> Publisher:
        pub = self._pubs.get(key)
        if pub is None:
            pub = Publisher(self.session, key, congestion_control=zenoh.CongestionControl.BLOCK)
            self._pubs[key] = pub
            deadline = time.monotonic() + self.wait_for_subscribers_s
            while not pub.matching and time.monotonic() < deadline:
                if self.stop_event.wait(0.01):
                    break
        return pub

    def run(self) -> int:
        """Play (looping if asked) until done or ``stop_event``; returns messages published.
        ConfigError ("nothing to play") when a pass selects no message (so ``loop`` cannot spin)."""
        t_first, t_last = time_range(self.files)
        start = t_first + int(self.opts.start_s * 1e9)
        end = None if self.opts.end_s is None else t_first + int(self.opts.end_s * 1e9)
        duration = ((t_last if end is None else min(end, t_last)) - t_first) / 1e9
        loop = 0
        try:
            while not self.stop_event.is_set():
                before = self.published
                self._play_once(start, end, t_first, duration, loop)
                if self.published == before and not self.stop_event.is_set():
                    raise ConfigError(self._nothing_to_play())
                loop += 1
                if not self.opts.loop:
                    break
        finally:
            for pub in self._pubs.values():
                pub.undeclare()
            self._pubs.clear()
        return self.published

    def selected_topics(self) -> set[str]:
        """The recorded topics this play publishes (before remapping): in the files, selected
        by ``topics``."""
        recorded = {c.topic for f in self.files for c in scan(f).channels}
        return recorded if self.opts.topics is None else recorded & set(self.opts.topics)

    def played_topics(self, among: Iterable[str]) -> list[str]:
        """The topics of ``among`` that this play publishes, as published (after remapping)."""
        wanted = {"/" + strip_topic(t) for t in among}
        return sorted({self.opts.remap.get(t, t) for t in self.selected_topics()} & wanted)

    def _nothing_to_play(self) -> str:
        o = self.opts
        names = ", ".join(str(f) for f in self.files)
        what = "all topics" if o.topics is None else "topics " + ", ".join(o.topics)
        window = f"{o.start_s:g} s .. " + ("end" if o.end_s is None else f"{o.end_s:g} s")
        recorded = sorted({c.topic for f in self.files for c in scan(f).channels})
        return (f"nothing to play: no message in {names} for {what} in the window {window} "
                f"(recorded topics: {', '.join(recorded) or 'none'})")  # fmt: skip

    def _play_once(self, start: int, end: int | None, t_first: int, duration: float, loop: int) -> None:
        rate = self.opts.rate
        wall0: float | None = None
        log0 = 0
        last_progress = time.monotonic()
        topics = None if self.opts.topics is None else list(self.opts.topics)
        for msg in iter_recording(self.files, topics, start, end):
            if self.stop_event.is_set():
                return
            key = output_key(msg, self.opts)
            pub = self._publisher(key)
            if wall0 is None:
                wall0, log0 = time.monotonic(), msg.log_time_ns
            if rate > 0:
                due = wall0 + (msg.log_time_ns - log0) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0 and self.stop_event.wait(delay):
                    return
            pub.put(msg.data)
            self.published += 1
            self.unheard += not pub.matching
            now = time.monotonic()
            if self.progress is not None and now - last_progress >= self.progress_interval_s:
                last_progress = now
                self.progress(PlayProgress(self.published, (msg.log_time_ns - t_first) / 1e9, duration, loop))
        if self.progress is not None:
            self.progress(PlayProgress(self.published, duration, duration, loop))
