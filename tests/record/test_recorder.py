# SPDX-License-Identifier: Apache-2.0
"""Recorder in-process: file format, metadata, rotation, slow disk, full disk, queue bound,
stop timeout, status size."""

from __future__ import annotations

import errno
import io
import json
import os
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pugsd.record.config import RecordConfig
from pugsd.record.mcapio import recover
from pugsd.record.recorder import Recorder
from pugsd.wire import codec
from pugsd.wire.attachment import encode_attachment
from pugsd.wire.keys import topic_key
from pugsd.wire.types import IMAGE, POSE_COV_STAMPED
from tests.record.conftest import GatedFile


def _cfg(tmp: Path, **kw: Any) -> RecordConfig:
    return RecordConfig(enabled=True, directory=str(tmp), **kw)


def _img(i: int, shape: tuple[int, int] = (16, 16)) -> bytes:
    return codec.encode_image(np.full(shape, i % 256, np.uint8), 1000 + i, "left")


def test_record_put_sample_format_and_metadata(tmp_path: Path) -> None:
    key = topic_key("/stereo/left/image_raw", IMAGE)
    gid = bytes(range(16))
    payloads = [_img(i) for i in range(5)]
    rec = Recorder(_cfg(tmp_path), metadata={"pugsd.config": {"toml": "x = 1"}})
    with rec:
        for i, p in enumerate(payloads):
            assert rec.put_sample(key, p, encode_attachment(i + 1, 5_000 + i, gid), 9_000 + i)
        # ros2dds key with a type from topic_types; and an unknown key
        rec.topic_types["/camera_pose"] = POSE_COV_STAMPED
        pose = codec.encode_pose_with_covariance(1, np.eye(4), np.eye(6))
        assert rec.put_sample("camera_pose", pose, None, 20_000)
        assert not rec.put_sample("unknown/topic", b"\x00\x01\x00\x00", None)
    files = rec.stats.files
    assert len(files) == 1 and files[0].endswith(".mcap") and Path(files[0]).exists()
    assert not list(tmp_path.glob("*.part"))
    assert rec.stats.written == 6 and rec.stats.unknown_type == 1 and rec.stats.bad_attachment == 1
    with open(files[0], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        msgs = list(reader.iter_decoded_messages())
        summary = reader.get_summary()
        md = {m.name: m.metadata for m in reader.iter_metadata()}
    assert summary is not None
    assert {s.name for s in summary.schemas.values()} == {IMAGE, POSE_COV_STAMPED}
    assert all(s.encoding == "ros2msg" for s in summary.schemas.values())
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    assert [m[1].topic for m in msgs] == ["/stereo/left/image_raw"] * 5 + ["/camera_pose"]
    assert [m[2].data for m in msgs[:5]] == payloads  # verbatim
    assert [m[2].log_time for m in msgs[:5]] == [9_000 + i for i in range(5)]
    assert [m[2].publish_time for m in msgs[:5]] == [5_000 + i for i in range(5)]
    assert [m[2].sequence for m in msgs[:5]] == [1, 2, 3, 4, 5]
    assert msgs[0][1].metadata["zenoh_key"] == key
    assert msgs[2][3].data[0] == 2  # decoded by mcap_ros2
    assert json.loads(md["pugsd.record"]["config"])["enabled"] is True
    assert md["pugsd.versions"]["pugsd"] and md["pugsd.versions"]["eclipse-zenoh"]
    assert md["pugsd.config"] == {"toml": "x = 1"}


def test_rotation_by_size_and_duration(tmp_path: Path) -> None:
    a = tmp_path / "size"
    rec = Recorder(_cfg(a, chunk_size_bytes=65536, rotate_size_bytes=300_000), queue_size=10_000)
    with rec:
        for i in range(60):  # 60 x ~40 kB, nearly incompressible
            data = codec.encode_image(np.random.default_rng(i).integers(0, 255, (200, 200), np.uint8), i)
            rec.put("/img", IMAGE, data, log_time_ns=i)
    files = [Path(f) for f in rec.stats.files]
    assert len(files) >= 5 and all(f.exists() for f in files)
    assert all(f.stat().st_size < 300_000 + 2 * 65536 + 100_000 for f in files)
    total = 0
    for f in files:
        with open(f, "rb") as fh:
            total += sum(1 for _ in make_reader(fh).iter_messages())
    assert total == 60

    b = tmp_path / "dur"
    rec = Recorder(_cfg(b, rotate_duration_s=0.15, flush_interval_s=0.05))
    with rec:
        for i in range(8):
            rec.put("/img", IMAGE, _img(i))
            time.sleep(0.06)
    assert len(rec.stats.files) >= 2
    assert len({Path(f).name for f in rec.stats.files}) == len(rec.stats.files)


class _SlowFile(io.RawIOBase):
    def __init__(self, path: Path, delay: float) -> None:
        self.f = open(path, "wb", buffering=0)  # noqa: SIM115
        self.delay = delay

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        time.sleep(self.delay)
        return int(self.f.write(b) or 0)

    def tell(self) -> int:
        return int(self.f.tell())

    def close(self) -> None:
        self.f.close()
        super().close()


def test_slow_disk_drops_and_counts_but_never_blocks(tmp_path: Path) -> None:
    def opener(p: Path) -> IO[bytes]:
        return _SlowFile(p, 0.02)  # type: ignore[return-value]

    rec = Recorder(_cfg(tmp_path, chunk_size_bytes=4096, flush_interval_s=0.01),
                   queue_size=16, opener=opener)  # fmt: skip
    times = []
    with rec:
        for i in range(400):
            t0 = time.perf_counter()
            rec.put("/img", IMAGE, _img(i, (32, 32)))
            times.append(time.perf_counter() - t0)
    s = rec.stats
    # a put that waited for the disk would take >= 20 ms each (8 s in all); allow scheduler noise
    assert sum(times) < 1.0 and float(np.percentile(times, 90)) < 0.005, max(times)
    assert s.dropped_queue > 0
    assert s.written + s.dropped_queue == s.received == 400
    with open(s.files[0], "rb") as f:
        # by header stamp (1000 + i): the pixel value (i % 256) wraps within the 400 messages
        seen = [codec.decode_image(m.data).stamp_ns for _, _, m in make_reader(f).iter_messages()]
    assert len(seen) == s.written and seen == sorted(seen)  # kept in order; the oldest dropped


class _FullDisk(io.RawIOBase):
    def __init__(self, path: Path, limit: int, full: threading.Event | None = None) -> None:
        self.f = open(path, "wb", buffering=0)  # noqa: SIM115
        self.n = 0
        self.limit = limit
        self.full = full  # when set: every write fails

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        if self.n + len(b) > self.limit or (self.full is not None and self.full.is_set()):
            raise OSError(errno.ENOSPC, "No space left on device")
        self.n += len(b)
        return int(self.f.write(b) or 0)

    def tell(self) -> int:
        return self.n

    def close(self) -> None:
        self.f.close()
        super().close()


def test_full_disk_is_reported_not_a_crash(tmp_path: Path) -> None:
    def opener(p: Path) -> IO[bytes]:
        return _FullDisk(p, 50_000)  # type: ignore[return-value]

    rec = Recorder(_cfg(tmp_path, chunk_size_bytes=8192, flush_interval_s=0.01), opener=opener)
    with rec:
        for i in range(100):
            rec.put("/img", IMAGE, codec.encode_image(
                np.random.default_rng(i).integers(0, 255, (40, 40), np.uint8), i))  # fmt: skip
            time.sleep(0.001)
        deadline = time.monotonic() + 10
        while not rec.stats.disk_full and time.monotonic() < deadline:
            time.sleep(0.01)
        assert rec.stats.disk_full
        assert not rec.put("/img", IMAGE, _img(0))  # refused and counted; no exception
    s = rec.stats
    assert s.disk_full and "No space left" in s.error
    assert s.written + s.dropped_error + s.dropped_queue == s.received
    assert s.files == []
    (part,) = tmp_path.glob("*.mcap.part")  # left for `mcap recover`
    # `written` is what reached the file: the messages of the lost chunk are counted as dropped
    res = recover(part, tmp_path / "recovered.mcap")
    assert res.messages == s.written > 0, (res.messages, s.written, s.dropped_error)
    assert s.buffered == 0


def test_a_finished_file_is_fsynced_before_its_rename(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A power cut on the vehicle must leave either a .part (recoverable) or a whole file: the
    data is fsynced before the rename, the directory after it; a failing fsync leaves the .part."""
    import pugsd.record.recorder as recorder_mod

    calls: list[tuple[str, list[str]]] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        calls.append((os.readlink(f"/proc/self/fd/{fd}"), sorted(p.name for p in tmp_path.iterdir())))
        real_fsync(fd)

    monkeypatch.setattr(recorder_mod.os, "fsync", fsync)
    rec = Recorder(_cfg(tmp_path))
    with rec:
        rec.put("/img", IMAGE, _img(0))
    (final,) = rec.stats.files
    assert [Path(c[0]).name for c in calls] == [Path(final).name + ".part", tmp_path.name]
    assert calls[0][1] == [Path(final).name + ".part"]  # the data first, still under .part
    assert calls[1][1] == [Path(final).name]  # then the directory, after the rename

    def failing(fd: int) -> None:
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(recorder_mod.os, "fsync", failing)
    rec = Recorder(_cfg(tmp_path / "b"))
    with rec:
        rec.put("/img", IMAGE, _img(0))
    assert rec.stats.files == [] and "I/O error" in rec.stats.error
    assert len(list((tmp_path / "b").glob("*.mcap.part"))) == 1


def test_flush_failure_counts_the_open_chunk_as_dropped(tmp_path: Path) -> None:
    full = threading.Event()

    def opener(p: Path) -> IO[bytes]:
        return _FullDisk(p, 1 << 30, full)  # type: ignore[return-value]

    # big chunks, no timed flush: every message stays in the open chunk until stop()
    rec = Recorder(_cfg(tmp_path, chunk_size_bytes=1 << 20, flush_interval_s=100.0), opener=opener)
    with rec:
        for i in range(10):
            rec.put("/img", IMAGE, _img(i))
        # the writer thread pops a message, then adds it to the chunk: wait for the chunk, not for
        # the queue to empty (a fixed sleep after that raced a descheduled writer)
        deadline = time.monotonic() + 10
        while rec.stats.buffered < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert rec.stats.written == 0 and rec.stats.buffered == 10  # nothing in the file yet
        full.set()  # the final chunk write (finish) fails
    s = rec.stats
    assert s.disk_full and s.written == 0 and s.dropped_error == 10 == s.received
    (part,) = tmp_path.glob("*.mcap.part")
    assert recover(part, tmp_path / "r.mcap").messages == 0


def test_failed_rotation_opens_no_new_file(tmp_path: Path) -> None:
    full = threading.Event()
    opened: list[Path] = []

    def opener(p: Path) -> IO[bytes]:
        opened.append(p)
        return _FullDisk(p, 1 << 30, full)  # type: ignore[return-value]

    rec = Recorder(_cfg(tmp_path, rotate_duration_s=0.2, flush_interval_s=100.0), opener=opener)
    with rec:
        rec.put("/img", IMAGE, _img(0))
        deadline = time.monotonic() + 10
        while not rec.stats.current_file and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)
        full.set()
        time.sleep(0.3)
        rec.put("/img", IMAGE, _img(1))  # rotation: finishing the first file fails
        while not rec.stats.error and time.monotonic() < deadline:
            time.sleep(0.01)
    s = rec.stats
    assert len(opened) == 1, opened
    assert s.error.startswith("finish") and s.disk_full
    assert s.written == 0 and s.dropped_error == 2 == s.received
    assert [p.name for p in tmp_path.glob("*.part")] == [opened[0].name] and s.files == []


def test_queue_bytes_bound_includes_the_message_being_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    size, bound = 16 * 1024, 1 << 20
    rec = Recorder(_cfg(tmp_path, queue_max_bytes=bound), queue_size=100_000)
    done = [0]
    peak = [0]

    def held() -> int:
        """Payload bytes accepted and neither written nor dropped (whatever holds them)."""
        with rec._cv:
            s = rec.stats
            return (s.received - s.dropped_queue - s.dropped_error - done[0]) * size

    orig = rec._write

    def slow_write(item: Any) -> None:
        peak[0] = max(peak[0], held())
        time.sleep(0.002)
        orig(item)
        done[0] += 1

    monkeypatch.setattr(rec, "_write", slow_write)
    blob = b"\x00\x01\x00\x00" + bytes(size - 4)
    with rec:
        for _ in range(300):
            rec.put("/img", IMAGE, blob)
            peak[0] = max(peak[0], held())
            time.sleep(0.0002)
    s = rec.stats
    assert s.dropped_queue > 0 and s.written + s.dropped_queue == s.received == 300
    assert peak[0] <= bound, (peak[0] / bound, s.dropped_queue)
    assert rec.queued_bytes == 0


def test_stop_timeout_is_reported(tmp_path: Path) -> None:
    gate = threading.Event()

    def opener(p: Path) -> IO[bytes]:
        return GatedFile(p, gate)  # type: ignore[return-value]

    rec = Recorder(_cfg(tmp_path), opener=opener).start()
    try:
        rec.put("/img", IMAGE, _img(0))
        assert rec.stop(timeout=0.2) == []
        assert "did not finish within 0.2 s" in rec.stats.error
        (part,) = tmp_path.glob("*.mcap.part")
        assert str(part) in rec.stats.error and "pugsd mcap recover" in rec.stats.error
    finally:
        gate.set()
        assert rec._thread is not None
        rec._thread.join(30)


def test_status_dict_is_bounded(tmp_path: Path) -> None:
    rec = Recorder(_cfg(tmp_path))
    rec.stats.files.extend(f"/r/pugsd_{i:03d}.mcap" for i in range(1000))
    rec.stats.files_finished = 1000
    d = rec.stats.as_dict()
    assert "files" not in d and d["files_finished"] == 1000 and d["last_file"] == "/r/pugsd_999.mcap"
    assert len(json.dumps(d)) < 1000
    assert len(rec.stats.files) == 1000  # the full list stays on the object
    assert Recorder(_cfg(tmp_path)).stats.as_dict()["last_file"] == ""


def test_unusable_directory_is_reported(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rec = Recorder(_cfg(blocker / "sub"))
    with rec:
        assert rec.stats.error and "cannot create" in rec.stats.error
        assert not rec.put("/img", IMAGE, _img(0))
    assert rec.stats.dropped_error == 1 and rec.stats.files == []


def test_a_bad_message_does_not_stop_the_writer(tmp_path: Path) -> None:
    rec = Recorder(_cfg(tmp_path))
    with rec:
        rec.put("/x", "no_pkg/msg/Nope", b"\x00\x01\x00\x00")  # no schema for this type
        rec.put("/img", IMAGE, _img(1))
    assert rec.stats.dropped_error == 1 and rec.stats.written == 1 and "/x" in rec.stats.error
    assert len(rec.stats.files) == 1


# ------------------------------------------------------------------ review fixes


def _read_all(path: str | Path) -> tuple[list[Any], Any]:
    """Every message record of a file (file order) and its summary, through the mcap reader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        msgs = [m for _, _, m in reader.iter_messages(log_time_order=False)]
        summary = reader.get_summary()
    return msgs, summary


def test_a_negative_source_timestamp_does_not_corrupt_the_chunk(tmp_path: Path) -> None:
    """Any int64 is a valid rmw_zenoh source time; MCAP's publish_time is uint64. Before the fix
    message 5 made struct.pack fail inside add_message after the chunk index was updated: the
    summary said 10 messages and reading stopped after 4."""
    key = topic_key("/camera_pose", POSE_COV_STAMPED)
    gid = bytes(range(16))
    payloads = [codec.encode_pose_with_covariance(i, np.eye(4), np.eye(6) * 1e-4) for i in range(1, 11)]
    rec = Recorder(_cfg(tmp_path))
    with rec:
        for i, p in enumerate(payloads, start=1):
            ts = -5 if i == 5 else 1_700_000_000_000_000_000 + i
            assert rec.put_sample(key, p, encode_attachment(i, ts, gid), 9_000 + i)
    s = rec.stats
    assert s.written == 10 and s.dropped_error == 0 and s.bad_attachment == 1 and not s.error
    (f,) = rec.stats.files
    msgs, summary = _read_all(f)
    assert [bytes(m.data) for m in msgs] == payloads  # all ten, intact, in order
    assert [codec.decode_pose_with_covariance(m.data).stamp_ns for m in msgs] == list(range(1, 11))
    assert [m.sequence for m in msgs] == list(range(1, 11))
    pubs = [m.publish_time for m in msgs]
    assert pubs[4] == msgs[4].log_time == 9_005  # the receive time instead of -5
    assert pubs[:4] + pubs[5:] == [1_700_000_000_000_000_000 + i for i in (1, 2, 3, 4, 6, 7, 8, 9, 10)]
    assert summary.statistics.message_count == 10 == len(msgs)
    assert sum(summary.statistics.channel_message_counts.values()) == 10


def test_put_drops_and_counts_times_and_sequences_mcap_cannot_store(tmp_path: Path) -> None:
    bad = [
        {"log_time_ns": -1},
        {"publish_time_ns": -5},
        {"publish_time_ns": 2**64},
        {"sequence": 2**32},
        {"sequence": -1},
    ]
    good = [_img(i) for i in range(6)]
    rec = Recorder(_cfg(tmp_path))
    with rec:
        for i, g in enumerate(good):
            assert rec.put("/img", IMAGE, g, log_time_ns=100 + i, publish_time_ns=2**64 - 1,
                           sequence=2**32 - 1)  # fmt: skip
            if i < len(bad):
                assert not rec.put("/img", IMAGE, _img(99), **{"log_time_ns": 200, **bad[i]})
    s = rec.stats
    assert s.dropped_invalid == len(bad) and s.written == len(good) and s.dropped_error == 0
    assert s.received == len(good) + len(bad)
    msgs, summary = _read_all(rec.stats.files[0])
    assert [bytes(m.data) for m in msgs] == good
    assert {(m.publish_time, m.sequence) for m in msgs} == {(2**64 - 1, 2**32 - 1)}
    assert summary.statistics.message_count == len(good)


def test_the_writer_checks_ranges_before_add_message(tmp_path: Path) -> None:
    """Defence in depth: an out-of-range item that reaches the writer queue without put() (a
    future intake path) is dropped and counted, and the chunk stays readable."""
    from pugsd.record.recorder import _Item

    rec = Recorder(_cfg(tmp_path))
    with rec:
        rec.put("/img", IMAGE, _img(1), log_time_ns=1)
        with rec._cv:
            rec._q.append(_Item("/img", IMAGE, "", _img(2), 2, -2, 0))
            rec._q_bytes += len(_img(2))
            rec._cv.notify()
        rec.put("/img", IMAGE, _img(3), log_time_ns=3)
    msgs, summary = _read_all(rec.stats.files[0])
    assert [bytes(m.data) for m in msgs] == [_img(1), _img(3)]
    assert summary.statistics.message_count == 2
    assert rec.stats.dropped_invalid == 1 and rec.stats.written == 2


def test_ros2dds_topic_names_are_normalised(tmp_path: Path) -> None:
    """[topics] names without a leading '/' or with a trailing one (accepted by the config and
    stripped by the wire layer) were unknown to the recorder: every such sample was dropped."""
    from pugsd.daemon.config import TopicsConfig
    from pugsd.wire.topics import key_for, topic_types

    t = TopicsConfig(key_style="ros2dds", left_image="stereo/left/image_raw", pose="/camera_pose/")
    img = _img(1)
    pose = codec.encode_pose_with_covariance(1, np.eye(4), np.eye(6) * 1e-4)
    rec = Recorder(_cfg(tmp_path), topic_types=topic_types(t))
    with rec:
        for role, data in (("left_image", img), ("pose", pose), ("right_image", img)):
            assert rec.put_sample(key_for(t, role), data, None), role
    assert rec.stats.unknown_type == 0 and rec.stats.written == 3
    with open(rec.stats.files[0], "rb") as f:
        got = [(c.topic, sc.name, bytes(m.data)) for sc, c, m in make_reader(f).iter_messages()]
    assert got == [
        ("/stereo/left/image_raw", IMAGE, img),
        ("/camera_pose", POSE_COV_STAMPED, pose),
        ("/stereo/right/image_raw", IMAGE, img),
    ]


def _fixed_stamp(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every recorder starts "in the same second"."""
    from datetime import UTC, datetime

    import pugsd.record.recorder as recmod

    fixed = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)

    class _Frozen(datetime):
        @classmethod
        def now(cls, tz: Any = None) -> Any:
            return fixed

    monkeypatch.setattr(recmod, "datetime", _Frozen)


def _topics_and_counts(path: Path) -> tuple[set[str], int]:
    msgs: list[Any] = []
    with open(path, "rb") as f:
        msgs = [(c.topic, m) for _, c, m in make_reader(f).iter_messages()]
    return {t for t, _ in msgs}, len(msgs)


def test_recorders_started_in_the_same_second_never_overwrite_each_other(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fixed_stamp(monkeypatch)
    # one after the other (a daemon restarted by systemd): the second used to replace the first
    a = Recorder(_cfg(tmp_path))
    with a:
        for i in range(50):
            a.put("/a", IMAGE, _img(i))
    b = Recorder(_cfg(tmp_path))
    with b:
        for i in range(3):
            b.put("/b", IMAGE, _img(i))
    # at the same time (`pugsd record` next to the daemon): "wb" truncated the other's .part
    c, d = Recorder(_cfg(tmp_path)).start(), Recorder(_cfg(tmp_path)).start()
    for i in range(7):
        c.put("/c", IMAGE, _img(i))
        d.put("/d", IMAGE, _img(i))
        time.sleep(0.005)
    c.stop()
    d.stop()
    files = [Path(f) for r in (a, b, c, d) for f in r.stats.files]
    assert len(files) == 4 and len({f.name for f in files}) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f.name for f in files)
    assert [_topics_and_counts(f) for f in files] == [({"/a"}, 50), ({"/b"}, 3), ({"/c"}, 7), ({"/d"}, 7)]
    assert all(f.name.startswith("pugsd_20260102T030405Z_") for f in files)


def test_a_finished_file_never_replaces_an_existing_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The final name can appear while the .part is written (another writer that finished in
    between): the rename goes to the next free index instead of replacing it."""
    _fixed_stamp(monkeypatch)
    rec = Recorder(_cfg(tmp_path)).start()
    rec.put("/x", IMAGE, _img(1))
    deadline = time.monotonic() + 10
    while not list(tmp_path.glob("*.part")) and time.monotonic() < deadline:
        time.sleep(0.01)
    (part,) = tmp_path.glob("*.part")
    other = part.with_name(part.name[: -len(".part")])
    other.write_bytes(b"someone else's recording")
    (mine,) = rec.stop()
    assert other.read_bytes() == b"someone else's recording"
    assert mine != other and mine.exists() and not part.exists()
    assert _topics_and_counts(mine) == ({"/x"}, 1)


def test_zenoh_delete_samples_are_skipped_and_counted(tmp_path: Path, daemon_side: Any) -> None:
    """A DELETE (empty payload) used to be recorded as an empty message that no ros2msg/cdr
    reader (mcap_ros2, Foxglove) can decode."""
    from pugsd.wire.keys import subscription_key
    from pugsd.wire.publisher import Publisher
    from pugsd.wire.session import close_session, loopback_config, open_session

    session, port = daemon_side
    other = open_session(loopback_config(connect_ports=[port]), require_loopback=True)
    key = topic_key("/camera_pose", POSE_COV_STAMPED)
    poses = [codec.encode_pose_with_covariance(i, np.eye(4), np.eye(6) * 1e-4) for i in (1, 2)]
    rec = Recorder(_cfg(tmp_path)).start()
    try:
        rec.subscribe(session, [subscription_key("/camera_pose")])
        pub = Publisher(other, key)
        deadline = time.monotonic() + 10
        while not pub.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        pub.put(poses[0])
        other.delete(key)
        pub.put(poses[1])
        deadline = time.monotonic() + 10
        while rec.stats.received < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        pub.undeclare()
    finally:
        files = rec.stop()
        close_session(other)
    with open(files[0], "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert [bytes(m.message.data) for m in decoded] == poses
    assert [int(m.decoded_message.header.stamp.nanosec) for m in decoded] == [1, 2]
    assert rec.stats.deletes == 1 and rec.stats.written == 2 and rec.stats.callback_errors == 0


def test_an_exception_in_the_zenoh_callback_is_counted(tmp_path: Path) -> None:
    class _Payload:
        def to_bytes(self) -> bytes:
            raise RuntimeError("payload gone")

    class _Sample:
        key_expr = topic_key("/camera_pose", POSE_COV_STAMPED)
        payload = _Payload()
        attachment = None
        kind = None

    rec = Recorder(_cfg(tmp_path))
    with rec:
        rec.on_sample(_Sample())
        rec.on_sample(_Sample())
    assert rec.stats.callback_errors == 2 and rec.stats.as_dict()["callback_errors"] == 2
    assert rec.stats.written == 0


def test_ros2dds_pose_is_recorded_with_the_configured_pose_type(tmp_path: Path) -> None:
    """ros2dds keys carry no type: with [topics] pose_type = PoseStamped the pose channel must
    get the PoseStamped schema (it used to be labelled PoseWithCovarianceStamped, undecodable)."""
    from pugsd.daemon.config import TopicsConfig
    from pugsd.wire.topics import key_for, topic_types
    from pugsd.wire.types import POSE_STAMPED

    t = TopicsConfig(key_style="ros2dds", pose_type="PoseStamped")
    pose = codec.encode_pose_stamped(7, np.eye(4))
    rec = Recorder(_cfg(tmp_path), topic_types=topic_types(t))
    with rec:
        assert rec.put_sample(key_for(t, "pose", POSE_STAMPED), pose, None)
    with open(rec.stats.files[0], "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert [(d.schema.name, d.channel.topic, bytes(d.message.data)) for d in decoded] == [
        (POSE_STAMPED, "/camera_pose", pose)
    ]
    assert int(decoded[0].decoded_message.header.stamp.nanosec) == 7


def test_outputs_without_inputs_are_counted_and_warned_of_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A recorder that hears the daemon's grasps but none of its camera says so: in its stats
    (and the status dict) from the first output, in the log once at OUTPUTS_BEFORE_WARNING; an
    input clears it. The status output alone (an idle daemon) is neither."""
    from pugsd.config import default_config
    from pugsd.record.recorder import OUTPUTS_BEFORE_WARNING, default_record_keys, watched_topics

    cfg = default_config()
    inputs, outputs = watched_topics(cfg, default_record_keys(cfg))
    assert "/stereo/left/image_raw" in inputs and "/pugs/grasps" in outputs
    assert "/pugs/status" not in outputs | inputs
    rec = Recorder(_cfg(tmp_path), input_topics=inputs, output_topics=outputs)
    rec.put("/pugs/status", "std_msgs/msg/String", b"x")
    assert not rec.stats.missing_inputs
    with caplog.at_level("WARNING", logger="pugsd.record.recorder"):
        for _ in range(2 * OUTPUTS_BEFORE_WARNING):
            rec.put("pugs/grasps", "pugs_msgs/msg/GraspArray", b"g")  # normalised: /pugs/grasps
            assert rec.stats.missing_inputs and rec.stats.as_dict()["missing_inputs"]
    warned = [r for r in caplog.records if "none on its inputs" in r.getMessage()]
    assert len(warned) == 1
    assert (rec.stats.outputs_received, rec.stats.inputs_received) == (2 * OUTPUTS_BEFORE_WARNING, 0)
    rec.put("/stereo/left/image_raw", IMAGE, codec.encode_image(np.zeros((2, 2), np.uint8), 1))
    assert rec.stats.inputs_received == 1 and not rec.stats.missing_inputs
    rec.stop()


def test_watched_topics_are_those_the_keys_subscribe_to() -> None:
    from pugsd.config import default_config
    from pugsd.record.recorder import watched_topics

    cfg = default_config()
    assert watched_topics(cfg, ["0/pugs/**"]) == (frozenset(), frozenset(
        {"/pugs/grasps", "/pugs/grasp_markers", "/pugs/cloud"}))  # fmt: skip
    inputs, outputs = watched_topics(cfg, ["0/camera_pose/**", "1/**", "a//b"])  # 'a//b': refused
    assert (inputs, outputs) == (frozenset({"/camera_pose"}), frozenset())
