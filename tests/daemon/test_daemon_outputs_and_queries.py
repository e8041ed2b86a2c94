# SPDX-License-Identifier: Apache-2.0
"""The daemon's output, query, arm and health paths (its input path is
test_daemon_input_accounting.py's): queries are answered on their own key with fixed texts and never
block; state-changing ones act only on their exact key; an arm stop always gets an answer, even in a
flood; grasps carry the stamp of their snapshot and are never published from a reset map; a failed
put is counted; the status says what it claims; shutdown undeclares everything and counts abandoned
work. No zenoh session: the handlers are called directly with stand-in queries, publishers, loops
and arms."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import sys
import threading
import time
import types
from typing import Any

import numpy as np
import pytest
import threadpoolctl

from pugsd.config import load_config_dict
from pugsd.core.types import DepthFrame
from pugsd.daemon.app import Command, Daemon
from pugsd.daemon.bridge import IngressGate
from pugsd.daemon.mailbox import Mailbox, Overflow
from pugsd.daemon.notify import Notifier
from pugsd.daemon.process import apply_thread_limits
from pugsd.daemon.recording import FINISH_TIMEOUT_S
from pugsd.errors import EmptyCloudError, PugsdError
from pugsd.wire import codec
from pugsd.wire.types import GRASP_ARRAY, MARKER_ARRAY
from tests.daemon.conftest import RIG, FakePipeline, RecordingPublisher

ROLES = ("grasps", "markers", "cloud", "status")


def _daemon(pipe: FakePipeline | None = None, **daemon: Any) -> Daemon:
    d = Daemon(load_config_dict({"daemon": daemon}), pipe or FakePipeline(), notifier=Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ROLES}  # type: ignore[misc]
    return d


def _shutdown(d: Daemon) -> None:
    for ex in (d._depth_exec, d._model_exec, d._train_exec, d._grasp_exec):
        ex.shutdown(wait=True)


def _puts(d: Daemon, role: str) -> list[bytes]:
    pub = d.outputs.publishers[role]
    assert isinstance(pub, RecordingPublisher)
    return pub.puts


class FakeQuery:
    """The parts of a zenoh Query the daemon uses; records replies, errors and drops."""

    def __init__(self, key: str, payload: bytes = b"", fail_reply: bool = False) -> None:
        self.key_expr = key
        self.payload = types.SimpleNamespace(to_bytes=lambda: payload)
        self.replies: list[tuple[str, Any]] = []
        self.errors: list[str] = []
        self.dropped = 0
        self.closed = 0
        self.fail_reply = fail_reply

    def __enter__(self) -> FakeQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        self.closed += 1

    def reply(self, key: str, payload: Any) -> None:
        if self.fail_reply:
            raise RuntimeError("reply refused")
        self.replies.append((key, payload))

    def reply_err(self, payload: str) -> None:
        self.errors.append(payload)

    def drop(self) -> None:
        self.dropped += 1


class FakeLoop:
    """``call_soon_threadsafe`` recorded (or refused like a closed loop)."""

    def __init__(self, closed: bool = False) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.closed = closed

    def call_soon_threadsafe(self, fn: Any, *args: Any) -> None:
        if self.closed:
            raise RuntimeError("Event loop is closed")
        self.calls.append((fn, *args))


class StopArm:
    """An arm whose ``stop`` waits for ``go`` (or raises), and whose release returns ``was``."""

    def __init__(self, fail: bool = False, was: str | None = None) -> None:
        self.go = asyncio.Event()
        self.stops: list[str] = []
        self.fail = fail
        self.was = was
        self.stop_latched: str | None = None
        self.release_error: Exception | None = None

    async def stop(self, reason: str) -> None:
        self.stops.append(reason)
        if self.fail:
            raise RuntimeError("link down")
        await self.go.wait()

    def release_stop(self) -> str | None:
        if self.release_error is not None:
            raise self.release_error
        return self.was


def _depth(stamp_ns: int) -> DepthFrame:
    cam = RIG.left
    depth_m = np.full((cam.height, cam.width), 0.5, np.float32)
    depth_m[0, :10] = np.nan
    cov = np.eye(6) * 1e-6
    return DepthFrame(stamp_ns=stamp_ns, depth_m=depth_m, camera=cam, T_W_C=np.eye(4), pose_cov=cov)


def _stamp_ns(payload: bytes, typename: str) -> int:
    """The header stamp of a GraspArray, or of a MarkerArray's first marker."""
    msg = codec.deserialize(payload, typename)
    st = (msg.markers[0] if typename == MARKER_ARRAY else msg).header.stamp
    return int(st.sec) * 10**9 + int(st.nanosec)


# --- queries ----------------------------------------------------------------------------------------


def test_status_and_latest_answer_a_wildcard_query_on_their_own_key() -> None:
    """Reading queries are not state-changing: a ``pugs/**`` query gets the answer, on the
    queryable's own key (not the asked wildcard)."""
    d = _daemon(node_name="vehicle_7")
    q = FakeQuery("pugs/**")
    d._on_query("status", q)
    assert q.errors == [] and [k for k, _ in q.replies] == ["pugs/status"]
    st = json.loads(q.replies[0][1])
    assert st["node"] == "vehicle_7" and st["ready"] is False and st["grasps_published"] == 0
    q = FakeQuery("pugs/**")
    d._on_query("latest", q)
    assert q.replies == [] and q.errors == ["no grasps yet: model not ready"]
    d.outputs.latest_grasps = b"grasp array bytes"
    q = FakeQuery("pugs/**")
    d._on_query("latest", q)
    assert q.replies == [("pugs/grasps/latest", b"grasp array bytes")] and q.errors == []
    assert q.closed == 1  # the query is finalised (``with query``)
    assert dict(d.health.rejected) == {}


def test_a_reset_query_is_accepted_until_the_command_queue_is_full_then_refused_with_the_reason() -> None:
    d = _daemon()
    d.commands = type(d.commands)("commands", 2, d.commands.policy)
    answers = []
    for _ in range(3):
        q = FakeQuery("pugs/reset")
        d._on_query("reset", q)
        answers.append((q.replies, q.errors))
    assert answers[:2] == [([("pugs/reset", "accepted")], [])] * 2
    assert answers[2] == ([], ["rejected: commands: busy (2/2 queued)"])
    assert len(d.commands) == 2 and d.health.rejected["commands: queue full"] == 1
    d.commands.close()
    d._stopping = True
    q = FakeQuery("pugs/reset")
    d._on_query("reset", q)
    assert q.errors == ["rejected: commands: shutting down"]
    assert d.health.rejected["commands: shutting down"] == 1


def test_a_command_refused_in_a_flood_is_logged_for_the_first_five_then_every_100th(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    d.commands = type(d.commands)("commands", 1, d.commands.policy)
    caplog.set_level(logging.WARNING, logger="pugsd")
    oks = [d._offer_command(Command("reset", None)) for _ in range(201)]
    assert oks == [True] + [False] * 200
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("command reset rejected")]
    assert [ln.split(":")[0] for ln in lines] == [
        f"command reset rejected (#{n})" for n in (1, 2, 3, 4, 5, 100, 200)
    ]
    assert lines[0] == "command reset rejected (#1): commands: busy (1/1 queued)"


