# SPDX-License-Identifier: Apache-2.0
"""rmw_zenoh's sample attachment: 33 bytes of zenoh-ext serialisation.

Layout: ``int64 sequence_number`` (LE, starts at 1), ``int64 source_timestamp`` (LE, ns since the
epoch, system clock), a LEB128 length byte ``0x10``, then the 16-byte publisher GID.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass

from pugsd.errors import DecodeError

ATTACHMENT_SIZE = 33
_FMT = struct.Struct("<qqB16s")


@dataclass(frozen=True, slots=True)
class Attachment:
    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        if len(self.gid) != 16:
            raise ValueError(f"GID must be 16 bytes, got {len(self.gid)}")


def new_gid() -> bytes:
    """A random 16-byte publisher GID (any stable 16 bytes per publisher interoperate)."""
    return os.urandom(16)


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    if len(gid) != 16:
        raise ValueError(f"GID must be 16 bytes, got {len(gid)}")
    return _FMT.pack(int(sequence_number), int(source_timestamp_ns), 16, bytes(gid))


def decode_attachment(data: bytes | bytearray | memoryview | None) -> Attachment:
    """Parse the 33-byte attachment; DecodeError on any other size or a wrong GID length byte."""
    if data is None:
        raise DecodeError("no attachment")
    b = bytes(data)
    if len(b) != ATTACHMENT_SIZE:
        raise DecodeError(f"attachment is {len(b)} bytes, expected {ATTACHMENT_SIZE}")
    seq, ts, n, gid = _FMT.unpack(b)
    if n != 16:
        raise DecodeError(f"attachment GID length byte is {n}, expected 16")
    return Attachment(seq, ts, gid)


def now_ns() -> int:
    return time.time_ns()
