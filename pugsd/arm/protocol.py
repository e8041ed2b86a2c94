# SPDX-License-Identifier: Apache-2.0
"""Reach "BPL" serial protocol (V1): packet ids, modes, devices, framing, typed payloads.

Framing (``docs/arm.md``; Reach System Communication Protocol): ``DATA | PACKET_ID | DEVICE_ID | LENGTH |
CRC8`` with ``LENGTH = len(DATA) + 4`` and the CRC over everything before it, then COBS and one
``0x00`` terminator. Floats are little-endian binary32, integers single unsigned bytes.
"""

from __future__ import annotations

import enum
import logging
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import crcmod
from cobs import cobs

from pugsd.errors import ArmError, DecodeError

log = logging.getLogger(__name__)

MAX_PACKET_LENGTH = 64  # bytes before stuffing, footer included
MAX_DATA_LENGTH = MAX_PACKET_LENGTH - 4
MAX_WIRE_CHUNK = MAX_PACKET_LENGTH + 2  # COBS overhead byte(s) for <=254 bytes, plus slack

# CRC-8: width 8, poly 0x4D (0x14D), init 0x00, reflected in/out, xorout 0xFF; check 0x7B.
# crcmod's initCrc is the register already XORed with xorOut, hence 0xFF.
crc8 = crcmod.mkCrcFun(0x14D, initCrc=0xFF, xorOut=0xFF, rev=True)


class PacketID(enum.IntEnum):
    """V1 packet ids (one byte). 0x67/0x6E follow the SDK Python (DEVICE_TYPE/PRESSURE)."""

    MODE = 0x01
    VELOCITY = 0x02
    POSITION = 0x03
    CURRENT = 0x05
    TORQUE = 0x0B
    INDEXED_RELATIVE_POSITION = 0x0D
    RELATIVE_POSITION = 0x0E
    POSITION_LIMITS = 0x10
    VELOCITY_LIMITS = 0x11
    CURRENT_LIMITS = 0x12
    FACTORY_CLIMATE = 0x28
    REQUEST_JAW_CALIBRATION = 0x38
    SAVE = 0x50
    PRESET_GO = 0x55
    PRESET_CAPTURE = 0x56
    PRESET_SET_0 = 0x57
    PRESET_SET_1 = 0x58
    PRESET_SET_2 = 0x59
    PRESET_SET_3 = 0x5A
    PRESET_NAME_0 = 0x5B
    PRESET_NAME_1 = 0x5C
    PRESET_NAME_2 = 0x5D
    PRESET_NAME_3 = 0x5E
    REQUEST = 0x60
    SERIAL_NUMBER = 0x61
    MODEL_NUMBER = 0x62
    DEVICE_ID = 0x64
    INTERNAL_HUMIDITY = 0x65
    TEMPERATURE = 0x66
    DEVICE_TYPE = 0x67
    HARDWARE_STATUS_FLAGS = 0x68
    SOFTWARE_VERSION = 0x6C
    PRESSURE = 0x6E
    VOLTAGE = 0x90
    HEARTBEAT_SET = 0x91
    HEARTBEAT_FREQUENCY = 0x92
    KM_END_POS = 0xA1
    KM_END_VEL = 0xA2
    BOX_OBSTACLE_1 = 0xA5
    BOX_OBSTACLE_2 = 0xA6
    BOX_OBSTACLE_3 = 0xA7
    BOX_OBSTACLE_4 = 0xA8
    CYLINDER_OBSTACLE_1 = 0xAB
    CYLINDER_OBSTACLE_2 = 0xAC
    CYLINDER_OBSTACLE_3 = 0xAD
    CYLINDER_OBSTACLE_4 = 0xAE
    COLLISION_FLAG = 0xAF
    COLLISION_COORDINATES = 0xB1
    MOUNT_TRANSFORM = 0xB4
    KM_END_VEL_LOCAL = 0xCB
    FT_SENSOR = 0xD8
    KM_END_VEL_LOCAL_ROLL = 0xF4
    RESET = 0xFD
    BOOTLOADER = 0xFF


#: Packet ids pugsd must never send (decoded if received).
FORBIDDEN_TX = frozenset({PacketID.RESET, PacketID.BOOTLOADER})


