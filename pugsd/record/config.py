# SPDX-License-Identifier: Apache-2.0
"""Config section of the MCAP recorder."""

from __future__ import annotations

from dataclasses import dataclass

from pugsd.configbase import opt
from pugsd.errors import ConfigError


@dataclass(frozen=True, slots=True)
class RecordConfig:
    """MCAP recording of the daemon's inputs and outputs (also the defaults of `pugsd record`)."""

    enabled: bool = opt(False, "record the daemon's inputs and outputs")
    directory: str = opt("/var/lib/pugsd/recordings", "where recordings go")
    name_prefix: str = opt("pugsd", "file names are PREFIX_<UTC time>_<index>.mcap")
    keys: tuple[str, ...] = opt((), "zenoh key expressions to record; empty: every [topics] input and output")
    compression: str = opt("zstd", "MCAP chunk compression", choices=("zstd", "lz4", "none"))
    chunk_size_bytes: int = opt(1048576, "MCAP chunk size (ZSTD)", unit="B", ge=4096, le=1073741824)
    flush_interval_s: float = opt(
        2.0,
        "close the open chunk at least this often (bounds what a crash loses)",
        unit="s",
        gt=0.0,
    )
    rotate_size_bytes: int = opt(
        1073741824,
        "start a new file once the current one holds this much (on disk: the chunks written so far)",
        unit="B",
        ge=1048576,
    )
    rotate_duration_s: float = opt(600.0, "start a new file after this long", unit="s", gt=0.0)
    max_total_bytes: int = opt(
        0,
        "keep the finished recordings of this name_prefix in directory within this size: after each "
        "finished file the oldest are deleted (never the newest; the file being written comes on "
        "top); 0: no limit, recording stops when the disk is full",
        unit="B",
        ge=0,
    )
    queue_max_bytes: int = opt(
        268435456,
        "payload bytes waiting for the writer thread before the oldest are dropped "
        "(the message count bound is [queues] record)",
        unit="B",
        ge=1048576,
        le=17179869184,
    )

    def __post_init__(self) -> None:
        """``keys`` must be key expressions zenoh accepts (``a//b`` or the non-canonical ``a/**/**``
        were refused only when the recorder subscribed: the daemon then ran without recording)."""
        if not self.keys:
            return
        import zenoh  # only for a config that names keys

        for key in self.keys:
            try:
                zenoh.KeyExpr(key)
            except Exception as exc:  # zenoh.ZError
                reason = str(exc).split(" at /", 1)[0]  # without zenoh's source path
                raise ConfigError(f"keys: {key!r} is not a zenoh key expression ({reason})") from None
