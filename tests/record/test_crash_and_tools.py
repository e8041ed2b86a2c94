# SPDX-License-Identifier: Apache-2.0
"""`pugsd record` as a process: SIGKILL then `mcap recover`; SIGTERM finishes cleanly. Tools."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import breakup_chunk, make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from pugsd.cli import main
from pugsd.errors import PugsdError
from pugsd.record import recorder as recorder_mod
from pugsd.record.mcapio import iter_recording, recover, scan
from pugsd.record.recorder import Recorder
from pugsd.record.synth import write_recording
from pugsd.wire import codec
from pugsd.wire.keys import topic_key
from pugsd.wire.publisher import Publisher
from pugsd.wire.types import IMAGE
from tests.record.conftest import GatedFile

N_MSGS = 80
CHUNK = 65536
IMG = (64, 64)  # 4 kB + header per message: about 16 messages per chunk


def _spawn_recorder(out: Path, port: int) -> subprocess.Popen[bytes]:
    cmd = [
        sys.executable, "-m", "pugsd", "record",
        "--connect", f"tcp/127.0.0.1:{port}",
        "--out", str(out),
        "--key", "0/crash/**",
        "--set", f"record.chunk_size_bytes={CHUNK}",
        "--set", "record.flush_interval_s=100.0",
        "--status-interval", "0.05",
    ]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


class _Lines:
    """Collects a pipe's lines on a thread (so the test never blocks on the child)."""

    def __init__(self, pipe: Any) -> None:
        self.lines: list[str] = []
        self.t = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self.t.start()

    def _read(self, pipe: Any) -> None:
        for raw in iter(pipe.readline, b""):
            self.lines.append(raw.decode(errors="replace"))

    def wait_for(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in ln for ln in list(self.lines)):
                return True
            time.sleep(0.02)
        return False

    def wait_status(self, received: int, timeout: float) -> tuple[int, int] | None:
        """(written, buffered) of the first status line where every received message has
        reached the writer (received == written + buffered), or None."""
        pat = re.compile(r"received=(\d+) written=(\d+) buffered=(\d+)")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for ln in list(self.lines):
                m = pat.search(ln)
                if m and int(m[1]) == received == int(m[2]) + int(m[3]):
                    return int(m[2]), int(m[3])
            time.sleep(0.02)
        return None


def _publish(session: Any, proc: subprocess.Popen[bytes]) -> list[bytes]:
    pub = Publisher(session, topic_key("/crash", IMAGE))
    try:
        deadline = time.monotonic() + 30
        while not pub.matching:
            assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
            assert time.monotonic() < deadline, "recorder process never subscribed"
            time.sleep(0.05)
        rng = np.random.default_rng(0)
        sent = []
        for i in range(N_MSGS):
            img = rng.integers(0, 255, IMG, dtype=np.uint8)
            img[0, 0] = i
            data = codec.encode_image(img, i + 1, "crash")
            pub.put(data)
            sent.append(data)
            time.sleep(0.01)
    finally:
        pub.undeclare()
    return sent


@pytest.mark.timeout(90)
def test_sigkill_then_recover_loses_at_most_the_open_chunk(
    daemon_side: tuple[Any, int], tmp_path: Path
) -> None:
    session, port = daemon_side
    proc = _spawn_recorder(tmp_path, port)
    err = _Lines(proc.stderr)
    try:
        sent = _publish(session, proc)
        # kill only once everything is in the writer (its status lines say so); `written` counts
        # the messages of chunks in the file, `buffered` those of the open chunk
        st = err.wait_status(N_MSGS, 30)
        assert st is not None, err.lines[-3:]
        written, _buffered = st
    finally:
        os.kill(proc.pid, signal.SIGKILL)  # the recorder we started, by its pid
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    (part,) = list(tmp_path.glob("*.mcap.part"))
    assert not list(tmp_path.glob("*.mcap"))
    info = scan(part)
    assert not info.complete and info.error == "end of file before the footer"  # not mcap's bare EndOfFile
    out = tmp_path / "recovered.mcap"
    res = recover(part, out)
    assert res.error == "end of file before the footer"  # stopped at the torn end
    got = [m.data for m in iter_recording([out])]
    assert got == sent[: len(got)]  # a prefix, in order, byte-identical
    per_chunk = CHUNK // len(sent[0]) + 1
    assert N_MSGS - per_chunk <= len(got) <= N_MSGS, (len(got), per_chunk)
    assert len(got) >= written  # what was reported written is in the file
    with open(out, "rb") as f:  # a complete, indexed file again
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(got)
        decoded = [d for *_, d in reader.iter_decoded_messages()]
    assert [d.data[0] for d in decoded] == list(range(len(got)))
    assert {m.name for m in reader_metadata(out)} >= {"pugsd.versions", "pugsd.record"}