class Mode(enum.IntEnum):
    """MODE values (PDF table 7 plus legacy values seen in older code)."""

    STANDBY = 0x00
    DISABLE = 0x01
    POSITION = 0x02
    VELOCITY = 0x03
    CURRENT = 0x04
    OPENLOOP = 0x05
    INIT = 0x06
    CALIBRATE = 0x07
    FACTORY = 0x08
    COMPLIANT = 0x09
    GRIP = 0x0A
    JAW_CALIBRATION = 0x0D
    INDEXED_RELATIVE_POSITION = 0x13
    POSITION_PRESET = 0x14
    ZERO_VELOCITY = 0x15
    KINEMATIC_POSITION = 0x17
    KINEMATIC_VELOCITY = 0x18
    KINEMATIC_VELOCITY_LOCAL = 0x1A
    POSITION_VELOCITY = 0x1C
    POSITION_HOLD = 0x1D
    PASSIVE = 0x26
    TORQUE = 0x30


class DeviceID(enum.IntEnum):
    """Bravo 7 device ids: axes A (jaw) .. G (base rotate), router, compute, broadcast."""

    JAW = 0x01  # A, linear, mm
    WRIST_ROTATE = 0x02  # B
    WRIST_BEND = 0x03  # C
    FOREARM_ROTATE = 0x04  # D
    ELBOW = 0x05  # E
    SHOULDER = 0x06  # F
    BASE_ROTATE = 0x07  # G
    ROUTER = 0x0D
    COMPUTE = 0x0E
    BROADCAST = 0xFF


#: DH joint 1..6 -> device id (an assumption: joint i drives 0x08 - i; ``docs/arm.md``).
JOINT_DEVICES: tuple[int, ...] = (0x07, 0x06, 0x05, 0x04, 0x03, 0x02)
JAW_DEVICE = 0x01
ALL_AXES: tuple[int, ...] = (*JOINT_DEVICES, JAW_DEVICE)

#: joint feedback every telemetry period: REQUESTed (poll) or pushed by the devices (HEARTBEAT_SET)
FEEDBACK_IDS: tuple[int, ...] = (PacketID.POSITION, PacketID.VELOCITY, PacketID.MODE)


def heartbeat_frequency_hz(rate_hz: float) -> int:
    """The HEARTBEAT_FREQUENCY byte for a telemetry rate: whole Hz in 1..255."""
    return max(1, min(255, round(rate_hz)))


Kind = Literal["f32", "u8", "ascii"]


@dataclass(frozen=True, slots=True)
class PacketSpec:
    """Payload layout of one packet id: kind and allowed value counts."""

    pid: int
    name: str
    kind: Kind
    min_count: int
    max_count: int
    doc: str = ""


def _spec(pid: PacketID, kind: Kind, n: int | tuple[int, int], doc: str = "") -> PacketSpec:
    lo, hi = (n, n) if isinstance(n, int) else n
    return PacketSpec(int(pid), pid.name, kind, lo, hi, doc)


