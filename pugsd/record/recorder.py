# SPDX-License-Identifier: Apache-2.0
"""The MCAP recorder: zenoh samples (or in-process messages) -> rotating ``ros2`` MCAP files.

Threading: :meth:`Recorder.put` and the zenoh callback only append to a bounded in-memory queue
(count and byte bounds, the message being written included; the oldest message is dropped and
counted when full), so recording never blocks the caller. One writer thread owns the MCAP writer:
it takes one message at a time, writes ZSTD chunks, closes the open chunk every
``flush_interval_s``, rotates files by size and duration, writes each file as ``NAME.mcap.part``
and renames it to ``NAME.mcap`` when finished. A file name is never reused: the ``.part`` is
created exclusively and the index bumped while a ``.part`` or ``.mcap`` of that name exists (two
recorders started in the same second in one directory), and a finished file never replaces one.
``stats.written`` counts messages whose chunk reached the file; ``stats.buffered`` those in the
open chunk. An ``OSError`` from the disk (``ENOSPC`` included) is logged and reported in
:attr:`Recorder.stats`; the messages of the lost chunk and everything after are counted as
dropped instead of crashing the host. Times and sequence numbers are checked against MCAP's
unsigned fields before a message reaches the writer: one bad value must not corrupt a chunk."""

from __future__ import annotations

import collections
import contextlib
import errno
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from mcap.opcode import Opcode
from mcap.writer import Writer

from pugsd.configbase import to_dict
from pugsd.errors import ConfigError, DecodeError
from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import ChannelTable, metadata_json, new_writer, versions
from pugsd.wire.attachment import decode_attachment
from pugsd.wire.keys import parse_key, strip_topic
from pugsd.wire.types import known_type

log = logging.getLogger(__name__)

Opener = Callable[[Path], IO[bytes]]

#: outputs seen on this many messages and not one input: the recorder warns (a grasp round is a
#: few messages, and a recording started mid-run may see one before the next camera frame)
OUTPUTS_BEFORE_WARNING = 10
#: the [topics] outputs a daemon computes from its inputs (its status goes out while idle too)
DERIVED_OUTPUT_ROLES = ("grasps", "markers", "cloud")

U64_MAX = 2**64 - 1  # MCAP log_time / publish_time are uint64
U32_MAX = 2**32 - 1  # MCAP sequence is uint32
_MAX_NAME_TRIES = 10_000


def _default_opener(path: Path) -> IO[bytes]:
    # unbuffered: every record the mcap writer emits reaches the OS at once (crash safety);
    # "xb": O_EXCL, never truncates another recorder's file (FileExistsError instead)
    return open(path, "xb", buffering=0)


def _invalid_fields(log_time: int, publish_time: int, sequence: int) -> str:
    """What does not fit the MCAP Message record ("" when all fit). Checked before
    ``Writer.add_message``: a value ``struct.pack`` refuses would leave the open chunk with its
    index and counts updated but the record half written (every later message unreadable)."""
    bad = []
    if not 0 <= log_time <= U64_MAX:
        bad.append(f"log_time {log_time}")
    if not 0 <= publish_time <= U64_MAX:
        bad.append(f"publish_time {publish_time}")
    if not 0 <= sequence <= U32_MAX:
        bad.append(f"sequence {sequence}")
    return ", ".join(bad)


def _is_delete(sample: Any) -> bool:
    import zenoh  # the zenoh callback path only

    return bool(getattr(sample, "kind", None) == zenoh.SampleKind.DELETE)


