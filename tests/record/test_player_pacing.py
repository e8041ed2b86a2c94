# SPDX-License-Identifier: Apache-2.0
"""Player timing rule, stop and option checks, without zenoh: each message is published at
(its log_time - the first *played* message's log_time) / rate after the start, a stop ends the
playback at once (also during a long pacing wait and at rate 0), a remapped ros2dds key stays
ros2dds, and negative offsets are refused."""

from __future__ import annotations

import threading
import time
import types
from typing import Any

import pytest

from pugsd.errors import ConfigError
from pugsd.record.mcapio import RecordedMessage, iter_recording
from pugsd.record.player import Player, PlayOptions, output_key
from pugsd.wire.types import POSE_COV_STAMPED


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now


class _ClockEvent(threading.Event):
    """A stop event whose ``wait`` advances the fake clock instead of sleeping."""

    def __init__(self, clock: _Clock) -> None:
        super().__init__()
        self.clock = clock

    def wait(self, timeout: float | None = None) -> bool:
        if not self.is_set() and timeout:
            self.clock.now += timeout
        return self.is_set()


class _Pub:
    matching_status = True

    def __init__(self, key: str, sent: list[tuple[float, str]], clock: _Clock | None) -> None:
        self.key, self.sent, self.clock = key, sent, clock

    def put(self, payload: bytes, **_: Any) -> None:
        self.sent.append((self.clock.now if self.clock else time.monotonic(), self.key))

    def undeclare(self) -> None:
        pass


class _Session:
    """Records (time, key) of each put; no zenoh."""

    def __init__(self, clock: _Clock | None = None) -> None:
        self.clock = clock
        self.sent: list[tuple[float, str]] = []

    def declare_publisher(self, key: str, **_: Any) -> _Pub:
        return _Pub(key, self.sent, self.clock)


@pytest.mark.parametrize("rate", [1.0, 3.0, 0.5])
def test_messages_are_published_at_their_log_time_offsets_divided_by_rate(
    synth_recording: Any, monkeypatch: pytest.MonkeyPatch, rate: float
) -> None:
    src, _ = synth_recording
    clock = _Clock()
    monkeypatch.setattr("pugsd.record.player.time", types.SimpleNamespace(monotonic=clock.monotonic))
    session = _Session(clock)
    n = Player(session, [src], PlayOptions(rate=rate), stop_event=_ClockEvent(clock)).run()
    logs = [m.log_time_ns for m in iter_recording([src])]
    assert n == len(logs) == len(session.sent) == 24
    want = [(t - logs[0]) / 1e9 / rate for t in logs]
    assert [t for t, _ in session.sent] == pytest.approx(want, abs=1e-9)


def test_start_offset_is_not_waited_for(synth_recording: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """--start 0.05 (from the first message, at 0.1 s) skips the first frame and plays the second
    (0.2 s) at once: pacing counts from the first message played, not the recording's first."""
    src, _ = synth_recording
    clock = _Clock()
    monkeypatch.setattr("pugsd.record.player.time", types.SimpleNamespace(monotonic=clock.monotonic))
    session = _Session(clock)
    opts = PlayOptions(rate=1.0, start_s=0.05, topics=("/camera_pose",))
    assert Player(session, [src], opts, stop_event=_ClockEvent(clock)).run() == 3
    assert [t for t, _ in session.sent] == pytest.approx([0.0, 0.1, 0.2], abs=1e-9)


@pytest.mark.timeout(30)
def test_a_stop_ends_a_long_pacing_wait_at_once(synth_recording: Any) -> None:
    """At rate 0.001 the next frame is 100 s away: a stop (SIGINT/SIGTERM in the CLI) 0.2 s in
    returns at once instead of after the wait."""
    src, _ = synth_recording
    stop = threading.Event()
    timer = threading.Timer(0.2, stop.set)
    timer.start()
    session = _Session()
    t0 = time.monotonic()
    try:
        n = Player(session, [src], PlayOptions(rate=0.001), stop_event=stop).run()
    finally:
        timer.cancel()
    assert time.monotonic() - t0 < 5.0
    assert n == 6  # the first frame's six messages (1 ms apart at this rate)


def test_a_stop_at_rate_0_ends_the_pass(synth_recording: Any) -> None:
    src, _ = synth_recording
    stop = threading.Event()

    def progress(p: Any) -> None:
        if p.published >= 3:
            stop.set()

    session = _Session()
    player = Player(session, [src], PlayOptions(rate=0), progress=progress, progress_interval_s=0.0,
                    stop_event=stop)  # fmt: skip
    assert player.run() == 3 and len(session.sent) == 3


def test_a_remapped_ros2dds_key_stays_ros2dds() -> None:
    msg = RecordedMessage("/camera_pose", POSE_COV_STAMPED, "camera_pose", b"", 1, 1, 1, 0)
    assert output_key(msg, PlayOptions(remap={"/camera_pose": "/p2"})) == "p2"


@pytest.mark.parametrize("start, end", [(-1.0, None), (0.2, 0.2), (0.3, 0.1)])
def test_bad_offsets_are_refused(start: float, end: float | None) -> None:
    with pytest.raises(ConfigError, match="bad start/end"):
        PlayOptions(start_s=start, end_s=end)