P = PacketID
PACKET_SPECS: dict[int, PacketSpec] = {
    s.pid: s
    for s in (
        _spec(P.MODE, "u8", 1, "mode byte"),
        _spec(P.VELOCITY, "f32", 1, "rad/s (jaw mm/s)"),
        _spec(P.POSITION, "f32", 1, "rad (jaw mm)"),
        _spec(P.CURRENT, "f32", 1, "mA"),
        _spec(P.TORQUE, "f32", 1, "N m"),
        _spec(P.INDEXED_RELATIVE_POSITION, "f32", 1, "rad"),
        _spec(P.RELATIVE_POSITION, "f32", 1, "rad"),
        _spec(P.POSITION_LIMITS, "f32", 2, "[max, min] per PDF"),
        _spec(P.VELOCITY_LIMITS, "f32", 2, "[max, min] per PDF"),
        _spec(P.CURRENT_LIMITS, "f32", 2, "[max, min] per PDF"),
        _spec(P.FACTORY_CLIMATE, "f32", 3, "degC, bar, %RH"),
        _spec(P.REQUEST_JAW_CALIBRATION, "f32", 2, "mA, rad/s"),
        _spec(P.SAVE, "u8", 1),
        _spec(P.PRESET_GO, "u8", 1, "preset index 0-3"),
        _spec(P.PRESET_CAPTURE, "u8", 1, "preset index 0-3"),
        *(_spec(PacketID(0x57 + i), "f32", 8, "rad, devices A..H") for i in range(4)),
        *(_spec(PacketID(0x5B + i), "ascii", 8, "name, NUL padded") for i in range(4)),
        _spec(P.REQUEST, "u8", (1, 10), "packet ids requested"),
        _spec(P.SERIAL_NUMBER, "f32", 1),
        _spec(P.MODEL_NUMBER, "f32", 1),
        _spec(P.DEVICE_ID, "u8", 1),
        _spec(P.INTERNAL_HUMIDITY, "f32", 1, "%RH"),
        _spec(P.TEMPERATURE, "f32", 1, "degC"),
        _spec(P.DEVICE_TYPE, "u8", 1, "0 rotary, 1 linear"),
        _spec(P.HARDWARE_STATUS_FLAGS, "u8", 4, "flag bytes A, B, C, D"),
        _spec(P.SOFTWARE_VERSION, "u8", 3, "major, sub, minor"),
        _spec(P.PRESSURE, "f32", 1, "bar"),
        _spec(P.VOLTAGE, "f32", 1, "V"),
        _spec(P.HEARTBEAT_SET, "u8", 10, "packet ids, unused 0"),
        _spec(P.HEARTBEAT_FREQUENCY, "u8", 1, "Hz, 0 = off"),
        _spec(P.KM_END_POS, "f32", 6, "x, y, z mm, yaw, pitch, roll rad"),
        _spec(P.KM_END_VEL, "f32", 6, "vx, vy, vz mm/s, rz, ry, rx rad/s"),
        *(_spec(PacketID(0xA5 + i), "f32", 6, "x1 y1 z1 x2 y2 z2 mm") for i in range(4)),
        *(_spec(PacketID(0xAB + i), "f32", 7, "x1 y1 z1 x2 y2 z2 r mm") for i in range(4)),
        _spec(P.COLLISION_FLAG, "u8", 3, "type, count, obstacle packet id"),
        _spec(P.COLLISION_COORDINATES, "f32", 3, "mm"),
        _spec(P.MOUNT_TRANSFORM, "f32", 6, "xyz mm, 3 angles"),
        _spec(P.KM_END_VEL_LOCAL, "f32", 6, "end-effector frame"),
        _spec(P.FT_SENSOR, "f32", 6, "Fx Fy Fz N, Tx Ty Tz N m"),
        _spec(P.KM_END_VEL_LOCAL_ROLL, "f32", 6, "x, y, z, rx, ry, rz"),
        _spec(P.RESET, "u8", (0, MAX_DATA_LENGTH), "never sent by pugsd"),
        _spec(P.BOOTLOADER, "u8", (0, MAX_DATA_LENGTH), "never sent by pugsd"),
    )
}

Values = tuple[float, ...] | tuple[int, ...] | str


@dataclass(frozen=True, slots=True)
class Packet:
    """One BPL packet: device id, packet id and the raw data bytes."""

    device_id: int
    packet_id: int
    data: bytes = b""

    def __post_init__(self) -> None:
        if not (0 <= self.device_id <= 0xFF and 0 <= self.packet_id <= 0xFF):
            raise ArmError(f"device/packet id out of range: {self.device_id}, {self.packet_id}")
        if len(self.data) > MAX_DATA_LENGTH:
            raise ArmError(f"packet data is {len(self.data)} bytes, max {MAX_DATA_LENGTH}")

    @property
    def spec(self) -> PacketSpec | None:
        return PACKET_SPECS.get(self.packet_id)

    @property
    def name(self) -> str:
        s = self.spec
        return s.name if s else f"0x{self.packet_id:02X}"

    def values(self) -> Values:
        """The typed payload (floats, bytes as ints, or text); DecodeError if it does not fit."""
        return decode_payload(self.packet_id, self.data)

    def floats(self) -> tuple[float, ...]:
        n, rem = divmod(len(self.data), 4)
        if rem:
            raise DecodeError(f"{self.name}: {len(self.data)} data bytes is not a float array")
        return struct.unpack(f"<{n}f", self.data)


