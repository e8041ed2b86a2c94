# SPDX-License-Identifier: Apache-2.0
"""MCAP helpers shared by the recorder, player and tools: writer set-up, versions metadata,
reading several files in log-time order, ``info`` and ``recover``."""

from __future__ import annotations

import contextlib
import heapq
import importlib.metadata
import json
import logging
import os
import platform
import struct
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer

from pugsd import __version__
from pugsd.errors import DecodeError, PugsdError
from pugsd.wire.types import msgdef

log = logging.getLogger(__name__)

PROFILE = Profile.ROS2  # "ros2"
SCHEMA_ENCODING = SchemaEncoding.ROS2  # "ros2msg"
MESSAGE_ENCODING = MessageEncoding.CDR  # "cdr"
KEY_METADATA = "zenoh_key"  # channel metadata: the zenoh key the messages travelled on

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


def file_error(path: str | Path, exc: OSError, what: str = "cannot read") -> PugsdError:
    """A one-line error naming the file, for an ``OSError`` (missing file, no directory, ...)."""
    return PugsdError(f"{what} {path}: {exc.strerror or exc}")


def _open_read(path: str | Path) -> IO[bytes]:
    try:
        return open(path, "rb")  # the caller closes it
    except OSError as exc:
        raise file_error(path, exc) from None


_MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first 8 bytes of every MCAP file (and its last 8)


def _require_magic(f: IO[bytes], path: str | Path) -> None:
    """DecodeError unless ``f`` starts with the MCAP magic (left at its start): a file that is
    not an MCAP was read as an incomplete one, and `pugsd mcap recover` cannot help it."""
    try:
        head = f.read(len(_MCAP_MAGIC))
        f.seek(0)
    except OSError as exc:
        raise file_error(path, exc) from None
    if head != _MCAP_MAGIC:
        what = "an empty file" if not head else "it does not start with the MCAP magic"
        raise DecodeError(f"{path}: not an MCAP file ({what})")


