# SPDX-License-Identifier: Apache-2.0
"""The daemon's arm glue: ``<prefix>/arm/execute``, ``arm/stop`` and ``arm/release`` to the arm
controller, one motion at a time, and each motion's report on ``<prefix>/arm/report``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from pugsd.daemon.health import jsonable
from pugsd.daemon.mailbox import Mailbox, Overflow
from pugsd.errors import PugsdError
from pugsd.stream.assembler import InputRejected

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

log = logging.getLogger(__name__)

_MAX_STOPS_IN_FLIGHT = 8  # a flood of stops: those on their way do the job


class ArmBridge:
    """Validates and queues arm requests for the daemon ``d`` and runs them (``worker``); stops
    go straight to the controller (``controller``: None while the arm is disabled or shut down)."""

    def __init__(self, d: Daemon) -> None:
        self.d = d
        self.controller: Any = None  # pugsd.arm.controller.ArmController when [arm] enabled
        self.report: dict[str, Any] | None = None  # the last motion's report
        # one arm motion at a time; a second request is rejected, never queued behind the first
        # (grasps, grasp id, width, the map generation they belong to)
        self.box: Mailbox[tuple[Any, int, float | None, int]] = Mailbox("arm", 1, Overflow.REJECT)
        self.stop_tasks: set[asyncio.Task[None]] = set()  # arm/stop requests being sent

    async def start(self) -> bool:
        """Connect to the arm when the config enables it; motion only on explicit requests."""
        if not self.d.cfg.arm.enabled:
            return False
        from pugsd.arm.controller import ArmController  # only when the arm is enabled

        self.controller = ArmController(self.d.cfg.arm)
        await self.controller.start()
        return True

    async def close(self) -> None:
        if self.controller is None:
            return
        try:
            await self.controller.close()  # sends zero velocity and the safe mode
        except Exception as exc:
            log.error("arm: stop on shutdown failed: %s", exc)
        self.controller = None

    def on_execute(self, query: Any) -> str:
        """Validate an ``<prefix>/arm/execute`` request and queue it; returns the reply text."""
        from pugsd.arm.controller import parse_execute_request

        if self.controller is None:
            raise InputRejected("disabled", "arm disabled: set [arm] enabled = true to allow motion")
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            grasp_id, width_m = parse_execute_request(payload)
        except PugsdError as exc:
            raise InputRejected("bad_request", str(exc)[:300]) from None
        except (RecursionError, OverflowError, ValueError) as exc:  # deep nesting, huge numbers
            msg = f"arm/execute: unreadable request ({type(exc).__name__})"
            raise InputRejected("bad_request", msg) from None
        return self.request_execute(grasp_id, width_m)

    def request_execute(self, grasp_id: int, width_m: float | None) -> str:
        """Queue grasp ``grasp_id`` of the latest grasps (at ``width_m``; None: its own width)
        for execution (the zenoh query and the ROS service); returns the reply text, raises
        InputRejected with the reason it is refused."""
        d, arm = self.d, self.controller
        if arm is None:
            raise InputRejected("disabled", "arm disabled: set [arm] enabled = true to allow motion")
        if d._stopping:  # the arm box is closed: "busy" would mislead
            raise InputRejected("shutting_down", "the daemon is shutting down")
        if arm.stop_latched is not None:
            msg = f"stopped ({arm.stop_latched}): query {d.key('arm/release')} first"
            raise InputRejected("stopped", msg[:300])
        if d._resetting:  # latest_result is the map being cleared
            raise InputRejected("resetting", "no grasps: the map is being reset")
        result = d.outputs.latest_result
        if result is None:
            raise InputRejected("not_ready", "no grasps yet: model not ready")
        if grasp_id not in {int(g) for g in result.grasps.grasp_id}:
            raise InputRejected("unknown_grasp", f"grasp id {grasp_id} is not among the latest grasps")
        item = (result.grasps, grasp_id, width_m, d._generation)
        if d._busy.get("arm") or not self.box.offer(item):
            raise InputRejected("busy", "busy: an arm motion is in progress")
        return f"accepted: grasp {grasp_id}"

    def stop(
        self, source: str, query: Any = None, answer: Callable[[bool, str], None] | None = None
    ) -> None:
        """``<prefix>/arm/stop`` (query or put) and the ROS service: stop the arm at once, here on
        the event loop, not through the arm mailbox, so it never waits behind a running motion;
        the stop latches (execute is refused until ``<prefix>/arm/release``). The reply follows
        once it is sent: to ``query`` as text, or through ``answer(ok, text)`` when given (the
        query is then closed after it)."""
        self.d.health.count("arm.stops")
        log.warning("arm: stop requested (%s)", source)
        if len(self.stop_tasks) >= _MAX_STOPS_IN_FLIGHT:
            if query is not None:
                with query, contextlib.suppress(Exception):
                    text = "stopping: a stop is already being sent"
                    if answer is not None:
                        answer(True, text)
                    else:
                        query.reply(self.d.key("arm/stop"), text)
            return
        task = asyncio.get_running_loop().create_task(self._send_stop(source, query, answer), name="arm-stop")
        self.stop_tasks.add(task)
        task.add_done_callback(self.stop_tasks.discard)

    async def _send_stop(
        self, source: str, query: Any, answer: Callable[[bool, str], None] | None = None
    ) -> None:
        d = self.d
        key = d.key("arm/stop")

        def respond(ok: bool, text: str) -> None:
            if answer is not None:
                answer(ok, text)
            elif query is not None and ok:
                query.reply(key, text)
            elif query is not None:
                query.reply_err(text)

        with query if query is not None else contextlib.nullcontext():
            try:
                if self.controller is None:
                    respond(False, "rejected: arm disabled or shut down")
                    return
                await self.controller.stop(reason=f"{key} ({source})")
                respond(
                    True,
                    f"stopped: zero velocity and {d.cfg.arm.safety.safe_mode} sent; motion "
                    f"is refused until {d.key('arm/release')}",
                )
            except Exception as exc:  # a bug: count and log, answer, keep serving
                d.report.internal_error("errors.query.arm_stop", "stopping the arm", exc)
                if query is not None:
                    with contextlib.suppress(Exception):
                        query.reply_err(f"internal error: {type(exc).__name__}")

    def on_release(self) -> str:
        """``<prefix>/arm/release`` (exact key only): clear a latched stop; returns the reply."""
        if self.controller is None:
            raise InputRejected("disabled", "arm disabled: set [arm] enabled = true to allow motion")
        was = self.controller.release_stop()
        self.d.health.count("arm.releases")
        log.warning("arm: stop released (was: %s)", was)
        return f"released (was: {was})" if was is not None else "not stopped: nothing to release"

    def on_stop_put(self, key_expr: str) -> None:
        if key_expr == self.d.key("arm/stop"):
            self.stop("put")
        else:  # a put on a wildcard (``pugs/**``) is data for someone else, not a stop request
            self.d._refuse_wildcard("arm_stop", key_expr)

    async def worker(self) -> None:
        d = self.d
        while not d._stopping:
            grasps, grasp_id, width_m, generation = await self.box.take()
            d._busy["arm"] = True
            try:
                async with d._motion_lock:
                    if generation != d._generation:  # a reset ran while it waited for the lock
                        raise InputRejected("reset", "the map was reset since the request")
                    rep = await self.controller.execute_grasp_id(grasps, grasp_id, width_m)
                report = jsonable(rep.to_dict())
            except PugsdError as exc:
                log.warning("arm: grasp %d refused or failed: %s", grasp_id, exc)
                report = {"grasp_id": grasp_id, "ok": False, "error": str(exc)}
            except Exception as exc:  # keep serving; the controller has already stopped the arm
                log.error("arm: grasp %d failed: %s", grasp_id, exc)
                report = {"grasp_id": grasp_id, "ok": False, "error": repr(exc)}
            finally:
                d._busy["arm"] = False
            self.publish_report(report)

    def cancel_queued(self) -> None:
        """Shutdown: answer an accepted request that never started with a failed report (its
        requester was told "accepted")."""
        why = "the daemon shut down before the motion started"
        while (item := self.box.take_nowait()) is not None:
            grasp_id = item[1]
            log.warning("arm: grasp %d not executed: %s", grasp_id, why)
            self.publish_report({"grasp_id": grasp_id, "ok": False, "error": why})

    def publish_report(self, report: dict[str, Any]) -> None:
        self.report = report
        try:
            self.d.session.put(self.d.key("arm/report"), json.dumps(report))
        except Exception as exc:
            log.warning("arm: could not publish the report: %s", exc)