def reader_metadata(path: Path) -> list[Any]:
    with open(path, "rb") as f:
        return list(make_reader(f).iter_metadata())


@pytest.mark.timeout(90)
def test_sigterm_finishes_the_file(daemon_side: tuple[Any, int], tmp_path: Path) -> None:
    session, port = daemon_side
    proc = _spawn_recorder(tmp_path, port)
    err = _Lines(proc.stderr)
    try:
        sent = _publish(session, proc)
        assert err.wait_for(f"received={N_MSGS}", 30), err.lines[-3:]  # SIGTERM stops intake
        os.kill(proc.pid, signal.SIGTERM)
        proc.wait(15)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)
    assert proc.returncode == 0, "".join(err.lines)
    assert not list(tmp_path.glob("*.part"))
    (final,) = list(tmp_path.glob("*.mcap"))
    assert [m.data for m in iter_recording([final])] == sent
    info = scan(final)
    assert info.complete and info.message_count == N_MSGS
    assert "pugsd.config" in info.metadata and "toml" in info.metadata["pugsd.config"]


def _chunk_ends(path: Path) -> list[tuple[int, int]]:
    """(end offset, messages) of each chunk of a complete file, in file order."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(index)
    return [(ci.chunk_start_offset + ci.chunk_length,
             sum(isinstance(r, Message) for r in breakup_chunk(ch)))
            for ci, ch in zip(index, chunks, strict=True)]  # fmt: skip


def test_recover_truncated_files_in_process(frames_factory: Any, tmp_path: Path) -> None:
    """Each cut recovers, in order and byte-identical, at least every message of the chunks that
    ended before the cut (only the torn chunk is lost); a cut at len-1 recovers everything."""
    src = tmp_path / "src.mcap"
    write_recording(src, frames_factory(6), chunk_size=16384)  # several chunks
    data = src.read_bytes()
    full = [m.data for m in iter_recording([src])]
    ends = _chunk_ends(src)
    assert len(ends) >= 4 and sum(n for _, n in ends) == len(full)
    cuts = {len(data) - 1, len(data) // 2, 200}
    cuts |= {e + d for e, _ in ends for d in (-1, 0, 1)}
    for cut in sorted(cuts):
        p = tmp_path / f"cut{cut}.mcap.part"
        p.write_bytes(data[:cut])
        out = tmp_path / f"cut{cut}.mcap"
        complete_before = sum(n for e, n in ends if e <= cut)
        try:
            res = recover(p, out)
        except PugsdError as exc:  # only when not even the header survived
            assert cut <= 200 and complete_before == 0, exc
            continue
        got = [m.data for m in iter_recording([out])]
        assert got == full[: len(got)], cut
        assert res.messages == len(got) >= complete_before, (cut, len(got), complete_before)
        if cut == len(data) - 1:
            assert len(got) == len(full)
    # recovering a complete file keeps everything
    res = recover(src, tmp_path / "same.mcap")
    assert res.messages == len(full) and res.error == ""


def test_scan_counts_the_whole_chunks_of_an_incomplete_file(frames_factory: Any, tmp_path: Path) -> None:
    """``mcap info`` on a file without a summary (a recorder's .part, a crash) streams through it;
    its chunk count is that of the chunks read whole (it said 0 chunks before)."""
    src = tmp_path / "src.mcap"
    write_recording(src, frames_factory(6), chunk_size=16384)
    data = src.read_bytes()
    ends = _chunk_ends(src)
    assert scan(src).complete and scan(src).chunk_count == len(ends) >= 4
    no_footer = tmp_path / "no_footer.mcap.part"
    no_footer.write_bytes(data[:-100])
    info = scan(no_footer)
    assert not info.complete and info.chunk_count == len(ends)
    cut = ends[2][0] + 10  # inside the fourth chunk: three read whole
    torn = tmp_path / "torn.mcap.part"
    torn.write_bytes(data[:cut])
    info = scan(torn)
    assert not info.complete and info.chunk_count == 3
    assert info.message_count == sum(n for _, n in ends[:3])


def test_cli_info_and_recover(synth_recording: Any, tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    src, _ = synth_recording
    assert main(["mcap", "info", str(src)]) == 0
    out = capsys.readouterr().out
    assert "24 messages" in out and "/stereo/left/image_raw  [sensor_msgs/msg/Image]" in out
    assert "schema sensor_msgs/msg/CameraInfo (ros2msg)" in out
    part = tmp_path / "x.mcap.part"
    part.write_bytes(Path(src).read_bytes()[:-100])
    assert main(["mcap", "recover", str(part), str(tmp_path / "x.mcap")]) == 0
    assert "recovered 24 messages" in capsys.readouterr().out
    assert main(["mcap", "info", "--json", str(part)]) == 0
    assert '"complete": false' in capsys.readouterr().out


def test_cli_file_errors_are_one_line(synth_recording: Any, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """Missing inputs and unwritable outputs: exit 1 with a one-line error naming the file."""
    src, _ = synth_recording
    missing = tmp_path / "missing.mcap"
    out = tmp_path / "out.mcap"
    cases = [
        (["mcap", "info", str(missing)], str(missing)),
        (["mcap", "recover", str(missing), str(out)], str(missing)),
        (["mcap", "recover", str(src), str(tmp_path / "nodir" / "x.mcap")], "nodir/x.mcap"),
        (["replay", str(missing)], str(missing)),
        # an output that cannot be written: before the pipeline runs (a file where --out's
        # directory would be), and the synthetic recording's file
        (
            ["replay", str(src), "--out", str(tmp_path / "afile" / "sub"), "--set", "stereo.downsample=1"],
            "afile/sub",
        ),
        (["mcap", "synth", str(tmp_path / "nodir" / "s.mcap"), "--frames", "1"], "nodir/s.mcap"),
    ]
    (tmp_path / "afile").write_text("not a directory")
    for argv, name in cases:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "error:" in err and name in err, (argv, err)
    assert not list(tmp_path.glob("**/*.recovering")) and not out.exists()
    # the library functions raise PugsdError too (not OSError)
    with pytest.raises(PugsdError, match=r"missing\.mcap"):
        list(iter_recording([missing]))
    with pytest.raises(PugsdError, match=r"missing\.mcap"):
        scan(missing)


def test_a_file_that_is_not_an_mcap_is_said_so_and_info_goes_on_with_the_others(
    synth_recording: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """info called it an INCOMPLETE MCAP (exit 0), and replay / play suggested `pugsd mcap
    recover`, which cannot help a file that is not one."""
    src, _ = synth_recording
    text, empty = tmp_path / "notes.mcap", tmp_path / "empty.mcap"
    text.write_text("hello\n")
    empty.write_bytes(b"")
    assert main(["mcap", "info", str(text), str(src), str(empty)]) == 1
    out, err = capsys.readouterr()
    assert err.splitlines() == [
        f"pugsd mcap info: error: {text}: not an MCAP file (it does not start with the MCAP magic)",
        f"pugsd mcap info: error: {empty}: not an MCAP file (an empty file)",
    ]
    assert out.startswith(f"{src}: ") and ", complete\n" in out  # the good one is still listed
    for path in (text, empty):
        with pytest.raises(PugsdError, match=r"not an MCAP file") as exc:
            list(iter_recording([src, path]))
        assert "recover" not in str(exc.value)
    truncated = tmp_path / "cut.mcap"
    truncated.write_bytes(src.read_bytes()[:1000])  # an MCAP cut short is still one: recover it
    assert not scan(truncated).complete


def test_recover_removes_its_temp_file_when_writing_fails(
    synth_recording: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mcap.writer import Writer

    src, _ = synth_recording

    def no_space(self: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "finish", no_space)
    out = tmp_path / "out.mcap"
    with pytest.raises(PugsdError, match=r"cannot write .*out\.mcap: No space left"):
        recover(src, out)
    assert list(tmp_path.iterdir()) == []


def test_cli_record_bad_key_is_an_error_and_closes_the_session(
    daemon_side: tuple[Any, int], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch, restore_signals: None,
) -> None:  # fmt: skip
    import pugsd.wire.session as ws

    _, port = daemon_side
    closed: list[Any] = []
    orig_close = ws.close_session

    def close(session: Any, *a: Any) -> None:
        closed.append(session)
        orig_close(session, *a)

    monkeypatch.setattr(ws, "close_session", close)
    rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path),
               "--key", "0/ok/**", "--key", "a//b", "--duration", "5"])  # fmt: skip
    err = capsys.readouterr().err
    assert rc == 1 and "'a//b'" in err and "Traceback" not in err, err
    assert len(closed) == 1 and not list(tmp_path.iterdir())


def test_cli_record_exits_1_when_the_writer_does_not_finish(
    daemon_side: tuple[Any, int], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch, restore_signals: None,
) -> None:  # fmt: skip
    _, port = daemon_side
    gate = threading.Event()
    recs: list[Recorder] = []
    orig_start = Recorder.start

    def start(self: Recorder) -> Recorder:
        orig_start(self)
        recs.append(self)
        self.put("/crash", "sensor_msgs/msg/Image", codec.encode_image(np.zeros((4, 4), np.uint8), 1))
        return self

    monkeypatch.setattr(recorder_mod, "_default_opener", lambda p: GatedFile(p, gate))
    monkeypatch.setattr(Recorder, "start", start)
    monkeypatch.setattr(Recorder.stop, "__defaults__", (0.3,))  # stop(timeout=0.3)
    try:
        rc = main(["record", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path),
                   "--key", "0/crash/**", "--duration", "0.2", "--status-interval", "0"])  # fmt: skip
        err = capsys.readouterr().err
        assert rc == 1, err
        assert "error: writer did not finish within 0.3 s" in err and ".mcap.part left" in err
    finally:
        gate.set()
        for r in recs:
            assert r._thread is not None
            r._thread.join(30)


def test_cli_play_and_synth(daemon_side: tuple[Any, int], synth_recording: Any, tmp_path: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    session, port = daemon_side
    src, _ = synth_recording
    got: list[bytes] = []
    sub = session.declare_subscriber("0/**", lambda s: got.append(s.payload.to_bytes()))
    handlers = (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT))
    try:
        rc = main(["play", str(src), "--connect", f"tcp/127.0.0.1:{port}", "--rate", "0",
                   "--quiet", "--wait-subscribers", "3"])  # fmt: skip
        deadline = time.monotonic() + 5
        while len(got) < 24 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        sub.undeclare()
        signal.signal(signal.SIGTERM, handlers[0])
        signal.signal(signal.SIGINT, handlers[1])
    assert rc == 0 and "24 messages published" in capsys.readouterr().err
    assert got == [m.data for m in iter_recording([src])]
    with pytest.raises(SystemExit):
        main(["play"])  # missing FILE
    assert main(["play", str(tmp_path / "missing.mcap")]) == 1
