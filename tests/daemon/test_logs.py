# SPDX-License-Identifier: Apache-2.0
"""pugsd.daemon.logs: the fields of a JSON log line (what the journal and a log
shipper parse), and what ``setup_logging`` does to the root logger (level, one handler, stderr,
the text format)."""

from __future__ import annotations

import io
import json
import logging
import re
import sys
from pathlib import Path

import pytest

from pugsd.daemon.logs import JsonFormatter, setup_logging


def _record(msg: str = "hello %d", args: tuple[object, ...] = (3,)) -> logging.LogRecord:
    rec = logging.LogRecord("pugsd.audit", logging.ERROR, "f.py", 7, msg, args, None)
    rec.created = 1_700_000_000.123456789
    return rec


def test_a_plain_record_has_exactly_the_four_standard_fields() -> None:
    out = json.loads(JsonFormatter().format(_record()))
    assert out == {"ts": 1_700_000_000.123457, "level": "error", "logger": "pugsd.audit", "msg": "hello 3"}


def test_attributes_set_by_other_formatters_and_private_ones_stay_out() -> None:
    """Another handler (the text one, pytest's) formatting the record first leaves ``message``
    and ``asctime`` on it; underscore attributes are internal: none of them is an ``extra``."""
    rec = _record()
    logging.Formatter("%(asctime)s %(message)s").format(rec)
    assert hasattr(rec, "message") and hasattr(rec, "asctime")
    rec._internal = "x"
    rec.stage = "depth"
    out = json.loads(JsonFormatter().format(rec))
    assert set(out) == {"ts", "level", "logger", "msg", "stage"} and out["stage"] == "depth"


def test_an_exception_goes_into_exc() -> None:
    try:
        raise ValueError("boom")
    except ValueError:
        info = sys.exc_info()
    rec = logging.LogRecord("pugsd.audit", logging.ERROR, "f.py", 7, "failed", None, info)
    out = json.loads(JsonFormatter().format(rec))
    assert out["msg"] == "failed"
    assert out["exc"].startswith("Traceback (most recent call last):")
    assert out["exc"].endswith("ValueError: boom")


def test_an_extra_json_cannot_encode_is_written_as_its_str() -> None:
    rec = _record()
    rec.path = Path("/var/lib/pugsd/run.mcap")
    rec.ids = {3}
    out = json.loads(JsonFormatter().format(rec))
    assert out["path"] == "/var/lib/pugsd/run.mcap" and out["ids"] == "{3}"


def _stderr(monkeypatch: pytest.MonkeyPatch) -> io.StringIO:
    """stderr as a buffer (set in the test itself: pytest's capture resets sys.stderr between a
    fixture's set-up and the test)."""
    buf = io.StringIO()
    monkeypatch.setattr(sys, "stderr", buf)
    return buf


@pytest.mark.usefixtures("root_saved")
def test_setup_logging_replaces_the_handlers_and_sets_the_level(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = _stderr(monkeypatch)
    setup_logging("debug", json_lines=True)
    setup_logging("debug", json_lines=True)  # a second call replaces, not adds
    root = logging.getLogger()
    assert root.level == logging.DEBUG and len(root.handlers) == 1
    logging.getLogger("pugsd.audit").debug("once")
    lines = stderr.getvalue().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["msg"] == "once"
    setup_logging("error")
    assert root.level == logging.ERROR and len(root.handlers) == 1
    setup_logging("no-such-level")
    assert root.level == logging.INFO


@pytest.mark.usefixtures("root_saved")
def test_setup_logging_text_lines(monkeypatch: pytest.MonkeyPatch) -> None:
    stderr = _stderr(monkeypatch)
    setup_logging("warning", json_lines=False)
    log = logging.getLogger("pugsd.audit")
    log.info("hidden")
    log.warning("queue %s full", "depth")
    lines = stderr.getvalue().splitlines()
    assert len(lines) == 1, lines
    assert re.fullmatch(
        r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} WARNING pugsd\.audit: queue depth full", lines[0]
    ), lines[0]


def test_an_extra_named_like_a_standard_field_does_not_replace_it() -> None:
    """``log.error("x", extra={"level": "debug"})`` used to write ``"level": "debug"`` over the
    record's real level (the extra came after the standard fields); such extras are now written
    as ``extra_<name>`` and the standard fields stay the record's."""
    rec = _record()
    for k, v in {"level": "debug", "ts": 0, "logger": "other", "exc": "e", "stack": "s"}.items():
        setattr(rec, k, v)
    out = json.loads(JsonFormatter().format(rec))
    assert (out["level"], out["ts"], out["logger"]) == ("error", 1_700_000_000.123457, "pugsd.audit")
    assert "exc" not in out and "stack" not in out
    assert (out["extra_level"], out["extra_ts"], out["extra_logger"]) == ("debug", 0, "other")
    assert (out["extra_exc"], out["extra_stack"]) == ("e", "s")