def encode_payload(packet_id: int, values: Values | Sequence[float] | Sequence[int]) -> bytes:
    """Typed values -> data bytes for ``packet_id`` (checks kind and count)."""
    spec = PACKET_SPECS.get(packet_id)
    if spec is None:
        raise ArmError(f"unknown packet id 0x{packet_id:02X}")
    if spec.kind == "ascii":
        text = values if isinstance(values, str) else "".join(chr(int(v)) for v in values)
        raw = text.encode("ascii")
        if len(raw) > spec.max_count:
            raise ArmError(f"{spec.name}: name longer than {spec.max_count} characters")
        return raw.ljust(spec.max_count, b"\x00")
    if isinstance(values, str):
        raise ArmError(f"{spec.name}: expected numbers, got text")
    n = len(values)
    if not spec.min_count <= n <= spec.max_count:
        want = (
            str(spec.min_count) if spec.min_count == spec.max_count else f"{spec.min_count}-{spec.max_count}"
        )
        raise ArmError(f"{spec.name}: expected {want} values, got {n}")
    if spec.kind == "f32":
        try:
            return struct.pack(f"<{n}f", *(float(v) for v in values))
        except (OverflowError, struct.error, TypeError, ValueError) as exc:
            raise ArmError(f"{spec.name}: {list(values)!r} does not fit binary32 floats ({exc})") from None
    out = []
    for v in values:
        try:
            iv = int(v)
        except (TypeError, ValueError, OverflowError):
            raise ArmError(f"{spec.name}: byte value {v!r} is not an integer") from None
        if iv != v or not 0 <= iv <= 0xFF:
            raise ArmError(f"{spec.name}: byte value {v!r} out of range 0-255")
        out.append(iv)
    return bytes(out)


def decode_payload(packet_id: int, data: bytes) -> Values:
    """Data bytes -> typed values for ``packet_id``; unknown ids give the raw bytes as ints."""
    spec = PACKET_SPECS.get(packet_id)
    if spec is None:
        return tuple(data)
    if spec.kind == "ascii":
        if len(data) != spec.max_count:
            raise DecodeError(f"{spec.name}: expected {spec.max_count} bytes, got {len(data)}")
        return data.rstrip(b"\x00").decode("ascii", errors="replace")
    size = 4 if spec.kind == "f32" else 1
    n, rem = divmod(len(data), size)
    if rem or not spec.min_count <= n <= spec.max_count:
        raise DecodeError(f"{spec.name}: {len(data)} data bytes do not fit {spec.kind} x {n}")
    if spec.kind == "f32":
        return struct.unpack(f"<{n}f", data)
    return tuple(data)


def has_nonfinite(packet: Packet) -> bool:
    """True when a float packet carries NaN or an infinity (never sent, never trusted)."""
    spec = packet.spec
    if spec is None or spec.kind != "f32" or len(packet.data) % 4:
        return False
    return not all(math.isfinite(v) for v in packet.floats())


def make_packet(
    device_id: int, packet_id: int, values: Values | Sequence[float] | Sequence[int] = ()
) -> Packet:
    """A typed packet: ``make_packet(0x01, PacketID.POSITION, [4.123])``."""
    return Packet(int(device_id), int(packet_id), encode_payload(int(packet_id), values))


def encode_frame(packet: Packet) -> bytes:
    """Packet -> wire bytes (COBS-stuffed, with the 0x00 terminator)."""
    body = packet.data + bytes((packet.packet_id, packet.device_id, len(packet.data) + 4))
    raw = body + bytes((crc8(body),))
    return bytes(cobs.encode(raw)) + b"\x00"


def decode_frame(chunk: bytes) -> Packet:
    """One wire chunk (without or with its 0x00 terminator) -> Packet, or DecodeError."""
    if chunk.endswith(b"\x00"):
        chunk = chunk[:-1]
    if not chunk:
        raise DecodeError("empty frame")
    if b"\x00" in chunk:
        raise DecodeError("zero byte inside a frame")
    try:
        raw = cobs.decode(chunk)
    except cobs.DecodeError as exc:
        raise DecodeError(f"COBS: {exc}") from None
    if len(raw) < 4:
        raise DecodeError(f"frame of {len(raw)} bytes is too short")
    length = raw[-2]
    if length >= 0x80:
        raise DecodeError(f"length byte 0x{length:02X} is not a V1 packet")
    if length > MAX_PACKET_LENGTH:
        raise DecodeError(f"length byte {length} exceeds the {MAX_PACKET_LENGTH}-byte maximum")
    if length != len(raw):
        raise DecodeError(f"length byte {length} does not match {len(raw)} bytes")
    if crc8(raw[:-1]) != raw[-1]:
        raise CrcError(f"CRC 0x{raw[-1]:02X} != 0x{crc8(raw[:-1]):02X}")
    return Packet(device_id=raw[-3], packet_id=raw[-4], data=bytes(raw[:-4]))


class CrcError(DecodeError):
    """A frame whose CRC-8 does not match."""