def _link_noreplace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst`` unless ``dst`` exists (FileExistsError then; ``src`` kept).
    A hard link + unlink is atomic about that; where the filesystem has no hard links, an
    existence check before the rename (racy only against a writer that ignores O_EXCL)."""
    try:
        os.link(src, dst)
    except FileExistsError:
        raise
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
            raise
        if dst.exists():
            raise FileExistsError(errno.EEXIST, "file exists", str(dst)) from None
        src.rename(dst)
        return
    src.unlink()


def _fsync(fh: Any) -> None:
    """fsync a file object that has a descriptor (test doubles without one are skipped)."""
    try:
        fd = fh.fileno()
    except (OSError, ValueError, AttributeError):  # io.UnsupportedOperation is an OSError
        return
    os.fsync(fd)


def _fsync_dir(path: Path) -> None:
    """Make a rename durable (best effort: not every filesystem lets a directory be fsynced)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class _Passthrough:
    """Hands writes straight to the opened file. (mcap's Writer would wrap a raw file in its own
    BufferedWriter, which it never flushes on ``finish()`` and which a crash would lose.)

    ``on_chunk`` is called once a whole Chunk record has been written: mcap's Writer hands each
    chunk record to ``write`` in one call, so from then on its messages are in the file."""

    def __init__(self, f: IO[bytes], on_chunk: Callable[[], None] | None = None) -> None:
        self._f = f
        self._pos = 0
        self._on_chunk = on_chunk

    def write(self, b: Any) -> int:
        view = memoryview(b).cast("B")
        total = len(view)
        is_chunk = total > 0 and view[0] == Opcode.CHUNK
        while len(view):
            n = self._f.write(view)
            if n is None or n <= 0:
                raise OSError("short write")
            self._pos += n
            view = view[n:]
        if is_chunk and self._on_chunk is not None:
            self._on_chunk()
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        self._f.flush()

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        self._f.close()


@dataclass(slots=True)
class _Item:
    topic: str
    typename: str
    key: str
    data: bytes
    log_time: int
    publish_time: int
    sequence: int


