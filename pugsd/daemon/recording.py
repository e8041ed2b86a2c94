# SPDX-License-Identifier: Apache-2.0
"""The daemon's recorder (``[record]``): started once the inputs listen, optional (the daemon
serves without it and says why), stopped at shutdown with one line naming its files."""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger(__name__)


def start_recording(cfg: Any, session: Any) -> Any:
    """The recorder of ``cfg``, recording from ``session``; None when it cannot be set up. One
    that cannot start or subscribe is returned with the error in its stats (the status shows it)."""
    from pugsd.record.recorder import Recorder, default_record_keys  # only when recording

    keys = default_record_keys(cfg)
    try:
        rec = Recorder.from_config(cfg)
    except Exception as exc:  # recording is optional: serve without it, say why
        log.error("recording off: the recorder could not be set up: %s: %s", type(exc).__name__, exc)
        return None
    try:
        rec.start()
        rec.subscribe(session, keys)
    except Exception as exc:  # a thread that cannot start, a key expression zenoh refuses
        msg = f"not recording: {type(exc).__name__}: {exc}"
        rec.stats.error = f"{rec.stats.error}; {msg}" if rec.stats.error else msg
        log.error("recorder: %s", msg)
        return rec
    if not rec.stats.error:  # else the recorder logged why it is not recording
        log.info("recording %d key expressions to %s", len(keys), cfg.record.directory)
    return rec


# how long the shutdown waits for the writer to write what is queued and finish the file (a full
# queue of [record] queue_max_bytes on a slow disk); not [daemon] shutdown_timeout_s, which bounds
# the calls in flight: what was recorded must not be left in a ``.part`` file by a short bound
FINISH_TIMEOUT_S = 10.0


def stop_recording(rec: Any, timeout_s: float = FINISH_TIMEOUT_S) -> None:
    files = rec.stop(timeout=timeout_s)
    # hours of rotation leave thousands of files: name the last five, count the rest
    shown = ", ".join(str(f) for f in files[-5:]) or "no file"
    more = f" (and {len(files) - 5} earlier)" if len(files) > 5 else ""
    log.info("recording finished: %d file(s): %s%s", len(files), shown, more)
