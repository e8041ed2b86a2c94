# SPDX-License-Identifier: Apache-2.0
"""Logging set-up: plain text for a terminal, one JSON object per line for the journal."""

from __future__ import annotations

import json
import logging
import sys
from typing import Any

# attributes every LogRecord has; anything else was passed with ``extra=`` and goes into the JSON
_STD_ATTRS = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {
    "message",
    "asctime",
}


# the keys JsonFormatter writes itself
_OUT_KEYS = frozenset({"ts", "level", "logger", "msg", "exc", "stack"})


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", ...extra}``; exceptions as ``exc``, ``stack_info=True``
    as ``stack``."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for k, v in vars(record).items():
            if k not in _STD_ATTRS and not k.startswith("_"):
                # an extra named like a standard field ("level", "ts") must not replace it
                out[f"extra_{k}" if k in _OUT_KEYS else k] = v
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        if record.stack_info:
            out["stack"] = self.formatStack(record.stack_info)
        return json.dumps(out, default=str)


def setup_logging(level: str = "info", json_lines: bool = False) -> None:
    """Configure the root logger once (replaces earlier handlers) to write to stderr."""
    handler = logging.StreamHandler(sys.stderr)
    if json_lines:
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(getattr(logging, level.upper(), logging.INFO))
