# SPDX-License-Identifier: Apache-2.0
"""The daemon's ROS 2 services (rmw_zenoh format, :mod:`pugsd.wire.services`), next to its zenoh
queryables (:mod:`pugsd.daemon.queries`), which stay for non-ROS clients:

- ``~/reset`` (``std_srvs/srv/Trigger``): clear the map, as ``<prefix>/reset``;
- ``~/get_grasps`` (``pugs_msgs/srv/GetGrasps``): the latest GraspArray, as ``grasps/latest``;
- with the arm enabled, ``~/arm/execute`` (``pugs_msgs/srv/ExecuteGrasp``: a grasp id of the
  latest grasps and an optional width), ``~/arm/stop`` and ``~/arm/release``
  (``std_srvs/srv/Trigger``), as ``<prefix>/arm/...``.

``~`` is the node ``/<daemon.node_name>`` (e.g. ``/pugsd/reset``). A refusal is a response with
``success = false`` and the reason in ``message`` (an rmw_zenoh client only logs an error reply and
then waits for its timeout); a request that is not one (no rmw_zenoh attachment, not the request's
CDR) gets an error reply. As for the zenoh queryables, the services that change state act only on
a query for exactly their key. Requests are answered on the loop, bounded as the queryables are
(``Bridge.query``): beyond that bound a request gets the bridge's plain-text answer ("busy", or
for a stop "a stop is already being sent"), which an rmw_zenoh client cannot decode.
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import TYPE_CHECKING, Any

from pugsd.daemon.bridge import Command
from pugsd.daemon.queries import refuse_wildcard
from pugsd.errors import PugsdError
from pugsd.stream.assembler import InputRejected
from pugsd.wire import codec
from pugsd.wire import services as srv
from pugsd.wire.topics import graph_tokens_enabled, ros_graph_tokens
from pugsd.wire.types import EXECUTE_GRASP, GET_GRASPS, GRASP_ARRAY, TRIGGER, msg_class

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

log = logging.getLogger(__name__)

#: service kind -> (name under the node, type); the bridge's query kind is the same string, and
#: ``arm_stop`` shares the arm stop's own ingress bound (a flood of queries never turns it away)
SERVICES: dict[str, tuple[str, str]] = {
    "reset": ("reset", TRIGGER),
    "latest": ("get_grasps", GET_GRASPS),
}
ARM_SERVICES: dict[str, tuple[str, str]] = {
    "arm_execute": ("arm/execute", EXECUTE_GRASP),
    "arm_stop": ("arm/stop", TRIGGER),
    "arm_release": ("arm/release", TRIGGER),
}
STATE_CHANGING = frozenset({"reset", "arm_execute", "arm_stop", "arm_release"})


def service_names(node_name: str, arm: bool) -> dict[str, str]:
    """Fully qualified service name -> type of the services a daemon serves."""
    table = {**SERVICES, **(ARM_SERVICES if arm else {})}
    return {f"/{node_name}/{name}": typename for name, typename in table.values()}


class RosServices:
    """Declares the services of the daemon ``d`` (queryables in ``d._entities``, their graph
    tokens in ``d._graph_tokens``, both undeclared at shutdown) and answers them."""

    def __init__(self, d: Daemon) -> None:
        self.d = d
        self.keys: dict[str, str] = {}  # kind -> service key

    def name(self, kind: str) -> str:
        return f"/{self.d.cfg.daemon.node_name}/{(SERVICES | ARM_SERVICES)[kind][0]}"

    def key(self, kind: str) -> str:
        t = self.d.cfg.topics
        return srv.service_key(self.name(kind), (SERVICES | ARM_SERVICES)[kind][1], domain_id=t.domain_id,
                               hash_mode=t.hash_mode)  # fmt: skip

    def declare(self, kinds: list[str]) -> None:
        """Declare the services ``kinds`` (keys of SERVICES or ARM_SERVICES); none with
        ``[topics] key_style = "ros2dds"`` (rmw_zenoh's format only)."""
        d = self.d
        t, node_name = d.cfg.topics, d.cfg.daemon.node_name
        if t.key_style != "rmw_zenoh":
            return
        s = d.session
        for kind in kinds:
            self.keys[kind] = key = self.key(kind)
            on_query = d.bridge.query(kind, self.answer)
            d._entities.append(s.declare_queryable(key, on_query, complete=True))
        if graph_tokens_enabled(t, node_name):
            names = service_names(node_name, d.cfg.arm.enabled)
            tokens = ros_graph_tokens(t, node_name, str(s.zid()), services=names).services
            for kind in kinds:
                d._graph_tokens.append(s.liveliness().declare_token(tokens[self.name(kind)]))
        log.info("ROS 2 services: %s", ", ".join(self.name(k) for k in kinds))

    def answer(self, kind: str, query: Any) -> None:
        """On the loop: answer one request of ``kind``."""
        d, key = self.d, self.keys[kind]
        typename = (SERVICES | ARM_SERVICES)[kind][1]
        if kind in STATE_CHANGING and str(query.key_expr) != key:
            with query, contextlib.suppress(Exception):
                refuse_wildcard(d, kind, str(query.key_expr))
                query.reply_err(f"rejected: {self.name(kind)} acts only on a query for exactly {key}")
            return
        try:
            payload = query.payload.to_bytes() if query.payload is not None else None
            attachment = query.attachment.to_bytes() if query.attachment is not None else None
            req = srv.read_request(typename, payload, attachment)
        except PugsdError as exc:
            d.report.reject("ros_service", InputRejected("bad_request", f"{self.name(kind)}: {exc}"[:300]))
            with query, contextlib.suppress(Exception):
                query.reply_err(f"rejected: not an rmw_zenoh {typename} request: {exc}"[:300])
            return
        if kind == "arm_stop":  # answered by the stop task once the stop is sent
            d.arm.stop("ROS service", query, answer=lambda ok, text: self._reply(query, kind, req, ok, text))
            return
        with query:
            try:
                ok, text, extra = self._act(kind, req.request)
                self._reply(query, kind, req, ok, text, **extra)
            except Exception as exc:  # a bug: count and log, answer, keep serving
                d.report.internal_error(f"errors.ros_service.{kind}", f"answering {self.name(kind)}", exc)
                with contextlib.suppress(Exception):
                    query.reply_err(f"internal error: {type(exc).__name__}")

    def _reply(
        self, query: Any, kind: str, req: srv.ServiceRequest, ok: bool, text: str, **extra: Any
    ) -> None:
        typename = (SERVICES | ARM_SERVICES)[kind][1]
        msg = srv.response(typename, success=bool(ok), message=str(text), **extra)
        srv.reply(query, self.keys[kind], typename, req, msg)

    def _act(self, kind: str, request: Any) -> tuple[bool, str, dict[str, Any]]:
        """(success, message, the response's other fields) of one request."""
        d = self.d
        if kind == "latest":
            if d._resetting:  # latest_grasps is the map being cleared
                return False, "no grasps: the map is being reset", {"grasps": self._no_grasps()}
            if d.outputs.latest_grasps is None:
                return False, "no grasps yet: model not ready", {"grasps": self._no_grasps()}
            return True, "", {"grasps": codec.deserialize(d.outputs.latest_grasps, GRASP_ARRAY)}
        if kind == "reset":
            if d._offer_command(Command("reset", None)):
                return True, "accepted: the map is cleared next", {}
            return False, f"rejected: {d.commands.reject_reason()}", {}
        try:
            if kind == "arm_execute":
                w = float(request.width)
                width_m = w if math.isfinite(w) and w > 0 else None
                return True, d.arm.request_execute(int(request.grasp_id), width_m), {}
            return True, d.arm.on_release(), {}  # arm_release
        except PugsdError as exc:
            if not isinstance(exc, InputRejected):
                exc = InputRejected("refused", str(exc))
            d.report.reject("arm", exc)
            return False, f"rejected: {exc}", {}

    def _no_grasps(self) -> Any:
        H, Time = msg_class("std_msgs/msg/Header"), msg_class("builtin_interfaces/msg/Time")
        header = H(stamp=Time(sec=0, nanosec=0), frame_id=self.d.frames.frame_id)
        return msg_class(GRASP_ARRAY)(header=header, grasps=[])
