# SPDX-License-Identifier: Apache-2.0
"""The streaming daemon: stereo (or depth) and poses in over zenoh, PUGS-scored grasps out.

It wires, it does not decide: zenoh callbacks hand samples to the loop (``bridge``), the frame
assembler (``pugsd.stream``) turns them into frames, bounded mailboxes carry the frames to the
depth and model workers and the model's changes to the grasp worker, the streaming schedule says
when the model trains and when grasps and clouds are due, and ``outputs`` publishes them. Heavy
calls run off the loop on four threads: depth estimation (stateless), ingest, training and grasp
computations. Ingest, reset and the grasp snapshot hold ``_model_lock`` (the map: store, TSDF,
free space); training takes its batch under it and steps the SVGP under ``_svgp_lock`` alone, so
that frames are integrated while the model trains; scoring and resets hold both (always
``_model_lock`` first). The grasp proposal runs on a snapshot, holding neither.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import zenoh

from pugsd.config import config_warnings
from pugsd.core.types import DepthFrame, StereoFrame
from pugsd.daemon import queries
from pugsd.daemon.arm_bridge import ArmBridge
from pugsd.daemon.bridge import Bridge, Command, Inbound, endpoints
from pugsd.daemon.health import (
    Health,
    InputWatch,
    OverloadWatch,
    Reporter,
    UnhealthyLog,
    report_unprocessed,
    status_of,
    status_round,
)
from pugsd.daemon.mailbox import Mailbox, Overflow
from pugsd.daemon.notify import Notifier, watchdog_interval_s
from pugsd.daemon.outputs import Outputs, output_stamp_ns
from pugsd.daemon.pipeline_api import Pipeline
from pugsd.daemon.process import FINISHED_AT_SHUTDOWN, WORKER_STAGES, apply_thread_limits
from pugsd.daemon.queries import QUERY_KEYS
from pugsd.daemon.recording import start_recording, stop_recording
from pugsd.daemon.ros_services import ARM_SERVICES, SERVICES, RosServices
from pugsd.daemon.training import Training
from pugsd.daemon.transforms import Transforms
from pugsd.errors import DecodeError, PugsdError
from pugsd.stream.assembler import FrameAssembler, InputRejected, expected_type, frame_nbytes, log_nth
from pugsd.stream.schedule import StreamingSchedule
from pugsd.wire import codec
from pugsd.wire.keys import parse_key
from pugsd.wire.publisher import Publisher
from pugsd.wire.session import close_session, open_session
from pugsd.wire.topics import (
    INPUT_ROLES,
    OUTPUT_ROLES,
    TRANSIENT_LOCAL_DEPTH,
    graph_tokens_enabled,
    key_for,
    ros_graph_tokens,
    subscribe_key_for,
)

log = logging.getLogger(__name__)

R = TypeVar("R")


class Daemon:
    """Owns the zenoh entities, mailboxes and workers; ``run(stop)`` serves until ``stop``."""

    def __init__(
        self,
        cfg: Any,  # pugsd.config.PugsdConfig
        pipeline: Pipeline,
        *,
        notifier: Notifier | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        self.cfg = cfg
        d, q = cfg.daemon, cfg.queues
        self.pipeline = pipeline
        self.notifier = notifier if notifier is not None else Notifier()
        self._own_session = session is None
        self._session = session
        self.health = Health(d.stall_timeout_s, d.max_consecutive_failures)
        self.report = Reporter(self.health)
        self.frames = FrameAssembler(
            d, q, self.report, self._on_frame, time.monotonic, expire_before=self._expire_before
        )
        # each bounded in bytes too; the depth stage starts a frame only while the depth box has
        # room (_depth_worker), so that the newest frame wins before stereo matching
        frame_bytes = {"max_bytes": q.buffered_bytes, "size_of": lambda item: frame_nbytes(item[0])}
        self.stereo_box: Mailbox[tuple[StereoFrame, float]] = Mailbox(
            "stereo", q.stereo, Overflow.DROP_OLDEST, **frame_bytes
        )
        self.depth_box: Mailbox[tuple[DepthFrame, float]] = Mailbox(
            "depth", q.depth, Overflow.DROP_OLDEST, **frame_bytes
        )
        self.commands: Mailbox[Command] = Mailbox("commands", q.commands, Overflow.REJECT)
        # the model side to the grasp worker: what last changed ("frame", "step"), or a reset's
        # end or a stop; the worker then looks at the model and the schedule again
        self.model_changes: Mailbox[str] = Mailbox("model_changes", 1, Overflow.KEEP_LATEST)
        self.arm = ArmBridge(self)
        self.schedule = StreamingSchedule(d)  # on time.monotonic()
        self.overload = OverloadWatch()
        self.bridge = Bridge(
            d.ingress_limit,
            lambda: self._loop,
            max_bytes=d.ingress_max_bytes,
            max_message_bytes=d.max_image_bytes + codec.MESSAGE_OVERHEAD_BYTES,
        )
        self._model_lock = threading.Lock()
        self._svgp_lock = threading.Lock()
        # each integrated frame wakes the training worker
        self.integrated: Mailbox[str] = Mailbox("integrated", 1, Overflow.KEEP_LATEST)
        pool = concurrent.futures.ThreadPoolExecutor  # one thread each: depth, model, train, grasps
        self._depth_exec = pool(1, thread_name_prefix="pugsd-depth")
        self._model_exec = pool(1, thread_name_prefix="pugsd-model")
        self._train_exec = pool(1, thread_name_prefix="pugsd-train")
        self._grasp_exec = pool(1, thread_name_prefix="pugsd-grasps")
        self._in_flight: set[concurrent.futures.Future[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subscribers: list[Any] = []
        self._entities: list[Any] = []  # queryables, token (undeclared after the subscribers)
        self.outputs = Outputs(self, time.monotonic)
        self.training = Training(self)
        self.ros_services = RosServices(self)
        self.transforms = Transforms(self)  # /tf and /tf_static
        # rmw_zenoh ROS graph tokens: the node's and its publishers', the subscriptions'
        self._graph_tokens: list[Any] = []
        self._sub_graph_tokens: list[Any] = []
        self._sub_graph_keys: list[str] = []
        self.recorder: Any = None  # pugsd.record.recorder.Recorder when [record] enabled
        self._stopping = False
        self._generation = 0  # bumped by reset: frames from before it are not integrated
        self._resetting = False  # from that bump until the map is cleared: no grasp computation
        # the last reset raised part-way: no grasps and unhealthy (a restart) until one succeeds
        self._reset_failed = False
        self._busy: dict[str, bool] = {}
        # a reset holds Python's GIL long enough to starve an arm motion's watchdog: a reset waits
        # for a motion to end, and a motion for the reset (an arm stop waits for neither)
        self._motion_lock = asyncio.Lock()
        self.latest_status: dict[str, Any] = {}
        self.elbo: float | None = None
        self.ready = False
        self.was_ready = False  # ready at least once since the start or the last reset
        self._newest_recv_s: float | None = None  # receive time of the newest integrated frame
        self.inputs = InputWatch(d.input_stale_s)
        # the outputs' stamp: written and read under _model_lock (with the map it labels)
        self._newest_stamp_ns = 0
        # bumped under _model_lock by every integrate and reset: which map a snapshot was of
        self.map_version = 0

    # --- lifecycle ------------------------------------------------------------------------------

    @property
    def session(self) -> zenoh.Session:
        assert self._session is not None
        return self._session

    def key(self, suffix: str) -> str:
        return f"{self.cfg.daemon.prefix}/{suffix}"

    async def run(self, stop: asyncio.Event) -> None:
        """Serve until ``stop`` is set; then stop intake, finish the calls in flight that have an
        effect within ``shutdown_timeout_s`` (abandon the others), undeclare everything and close
        the session."""
        self._loop = asyncio.get_running_loop()
        apply_thread_limits(self.cfg)
        for w in config_warnings(self.cfg):
            log.warning("config: %s", w)
        if self._session is None:
            loopback = not self.cfg.daemon.allow_non_loopback
            self._session = open_session(self.cfg.zenoh, require_loopback=loopback)
        try:
            self._declare_outputs()
            await self._start_arm()
            warm_up = getattr(self.pipeline, "warm_up", None)
            if warm_up is not None:  # first-call costs before READY, not on the first frame
                t0 = time.monotonic()
                await asyncio.to_thread(self._locked, warm_up)
                log.info("pipeline warmed up in %.1f s", time.monotonic() - t0)
            if stop.is_set():  # SIGTERM during the start (the warm-up takes seconds): never READY
                log.info("stop requested while starting: not serving")
                return
            svgp = getattr(self.pipeline, "svgp", None)
            if svgp is not None:  # the automatic M depends on the device (svgp.num_inducing = 0)
                log.info("SVGP on %s with M = %d inducing points", svgp.device, svgp.num_inducing)
            self._declare_inputs()
            self._start_recorder()
            # "alive" means serving: declared with READY, after the warm-up (seconds on a GPU),
            # so that a source that waits for it finds the inputs subscribed
            self._entities.append(
                self.session.liveliness().declare_token(self.key(f"alive/{self.cfg.daemon.node_name}"))
            )
            log.info(
                "pugsd serving: prefix %r, %d input keys, zenoh %s, listening on %s, connecting to %s",
                self.cfg.daemon.prefix,
                len(self._subscribers),
                self.session.zid(),
                endpoints(self.cfg.zenoh, "listen"),
                endpoints(self.cfg.zenoh, "connect"),
            )
            self.notifier.send("READY=1", "STATUS=waiting for frames")
            async with asyncio.TaskGroup() as tg:
                workers = {
                    "depth": tg.create_task(self._depth_worker(), name="depth"),
                    "model": tg.create_task(self._model_worker(), name="model"),
                    "train": tg.create_task(self.training.worker(), name="train"),
                    "grasps": tg.create_task(self._grasp_worker(), name="grasps"),
                    "commands": tg.create_task(self._command_worker(), name="commands"),
                    "status": tg.create_task(self._status_worker(), name="status"),
                    "watchdog": tg.create_task(self._watchdog_worker(), name="watchdog"),
                    "gate": tg.create_task(self._gate_worker(), name="gate"),
                    "arm": tg.create_task(self.arm.worker(), name="arm"),
                }
                tg.create_task(self._supervise(stop, workers), name="supervisor")
        finally:
            self.notifier.send("STOPPING=1")
            await self.arm.close()
            self._close()
            for ex in (self._depth_exec, self._model_exec, self._train_exec, self._grasp_exec):
                ex.shutdown(wait=False, cancel_futures=True)
            log.info("pugsd stopped")

    @property
    def serving(self) -> bool:
        """True once the subscriptions are live (READY was sent) and until shutdown begins."""
        return bool(self._subscribers) and not self._stopping

    def abandoned_work(self) -> int:
        """Offloaded calls still running after shutdown (abandoned; the CLI's exit does not wait)."""
        return sum(1 for f in self._in_flight if not f.done())

    async def _supervise(self, stop: asyncio.Event, workers: dict[str, asyncio.Task[None]]) -> None:
        await stop.wait()
        t0 = time.monotonic()
        log.info("shutdown: stopping intake")
        self._stopping = True
        self.model_changes.offer("stop")  # a waiting grasp worker ends at once
        self._undeclare_subscribers()
        for box in (
            self.stereo_box, self.depth_box, self.commands, self.arm.box, self.model_changes, self.integrated
        ):  # fmt: skip
            box.close()
        busy: list[asyncio.Task[None]] = []
        for name, task in workers.items():
            in_call = [stage for stage in WORKER_STAGES.get(name, ()) if self._busy.get(stage)]
            if any(stage in FINISHED_AT_SHUTDOWN for stage in in_call):
                busy.append(task)  # inside a call with an effect: let it finish (its loop then ends)
            else:
                if in_call:  # the thread runs on until the call returns; the exit does not wait
                    log.info("shutdown: abandoning the %s call in flight", " and ".join(in_call))
                task.cancel()
        if busy:
            log.info("shutdown: finishing in-flight work (%s)", ", ".join(t.get_name() for t in busy))
            _, pending = await asyncio.wait(busy, timeout=self.cfg.daemon.shutdown_timeout_s)
            for t in pending:
                log.warning("shutdown: %s did not finish in time; abandoning it", t.get_name())
                t.cancel()
        log.info("shutdown: workers stopped in %.2f s", time.monotonic() - t0)
        self._report_unprocessed()

    def _report_unprocessed(self) -> None:
        report_unprocessed(self)

    def _undeclare_subscribers(self) -> None:
        for tok in self._sub_graph_tokens:
            self._undeclare(tok)
        self._sub_graph_tokens.clear()
        for sub in self._subscribers:
            self._undeclare(sub)
        self._subscribers.clear()

    def _undeclare(self, ent: Any) -> None:
        try:
            ent.undeclare()
        except Exception as exc:
            log.debug("undeclare failed: %s", exc)

    async def _start_arm(self) -> None:
        """Connect to the arm when the config enables it and declare its keys."""
        if not await self.arm.start():
            return
        s = self.session
        for kind in ("arm_execute", "arm_stop", "arm_release"):
            on_query = self.bridge.query(kind, self._on_query)
            self._entities.append(s.declare_queryable(self.key(QUERY_KEYS[kind]), on_query))
        self.ros_services.declare(list(ARM_SERVICES))
        on_put = self.bridge.control_put(self.arm.on_stop_put, self.bridge.stop_ingress)
        self._entities.append(s.declare_subscriber(self.key("arm/stop"), on_put))
        log.info(
            "arm enabled (%s); execute on %s, stop on %s, release on %s",
            self.cfg.arm.transport, self.key("arm/execute"), self.key("arm/stop"), self.key("arm/release"),
        )  # fmt: skip

    def _start_recorder(self) -> None:
        if self.cfg.record.enabled:
            self.recorder = start_recording(self.cfg, self.session)  # stopped by _close

    def _close(self) -> None:
        if self.recorder is not None:
            stop_recording(self.recorder)
            self.recorder = None
        self._undeclare_subscribers()
        for ent in self._entities:
            self._undeclare(ent)
        self._entities.clear()
        for pub in self.outputs.publishers.values():
            self._undeclare(pub)
        self.outputs.publishers.clear()
        for tok in reversed(self._graph_tokens):  # the node's last, as rmw_zenoh destroys a node
            self._undeclare(tok)
        self._graph_tokens.clear()
        if self._own_session and self._session is not None:
            close_session(self._session)
            self._session = None

    # --- zenoh entities ---------------------------------------------------------------------------

    def _declare_outputs(self) -> None:
        t = self.cfg.topics
        for role in OUTPUT_ROLES:
            depth = TRANSIENT_LOCAL_DEPTH.get(role, 0)
            self.outputs.publishers[role] = Publisher(self.session, key_for(t, role), cache_depth=depth)
        s = self.session
        node_name = self.cfg.daemon.node_name
        if graph_tokens_enabled(t, node_name):
            graph = ros_graph_tokens(t, node_name, str(s.zid()), outputs=OUTPUT_ROLES, inputs=INPUT_ROLES)
            for key in (graph.node, *graph.publishers.values()):
                self._graph_tokens.append(s.liveliness().declare_token(key))
            self._sub_graph_keys = list(graph.subscriptions.values())
            log.info(
                "ROS graph: node /%s with %d publishers and %d subscriptions (rmw_zenoh liveliness "
                "tokens, domain %d)",
                node_name,
                len(graph.publishers),
                len(graph.subscriptions),
                t.domain_id,
            )
        for kind in ("latest", "status", "reset"):
            on_query = self.bridge.query(kind, self._on_query)
            self._entities.append(s.declare_queryable(self.key(QUERY_KEYS[kind]), on_query))
        on_reset = self.bridge.control_put(self._on_reset_put, self.bridge.query_ingress)
        self._entities.append(s.declare_subscriber(self.key("reset"), on_reset))
        self.ros_services.declare(list(SERVICES))

    def _declare_inputs(self) -> None:
        t = self.cfg.topics
        for role in INPUT_ROLES:
            key = subscribe_key_for(t, role)
            on_sample = self.bridge.sample(role, self._on_inbound)
            self._subscribers.append(self.session.declare_subscriber(key, on_sample))
        for key in self._sub_graph_keys:  # announced once the subscribers listen
            self._sub_graph_tokens.append(self.session.liveliness().declare_token(key))

    def _on_reset_put(self, key_expr: str) -> None:
        if key_expr == self.key("reset"):
            self._offer_command(Command("reset", None))
        else:  # a put on a wildcard (``pugs/**``) must not clear the map
            self._refuse_wildcard("reset", key_expr)

    # --- loop-side handlers -----------------------------------------------------------------------

    def _on_query(self, kind: str, query: Any) -> None:
        queries.answer(self, kind, query)

    def _refuse_wildcard(self, kind: str, asked: str) -> None:
        queries.refuse_wildcard(self, kind, asked)

    def _offer_command(self, cmd: Command) -> bool:
        ok = self.commands.offer(cmd)
        if not ok:  # counted each; logged like rejected input: the first five, then every 100th
            reason = "queue full" if not self._stopping else "shutting down"
            self.health.reject("commands", reason)
            n = self.health.rejected[f"commands: {reason}"]
            if log_nth(n):
                log.warning("command %s rejected (#%d): %s", cmd.name, n, self.commands.reject_reason())
        return ok

    def dropped_total(self) -> int:
        """Everything the daemon itself dropped: the stereo and depth mailboxes (drop oldest, and
        reset), the ingress bound, unpaired stereo halves, and the counted drops (pose wait,
        duplicate stamps, reset, in flight during a reset)."""
        return (
            self.stereo_box.dropped
            + self.depth_box.dropped
            + self.bridge.ingress.dropped
            + self.frames.pairer.unpaired_dropped
            + self.health.counts.get("dropped", 0)
        )

    def _on_inbound(self, item: Inbound) -> None:
        self.bridge.handled(item)
        self.health.count(f"received.{item.role}")
        self.inputs.received(item.role, time.monotonic())
        if item.lost_before:  # counted by self.upstream; logged like rejections
            self.health.count(f"upstream_gaps.{item.role}")
            n = self.health.counts[f"upstream_gaps.{item.role}"]
            if log_nth(n):
                log.warning(
                    "%s: %d message(s) lost before pugsd (rmw_zenoh sequence gap #%d): the "
                    "publisher's congestion control or the link dropped them",
                    item.role, item.lost_before, n,
                )  # fmt: skip
        if self._stopping:
            return
        try:
            self._dispatch(item)
        except PugsdError as exc:
            self.report.reject(item.role, exc)
        except Exception as exc:  # a bug, not bad input: count and log, keep serving
            self.report.internal_error(f"errors.input.{item.role}", f"handling {item.role} input", exc)

    def _msg_type(self, item: Inbound, default: str) -> str:
        if self.cfg.topics.key_style == "rmw_zenoh":
            try:
                return parse_key(item.key).typename
            except DecodeError as exc:
                raise InputRejected("wrong_type", f"{item.role}: {exc}"[:300]) from None
        return default

    def _dispatch(self, item: Inbound) -> None:
        typename = self._msg_type(item, expected_type(item.role, self.cfg.topics.pose_type))
        self.frames.feed(item.role, item.payload, item.recv_s, typename, item.publisher, item.key)
        if item.role == "pose":  # accepted: on /tf
            self.transforms.on_pose(item.payload, typename)

    def _expire_before(self, now_s: float) -> float:
        """A frame's deadline counts as passed only before the oldest pose still queued for the
        loop came in: after a stall of the loop that pose is handled next and may be the frame's."""
        backlog = self.bridge.pose_backlog_s
        return min(now_s, backlog[0]) if backlog else now_s

    def _on_frame(self, frame: StereoFrame | DepthFrame, recv_s: float) -> None:
        if isinstance(frame, StereoFrame):
            self.stereo_box.offer((frame, recv_s))
        else:
            self.depth_box.offer((frame, recv_s))

    # --- workers ----------------------------------------------------------------------------------

    async def _offload(self, stage: str, fn: Callable[..., R], *args: Any) -> R:
        """Run ``fn(*args)`` off the loop, timed and watched as ``stage``."""
        loop = asyncio.get_running_loop()
        self._busy[stage] = True
        try:
            with self.health.busy(stage):
                ex = {"depth": self._depth_exec, "train": self._train_exec, "grasps": self._grasp_exec}.get(
                    stage, self._model_exec
                )
                fut = ex.submit(fn, *args)
                self._in_flight.add(fut)
                fut.add_done_callback(self._in_flight.discard)
                return await asyncio.wrap_future(fut, loop=loop)
        finally:
            self._busy[stage] = False

    def _locked(self, fn: Callable[..., R], *args: Any) -> R:
        with self._model_lock, self._svgp_lock:
            return fn(*args)

    async def _guard(self, stage: str, coro: Awaitable[R]) -> R | None:
        return await self.report.guard(stage, coro)

    async def _depth_worker(self) -> None:
        while not self._stopping:
            await self.depth_box.wait_room()  # match only what the model takes next: the newest
            frame, recv_s = await self.stereo_box.take()
            gen = self._generation
            depth = await self._guard("depth", self._offload("depth", self.pipeline.depth_from_stereo, frame))
            if depth is not None and gen != self._generation:
                self.health.drop("depth", "map reset while in flight")
            elif depth is not None:
                self.health.count("depth")
                self.depth_box.offer((depth, recv_s))

    async def _model_worker(self) -> None:
        """Integrates each depth frame; the training worker trains meanwhile."""
        while not self._stopping:
            depth, recv_s = await self.depth_box.take()
            if await self._integrate(depth, recv_s):
                self.integrated.offer("frame")

    async def _integrate(self, depth: DepthFrame, recv_s: float) -> bool:
        """Integrate one frame (on the model thread), count it and tell the schedule and the grasp
        worker; False if it failed (counted by the guard)."""
        n = await self._guard("integrate", self._offload("integrate", self._integrate_locked, depth))
        if n is None:
            return False
        self.health.count("integrated")
        if self.health.counts["integrated"] == 1:
            log.info("first frame integrated (%d points)", n)
        self.health.count("points", n)
        self.health.observe("frame_age_at_integrate", time.monotonic() - recv_s)
        self.schedule.frame_integrated(time.monotonic(), recv_s)
        self.model_changes.offer("frame")
        self._newest_recv_s = recv_s
        return True

    def _integrate_locked(self, depth: DepthFrame) -> int:
        """On the model thread: integrate ``depth`` and advance the outputs' stamp under the same
        hold of the model lock, so that a grasp computation's snapshot and its stamp agree."""
        with self._model_lock:
            n = self.pipeline.integrate(depth)
            gap_ns = self.frames.poses.max_gap_ns
            self._newest_stamp_ns = output_stamp_ns(self._newest_stamp_ns, depth.stamp_ns, gap_ns)
            self.map_version += 1
            return n

    def _reset_locked(self) -> bool:
        """On the model thread: reset the pipeline and the outputs' stamp under both locks."""
        with self._model_lock, self._svgp_lock:
            self._newest_stamp_ns = 0
            self.map_version += 1
            self.pipeline.reset()
        return True

    def _cloud_gives_way(self) -> bool:
        """Whether the running computation's cloud gives way to fresh grasps (the schedule's
        ``cloud_gives_way``), and at shutdown at once: the cloud would not outlive the session,
        and would hold the exit. Called from the grasp thread; reads values only the loop writes."""
        return self._stopping or self.schedule.cloud_gives_way(time.monotonic(), self.frames_in_flight())

    def frames_in_flight(self) -> int:
        """Frames received but not yet integrated: waiting for or in depth estimation, waiting
        for or in integration. While there are any, the input has not paused."""
        busy = sum(bool(self._busy.get(stage)) for stage in ("depth", "integrate"))
        return len(self.stereo_box) + len(self.depth_box) + busy

    def _proposal_gives_way(self, snapshot_map_version: int) -> bool:
        """Whether the running computation's proposal, on the map of ``snapshot_map_version``,
        gives way: a frame was integrated since its snapshot and the schedule's
        ``proposal_gives_way`` holds; and at shutdown at once. Called from the grasp threads."""
        if self._stopping:
            return True
        return self.map_version != snapshot_map_version and self.schedule.proposal_gives_way(
            time.monotonic(), self.frames_in_flight()
        )

    async def _grasp_worker(self) -> None:
        """A grasp round when the model changed and the schedule says grasps are due. Between
        rounds it waits on ``model_changes``: until the next change while there is nothing to
        publish, and while a change waits for its grasps to be due, until then (or the next
        change, which may make them due sooner)."""
        loop, s, changes = asyncio.get_running_loop(), self.schedule, self.model_changes
        while not self._stopping:
            changes.take_nowait()  # this look at the model covers every change offered so far
            publishable = self.ready or (self.cfg.daemon.ready_latch and self.was_ready)
            if self._resetting or self._reset_failed:
                await changes.take()
            elif not publishable and s.frame_unpublished and self.outputs.prepared_for != self.map_version:
                await self.outputs.propose_early(changes)  # the model is not ready yet
            elif not (publishable and s.changed):
                await changes.take()
            else:
                await self.outputs.grasp_round(loop)

    async def _command_worker(self) -> None:
        while not self._stopping:
            cmd = await self.commands.take()
            if cmd.name == "reset":
                if self._motion_lock.locked():
                    log.info("reset: waiting for the arm motion in progress to end")
                async with self._motion_lock:
                    await self._reset()

    async def _reset(self) -> None:
        """The reset command: clear the queues, the pipeline and every published state."""
        self._generation += 1
        self._resetting = True
        try:
            await self._clear_all()
        finally:
            self._resetting = False
            self.model_changes.offer("reset")  # the grasp worker looks again

    async def _clear_all(self) -> None:
        """``_reset`` proper: the queues, the pipeline (on the model thread) and the published state."""
        cleared_stamp_ns = self._newest_stamp_ns  # the old map's time line (and its transforms)
        self.stereo_box.clear()  # counted by the mailboxes
        self.depth_box.clear()
        waiting, unpaired = self.frames.clear()
        if waiting:
            self.report.drop("reset", "frames waiting for a pose", waiting)
        if unpaired:
            self.report.drop("reset", "unpaired stereo halves", unpaired)
        if await self._guard("reset", self._offload("reset", self._reset_locked)):
            # a run of integrate failures belonged to the old map (out_of_map_range: its anchor)
            self.health.succeeded("integrate")
            self._reset_failed = False
        else:
            self._reset_failed = True
            log.error("reset: the pipeline could not be cleared; no grasps until a reset succeeds")
        self.outputs.clear()
        self.ready = False
        self.was_ready = False
        self.schedule.reset()
        self._newest_recv_s = None
        self.elbo = None
        self.health.count("resets")
        self.outputs.publish_cleared(cleared_stamp_ns)
        log.info("reset: map cleared")

    def input_ages_s(self, now: float | None = None) -> dict[str, float]:
        return self.inputs.ages_s(time.monotonic() if now is None else now)

    def stale_inputs(self, now: float | None = None) -> list[str]:
        return self.inputs.stale(time.monotonic() if now is None else now)

    def problems(self) -> list[str]:
        """Why the daemon is unhealthy (empty: healthy): the health monitor's and a failed reset."""
        out = self.health.problems()
        if self._reset_failed:
            out.append("reset failed: the map may not be cleared (grasps withheld; send a reset again)")
        return out

    def status(self) -> dict[str, Any]:
        return status_of(self)

    async def _status_worker(self) -> None:
        period = 1.0 / self.cfg.daemon.status_rate_hz
        while not self._stopping:
            await asyncio.sleep(period)
            try:
                status_round(self)
            except Exception as exc:  # a bug: count and log; the daemon keeps serving
                self.report.internal_error("errors.status", "the status round", exc)

    def _report_overload(self, now_s: float) -> None:
        c, age = self.health.counts, self.health.latency.get("frame_age_at_integrate")
        self.overload.check(
            now_s,
            self.stereo_box.overflowed + self.depth_box.overflowed,
            c.get("frames.stereo", 0) + c.get("frames.depth", 0),
            c.get("integrated", 0),
            age.summary().get("p50_ms") if age is not None else None,
        )

    async def _watchdog_worker(self) -> None:
        interval = watchdog_interval_s()
        period = min(1.0, interval) if interval else 1.0
        unhealthy = UnhealthyLog()
        while not self._stopping:
            try:
                self.health.tick()
                problems: list[str] | None = self.problems()
            except Exception as exc:  # a bug: no verdict this round, so no ping; the daemon serves on
                self.report.internal_error("errors.watchdog", "the watchdog round", exc)
                problems = None
            if problems is not None and unhealthy.note(problems, time.monotonic()) and interval:
                self.notifier.send("WATCHDOG=1")
            await asyncio.sleep(period)

    async def _gate_worker(self) -> None:
        """Expire frames whose pose never came (deadlines pass without new input)."""
        while not self._stopping:
            await asyncio.sleep(0.05)
            if len(self.frames.gate):
                try:
                    self.frames.poll()
                except Exception as exc:  # a bug in the lookup itself: keep the worker alive
                    self.report.internal_error("errors.gate", "polling the pose gate", exc)