@pytest.mark.parametrize("kind", ["reset", "arm_execute", "arm_release", "arm_stop"])
def test_a_state_changing_queryable_refuses_a_wildcard_query(kind: str) -> None:
    d = _daemon()
    d.arm.controller = StopArm(was="tripped")
    d.outputs.latest_result = FakePipeline().compute()
    q = FakeQuery("pugs/**", b"1")
    d._on_query(kind, q)
    key = {
        "reset": "reset", "arm_execute": "arm/execute", "arm_release": "arm/release", "arm_stop": "arm/stop"
    }  # fmt: skip
    assert q.replies == []
    assert q.errors == [f"rejected: pugs/{key[kind]} acts only on a query for exactly that key"]
    source = "reset" if kind == "reset" else "arm"
    assert dict(d.health.rejected) == {f"{source}: wildcard_key": 1}
    assert len(d.commands) == 0 and len(d.arm.box) == 0 and "arm.stops" not in d.health.counts
    assert "arm.releases" not in d.health.counts


def test_the_wildcard_refusal_names_the_key_and_truncates_what_was_asked(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    caplog.set_level(logging.WARNING, logger="pugsd")
    d._refuse_wildcard("arm_release", "pugs/" + "x" * 400)
    (line,) = [r.getMessage() for r in caplog.records]
    asked = ("pugs/" + "x" * 400)[:200]
    assert line == (
        f"rejected arm input (wildcard_key, #1): arm_release needs exactly 'pugs/arm/release', not {asked!r}"
    )


def test_an_error_while_answering_is_counted_and_answered_with_its_type(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    d.outputs.latest_grasps = b"g"
    caplog.set_level(logging.ERROR, logger="pugsd")
    for _ in range(2):
        q = FakeQuery("pugs/grasps/latest", fail_reply=True)
        d._on_query("latest", q)
        assert q.errors == ["internal error: RuntimeError"]
    assert d.health.counts["errors.query.latest"] == 2
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == [
        "answering a latest query failed: reply refused",
        "answering a latest query failed (#2): RuntimeError: reply refused",
    ]
    assert caplog.records[0].exc_info is not None  # the first one with its traceback


# --- arm requests -----------------------------------------------------------------------------------


def test_arm_execute_refusals_and_the_queued_request() -> None:
    """Disabled, latched stop, no grasps yet, a motion running (busy with an empty mailbox):
    each refused under its own class; an accepted request carries the width and the map's
    generation."""
    d = _daemon()

    def ask(payload: bytes) -> FakeQuery:
        q = FakeQuery("pugs/arm/execute", payload)
        d._on_query("arm_execute", q)
        return q

    assert ask(b"1").errors == ["rejected: arm disabled: set [arm] enabled = true to allow motion"]
    arm = StopArm()
    d.arm.controller = arm
    arm.stop_latched = "operator"
    assert ask(b"1").errors == ["rejected: stopped (operator): query pugs/arm/release first"]
    arm.stop_latched = None
    assert ask(b"1").errors == ["rejected: no grasps yet: model not ready"]
    d.outputs.latest_result = FakePipeline().compute()
    d._busy["arm"] = True  # the worker took the last request: the mailbox is empty
    assert ask(b"1").errors == ["rejected: busy: an arm motion is in progress"]
    assert len(d.arm.box) == 0
    d._busy["arm"] = False
    d._generation = 3
    q = ask(b'{"grasp_id": 2, "width_m": 0.04}')
    assert q.replies == [("pugs/arm/execute", "accepted: grasp 2")] and q.errors == []
    grasps, gid, width_m, gen = d.arm.box.take_nowait()  # type: ignore[misc]
    assert (gid, width_m, gen) == (2, 0.04, 3) and grasps is d.outputs.latest_result.grasps
    assert dict(d.health.rejected) == {
        "arm: disabled": 1,
        "arm: stopped": 1,
        "arm: not_ready": 1,
        "arm: busy": 1,
    }


def test_arm_execute_during_shutdown_is_refused_as_such_not_as_busy() -> None:
    """The arm mailbox closes at shutdown: a request then was answered "busy: an arm motion is
    in progress" although no motion ran."""
    d = _daemon()
    d.arm.controller = StopArm()  # type: ignore[assignment]
    d.outputs.latest_result = FakePipeline().compute()
    d._stopping = True
    d.arm.box.close()
    q = FakeQuery("pugs/arm/execute", b"1")
    d._on_query("arm_execute", q)
    assert q.errors == ["rejected: the daemon is shutting down"] and q.replies == []
    assert dict(d.health.rejected) == {"arm: shutting_down": 1}


def test_status_reports_the_stop_bound_and_what_it_dropped() -> None:
    """Stops beyond the eight on their way were dropped with no trace in the status."""
    d = _daemon()
    assert d.bridge.stop_ingress.limit == 8
    for _ in range(9):
        d.bridge.stop_ingress.enter()
    st = d.status()
    assert st["stop_ingress"] == {"pending": 8, "dropped": 1}
    assert st["query_ingress"] == {"pending": 0, "dropped": 0}


class PutSession:
    """``put`` recorded (or refused)."""

    def __init__(self, fail: bool = False) -> None:
        self.puts: list[tuple[str, Any]] = []
        self.fail = fail

    def put(self, key: str, payload: Any) -> None:
        if self.fail:
            raise RuntimeError("session closed")
        self.puts.append((key, payload))


def test_shutdown_reports_what_was_left_queued_and_answers_an_accepted_arm_request(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """What the queues still held at shutdown was dropped without a word; a request already told
    "accepted: grasp N" never got a report."""
    d = _daemon()
    d.depth_box = Mailbox("depth", 2, Overflow.DROP_OLDEST)  # two frames left in it
    session = PutSession()
    d._session = session  # type: ignore[assignment]
    depth = DepthFrame(1, np.ones((RIG.left.height, RIG.left.width), np.float32), RIG.left, np.eye(4))
    assert d.depth_box.offer((depth, 0.0)) and d.depth_box.offer((depth, 0.1))
    assert d.commands.offer(Command("reset", None))
    assert d.arm.box.offer((None, 4, None, 0))
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        d._report_unprocessed()
    text = caplog.text
    assert "shutdown: left unprocessed: 2 in the depth queue, 1 in the commands queue" in text
    assert "stereo queue" not in text  # empty queues are not listed
    assert d.health.counts["shutdown_unprocessed"] == 3
    report = {"grasp_id": 4, "ok": False, "error": "the daemon shut down before the motion started"}
    assert [(k, json.loads(v)) for k, v in session.puts] == [("pugs/arm/report", report)]
    assert d.arm.report == report and len(d.arm.box) == 0
    assert "arm: grasp 4 not executed: the daemon shut down before the motion started" in text


def test_shutdown_with_empty_queues_says_nothing_and_a_failed_report_put_is_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    d._session = PutSession(fail=True)  # type: ignore[assignment]
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        d._report_unprocessed()
    assert caplog.text == "" and "shutdown_unprocessed" not in d.health.counts
    assert d.arm.box.offer((None, 7, 0.03, 0))
    with caplog.at_level(logging.WARNING, logger="pugsd"):
        d._report_unprocessed()  # the put fails: logged, no raise, the report is still kept
    assert "arm: could not publish the report: session closed" in caplog.text
    assert d.arm.report is not None and d.arm.report["grasp_id"] == 7


def test_arm_release_replies_and_counts() -> None:
    d = _daemon()

    def release() -> FakeQuery:
        q = FakeQuery("pugs/arm/release")
        d._on_query("arm_release", q)
        return q

    q = release()
    assert q.errors == ["rejected: arm disabled: set [arm] enabled = true to allow motion"]
    arm = StopArm(was="pugs/arm/stop (put)")
    d.arm.controller = arm
    assert release().replies == [("pugs/arm/release", "released (was: pugs/arm/stop (put))")]
    arm.was = None
    assert release().replies == [("pugs/arm/release", "not stopped: nothing to release")]
    assert d.health.counts["arm.releases"] == 2
    arm.release_error = PugsdError("controller not started")  # not an InputRejected: "refused"
    assert release().errors == ["rejected: controller not started"]
    assert dict(d.health.rejected) == {"arm: disabled": 1, "arm: refused": 1}
    assert not any(k.startswith("errors.") for k in d.health.counts)


def test_a_flood_of_arm_stops_sends_eight_and_answers_every_one() -> None:
    """Eight stops on their way: a ninth is answered at once ("already being sent") and starts
    no task; each of the eight is answered once its stop was sent, naming the safe mode."""
    d = _daemon()
    arm = StopArm()
    d.arm.controller = arm
    queries = [FakeQuery("pugs/arm/stop") for _ in range(9)]

    async def main() -> None:
        for q in queries:
            d._on_query("arm_stop", q)
        assert len(d.arm.stop_tasks) == 8
        assert queries[8].replies == [("pugs/arm/stop", "stopping: a stop is already being sent")]
        await asyncio.sleep(0)
        arm.go.set()
        await asyncio.gather(*list(d.arm.stop_tasks))

    asyncio.run(main())
    assert d.health.counts["arm.stops"] == 9 and arm.stops == ["pugs/arm/stop (query)"] * 8
    text = "stopped: zero velocity and disable sent; motion is refused until pugs/arm/release"
    for q in queries[:8]:
        assert q.replies == [("pugs/arm/stop", text)] and q.errors == [] and q.closed == 1
    assert queries[8].closed == 1 and not d.arm.stop_tasks


def test_an_arm_stop_without_an_arm_or_with_a_failing_one_is_still_answered(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    caplog.set_level(logging.WARNING, logger="pugsd")
    q_none, q_fail = FakeQuery("pugs/arm/stop"), FakeQuery("pugs/arm/stop")

    async def main() -> None:
        d._on_query("arm_stop", q_none)
        await asyncio.gather(*list(d.arm.stop_tasks))
        d.arm.controller = StopArm(fail=True)
        d._on_query("arm_stop", q_fail)
        await asyncio.gather(*list(d.arm.stop_tasks))

    asyncio.run(main())
    assert q_none.errors == ["rejected: arm disabled or shut down"] and q_none.replies == []
    assert q_fail.errors == ["internal error: RuntimeError"] and q_fail.replies == []
    assert d.health.counts["errors.query.arm_stop"] == 1 and d.health.counts["arm.stops"] == 2
    assert "arm: stop requested (query)" in caplog.text
    assert "stopping the arm failed: link down" in caplog.text


def test_an_arm_stop_put_acts_only_on_its_exact_key() -> None:
    d = _daemon()
    arm = StopArm()
    arm.go.set()
    d.arm.controller = arm

    async def main() -> None:
        d.arm.on_stop_put("pugs/**")
        assert not d.arm.stop_tasks
        d.arm.on_stop_put("pugs/arm/stop")
        await asyncio.gather(*list(d.arm.stop_tasks))

    asyncio.run(main())
    assert arm.stops == ["pugs/arm/stop (put)"]
    assert d.health.counts["arm.stops"] == 1 and dict(d.health.rejected) == {"arm: wildcard_key": 1}


def test_a_reset_put_acts_only_on_its_exact_key() -> None:
    d = _daemon()
    d._on_reset_put("pugs/*")
    assert len(d.commands) == 0 and dict(d.health.rejected) == {"reset: wildcard_key": 1}
    d._on_reset_put("pugs/reset")
    cmd = d.commands.take_nowait()
    assert cmd == Command("reset", None)


# --- the zenoh-thread bridges ------------------------------------------------------------------------


def test_a_query_beyond_the_bound_is_answered_busy_and_stops_have_their_own_bound() -> None:
    d = _daemon(ingress_limit=2)
    loop = FakeLoop()
    d._loop = loop  # type: ignore[assignment]
    on_status = d.bridge.query("status", d._on_query)
    on_stop = d.bridge.query("arm_stop", d._on_query)
    qs = [FakeQuery("pugs/status") for _ in range(3)]
    for q in qs:
        on_status(q)
    assert [c[1:3] for c in loop.calls] == [("status", qs[0]), ("status", qs[1])]
    assert loop.calls[0][3] is d.bridge.query_ingress
    assert qs[2].errors == ["busy: too many queries waiting; try again"] and qs[2].dropped == 1
    assert qs[0].dropped == 0 and d.bridge.query_ingress.dropped == 1
    # the queries' bound is full: a stop still goes through, up to eight waiting
    stops = [FakeQuery("pugs/arm/stop") for _ in range(9)]
    for q in stops:
        on_stop(q)
    assert [c[2] for c in loop.calls[2:]] == stops[:8]
    assert all(c[3] is d.bridge.stop_ingress for c in loop.calls[2:])
    assert stops[8].replies == [("pugs/arm/stop", "stopping: a stop is already being sent")]
    assert stops[8].errors == [] and stops[8].dropped == 1
    # handled on the loop: the bound is free again, even when the handler raises
    fn, kind, q, gate = loop.calls[0]
    fn(kind, q, gate)
    assert d.bridge.query_ingress.pending == 1 and q.replies and q.replies[0][0] == "pugs/status"
    fn, kind, q, gate = loop.calls[2]
    with pytest.raises(RuntimeError):  # no running loop for the stop task here
        fn(kind, q, gate)
    assert d.bridge.stop_ingress.pending == 7


def test_a_query_to_a_closed_loop_is_dropped_and_frees_its_place() -> None:
    d = _daemon(ingress_limit=1)
    d._loop = FakeLoop(closed=True)  # type: ignore[assignment]
    on_status = d.bridge.query("status", d._on_query)
    for _ in range(3):
        q = FakeQuery("pugs/status")
        on_status(q)
        assert q.dropped == 1 and q.errors == []
    assert d.bridge.query_ingress.pending == 0 and d.bridge.query_ingress.dropped == 0


def test_a_control_put_is_handed_over_bounded_and_its_place_freed() -> None:
    d = _daemon()
    loop = FakeLoop()
    d._loop = loop  # type: ignore[assignment]
    handled: list[str] = []
    gate = IngressGate(1)
    on_put = d.bridge.control_put(handled.append, gate)
    sample = types.SimpleNamespace(key_expr="pugs/reset")
    on_put(sample)
    on_put(sample)  # the bound (1) is full: not scheduled
    assert len(loop.calls) == 1 and gate.dropped == 1 and gate.pending == 1
    fn, key = loop.calls[0]
    fn(key)
    assert handled == ["pugs/reset"] and gate.pending == 0

    def boom(key: str) -> None:
        raise ValueError(key)

    on_put = d.bridge.control_put(boom, gate)
    on_put(sample)
    fn, key = loop.calls[1]
    with pytest.raises(ValueError):
        fn(key)
    assert gate.pending == 0
    d._loop = FakeLoop(closed=True)  # type: ignore[assignment]
    d.bridge.control_put(handled.append, gate)(sample)
    assert gate.pending == 0 and handled == ["pugs/reset"]


# --- the model thread's calls -------------------------------------------------------------------------


def test_output_stamps_never_go_back_within_the_gap_follow_beyond_it_and_restart_after_a_reset() -> None:
    d = _daemon(pose_max_gap_s=0.5)
    pipe = d.pipeline
    assert isinstance(pipe, FakePipeline)
    s = 10**10
    assert d._integrate_locked(_depth(s)) == RIG.left.height * RIG.left.width - 10
    assert d._newest_stamp_ns == s
    d._integrate_locked(_depth(s - 500_000_000))  # exactly the gap back: out of order, kept
    assert d._newest_stamp_ns == s
    d._integrate_locked(_depth(s - 500_000_001))  # beyond the gap: the source restarted
    assert d._newest_stamp_ns == s - 500_000_001
    d._integrate_locked(_depth(s + 1))
    assert d._reset_locked() is True
    assert d._newest_stamp_ns == 0 and pipe.resets == 1
    d._integrate_locked(_depth(s - 100_000_000))  # the new map's own time line
    assert d._newest_stamp_ns == s - 100_000_000
    assert pipe.integrated == [s - 100_000_000]


def test_a_training_step_on_an_emptied_map_returns_none() -> None:
    class Emptied(FakePipeline):
        def training_batch(self) -> int:
            raise EmptyCloudError("no points")

    d = _daemon()
    stats = d.training.step_locked()
    assert stats.elbo == -0.5 and d.pipeline.steps == 1  # type: ignore[attr-defined]
    e = _daemon(Emptied())
    assert e.training.step_locked() is None and e.pipeline.steps == 0  # type: ignore[attr-defined]
    for x in (d, e):
        assert not x._model_lock.locked() and not x._svgp_lock.locked()


def test_a_training_step_takes_its_batch_under_the_model_lock_and_steps_under_the_svgp_lock() -> None:
    held: list[tuple[str, bool, bool]] = []

    class Spy(FakePipeline):
        def training_batch(self) -> int:
            held.append(("batch", d._model_lock.locked(), d._svgp_lock.locked()))
            return super().training_batch()

        def train_on(self, batch: int, n: int, rate_scale: float = 1.0) -> Any:
            held.append(("step", d._model_lock.locked(), d._svgp_lock.locked()))
            return super().train_on(batch, n, rate_scale)

    d = _daemon(Spy())
    d.training.step_locked()
    # the SVGP lock is taken before the model lock is released: no reset between batch and step
    assert held == [("batch", True, False), ("step", False, True)]
    assert not d._model_lock.locked() and not d._svgp_lock.locked()


def test_a_noted_step_counts_steps_latches_readiness_and_hides_a_non_finite_elbo(
    caplog: pytest.LogCaptureFixture,
) -> None:
    d = _daemon()
    caplog.set_level(logging.INFO, logger="pugsd")
    stats = types.SimpleNamespace
    d.training.note(stats(elbo=np.float32(-2.5), ready=False), 3)
    assert (d.elbo, d.ready, d.was_ready) == (-2.5, False, False)
    d.training.note(stats(elbo=float("nan"), ready=True), 1)
    assert d.elbo is None and d.ready and d.was_ready
    d.training.note(stats(elbo=-1.0, ready=True), 1)
    d.training.note(stats(elbo=float("-inf"), ready=False), 1)
    assert (d.elbo, d.ready, d.was_ready) == (None, False, True)
    assert d.health.counts["train_steps"] == 6
    assert [r.getMessage() for r in caplog.records] == ["model ready (ELBO nan)"]


# --- the grasp computation ----------------------------------------------------------------------------


class Handed:
    def __init__(self) -> None:
        self.calls: list[tuple[Any, dict[str, bytes]]] = []

    def __call__(self, result: Any, payloads: dict[str, bytes]) -> None:
        self.calls.append((result, payloads))


def test_grasps_and_markers_are_stamped_with_the_snapshot_and_the_cloud_follows() -> None:
    d = _daemon(markers_top_k=2)
    d._newest_stamp_ns = 7 * 10**9 + 5
    h = Handed()
    assert d.outputs.compute_and_encode("map", d._generation, h, False) == "published"
    ((result, out),) = h.calls
    assert sorted(out) == ["grasps", "markers"] and result is not None
    assert _stamp_ns(out["grasps"], GRASP_ARRAY) == 7 * 10**9 + 5
    g = codec.decode_grasp_array(out["grasps"])
    np.testing.assert_array_equal(g.grasp_id, [0, 1, 2])
    markers = codec.deserialize(out["markers"], MARKER_ARRAY).markers
    assert [m.action for m in markers] == [3, 0, 0]  # DELETEALL, then the top 2
    assert _stamp_ns(out["markers"], MARKER_ARRAY) == 7 * 10**9 + 5
    assert {m.header.frame_id for m in markers} == {"map"}
    h = Handed()
    assert d.outputs.compute_and_encode("map", d._generation, h, True) == "published"
    assert [sorted(p) for _, p in h.calls] == [["grasps", "markers"], ["cloud"]]
    scored, finished = h.calls[0][0], h.calls[1][0]  # the cloud comes with its round's finished result
    assert finished.grasps is scored.grasps and np.isnan(scored.sigma2_occ).all()
    np.testing.assert_allclose(finished.sigma2_occ, 0.1)
    cloud = codec.decode_cloud(h.calls[1][1]["cloud"])
    assert (cloud.stamp_ns, cloud.frame_id, len(cloud.points)) == (7 * 10**9 + 5, "map", 50)
    np.testing.assert_allclose(cloud.fields["sigma2_occ"], 0.1)  # finished, not the NaN of scoring
    np.testing.assert_allclose(cloud.fields["pugs_confidence"], 0.5)


def test_a_reset_discards_the_computation_before_scoring_or_after_the_grasps() -> None:
    d = _daemon()
    h = Handed()
    assert d.outputs.compute_and_encode("world", d._generation - 1, h, True) == "discarded"
    assert h.calls == []

    class Preempting(FakePipeline):
        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            return None

    d = _daemon(Preempting())
    h = Handed()
    assert d.outputs.compute_and_encode("world", d._generation, h, True) == "preempted"
    assert len(h.calls) == 1

    class ResetMeanwhile(FakePipeline):
        daemon: Daemon | None = None

        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            assert self.daemon is not None
            self.daemon._generation += 1
            return super().finish_cloud(result, should_stop)

    pipe = ResetMeanwhile()
    d = _daemon(pipe)
    pipe.daemon = d
    h = Handed()
    assert d.outputs.compute_and_encode("world", d._generation, h, True) == "cloud discarded"
    assert [sorted(p) for _, p in h.calls] == [["grasps", "markers"]]


def test_results_of_an_older_map_are_counted_and_not_published(caplog: pytest.LogCaptureFixture) -> None:
    d = _daemon()
    caplog.set_level(logging.INFO, logger="pugsd")
    result = FakePipeline().compute()
    d._generation = 2
    d.outputs.publish(result, {"grasps": b"g", "markers": b"m"}, None, 1)
    d.outputs.publish(None, {"cloud": b"c"}, None, 1)
    assert all(_puts(d, r) == [] for r in ROLES)
    out = d.outputs
    assert out.latest_grasps is None and out.latest_result is None and out.grasps_published == 0
    assert d.health.counts["grasps_discarded"] == 1 and d.health.counts["clouds_discarded"] == 1
    assert "grasp results discarded: the map was reset while they were computed" in caplog.text


def test_a_published_cloud_alone_changes_no_grasp_state_and_grasps_end_the_urgency() -> None:
    d = _daemon()
    d.schedule.grasps_urgent = True
    before = d.schedule.last_cloud_published_s
    d.outputs.publish(None, {"cloud": b"c"}, None, d._generation)
    assert _puts(d, "cloud") == [b"c"] and d.schedule.last_cloud_published_s > before
    assert d.schedule.grasps_urgent and d.outputs.latest_grasps is None and d.outputs.grasps_published == 0
    assert "grasps_published" not in d.health.counts
    result = FakePipeline().compute()
    result.model_version = np.int64(12)  # type: ignore[assignment]
    t0 = d.schedule.last_cloud_published_s
    d.outputs.publish(result, {"grasps": b"g", "markers": b"m"}, time.monotonic(), d._generation)
    assert d.schedule.last_cloud_published_s == t0  # no cloud in this hand-over
    assert not d.schedule.grasps_urgent
    assert d.outputs.latest_grasps == b"g" and d.outputs.latest_result is result
    assert d.outputs.model_version == 12 and type(d.outputs.model_version) is int
    assert (_puts(d, "grasps"), _puts(d, "markers")) == ([b"g"], [b"m"])
    assert d.health.counts["grasps_published"] == 1 and "newest_frame_to_grasps" in d.health.latency


def test_the_cloud_of_the_latest_round_completes_latest_result_and_another_rounds_does_not() -> None:
    """The demo draws ``latest_result``: after its round's cloud it has sigma^2_occ over the whole
    query cloud, not only at the grasp contacts (it kept the scoring's NaN elsewhere)."""
    d = _daemon()
    pipe = FakePipeline()
    scored = pipe.score(0)
    d.outputs.publish(scored, {"grasps": b"g", "markers": b"m"}, None, d._generation)
    assert d.outputs.latest_result is scored and np.isnan(d.outputs.latest_result.sigma2_occ).all()
    other_round = pipe.finish_cloud(pipe.score(0))  # equal values, other grasps object
    d.outputs.publish(other_round, {"cloud": b"c0"}, None, d._generation)
    assert d.outputs.latest_result is scored
    finished = pipe.finish_cloud(scored)
    d.outputs.publish(finished, {"cloud": b"c1"}, None, d._generation)
    assert d.outputs.latest_result is finished and d.outputs.latest_grasps == b"g"
    np.testing.assert_allclose(d.outputs.latest_result.sigma2_occ, 0.1)
    assert _puts(d, "cloud") == [b"c0", b"c1"] and d.outputs.grasps_published == 1
    d.outputs.publish(pipe.finish_cloud(finished), {"cloud": b"c2"}, None, d._generation - 1)
    assert d.outputs.latest_result is finished and d.health.counts["clouds_discarded"] == 1


def test_a_failed_put_is_logged_for_the_first_ten_of_a_role_then_every_100th(
    caplog: pytest.LogCaptureFixture,
) -> None:
    class Refusing(RecordingPublisher):
        def put(self, payload: bytes) -> int:
            raise RuntimeError("session closed")

    d = _daemon()
    d.outputs.publishers["cloud"] = Refusing()  # type: ignore[assignment]
    caplog.set_level(logging.WARNING, logger="pugsd")
    assert [d.outputs.put("cloud", b"c") for _ in range(200)] == [False] * 200
    counts = [int(r.getMessage().split("(")[1].split(" ")[0]) for r in caplog.records]
    assert counts == [*range(1, 11), 100, 200]
    assert d.health.failures["publish"] == 200 and d.outputs.put("status", b"s")
    assert "publish" not in d.health.failures


# --- when grasps are due ------------------------------------------------------------------------------


def test_streaming_means_a_frame_queued_or_one_within_pause_publish_s() -> None:
    d = _daemon(pause_publish_s=0.25)
    sch, box = d.schedule, d.depth_box
    assert not sch.streaming(100.0, len(box))
    d.schedule.last_frame_s = 100.0
    assert sch.streaming(100.24, len(box)) and not sch.streaming(100.25, len(box))
    d.depth_box.offer((_depth(1), 0.0))
    assert sch.streaming(500.0, len(box))


def test_the_cloud_gives_way_only_to_a_newer_frame_after_a_pause_within_the_cloud_interval() -> None:
    d = _daemon(pause_publish_s=0.1, cloud_interval_s=5.0)
    now = time.monotonic()
    d.schedule.last_frame_s = now - 10.0  # paused
    d.schedule.last_cloud_published_s = now - 1.0
    assert not d._cloud_gives_way()  # no newer frame
    d.schedule.frame_unpublished = True
    assert d._cloud_gives_way()
    d.schedule.last_cloud_published_s = now - 60.0  # clouds overdue: this one finishes
    assert not d._cloud_gives_way()
    d.schedule.last_cloud_published_s = now - 1.0
    d.schedule.last_frame_s = now + 60.0  # streaming: the grasps are not due at once
    assert not d._cloud_gives_way()
    d.schedule.frame_unpublished = False
    d._stopping = True  # shutdown: always
    assert d._cloud_gives_way()


def test_grasps_are_due_every_period_and_at_once_after_a_pause() -> None:
    d = _daemon(grasp_rate_hz=2.0, pause_publish_s=0.1, train_steps_per_frame=4)
    sch, box = d.schedule, d.depth_box
    last = 100.0
    assert sch.grasps_due(100.5, last, len(box)) and not sch.grasps_due(100.49, last, len(box))
    d.schedule.frame_unpublished = True
    d.schedule.last_frame_s = 100.1
    d.schedule.steps_since_frame = 4
    assert sch.grasps_due(100.25, last, len(box))  # paused 0.15 s after its steps: half a period suffices
    assert not sch.grasps_due(100.249, last, len(box))  # not yet half a period
    assert not sch.grasps_due(100.19, last, len(box))  # 0.09 s after the frame: still streaming
    d.schedule.steps_since_frame = 3
    assert not sch.grasps_due(100.3, last, len(box))  # the newest frame's training steps are not done
    d.schedule.steps_since_frame = 4
    d.schedule.frame_unpublished = False
    assert not sch.grasps_due(100.3, last, len(box))
    d.schedule.frame_unpublished = True
    d.schedule.last_frame_s = None
    assert not sch.grasps_due(100.3, last, len(box))
    off = _daemon(grasp_rate_hz=2.0, pause_publish_s=0.0, train_steps_per_frame=4)
    off.schedule.frame_unpublished, off.schedule.last_frame_s, off.schedule.steps_since_frame = True, 100.1, 4
    assert not off.schedule.grasps_due(100.3, last, 0)


def _grasp_rounds(d: Daemon, until: Any, timeout_s: float = 5.0) -> None:
    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        task = asyncio.create_task(d._grasp_worker())
        t0 = time.monotonic()
        try:
            while not until() and time.monotonic() - t0 < timeout_s:  # noqa: ASYNC110 (poll with a timeout)
                await asyncio.sleep(0.01)
        finally:
            d._stopping = True
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            _shutdown(d)

    asyncio.run(main())


def test_the_grasp_worker_publishes_a_changed_ready_model_once_with_its_cloud() -> None:
    d = _daemon(grasp_rate_hz=50.0, markers_top_k=1)
    d.ready = d.schedule.changed = True
    d.frames.frame_id = "odom"
    d._newest_stamp_ns = 42
    _grasp_rounds(d, lambda: len(_puts(d, "cloud")) >= 1)
    assert (len(_puts(d, "grasps")), len(_puts(d, "markers")), len(_puts(d, "cloud"))) == (1, 1, 1)
    assert d.outputs.grasps_published == 1 and not d.schedule.changed
    assert codec.decode_cloud(_puts(d, "cloud")[0]).frame_id == "odom"
    assert _stamp_ns(_puts(d, "grasps")[0], GRASP_ARRAY) == 42


def test_the_grasp_worker_publishes_no_cloud_when_it_is_off_and_nothing_unready_without_the_latch() -> None:
    d = _daemon(grasp_rate_hz=50.0, publish_cloud=False)
    d.ready = d.schedule.changed = True
    _grasp_rounds(d, lambda: d.outputs.grasps_published >= 1)
    assert d.outputs.grasps_published == 1 and _puts(d, "cloud") == []
    unlatched = _daemon(grasp_rate_hz=50.0, ready_latch=False)
    unlatched.was_ready = unlatched.schedule.changed = True
    t_end = time.monotonic() + 0.3  # an observation window (about 15 rounds), not a synchronisation
    _grasp_rounds(unlatched, lambda: time.monotonic() > t_end)
    assert unlatched.outputs.grasps_published == 0 and _puts(unlatched, "grasps") == []
    latched = _daemon(grasp_rate_hz=50.0, publish_cloud=False)
    latched.was_ready = latched.schedule.changed = True
    _grasp_rounds(latched, lambda: latched.outputs.grasps_published >= 1)
    assert latched.outputs.grasps_published == 1


# --- a reset's published state ------------------------------------------------------------------------


def test_a_reset_clears_the_model_state_and_publishes_empties_on_the_old_time_line() -> None:
    d = _daemon(publish_cloud=False)
    d._newest_stamp_ns = 3 * 10**9
    d.frames.frame_id = "odom"
    d.outputs.latest_grasps, d.outputs.latest_result = b"g", FakePipeline().compute()
    d.ready = d.was_ready = d.schedule.changed = d.schedule.frame_unpublished = True
    d.elbo, d.schedule.last_frame_s, d._newest_recv_s = -1.0, 5.0, 4.0
    d.health.failed("integrate")
    d.outputs.grasps_logged_s = 10.0

    async def main() -> None:
        d._loop = asyncio.get_running_loop()
        try:
            await d._reset()
        finally:
            _shutdown(d)

    asyncio.run(main())
    assert (d.outputs.latest_grasps, d.outputs.latest_result, d.schedule.changed) == (None, None, False)
    assert (d.ready, d.was_ready) == (False, False)
    sch = d.schedule
    assert (sch.frame_unpublished, sch.last_frame_s, d._newest_recv_s, d.elbo) == (False, None, None, None)
    assert d.outputs.grasps_logged_s == -math.inf and d.health.counts["resets"] == 1
    assert "integrate" not in d.health.failures and d._newest_stamp_ns == 0 and not d._resetting
    assert _puts(d, "cloud") == []  # publish_cloud off
    (g,) = _puts(d, "grasps")
    (m,) = _puts(d, "markers")
    assert _stamp_ns(g, GRASP_ARRAY) == _stamp_ns(m, MARKER_ARRAY) == 3 * 10**9
    assert codec.deserialize(g, GRASP_ARRAY).header.frame_id == "odom"


def test_cleared_outputs_skip_roles_without_a_publisher_and_survive_a_failed_put() -> None:
    class Refusing(RecordingPublisher):
        def put(self, payload: bytes) -> int:
            raise RuntimeError("closed")

    d = _daemon()
    del d.outputs.publishers["markers"]
    d.outputs.publishers["grasps"] = Refusing()  # type: ignore[assignment]
    d.outputs.publish_cleared(5)
    assert len(_puts(d, "cloud")) == 1 and len(codec.decode_cloud(_puts(d, "cloud")[0]).points) == 0
    assert codec.decode_cloud(_puts(d, "cloud")[0]).stamp_ns == 5
    assert d.health.counts["publish_failed.grasps"] == d.health.counts["publish_failed"] == 1
    assert "publish_failed.markers" not in d.health.counts  # no publisher: not tried, not a failure


# --- health -----------------------------------------------------------------------------------------


def test_the_skew_summary_is_median_min_max_in_seconds_rounded() -> None:
    d = _daemon()
    assert d.frames.skew_summary() == {"n": 0}
    d.frames.stamp_skew_s.extend([0.123456, -0.20034, 0.30006, 0.05])
    assert d.frames.skew_summary() == {"n": 4, "p50": 0.0867, "min": -0.2003, "max": 0.3001}


def test_input_ages_and_staleness(caplog: pytest.LogCaptureFixture) -> None:
    d = _daemon(input_stale_s=2.0)
    d.inputs.last_recv_s = {"pose": 9.87654, "left_image": 7.5, "depth": 8.0}
    assert d.input_ages_s(10.0) == {"depth": 2.0, "left_image": 2.5, "pose": 0.123}
    assert list(d.input_ages_s(10.0)) == ["depth", "left_image", "pose"]
    assert d.stale_inputs(10.0) == ["left_image"]  # depth exactly at the limit: not stale
    assert d.stale_inputs(12.1) == ["depth", "left_image", "pose"]
    assert _daemon(input_stale_s=0.0).stale_inputs(1e9) == []
    caplog.set_level(logging.WARNING, logger="pugsd")
    now = time.monotonic()
    d.inputs.last_recv_s = {"pose": now - 3.0, "left_image": now - 5.0}
    d.inputs.report_stale(["left_image"], time.monotonic())
    d.inputs.report_stale(["left_image", "pose"], time.monotonic())
    d.inputs.report_stale(["left_image", "pose"], time.monotonic())
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == [
        "input silent: left_image for 5.0 s (daemon.input_stale_s = 2.0 s)",
        "input silent: pose for 3.0 s (daemon.input_stale_s = 2.0 s)",
    ]
    assert d.inputs.stale_reported == {"left_image", "pose"}


def test_status_reports_its_counters_and_survives_a_failing_pipeline() -> None:
    class NoStats(FakePipeline):
        def stats(self) -> dict[str, Any]:
            raise RuntimeError("cuda gone")

    d = _daemon(NoStats(), max_consecutive_failures=2)
    d.bridge.query_ingress.enter()
    d.bridge.query_ingress.dropped = 3
    d.bridge.deletes_ignored = 4
    d.bridge.errors["pose"] = 2
    d.frames.pose_publisher = bytes(range(16))
    d.outputs.model_version, d.elbo, d.outputs.grasps_published = 7, -1.5, 9
    st = d.status()
    assert st["pipeline"] == {"error": "cuda gone"}
    assert st["healthy"] is True and st["problems"] == []
    assert st["query_ingress"] == {"pending": 1, "dropped": 3}
    assert st["ingress"] == {"pending": 0, "pending_bytes": 0, "dropped": 0, "refused": {}, "too_large": {}}
    assert (st["deletes_ignored"], st["bridge_errors"]) == (4, {"pose": 2})
    assert st["bridge_errors"] is not d.bridge.errors
    assert st["upstream"]["pose_publisher"] == "000102030405"
    assert (st["model_version"], st["elbo"], st["grasps_published"]) == (7, -1.5, 9)
    assert sorted(st["mailboxes"]) == ["commands", "depth", "stereo"] and st["recorder"] is None
    d.health.failed("publish")
    d.health.failed("publish")
    st = d.status()
    assert st["healthy"] is False and st["problems"] == ["publish failed 2 times in a row"]
    json.dumps(st)


# --- shutdown -----------------------------------------------------------------------------------------


class Entity:
    def __init__(self, name: str, order: list[str], fail: bool = False) -> None:
        self.name, self.order, self.fail = name, order, fail

    def undeclare(self) -> None:
        self.order.append(self.name)
        if self.fail:
            raise RuntimeError("already gone")


def test_close_undeclares_everything_in_order_despite_failures_and_leaves_a_lent_session() -> None:
    order: list[str] = []
    closed: list[str] = []
    session = types.SimpleNamespace(close=lambda: closed.append("session"))
    d = Daemon(load_config_dict({}), FakePipeline(), notifier=Notifier(""), session=session)  # type: ignore[arg-type]
    d._sub_graph_tokens = [Entity("sub-token", order)]
    d._subscribers = [Entity("sub-1", order, fail=True), Entity("sub-2", order)]
    d._entities = [Entity("queryable", order, fail=True), Entity("alive", order)]
    d.outputs.publishers = {"grasps": Entity("pub-grasps", order), "status": Entity("pub-status", order)}  # type: ignore[dict-item]
    d._graph_tokens = [Entity("node-token", order), Entity("pub-token", order)]
    d._close()
    assert order == [
        "sub-token", "sub-1", "sub-2", "queryable", "alive", "pub-grasps", "pub-status", "pub-token",
        "node-token",
    ]  # fmt: skip
    assert not (d._subscribers or d._entities or d.outputs.publishers)
    assert not (d._graph_tokens or d._sub_graph_tokens)
    assert closed == [] and d._session is session
    assert not d.serving


def test_close_stops_the_recorder_and_names_the_last_five_files(caplog: pytest.LogCaptureFixture) -> None:
    stopped: list[float] = []

    class Rec:
        def stop(self, timeout: float) -> list[str]:
            stopped.append(timeout)
            return [f"f{i}.mcap" for i in range(1, 8)]

    d = _daemon(shutdown_timeout_s=3.5)
    d._own_session = False
    d.recorder = Rec()
    caplog.set_level(logging.INFO, logger="pugsd")
    d._close()
    assert stopped == [FINISH_TIMEOUT_S] and d.recorder is None  # not the calls' shutdown bound
    files = "f3.mcap, f4.mcap, f5.mcap, f6.mcap, f7.mcap (and 2 earlier)"
    assert f"recording finished: 7 file(s): {files}" in caplog.text


def test_abandoned_work_counts_the_offloaded_calls_still_running() -> None:
    d = _daemon()
    gate = threading.Event()
    pool = concurrent.futures.ThreadPoolExecutor(2)
    try:
        running = pool.submit(gate.wait, 10.0)
        done = pool.submit(int)
        done.result(5.0)
        d._in_flight = {running, done}
        assert d.abandoned_work() == 1
        gate.set()
        running.result(5.0)
        assert d.abandoned_work() == 0
    finally:
        gate.set()
        pool.shutdown(wait=True)


def test_thread_limits_apply_to_an_imported_torch_only_when_set(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    monkeypatch.setitem(sys.modules, "torch", types.SimpleNamespace(set_num_threads=calls.append))
    apply_thread_limits(load_config_dict({"daemon": {"torch_threads": 3}}))
    apply_thread_limits(load_config_dict({"daemon": {"torch_threads": 0}}))
    assert calls == [3]
    monkeypatch.delitem(sys.modules, "torch")
    apply_thread_limits(load_config_dict({"daemon": {"torch_threads": 2}}))  # not imported: nothing
    assert calls == [3]


def test_blas_threads_limit_numpys_blas_and_0_leaves_it_alone() -> None:
    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"}

    with threadpoolctl.threadpool_limits(2, user_api="blas"):  # restored after the test
        before = blas_threads()
        assert before and before != {1}
        apply_thread_limits(load_config_dict({"daemon": {"blas_threads": 0, "torch_threads": 0}}))
        assert blas_threads() == before
        apply_thread_limits(load_config_dict({"daemon": {"blas_threads": 1, "torch_threads": 0}}))
        assert blas_threads() == {1}


def test_the_grasp_worker_counts_each_outcome_of_a_round(caplog: pytest.LogCaptureFixture) -> None:
    """A cloud that gave way is counted as preempted; one computed across a reset as discarded
    (its grasps went out before the reset); a round whose map was reset before scoring publishes
    nothing and is counted and logged."""

    class Preempting(FakePipeline):
        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            return None

    d = _daemon(Preempting(), grasp_rate_hz=50.0)
    d.ready = d.schedule.changed = True
    _grasp_rounds(d, lambda: d.health.counts["clouds_preempted"] >= 1)
    assert d.health.counts["clouds_preempted"] == 1 and _puts(d, "cloud") == []
    assert d.outputs.grasps_published == 1 and "clouds_discarded" not in d.health.counts

    class ResetDuringCloud(FakePipeline):
        daemon: Daemon | None = None

        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            assert self.daemon is not None
            self.daemon._generation += 1  # what a reset on the loop does meanwhile
            return super().finish_cloud(result, should_stop)

    pipe = ResetDuringCloud()
    d = _daemon(pipe, grasp_rate_hz=50.0)
    pipe.daemon = d
    d.ready = d.schedule.changed = True
    _grasp_rounds(d, lambda: d.health.counts["clouds_discarded"] >= 1)
    assert d.health.counts["clouds_discarded"] == 1 and _puts(d, "cloud") == []
    # (its grasps were handed over before the reset: the loop may have published them before the
    # reset's bump or discarded them after it; either is right, so neither is asserted)

    class ResetBeforeScoring(FakePipeline):
        daemon: Daemon | None = None

        def propose(self, inp: int, should_stop: Any = None) -> int:
            assert self.daemon is not None
            self.daemon._generation += 1
            return inp

    pipe2 = ResetBeforeScoring()
    d = _daemon(pipe2, grasp_rate_hz=50.0)
    pipe2.daemon = d
    d.ready = d.schedule.changed = True
    caplog.set_level(logging.INFO, logger="pugsd")
    _grasp_rounds(d, lambda: d.health.counts["grasps_discarded"] >= 1)
    assert d.health.counts["grasps_discarded"] == 1 and d.outputs.grasps_published == 0
    assert all(_puts(d, r) == [] for r in ROLES)
    assert "grasp computation discarded: the map was reset while it ran" in caplog.text


def test_a_grasp_round_handed_over_after_a_reset_publishes_nothing() -> None:
    """The hand-over carries the generation the round began with: a reset while the grasps are
    scored (after the check before scoring) discards them on the loop (the map is gone)."""

    class ResetAfterScoring(FakePipeline):
        daemon: Daemon | None = None

        def score(self, proposal: int) -> Any:
            assert self.daemon is not None
            self.daemon._generation += 1  # what a reset on the loop does meanwhile
            return super().score(proposal)

    pipe = ResetAfterScoring()
    d = _daemon(pipe, grasp_rate_hz=50.0)
    pipe.daemon = d
    d.ready = d.schedule.changed = True
    _grasp_rounds(d, lambda: d.health.counts["grasps_discarded"] >= 1)
    assert d.health.counts["grasps_discarded"] == 1
    assert d.outputs.grasps_published == 0 and _puts(d, "grasps") == [] and d.outputs.latest_grasps is None


def test_while_frames_stream_the_first_cloud_waits_for_the_cloud_interval() -> None:
    """Streaming (a frame queued): grasps go out, the whole cloud not before cloud_interval_s."""
    d = _daemon(grasp_rate_hz=50.0, cloud_interval_s=60.0)
    d.ready = d.schedule.changed = True
    d.depth_box.offer((_depth(1), 0.0))  # a frame waits: the input streams
    _grasp_rounds(d, lambda: d.outputs.grasps_published >= 1)
    assert d.outputs.grasps_published == 1 and _puts(d, "cloud") == []


def test_no_grasp_round_starts_while_a_reset_is_in_progress() -> None:
    d = _daemon(grasp_rate_hz=50.0)
    d.ready = d.schedule.changed = True
    d._resetting = True
    t_end = time.monotonic() + 0.3  # an observation window (about 15 rounds), not a synchronisation
    _grasp_rounds(d, lambda: time.monotonic() > t_end)
    assert d.outputs.grasps_published == 0 and d.schedule.changed and _puts(d, "grasps") == []


def test_the_grasp_worker_marks_grasps_for_a_new_frame_urgent_while_they_are_computed() -> None:
    """Idle training yields while grasps for a newly integrated frame are computed; the flag ends
    with the round."""
    seen: list[bool] = []

    class Watching(FakePipeline):
        daemon: Daemon | None = None

        def propose(self, inp: int, should_stop: Any = None) -> int:
            assert self.daemon is not None
            seen.append(self.daemon.schedule.grasps_urgent)
            return inp

    pipe = Watching()
    d = _daemon(pipe, grasp_rate_hz=50.0, publish_cloud=False)
    pipe.daemon = d
    d.ready = d.schedule.changed = d.schedule.frame_unpublished = True
    _grasp_rounds(d, lambda: d.outputs.grasps_published >= 1)
    assert seen == [True] and not d.schedule.grasps_urgent and not d.schedule.frame_unpublished


def test_a_status_query_with_numpy_values_and_nan_is_answered_in_strict_json() -> None:
    d = _daemon()
    d.elbo = float("nan")
    d.outputs.model_version = np.int64(4)  # type: ignore[assignment]
    q = FakeQuery("pugs/status")
    d._on_query("status", q)
    assert q.errors == [] and "errors.query.status" not in d.health.counts
    st = json.loads(q.replies[0][1], parse_constant=lambda c: pytest.fail(f"non-strict JSON: {c}"))
    assert st["elbo"] is None and st["model_version"] == 4


def test_the_cloud_keeps_the_snapshots_stamp_when_a_frame_is_integrated_meanwhile() -> None:
    """The cloud runs without the model lock: a frame integrated meanwhile advances the outputs'
    stamp, but the cloud labels the map of its snapshot, as its grasps do."""

    class IntegrateMeanwhile(FakePipeline):
        daemon: Daemon | None = None

        def finish_cloud(self, result: Any, should_stop: Any = None) -> Any:
            assert self.daemon is not None
            self.daemon._integrate_locked(_depth(9 * 10**9))
            return super().finish_cloud(result, should_stop)

    pipe = IntegrateMeanwhile()
    d = _daemon(pipe)
    pipe.daemon = d
    d._newest_stamp_ns = 8 * 10**9
    h = Handed()
    assert d.outputs.compute_and_encode("world", d._generation, h, True) == "published"
    assert _stamp_ns(h.calls[0][1]["grasps"], GRASP_ARRAY) == 8 * 10**9
    assert codec.decode_cloud(h.calls[1][1]["cloud"]).stamp_ns == 8 * 10**9
    assert d._newest_stamp_ns == 9 * 10**9


class ResetFailsPipeline(FakePipeline):
    """``reset`` raises while ``fail_reset`` is set (e.g. a MemoryError allocating the new grid)."""

    fail_reset = True

    def reset(self) -> None:
        if self.fail_reset:
            raise MemoryError("new TSDF grid")
        super().reset()


def test_a_failed_reset_withholds_grasps_and_makes_the_daemon_unhealthy_until_one_succeeds(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A reset whose pipeline reset raised went on as if the map were cleared: the model, still
    holding the old map, became ready again and its grasps went out under the new generation."""
    pipe = ResetFailsPipeline()
    d = _daemon(pipe, grasp_rate_hz=50.0, publish_cloud=False)

    async def reset() -> None:
        d._loop = asyncio.get_running_loop()
        await d._reset()

    with caplog.at_level(logging.ERROR, logger="pugsd"):
        asyncio.run(reset())
    assert "reset: the pipeline could not be cleared; no grasps until a reset succeeds" in caplog.text
    assert d.health.counts["errors.reset"] == 1 and d._generation == 1
    problem = "reset failed: the map may not be cleared (grasps withheld; send a reset again)"
    st = d.status()
    assert st["healthy"] is False and st["problems"] == [problem] and d.problems() == [problem]
    cleared = len(_puts(d, "grasps"))  # the empty GraspArray of the reset
    d.ready = d.schedule.changed = True  # the old map's model trains on and is ready again
    t_end = time.monotonic() + 0.3  # an observation window (about 15 rounds), not a synchronisation
    _grasp_rounds(d, lambda: time.monotonic() > t_end)
    assert d.outputs.grasps_published == 0 and len(_puts(d, "grasps")) == cleared

    pipe.fail_reset = False  # the operator sends a reset again: it succeeds
    d._stopping = False  # _grasp_rounds stopped the daemon and its executors: fresh ones
    d._depth_exec, d._model_exec, d._grasp_exec = (concurrent.futures.ThreadPoolExecutor(1) for _ in range(3))
    asyncio.run(reset())
    assert pipe.resets == 1 and d.problems() == [] and d.status()["healthy"] is True
    d.ready = d.schedule.changed = True
    _grasp_rounds(d, lambda: d.outputs.grasps_published >= 1)
    assert d.outputs.grasps_published == 1