@dataclass(slots=True)
class DecoderStats:
    """Counters of the stream decoder."""

    packets: int = 0
    crc_errors: int = 0
    framing_errors: int = 0
    overflows: int = 0
    bytes_in: int = 0
    bytes_dropped: int = 0

    @property
    def errors(self) -> int:
        return self.crc_errors + self.framing_errors + self.overflows

    def as_dict(self) -> dict[str, int]:
        return {
            "packets": self.packets,
            "crc_errors": self.crc_errors,
            "framing_errors": self.framing_errors,
            "overflows": self.overflows,
            "bytes_in": self.bytes_in,
            "bytes_dropped": self.bytes_dropped,
        }


@dataclass(slots=True)
class StreamDecoder:
    """Byte stream -> packets. Splits on 0x00, drops bad frames and resyncs; never raises."""

    max_chunk: int = MAX_WIRE_CHUNK
    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray)
    _discarding: bool = False

    @property
    def pending_bytes(self) -> int:
        """Bytes of an unfinished frame (no 0x00 seen yet)."""
        return len(self._buf)

    def reset(self) -> None:
        self.stats.bytes_dropped += len(self._buf)
        self._buf.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list[Packet]:
        out: list[Packet] = []
        self.stats.bytes_in += len(data)
        start = 0
        while start < len(data):
            end = data.find(b"\x00", start)
            if end < 0:
                piece = data[start:]
                if self._discarding:
                    self.stats.bytes_dropped += len(piece)
                else:
                    self._buf += piece
                    if len(self._buf) > self.max_chunk:
                        self.stats.overflows += 1
                        self.stats.bytes_dropped += len(self._buf)
                        self._buf.clear()
                        self._discarding = True
                break
            piece = data[start:end]
            start = end + 1
            if self._discarding:
                self.stats.bytes_dropped += len(piece) + 1
                self._discarding = False
                continue
            self._buf += piece
            chunk = bytes(self._buf)
            self._buf.clear()
            if not chunk:
                continue  # empty chunk between delimiters
            if len(chunk) > self.max_chunk:
                self.stats.overflows += 1
                self.stats.bytes_dropped += len(chunk) + 1
                continue
            try:
                out.append(decode_frame(chunk))
                self.stats.packets += 1
            except CrcError:
                self.stats.crc_errors += 1
                self.stats.bytes_dropped += len(chunk) + 1
            except DecodeError:
                self.stats.framing_errors += 1
                self.stats.bytes_dropped += len(chunk) + 1
            except Exception:  # defensive: a decoder bug must not kill a link
                log.exception("unexpected error decoding a frame")
                self.stats.framing_errors += 1
                self.stats.bytes_dropped += len(chunk) + 1
        return out


# ---------------------------------------------------------------- hardware status flags

HW_FLAG_BITS: dict[tuple[int, int], str] = {
    (0, 0x80): "flash_read_failed",
    (0, 0x40): "over_humidity",
    (0, 0x20): "over_temperature",
    (0, 0x10): "serial_comms_error",
    (0, 0x08): "crc_comms_error",
    (0, 0x04): "motor_driver_fault",
    (0, 0x02): "encoder_position_error",
    (0, 0x01): "encoder_not_detected",
    (1, 0x80): "device_axis_conflict",
    (1, 0x40): "motor_not_connected",
    (1, 0x20): "motor_over_current",
    (1, 0x10): "inner_encoder_error",
    (1, 0x08): "device_id_conflict",
    (1, 0x04): "over_pressure",
    (1, 0x02): "driver_over_current_or_under_voltage",
    (1, 0x01): "driver_over_temperature",
    (2, 0x08): "joint_service_due",
    (2, 0x02): "encoder_fault_backlash",
    (3, 0x10): "low_supply_voltage",
    (3, 0x01): "position_report_not_received",
}


@dataclass(frozen=True, slots=True)
class HardwareStatus:
    """HARDWARE_STATUS_FLAGS bytes A, B, C, D and their decoded names."""

    a: int = 0
    b: int = 0
    c: int = 0
    d: int = 0

    @classmethod
    def from_bytes(cls, data: bytes | Sequence[int]) -> HardwareStatus:
        if len(data) != 4:
            raise DecodeError(f"HARDWARE_STATUS_FLAGS: expected 4 bytes, got {len(data)}")
        return cls(*(int(x) for x in data))

    def to_bytes(self) -> bytes:
        return bytes((self.a, self.b, self.c, self.d))

    @property
    def names(self) -> list[str]:
        raw = self.to_bytes()
        out = [name for (i, bit), name in HW_FLAG_BITS.items() if raw[i] & bit]
        for i, letter in enumerate("ABCD"):
            known = 0
            for (j, bit), _ in HW_FLAG_BITS.items():
                if j == i:
                    known |= bit
            unknown = raw[i] & ~known & 0xFF
            if unknown:
                out.append(f"reserved_{letter}_0x{unknown:02X}")
        return out

    def any(self) -> bool:
        return any(self.to_bytes())

    def masked(self, mask: Sequence[int]) -> bool:
        """True when any flag selected by the 4-byte ``mask`` is set."""
        return any(v & m for v, m in zip(self.to_bytes(), mask))