@dataclass
class RecorderStats:
    """Counters (read them from any thread; they only grow; those updated from more than one
    thread are updated under the recorder's lock)."""

    received: int = 0
    written: int = 0  # in the file: their chunk was written
    buffered: int = 0  # in the open chunk, not in the file yet
    dropped_queue: int = 0  # oldest dropped because the writer fell behind
    dropped_error: int = 0  # dropped because the disk failed (or the writer refused the message)
    dropped_invalid: int = 0  # times or sequence outside the MCAP ranges (uint64 / uint32)
    unknown_type: int = 0  # samples whose ROS type could not be determined
    # samples without a valid rmw_zenoh attachment, or whose source time is negative: publish_time
    # is then the receive time
    bad_attachment: int = 0
    deletes: int = 0  # zenoh DELETE samples (no message to record): skipped
    inputs_received: int = 0  # messages on the daemon's input topics (Recorder input_topics)
    outputs_received: int = 0  # messages on the outputs it computes from them (output_topics)
    callback_errors: int = 0  # samples lost to an exception in the zenoh callback
    files_finished: int = 0
    files_deleted: int = 0  # finished recordings deleted to keep within max_total_bytes
    bytes_deleted: int = 0
    bytes_written: int = 0  # finished files plus the current file so far
    disk_full: bool = False
    error: str = ""
    current_file: str = ""
    files: list[str] = field(default_factory=list)  # every finished file not deleted (not in as_dict)

    @property
    def missing_inputs(self) -> bool:
        """The daemon's outputs were recorded and not one of its inputs: the recording cannot be
        replayed (the inputs did not reach this recorder, or ended before it started)."""
        return self.outputs_received > 0 and self.inputs_received == 0

    def as_dict(self) -> dict[str, Any]:
        """The counters for a status message: bounded in size, so ``files`` is replaced by
        ``last_file`` (``files_finished`` is the count)."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "files"}
        d["last_file"] = self.files[-1] if self.files else ""
        d["missing_inputs"] = self.missing_inputs
        return d


def default_record_keys(cfg: Any) -> list[str]:
    """``[record] keys``, or one key expression per ``[topics]`` input and output (any type)."""
    from pugsd.wire.keys import subscription_key
    from pugsd.wire.topics import INPUT_ROLES, OUTPUT_ROLES

    if cfg.record.keys:
        return list(cfg.record.keys)
    t = cfg.topics
    return sorted(
        {
            subscription_key(getattr(t, r), domain_id=t.domain_id, key_style=t.key_style)
            for r in INPUT_ROLES + OUTPUT_ROLES
        }
    )


def watched_topics(cfg: Any, keys: Iterable[str]) -> tuple[frozenset[str], frozenset[str]]:
    """The ``[topics]`` inputs, and the outputs computed from them (:data:`DERIVED_OUTPUT_ROLES`),
    that the key expressions ``keys`` subscribe to, as ROS topic names (``/a/b``): the
    ``input_topics`` and ``output_topics`` of a :class:`Recorder` of ``keys``."""
    import zenoh

    from pugsd.wire.keys import subscription_key
    from pugsd.wire.topics import INPUT_ROLES

    t = cfg.topics
    subscribed = []
    for k in keys:
        with contextlib.suppress(Exception):  # one zenoh refuses: Recorder.subscribe names it
            subscribed.append(zenoh.KeyExpr.autocanonize(k))

    def topics(roles: Iterable[str]) -> frozenset[str]:
        out = set()
        for r in roles:
            topic = getattr(t, r)
            k = zenoh.KeyExpr(subscription_key(topic, domain_id=t.domain_id, key_style=t.key_style))
            if any(s.intersects(k) for s in subscribed):
                out.add("/" + strip_topic(topic))
        return frozenset(out)

    return topics(INPUT_ROLES), topics(DERIVED_OUTPUT_ROLES)


class Recorder:
    """Records ROS 2 CDR messages to MCAP on a writer thread.

    ``topic_types`` maps ROS topic names to types for keys that do not carry the type
    (``ros2dds`` style); rmw_zenoh keys carry it. ``metadata`` (name -> str map) is written into
    every file next to the versions and the record config. Messages on ``input_topics`` (a
    daemon's inputs) and ``output_topics`` (the outputs it computes from them) are counted in
    ``stats.inputs_received``/``outputs_received``; :data:`OUTPUTS_BEFORE_WARNING` outputs and
    no input log a warning (``stats.missing_inputs`` says it from the first output on).
    """

    def __init__(
        self,
        cfg: RecordConfig,
        *,
        directory: str | Path | None = None,
        queue_size: int = 256,
        topic_types: Mapping[str, str] | None = None,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        opener: Opener | None = None,
        clock: Callable[[], int] = time.time_ns,
        input_topics: Iterable[str] = (),
        output_topics: Iterable[str] = (),
    ) -> None:
        self.cfg = cfg
        self.directory = Path(directory if directory is not None else cfg.directory)
        self.queue_size = int(queue_size)
        # ROS topic ("/a/b", normalised as the wire layer does) -> type
        self.topic_types = {"/" + strip_topic(k): v for k, v in (topic_types or {}).items()}
        self.metadata = {k: dict(v) for k, v in (metadata or {}).items()}
        self.input_topics = frozenset("/" + strip_topic(t) for t in input_topics)
        self.output_topics = frozenset("/" + strip_topic(t) for t in output_topics)
        self._open = opener or _default_opener
        self._clock = clock
        self.stats = RecorderStats()
        self._q: collections.deque[_Item] = collections.deque()
        self._q_bytes = 0  # payload bytes in _q
        self._inflight_bytes = 0  # payload bytes of the message the writer thread holds
        self._pending = 0  # messages in the open chunk (mirrored in stats.buffered)
        self._cv = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._file_index = 0
        self._session_stamp = ""
        self._writer: Writer | None = None
        self._fh: _Passthrough | None = None
        self._table: ChannelTable | None = None
        self._part: Path | None = None
        self._file_t0 = 0.0
        self._last_flush = 0.0
        self._failed = False
        self._subs: list[Any] = []
        self._finished_bytes = 0

    @classmethod
    def from_config(cls, cfg: Any, *, directory: str | Path | None = None) -> Recorder:
        """A recorder for the daemon: ``[record]`` settings, ``[queues] record`` bound, the
        ``[topics]`` types, inputs and outputs of :func:`default_record_keys`, and the full
        effective config (TOML) in every file's metadata."""
        from pugsd.config import dump_config
        from pugsd.wire.topics import topic_types

        inputs, outputs = watched_topics(cfg, default_record_keys(cfg))
        return cls(
            cfg.record,
            directory=directory,
            queue_size=cfg.queues.record,
            topic_types=topic_types(cfg.topics),
            metadata={"pugsd.config": {"toml": dump_config(cfg)}},
            input_topics=inputs,
            output_topics=outputs,
        )

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Recorder:
        if self._thread is not None:
            return self
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # reported, not raised: the host keeps running
            self._fail(exc, f"cannot create {self.directory}")
        self._session_stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        self._thread = threading.Thread(target=self._run, name="pugsd-recorder", daemon=True)
        self._thread.start()
        return self

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self, timeout: float = 10.0) -> list[Path]:
        """Write what is queued (within ``timeout``), finish the file and rename it; returns the
        finished files of this recorder. Undeclares zenoh subscribers it declared. When the
        writer does not finish in time, ``stats.error`` says so (the ``.part`` file is left)."""
        self.unsubscribe()
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                part = self._part or self.stats.current_file or "the current .part file"
                msg = (f"writer did not finish within {timeout:.1f} s; {part} left for "
                       "`pugsd mcap recover`")  # fmt: skip
                log.error("recorder: %s", msg)
                self.stats.error = f"{self.stats.error}; {msg}" if self.stats.error else msg
        return [Path(p) for p in self.stats.files]

    # ------------------------------------------------------------------ intake (any thread)
    def put(
        self,
        topic: str,
        typename: str,
        data: bytes,
        *,
        key: str = "",
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> bool:
        """Queue one message; never blocks. Returns False if it (or an older one) was dropped.
        Times must fit MCAP's uint64 and ``sequence`` its uint32, else the message is dropped
        and counted in ``stats.dropped_invalid``."""
        now = self._clock() if log_time_ns is None else int(log_time_ns)
        pub = now if publish_time_ns is None else int(publish_time_ns)
        item = _Item(topic, typename, key, bytes(data), now, pub, int(sequence))
        bad = _invalid_fields(item.log_time, item.publish_time, item.sequence)
        ok = True
        with self._cv:
            self.stats.received += 1
            self._count_role(topic)
            if bad:
                self.stats.dropped_invalid += 1
                log.debug("recorder: dropped a %s message: %s out of range", topic, bad)
                return False
            if self._failed or self._stop:
                self.stats.dropped_error += 1
                return False
            self._q.append(item)
            self._q_bytes += len(item.data)
            limit = self.cfg.queue_max_bytes
            while len(self._q) > self.queue_size or (
                self._q_bytes + self._inflight_bytes > limit and len(self._q) > 1
            ):
                old = self._q.popleft()
                self._q_bytes -= len(old.data)
                self.stats.dropped_queue += 1
                ok = False
            if self._inflight_bytes and self._q_bytes + self._inflight_bytes > limit:
                # only this message is queued and it does not fit next to the one being written
                self._q.pop()
                self._q_bytes -= len(item.data)
                self.stats.dropped_queue += 1
                ok = False
            self._cv.notify()
        return ok

    def _count_role(self, topic: str) -> None:
        """Count an input or output message (under the lock); warn once of outputs without input."""
        s = self.stats
        topic = "/" + topic.strip("/")
        if topic in self.input_topics:
            s.inputs_received += 1
        elif topic in self.output_topics:
            s.outputs_received += 1
            if s.outputs_received == OUTPUTS_BEFORE_WARNING and s.inputs_received == 0:
                log.warning(
                    "recorder: %d messages on the daemon's outputs and none on its inputs (%s): the "
                    "inputs do not reach this recorder (a zenoh peer hears only the sessions linked "
                    "to it; `pugsd record` joins the daemon as a client), or none are sent",
                    s.outputs_received, ", ".join(sorted(self.input_topics)),
                )  # fmt: skip

    def put_sample(
        self,
        key: str,
        data: bytes,
        attachment: bytes | None = None,
        log_time_ns: int | None = None,
    ) -> bool:
        """Queue a zenoh sample: topic and type from the key (rmw_zenoh) or ``topic_types``
        (ros2dds); publish time and sequence from the rmw_zenoh attachment when present. A
        negative source time (any int64 is valid on the wire, MCAP's publish_time is unsigned)
        is replaced by the receive time and counted in ``stats.bad_attachment``."""
        now = self._clock() if log_time_ns is None else int(log_time_ns)
        try:
            info = parse_key(key)
            topic, typename = info.topic, info.typename
        except DecodeError:
            topic = "/" + key.strip("/")
            typename = self.topic_types.get(topic, "")
        if not typename or not known_type(typename):
            with self._cv:
                self.stats.unknown_type += 1
                self.stats.received += 1
            log.debug("recorder: no known ROS type for key %s", key)
            return False
        pub, seq = now, 0
        att = None
        if attachment is not None:
            try:
                att = decode_attachment(attachment)
                seq = att.sequence_number
                if 0 <= att.source_timestamp_ns <= U64_MAX:
                    pub = att.source_timestamp_ns
                else:
                    att = None  # publish_time = receive time, counted below
            except DecodeError:
                att = None
        if att is None:
            with self._cv:
                self.stats.bad_attachment += 1
        # mcap's sequence field is uint32; the rmw_zenoh sequence number is int64
        return self.put(topic, typename, data, key=key, log_time_ns=now, publish_time_ns=pub,
                        sequence=seq & 0xFFFFFFFF)  # fmt: skip

    def on_sample(self, sample: Any) -> None:
        """zenoh subscriber callback: copies key, payload and attachment, queues; never blocks.
        DELETE samples carry no message: they are skipped and counted in ``stats.deletes``."""
        try:
            if _is_delete(sample):
                with self._cv:
                    self.stats.received += 1
                    self.stats.deletes += 1
                return
            now = self._clock()
            att = sample.attachment
            self.put_sample(
                str(sample.key_expr),
                sample.payload.to_bytes(),
                None if att is None else att.to_bytes(),
                now,
            )
        except Exception as exc:  # never let an exception into zenoh's thread
            with self._cv:
                self.stats.callback_errors += 1
                n = self.stats.callback_errors
            if n <= 5 or n % 100 == 0:
                log.warning("recorder: dropped a sample (%d so far): %s", n, exc)

    def subscribe(self, session: Any, key_exprs: Iterable[str]) -> list[Any]:
        """Declare one subscriber per key expression feeding :meth:`on_sample`; ConfigError
        naming the key when zenoh refuses one (those declared before it stay declared)."""
        for k in key_exprs:
            try:
                self._subs.append(session.declare_subscriber(k, self.on_sample))
            except Exception as exc:  # zenoh.ZError: invalid key expression, closed session
                raise ConfigError(f"cannot subscribe to key expression {k!r}: {exc}") from None
        return list(self._subs)

    def unsubscribe(self) -> None:
        while self._subs:
            sub = self._subs.pop()
            with contextlib.suppress(Exception):
                sub.undeclare()

    @property
    def queued(self) -> int:
        return len(self._q)

    @property
    def queued_bytes(self) -> int:
        """Payload bytes held for the writer: queued plus the message being written."""
        with self._cv:
            return self._q_bytes + self._inflight_bytes

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        try:
            while True:
                item: _Item | None = None
                with self._cv:
                    while not self._q and not self._stop:
                        self._cv.wait(timeout=self._wait_s())
                        if not self._q:
                            break
                    if self._q:  # one at a time: its bytes stay counted until it is written
                        item = self._q.popleft()
                        self._q_bytes -= len(item.data)
                        self._inflight_bytes = len(item.data)
                    stopping = self._stop
                if item is not None:
                    try:
                        self._write(item)
                    finally:
                        with self._cv:
                            self._inflight_bytes = 0
                self._maybe_flush()
                if stopping and not self._q:
                    break
        finally:
            self._close_file(finish=not self._failed)

    def _wait_s(self) -> float:
        if self._writer is None:
            return 1.0
        return max(0.01, self.cfg.flush_interval_s - (time.monotonic() - self._last_flush))

    def _count_dropped_error(self, n: int = 1) -> None:
        with self._cv:  # put() updates it from other threads
            self.stats.dropped_error += n

    def _fail(self, exc: OSError, what: str) -> None:
        self._failed = True
        self.stats.disk_full = exc.errno == errno.ENOSPC
        self.stats.error = f"{what}: {exc}"
        log.error(
            "recorder stopped writing (%s): %s; messages are now dropped and counted",
            "disk full" if self.stats.disk_full else "disk error",
            exc,
        )
        self._drop_pending()
        with self._cv:
            self.stats.dropped_error += len(self._q)
            self._q.clear()
            self._q_bytes = 0

    def _commit_chunk(self) -> None:
        """The open chunk reached the file: its messages count as written."""
        self.stats.written += self._pending
        self._pending = 0
        self.stats.buffered = 0

    def _drop_pending(self) -> None:
        """The open chunk is lost: its messages count as dropped."""
        self._count_dropped_error(self._pending)
        self._pending = 0
        self.stats.buffered = 0

    def _write(self, item: _Item) -> None:
        if self._failed:
            self._count_dropped_error()
            return
        bad = _invalid_fields(item.log_time, item.publish_time, item.sequence)
        if bad:  # (put() checks too) never hand add_message what it cannot pack
            with self._cv:
                self.stats.dropped_invalid += 1
            log.warning("recorder: dropped a %s message: %s out of range", item.topic, bad)
            return
        in_chunk = False
        try:
            self._maybe_rotate()
            if self._table is None or self._writer is None:  # failed while rotating
                self._count_dropped_error()
                return
            cid = self._table.channel_id(item.topic, item.typename, item.key)
            self._pending += 1  # before add_message: it may write the chunk (then _commit_chunk)
            in_chunk = True
            self._writer.add_message(cid, item.log_time, item.data, item.publish_time, item.sequence)
            self.stats.buffered = self._pending
        except OSError as exc:
            if not in_chunk:
                self._count_dropped_error()
            self._fail(exc, "write")  # the open chunk, this message included, is dropped
            self._close_file(finish=False)
        except Exception as exc:  # a bad message must not kill the writer thread
            if in_chunk:  # it did not make it into the chunk
                self._pending = max(0, self._pending - 1)
                self.stats.buffered = self._pending
            self._count_dropped_error()
            self.stats.error = f"write {item.topic}: {type(exc).__name__}: {exc}"
            log.exception("recorder: dropped a %s message", item.topic)

    def _maybe_flush(self) -> None:
        if self._writer is None or self._failed:
            return
        if time.monotonic() - self._last_flush >= self.cfg.flush_interval_s:
            try:
                self._writer.flush()
            except OSError as exc:
                self._fail(exc, "flush")
                self._close_file(finish=False)
                return
            self._commit_chunk()  # (already done by the chunk write; kept as a safety net)
            self._last_flush = time.monotonic()
            self._update_size()

    def _update_size(self) -> None:
        if self._fh is not None:
            with contextlib.suppress(OSError, ValueError):
                self.stats.bytes_written = self._finished_bytes + self._fh.tell()

    def _maybe_rotate(self) -> None:
        if self._writer is not None:
            self._update_size()
            size = self._fh.tell() if self._fh is not None else 0
            age = time.monotonic() - self._file_t0
            if size < self.cfg.rotate_size_bytes and age < self.cfg.rotate_duration_s:
                return
            log.info("recorder: rotating %s (%d B, %.0f s)", self._part, size, age)
            self._close_file(finish=True)
        if self._failed:  # finishing the old file failed: open no new one
            return
        self._open_file()

    def _file_name(self) -> str:
        return f"{self.cfg.name_prefix}_{self._session_stamp}_{self._file_index:03d}.mcap"

    def _open_file(self) -> None:
        """Open the next ``.part`` exclusively: the index is bumped past every name another
        recorder (same second, same directory) holds as ``.part`` or ``.mcap``."""
        for _ in range(_MAX_NAME_TRIES):
            self._file_index += 1
            final = self.directory / self._file_name()
            part = final.with_name(final.name + ".part")
            if final.exists():
                continue
            try:
                f = self._open(part)  # FileExistsError when the name is taken
            except FileExistsError:
                continue
            break
        else:
            raise OSError(errno.EEXIST, f"no free file name after {_MAX_NAME_TRIES} tries", str(part))
        self._part = part
        self._fh = _Passthrough(f, on_chunk=self._commit_chunk)
        self._writer = new_writer(self._fh, self.cfg.chunk_size_bytes, self.cfg.compression)
        self._table = ChannelTable(self._writer)
        v = versions()
        self._writer.add_metadata("pugsd.versions", v)
        self._writer.add_metadata(
            "pugsd.record",
            {
                "config": metadata_json(to_dict(self.cfg)),
                "file_index": str(self._file_index),
                "started_utc": datetime.now(UTC).isoformat(),
            },
        )
        for name_md, md in self.metadata.items():
            self._writer.add_metadata(name_md, md)
        self._file_t0 = self._last_flush = time.monotonic()
        self.stats.current_file = str(self._part)
        log.info("recorder: writing %s", self._part)

    def _close_file(self, *, finish: bool) -> None:
        w, fh, part = self._writer, self._fh, self._part
        self._writer = self._fh = self._table = self._part = None
        self.stats.current_file = ""
        if fh is None or part is None:
            return
        ok = False
        if finish and w is not None:
            try:
                w.finish()
                ok = True
                self._commit_chunk()  # (already done by the chunk write; kept as a safety net)
            except OSError as exc:
                self._fail(exc, "finish")
        if not ok:
            self._drop_pending()
        with contextlib.suppress(OSError, ValueError):
            self._finished_bytes += fh.tell()
        self.stats.bytes_written = self._finished_bytes  # the summary and footer included
        try:
            if ok:
                fh.flush()
                _fsync(fh)  # on disk before the rename: a power cut leaves a .part or a whole file
            fh.close()
        except OSError as exc:
            if ok:
                self._fail(exc, "close")
            ok = False
        if ok:
            try:
                final = self._publish(part)
            except OSError as exc:
                self._fail(exc, "rename")
                return
            _fsync_dir(final.parent)
            self.stats.files.append(str(final))
            self.stats.files_finished += 1
            log.info("recorder: finished %s", final)
            self._enforce_max_total(final)
        else:
            log.error("recorder: left %s unfinished (use `pugsd mcap recover`)", part)

    def _enforce_max_total(self, newest: Path) -> None:
        """``max_total_bytes``: delete the oldest finished recordings of this name prefix in the
        directory (``.mcap`` files named as this recorder names them, earlier runs' included;
        never ``newest``, never a ``.part``) until the rest fit. Rotation alone never frees space."""
        limit = self.cfg.max_total_bytes
        if limit <= 0:
            return
        name = re.compile(re.escape(self.cfg.name_prefix) + r"_\d{8}T\d{6}Z_\d{3,}\.mcap")
        found = []
        try:
            for p in self.directory.iterdir():
                if not name.fullmatch(p.name):
                    continue
                with contextlib.suppress(OSError):  # deleted meanwhile (another recorder)
                    st = p.stat()
                    found.append((st.st_mtime_ns, p.name, p, st.st_size))
        except OSError as exc:
            log.warning("recorder: cannot list %s to keep it within max_total_bytes: %s", self.directory, exc)
            return
        found.sort()  # oldest first (names alone misorder index 1000 before 999)
        total = sum(size for *_, size in found)
        for _, _, p, size in found:
            if total <= limit:
                break
            if p == newest:
                continue
            try:
                p.unlink()
            except FileNotFoundError:
                pass  # another recorder deleted it
            except OSError as exc:
                log.warning("recorder: cannot delete %s: %s", p, exc)
                continue
            total -= size
            self.stats.files_deleted += 1
            self.stats.bytes_deleted += size
            with contextlib.suppress(ValueError):
                self.stats.files.remove(str(p))
            log.info("recorder: deleted %s (%d B) to keep recordings within max_total_bytes = %d B",
                     p, size, limit)  # fmt: skip

    def _publish(self, part: Path) -> Path:
        """Rename the finished ``.part`` to its ``.mcap`` name, or to a later free index when that
        name has appeared meanwhile: a finished file is never replaced."""
        final = part.with_name(part.name[: -len(".part")])
        for _ in range(_MAX_NAME_TRIES):
            try:
                _link_noreplace(part, final)
                return final
            except FileExistsError:
                log.warning("recorder: %s exists; not replacing it", final)
                self._file_index += 1
                final = self.directory / self._file_name()
        raise OSError(errno.EEXIST, f"no free file name after {_MAX_NAME_TRIES} tries", str(part))
