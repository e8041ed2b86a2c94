# SPDX-License-Identifier: Apache-2.0
"""Config section of the MCAP recorder."""

from __future__ import annotations

from dataclasses import dataclass

from pugsd.configbase import opt


@dataclass(frozen=True, slots=True)
class RecordConfig:
    """MCAP recording of the daemon's own inputs and outputs."""

    enabled: bool = opt(False, "record the daemon's inputs and outputs")
    directory: str = opt("/var/lib/pugsd/recordings", "where recordings go")
    chunk_size_bytes: int = opt(1048576, "MCAP chunk size (ZSTD)", unit="B", ge=4096)
    rotate_size_bytes: int = opt(1073741824, "start a new file beyond this size", unit="B", ge=1048576)
    rotate_duration_s: float = opt(600.0, "start a new file after this long", unit="s", gt=0.0)