# ---------------------------------------------------------------- name lookups


def parse_packet_id(text: str | int) -> int:
    """A packet id from a name (``position``) or a number (``3``, ``0x03``)."""
    if isinstance(text, int):
        return text
    t = text.strip()
    try:
        return PacketID[t.upper()].value
    except KeyError:
        pass
    try:
        v = int(t, 0)
    except ValueError:
        raise ArmError(f"unknown packet {text!r}") from None
    if not 0 <= v <= 0xFF:
        raise ArmError(f"packet id {v} out of range")
    return v


def parse_device_id(text: str | int) -> int:
    """A device id from a name (``jaw``, ``broadcast``, ``compute``, axis letter) or a number."""
    if isinstance(text, int):
        return text
    t = text.strip()
    letters = {"A": 1, "B": 2, "C": 3, "D": 4, "E": 5, "F": 6, "G": 7}
    if t.upper() in letters:
        return letters[t.upper()]
    try:
        return DeviceID[t.upper()].value
    except KeyError:
        pass
    try:
        v = int(t, 0)
    except ValueError:
        raise ArmError(f"unknown device {text!r}") from None
    if not 0 <= v <= 0xFF:
        raise ArmError(f"device id {v} out of range")
    return v


def parse_mode(text: str | int) -> int:
    if isinstance(text, int):
        return text
    try:
        return Mode[text.strip().upper()].value
    except KeyError:
        pass
    try:
        return int(text, 0)
    except ValueError:
        raise ArmError(f"unknown mode {text!r}") from None


def packet_to_json(p: Packet) -> dict[str, object]:
    """A JSON-ready description of a packet (used by ``pugsd bpl decode``)."""
    out: dict[str, object] = {
        "device_id": p.device_id,
        "device": _device_name(p.device_id),
        "packet_id": p.packet_id,
        "packet": p.name,
        "data_hex": p.data.hex(" ").upper(),
    }
    try:
        vals = p.values()
    except DecodeError as exc:
        out["error"] = str(exc)
        return out
    if isinstance(vals, str):
        out["values"] = vals
    elif p.spec is not None and p.spec.kind == "f32":
        # shortest text that round-trips through binary32 (4.123, not 4.123000144958496); NaN and
        # infinities as the strings Python's json would write unquoted (not valid JSON)
        out["values"] = [_json_f32(v) for v in vals]
    else:
        out["values"] = list(vals)
    if p.packet_id == PacketID.MODE and isinstance(vals, tuple) and vals:
        out["mode"] = _mode_name(int(vals[0]))
    elif p.packet_id in (PacketID.REQUEST, PacketID.HEARTBEAT_SET) and isinstance(vals, tuple):
        out["packets"] = [
            PACKET_SPECS[int(v)].name if int(v) in PACKET_SPECS else int(v) for v in vals if int(v) != 0
        ]
    elif p.packet_id == PacketID.HARDWARE_STATUS_FLAGS:
        out["flags"] = HardwareStatus.from_bytes(p.data).names
    return out


def _json_f32(v: float) -> float | str:
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "Infinity" if v > 0 else "-Infinity"
    short = _short_f32(v)
    return float(short) if short else float(f"{v:.9g}")


def _short_f32(v: float) -> str:
    """Shortest decimal text whose binary32 rounding equals ``v`` ('' if none up to 9 digits)."""
    target = struct.pack("<f", v)
    for digits in range(1, 10):
        t = f"{v:.{digits}g}"
        try:
            if struct.pack("<f", float(t)) == target:
                return t
        except OverflowError:  # near FLT_MAX a short text rounds beyond binary32 (3.403e38)
            continue
    return ""


def _device_name(dev: int) -> str:
    try:
        return DeviceID(dev).name
    except ValueError:
        return f"0x{dev:02X}"


def _mode_name(m: int) -> str:
    try:
        return Mode(m).name
    except ValueError:
        return f"0x{m:02X}"
