# SPDX-License-Identifier: Apache-2.0
"""The daemon's queryables: ``grasps/latest``, ``status``, ``reset`` and the arm's, answered on
the loop. Each reply goes out on the queryable's own key (a wildcard query's replies stay apart
under zenoh's consolidation); those that change state act only on a query for exactly their
key, and a wildcard query reaching them gets an error reply."""

from __future__ import annotations

import contextlib
import json
from typing import TYPE_CHECKING, Any

from pugsd.daemon.bridge import Command
from pugsd.daemon.health import jsonable
from pugsd.errors import PugsdError
from pugsd.stream.assembler import InputRejected

if TYPE_CHECKING:
    from pugsd.daemon.app import Daemon

# queryable kind -> its key under the prefix
QUERY_KEYS = {
    "latest": "grasps/latest",
    "status": "status",
    "reset": "reset",
    "arm_execute": "arm/execute",
    "arm_stop": "arm/stop",
    "arm_release": "arm/release",
}
# a wildcard query (``pugs/**``, to read the status or discover the API) must not stop the arm
# mid-grasp or change anything else: these act on a query for exactly their key
STATE_CHANGING = frozenset({"reset", "arm_execute", "arm_stop", "arm_release"})
# how the error replies to grasps/latest begin when there are no grasps to give yet (no model yet,
# or a reset clearing the map): clients tell "not ready" apart from a failure by it
NO_GRASPS = "no grasps"
# how they begin when the latest grasp computation failed (a failure, not "not ready")
GRASPS_FAILED = "grasps failed"


def answer(d: Daemon, kind: str, query: Any) -> None:
    """Answer one query of ``kind``; a bug is counted and logged, and answered with an error."""
    key = d.key(QUERY_KEYS[kind])
    if kind == "arm_stop" and str(query.key_expr) == key:
        d.arm.stop("query", query)  # answered by the stop task once the stop is sent
        return
    with query:
        try:
            if kind in STATE_CHANGING and str(query.key_expr) != key:
                refuse_wildcard(d, kind, str(query.key_expr))
                query.reply_err(f"rejected: {key} acts only on a query for exactly that key")
            elif kind == "latest":
                if d._resetting:  # latest_grasps is the map being cleared
                    query.reply_err(f"{NO_GRASPS}: the map is being reset")
                elif d.outputs.latest_grasps is None:
                    query.reply_err(no_grasps_reason(d))
                else:
                    query.reply(key, d.outputs.latest_grasps)
            elif kind == "status":
                query.reply(key, json.dumps(jsonable(d.status())))
            elif kind in ("arm_execute", "arm_release"):
                try:
                    query.reply(key, d.arm.on_execute(query) if kind == "arm_execute" else d.arm.on_release())
                except PugsdError as exc:
                    if not isinstance(exc, InputRejected):
                        exc = InputRejected("refused", str(exc))
                    d.report.reject("arm", exc)
                    query.reply_err(f"rejected: {exc}")
            elif kind == "reset":
                if d._offer_command(Command("reset", None)):
                    query.reply(key, "accepted")
                else:
                    query.reply_err(f"rejected: {d.commands.reject_reason()}")
        except Exception as exc:  # a bug: count and log, answer, keep serving
            d.report.internal_error(f"errors.query.{kind}", f"answering a {kind} query", exc)
            with contextlib.suppress(Exception):
                query.reply_err(f"internal error: {type(exc).__name__}")


def no_grasps_reason(d: Daemon) -> str:
    """Why ``grasps/latest`` has no grasps to answer with: the latest grasp computation's
    failure when it failed, else that the model is not ready (or has not been published yet)."""
    failure = d.health.last_failure.get("grasps")
    if failure is not None:
        return f"{GRASPS_FAILED}: the last grasp computation failed ({failure})"
    if not (d.ready or d.was_ready):
        return f"{NO_GRASPS} yet: model not ready"
    return f"{NO_GRASPS} yet: the first grasp computation has not finished"


def refuse_wildcard(d: Daemon, kind: str, asked: str) -> None:
    """Count a state-changing request that named a wildcard instead of its exact key."""
    source = "arm" if kind.startswith("arm_") else kind
    msg = f"{kind} needs exactly {d.key(QUERY_KEYS[kind])!r}, not {asked[:200]!r}"
    d.report.reject(source, InputRejected("wildcard_key", msg))
