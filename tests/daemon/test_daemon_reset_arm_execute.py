# SPDX-License-Identifier: Apache-2.0
"""A reset that waits for the model thread: an ``arm/execute`` request meanwhile must not move the
arm to a grasp of the map being cleared (the reset had begun, yet the request was accepted from
the old ``latest_result`` and the motion ran once the reset released the motion lock)."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from typing import Any

from pugsd.config import load_config_dict
from pugsd.daemon.app import Daemon, InputRejected
from pugsd.daemon.notify import Notifier
from tests.daemon.conftest import FakePipeline, RecordingPublisher, running_worker


@dataclass
class FakeArm:
    stop_latched: str | None = None
    executed: list[int] = field(default_factory=list)

    async def execute_grasp_id(self, grasps: Any, grasp_id: int, width_m: Any) -> Any:
        self.executed.append(grasp_id)

        class Rep:
            def to_dict(self) -> dict[str, Any]:
                return {"grasp_id": grasp_id, "ok": True}

        return Rep()


class Query:
    def __init__(self, body: bytes) -> None:
        self.payload = type("P", (), {"to_bytes": lambda _self: body})()


def _daemon() -> tuple[Daemon, FakeArm]:
    cfg = load_config_dict({"daemon": {"publish_cloud": False}})
    pipe = FakePipeline()
    d = Daemon(cfg, pipe, notifier=Notifier(""))
    d.outputs.publishers = {r: RecordingPublisher() for r in ("grasps", "markers", "cloud", "status")}  # type: ignore[assignment]
    d._session = type("S", (), {"put": lambda *a, **k: None})()  # arm reports
    arm = FakeArm()
    d.arm.controller = arm
    d.outputs.latest_result = pipe.compute(full_cloud=False)  # grasp ids 0, 1, 2 of the old map
    return d, arm


def _run(d: Daemon, body: Any) -> None:
    async def main() -> None:
        async with running_worker(d, d.arm.worker()):
            await body()
            await asyncio.sleep(0.2)  # the arm worker's turn

    asyncio.run(main())


def test_an_execute_request_while_a_reset_waits_is_refused() -> None:
    d, arm = _daemon()
    busy = threading.Event()

    async def body() -> None:
        d._model_exec.submit(busy.wait, 10.0)  # the model thread is busy: the reset waits for it
        reset = asyncio.create_task(d._reset())
        await asyncio.sleep(0.05)
        assert d._resetting and d.outputs.latest_result is not None  # the reset has begun, not finished
        refused = None
        try:
            d.arm.on_execute(Query(b"1"))
        except InputRejected as exc:
            refused = exc
        busy.set()
        await asyncio.wait_for(reset, 10.0)
        assert refused is not None, "arm/execute accepted a grasp of the map being reset"

    _run(d, body)
    assert arm.executed == []


def test_an_execute_accepted_before_a_reset_does_not_run_after_it() -> None:
    """Accepted just before the reset began, the motion waits for the motion lock the reset holds:
    once the reset has cleared the map, that grasp is not the current map's any more."""
    d, arm = _daemon()
    busy = threading.Event()

    async def body() -> None:
        d._model_exec.submit(busy.wait, 10.0)
        d.arm.on_execute(Query(b"1"))  # accepted: the map is still the old one
        async with d._motion_lock:  # the command worker holds it during the reset
            reset = asyncio.create_task(d._reset())
            await asyncio.sleep(0.05)
            busy.set()
            await asyncio.wait_for(reset, 10.0)

    _run(d, body)
    assert arm.executed == []
    assert d.arm.report is not None and d.arm.report["ok"] is False, d.arm.report


class LatestQuery:
    key_expr = "pugs/grasps/latest"

    def __init__(self) -> None:
        self.ok: list[Any] = []
        self.err: list[str] = []

    def __enter__(self) -> LatestQuery:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def reply(self, key: str, payload: Any) -> None:
        self.ok.append(payload)

    def reply_err(self, text: str) -> None:
        self.err.append(text)


def test_latest_grasps_are_not_served_while_a_reset_waits() -> None:
    """``pugsd arm execute --grasp-id`` asks ``<prefix>/grasps/latest`` first: during the reset it
    must not get the grasps of the map being cleared."""
    d, _ = _daemon()
    d.outputs.latest_grasps = b"old map"
    busy = threading.Event()
    q = LatestQuery()

    async def body() -> None:
        d._model_exec.submit(busy.wait, 10.0)
        reset = asyncio.create_task(d._reset())
        await asyncio.sleep(0.05)
        assert d._resetting
        d._on_query("latest", q)
        busy.set()
        await asyncio.wait_for(reset, 10.0)

    _run(d, body)
    assert q.ok == [] and q.err and "reset" in q.err[0], (q.ok, q.err)