def versions() -> dict[str, str]:
    """Software versions for the MCAP metadata record ``pugsd.versions``."""
    out = {
        "pugsd": __version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    for dist in ("eclipse-zenoh", "rosbags", "mcap", "mcap-ros2-support", "numpy"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return out


def library_string() -> str:
    v = versions()
    return f"pugsd {v['pugsd']}; mcap-python {v['mcap']}"


def new_writer(stream: Any, chunk_size: int, compression: str = "zstd") -> Writer:
    """A started ``ros2``-profile writer with ZSTD chunks."""
    w = Writer(stream, chunk_size=chunk_size, compression=_COMPRESSION[compression])
    w.start(profile=PROFILE, library=library_string())
    return w


class ChannelTable:
    """Schemas (one per ROS type) and channels (one per topic + key) of one open writer."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str, str], int] = {}

    def schema_id(self, typename: str, text: str | None = None) -> int:
        sid = self._schemas.get(typename)
        if sid is None:
            data = (text if text is not None else msgdef(typename)).encode()
            sid = self.writer.register_schema(typename, SCHEMA_ENCODING, data)
            self._schemas[typename] = sid
        return sid

    def channel_id(
        self, topic: str, typename: str, key: str = "", metadata: Mapping[str, str] | None = None
    ) -> int:
        k = (topic, typename, key)
        cid = self._channels.get(k)
        if cid is None:
            md = dict(metadata or {})
            if key:
                md[KEY_METADATA] = key
            cid = self.writer.register_channel(topic, MESSAGE_ENCODING, self.schema_id(typename), metadata=md)
            self._channels[k] = cid
        return cid


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    topic: str
    typename: str
    key: str  # "" when the recording has none
    data: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    file_index: int


_FOOTER = struct.Struct("<BQQQI")  # opcode, record length, summary_start, summary_offset_start, crc


def summary_crc_error(f: IO[bytes]) -> str:
    """Why the file's summary section fails its checksum ("" when it passes, has none, or the
    file has no footer). The mcap reader ignores the footer's ``summary_crc``: a bit flip in the
    summary would silently change a channel's topic or type (chunk CRCs cover only the data)."""
    try:
        f.seek(0, os.SEEK_END)
        size = f.tell()
        end = size - 8  # the closing magic
        if end - _FOOTER.size < 8:
            return ""
        f.seek(end - _FOOTER.size)
        opcode, length, summary_start, _, crc = _FOOTER.unpack(f.read(_FOOTER.size))
        if opcode != Opcode.FOOTER or length != 20 or crc == 0:  # not a footer, or written without CRCs
            return ""
        start = summary_start if summary_start else end - _FOOTER.size
        if not 8 <= start <= end - _FOOTER.size:
            return f"footer: summary start {summary_start} is outside the file"
        f.seek(start)
        got = zlib.crc32(f.read(end - 4 - start))
    finally:
        f.seek(0)
    if got != crc:
        return f"summary checksum mismatch (expected {crc:#010x}, got {got:#010x})"
    return ""


def _iter_file(
    path: Path, idx: int, topics: list[str] | None, start_ns: int | None, end_ns: int | None
) -> Iterator[tuple[int, int, int, RecordedMessage]]:
    with _open_read(path) as f:
        _require_magic(f, path)
        try:
            # the chunk CRCs: a corrupt chunk is an error, not altered payloads (zstd has no
            # checksum); the summary's, which the reader does not check, tells what the channels are
            bad_summary = summary_crc_error(f)
            if bad_summary:
                raise DecodeError(f"{path}: {bad_summary}; try `pugsd mcap recover`")
            reader = make_reader(f, validate_crcs=True)
            it = reader.iter_messages(
                topics=topics, starting_at=start_ns, ending_before=end_ns, log_time_order=True
            )
            for n, (schema, channel, msg) in enumerate(it):
                yield (msg.log_time, idx, n, _rec(schema, channel, msg, idx))
        except DecodeError:
            raise
        except Exception as exc:
            raise DecodeError(f"{path}: not a readable MCAP file ({exc}); try `pugsd mcap recover`") from None


def _rec(schema: Schema | None, channel: Channel, msg: Message, idx: int) -> RecordedMessage:
    return RecordedMessage(
        topic=channel.topic,
        typename=schema.name if schema is not None else "",
        key=channel.metadata.get(KEY_METADATA, ""),
        data=bytes(msg.data),
        log_time_ns=msg.log_time,
        publish_time_ns=msg.publish_time,
        sequence=msg.sequence,
        file_index=idx,
    )


def iter_recording(
    paths: Iterable[str | Path],
    topics: Iterable[str] | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> Iterator[RecordedMessage]:
    """Messages of several MCAP files merged in log-time order (ties: file order, then file
    order of appearance). ``start_ns``/``end_ns`` are absolute log times."""
    tl = None if topics is None else list(topics)
    its = [_iter_file(Path(p), i, tl, start_ns, end_ns) for i, p in enumerate(paths)]
    for _t, _i, _n, rec in heapq.merge(*its, key=lambda x: (x[0], x[1], x[2])):
        yield rec


def time_range(paths: Iterable[str | Path]) -> tuple[int, int]:
    """(first, last) log time over the files, from their summaries (or a scan without one)."""
    lo, hi = None, None
    for p in paths:
        s = scan(p)
        if s.message_count == 0:
            continue
        lo = s.start_ns if lo is None else min(lo, s.start_ns)
        hi = s.end_ns if hi is None else max(hi, s.end_ns)
    return (lo or 0, hi or 0)


# ----------------------------------------------------------------------------- info


@dataclass
class ChannelInfo:
    topic: str
    typename: str
    key: str
    count: int = 0


@dataclass
class FileInfo:
    path: str
    size_bytes: int
    complete: bool  # has a readable summary
    profile: str = ""
    library: str = ""
    message_count: int = 0
    start_ns: int = 0
    end_ns: int = 0
    chunk_count: int = 0
    channels: list[ChannelInfo] = field(default_factory=list)
    schemas: dict[str, str] = field(default_factory=dict)  # name -> encoding
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    error: str = ""

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9 if self.message_count else 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "size_bytes": self.size_bytes,
            "complete": self.complete,
            "profile": self.profile,
            "library": self.library,
            "messages": self.message_count,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "chunks": self.chunk_count,
            "channels": [c.__dict__ for c in self.channels],
            "schemas": self.schemas,
            "metadata": self.metadata,
            "error": self.error,
        }


def _channel_infos(
    channels: Mapping[int, Channel], schemas: Mapping[int, Schema], counts: Mapping[int, int]
) -> list[ChannelInfo]:
    """One ChannelInfo per channel, by channel id: topic, schema name, key, message count."""
    out = []
    for cid, ch in sorted(channels.items()):
        sch = schemas.get(ch.schema_id)
        name = sch.name if sch else ""
        out.append(ChannelInfo(ch.topic, name, ch.metadata.get(KEY_METADATA, ""), counts.get(cid, 0)))
    return out


def scan(path: str | Path) -> FileInfo:
    """Topics, counts, duration and schemas of one file: from the summary when the file is
    complete, otherwise by streaming through it (``complete`` False, ``error`` says why)."""
    p = Path(path)
    with _open_read(p) as f:
        _require_magic(f, p)
        try:
            size = os.fstat(f.fileno()).st_size
        except OSError as exc:
            raise file_error(p, exc) from None
        info = FileInfo(str(p), size, complete=False)
        summary_error = summary_crc_error(f)
        try:
            reader = make_reader(f)
            header = reader.get_header()
            info.profile, info.library = header.profile, header.library
            summary = None if summary_error else reader.get_summary()
        except Exception:
            summary = None
        if summary is not None and summary.statistics is not None:
            st = summary.statistics
            info.complete = True
            info.message_count = st.message_count
            info.start_ns, info.end_ns = st.message_start_time, st.message_end_time
            info.chunk_count = st.chunk_count
            info.schemas = {s.name: s.encoding for s in summary.schemas.values()}
            info.channels = _channel_infos(summary.channels, summary.schemas, st.channel_message_counts)
            with contextlib.suppress(Exception):
                for md in reader.iter_metadata():
                    info.metadata[md.name] = dict(md.metadata)
            return info
    # incomplete: stream through
    res = _stream(p, lambda *_: None)
    info.complete = False
    info.error = f"{summary_error}; every message was read" if summary_error and not res.error else res.error
    info.message_count = res.messages
    info.chunk_count = res.chunks
    info.start_ns, info.end_ns = res.start_ns, res.end_ns
    info.profile, info.library = res.profile, res.library
    info.schemas = {s.name: s.encoding for s in res.schemas.values()}
    info.channels = _channel_infos(res.channels, res.schemas, res.channel_counts)
    info.metadata = {m.name: dict(m.metadata) for m in res.metadata}
    return info


# ----------------------------------------------------------------------------- recover


@dataclass
class StreamResult:
    messages: int = 0
    start_ns: int = 0
    end_ns: int = 0
    profile: str = ""
    library: str = ""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    channel_counts: dict[int, int] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    chunks: int = 0  # chunks read whole (CRC checked, every record parsed)
    error: str = ""  # why reading stopped before the footer ("" if the file was complete)


class _Abort(Exception):
    """Raised by an ``on_record`` callback to end :func:`_stream` with its cause (not a read error)."""

    def __init__(self, cause: BaseException) -> None:
        super().__init__(str(cause))
        self.cause = cause


def _stream(path: Path, on_record: Any, *, fh: IO[bytes] | None = None) -> StreamResult:
    """Read records in file order until the footer, end of file or the first bad record (from
    ``fh`` when given, else by opening ``path``). ``on_record`` may raise :class:`_Abort`."""
    from mcap.records import Chunk, DataEnd, Footer, Header

    res = StreamResult()
    data_end = False  # every message is read; the summary, footer and magic must follow

    def records(reader: StreamReader) -> Iterator[Any]:
        """The reader's records with each chunk's records in its place (counting the chunks)."""
        for rec in reader.records:
            if isinstance(rec, Chunk):
                inner = breakup_chunk(rec, validate_crc=True)
                res.chunks += 1
                yield from inner
            else:
                yield rec

    with contextlib.nullcontext(fh) if fh is not None else _open_read(path) as f:
        reader = StreamReader(f, validate_crcs=True, record_size_limit=1 << 31, emit_chunks=True)
        try:
            for rec in records(reader):
                if data_end:  # the summary repeats what the data section gave
                    continue
                if isinstance(rec, Header):
                    res.profile, res.library = rec.profile, rec.library
                elif isinstance(rec, Schema):
                    res.schemas.setdefault(rec.id, rec)
                elif isinstance(rec, Channel):
                    res.channels.setdefault(rec.id, rec)
                elif isinstance(rec, Message):
                    if rec.channel_id not in res.channels:
                        raise DecodeError(f"message on unknown channel {rec.channel_id}")
                    res.start_ns = rec.log_time if res.messages == 0 else min(res.start_ns, rec.log_time)
                    res.end_ns = max(res.end_ns, rec.log_time)
                    res.messages += 1
                    res.channel_counts[rec.channel_id] = res.channel_counts.get(rec.channel_id, 0) + 1
                elif isinstance(rec, Metadata):
                    res.metadata.append(rec)
                elif isinstance(rec, (DataEnd, Footer)):
                    on_record(rec, res)
                    data_end = True
                    continue
                on_record(rec, res)
            if data_end:  # the records ended with the footer and the closing magic
                return res
            res.error = "end of file before the footer"
        except EndOfFile:  # mcap raises it for a file cut inside a record and at a record's end alike
            res.error = "end of file before the footer"
        except _Abort:
            raise
        except Exception as exc:
            res.error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    if data_end:
        res.error = f"summary or footer unreadable ({res.error}); every message was read"
    return res


@dataclass
class RecoverResult:
    messages: int
    channels: int
    schemas: int
    metadata: int
    error: str  # why reading stopped ("" when the input was complete)


def recover(src: str | Path, dst: str | Path, *, chunk_size: int = 1 << 20,
            compression: str = "zstd") -> RecoverResult:  # fmt: skip
    """Rebuild a file whose writer died (no footer, or a torn last chunk) from every record that
    can still be read, in file order: schemas, channels, messages and metadata (a new summary
    and indexes are written). Reading stops at the first unreadable record. The output is
    written as ``DST.recovering`` (removed on failure) and renamed; an ``OSError`` of either
    file becomes a PugsdError naming it."""
    src, dst = Path(src), Path(dst)
    if src.resolve() == dst.resolve():
        raise DecodeError("recover: output must differ from the input")
    tmp = dst.with_name(dst.name + ".recovering")
    if tmp.resolve() == src.resolve():
        raise DecodeError("recover: choose another output name")
    with _open_read(src) as src_f:  # the source first: nothing is created when it is missing
        try:
            out = open(tmp, "wb")  # noqa: SIM115 (closed by the with below)
        except OSError as exc:
            raise file_error(dst, exc, "cannot write") from None
        done = False
        try:
            with out:
                res, counts = _copy_records(src, src_f, out, chunk_size, compression)
            tmp.replace(dst)
            done = True
        except OSError as exc:
            raise file_error(dst, exc, "cannot write") from None
        finally:
            if not done:
                with contextlib.suppress(OSError):
                    tmp.unlink(missing_ok=True)
    log.info("recovered %d messages from %s (%s)", counts["messages"], src, res.error or "complete")
    return RecoverResult(counts["messages"], counts["channels"], counts["schemas"],
                         counts["metadata"], res.error)  # fmt: skip


def _copy_records(src: Path, src_f: IO[bytes], out: IO[bytes], chunk_size: int,
                  compression: str) -> tuple[StreamResult, dict[str, int]]:  # fmt: skip
    """Stream the records of ``src_f`` into a new writer on ``out`` (finished). An OSError of
    the output propagates (it is no reason to stop reading)."""
    from mcap.records import Header

    writer: Writer | None = None
    sid_map: dict[int, int] = {}
    cid_map: dict[int, int] = {}
    counts = {"messages": 0, "metadata": 0}

    def on_record(rec: Any, res: StreamResult) -> None:
        nonlocal writer
        try:
            if isinstance(rec, Header):
                writer = Writer(out, chunk_size=chunk_size, compression=_COMPRESSION[compression])
                writer.start(profile=rec.profile, library=rec.library or library_string())
                return
            if writer is None:
                raise DecodeError("no MCAP header")
            if isinstance(rec, Schema) and rec.id not in sid_map:
                sid_map[rec.id] = writer.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel) and rec.id not in cid_map:
                cid_map[rec.id] = writer.register_channel(
                    rec.topic, rec.message_encoding, sid_map.get(rec.schema_id, 0),
                    metadata=dict(rec.metadata),
                )  # fmt: skip
            elif isinstance(rec, Message):
                writer.add_message(
                    cid_map[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence
                )
                counts["messages"] += 1
            elif isinstance(rec, Metadata):
                writer.add_metadata(rec.name, dict(rec.metadata))
                counts["metadata"] += 1
        except OSError as exc:  # writing the output failed
            raise _Abort(exc) from exc

    try:
        res = _stream(src, on_record, fh=src_f)
        if writer is None:
            raise DecodeError(f"{src}: no readable MCAP header ({res.error or 'empty'})")
        writer.add_metadata("pugsd.recover", {"source": str(src), "stopped": res.error or "complete"})
        writer.finish()
    except _Abort as exc:
        raise exc.cause from None
    return res, {**counts, "channels": len(cid_map), "schemas": len(sid_map)}


def metadata_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str)
