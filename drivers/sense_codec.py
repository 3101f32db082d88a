"""BRUCE's sense board (Raspberry Pi Pico, BRUCE-OP v0.0.5/v0.0.7 firmware): the wire protocol (firmware
`Library/BRUCE_SENSE/pico/pico.ino`, host `Manager.py`) without I/O: `encode_command`, `encode_packet`,
`check_packet`, `decode_packet` and `SenseParser`, which resynchronises on the header and counts what it rejects. A
packet carries what the hw backend's IMU sample wants (rad/s, m/s^2 specific force, IMU frame): no conversion is made.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from drivers.errors import LinkStats

HEADER = 0xFF
TRAILER = 0xFE
PACKET_LEN = 29
PACKET_REST_LEN = PACKET_LEN - 2  # the length byte: bytes after it
COMMAND_LEN = 5
COMMAND_REST_LEN = COMMAND_LEN - 2
CONTACT_MARK = 0x80        # bit 7 of the contact byte is always set
BIAS_REPORT_FLAGS = 0xFF   # contact byte of a calibration bias report
MAX_COOLING_SPEED = 10
FIRMWARE_GRAVITY = 9.80665  # m/s^2 per g in the firmware's accelerometer scale (ISM330DHCX.h)
_FLOATS = struct.Struct("<6f")
_HEADER_AND_LENGTH = bytes((HEADER, PACKET_REST_LEN))


class PicoMode(IntEnum):
    IDLE = 0
    NOMINAL = 1
    RESET = 2
    CALIBRATE = 3

    @classmethod
    def parse(cls, mode: PicoMode | int | str) -> PicoMode:
        if isinstance(mode, str):
            name = {"calibration": "calibrate", "stream": "nominal"}.get(mode.lower(), mode.lower())
            try:
                return cls[name.upper()]
            except KeyError:
                raise ValueError(f"unknown sense-board mode {mode!r} (idle, nominal, reset, calibrate)") from None
        return cls(mode)


def checksum(body: bytes | bytearray | memoryview) -> int:
    """NOT of the low byte of the sum: what both directions use over the bytes between header and checksum."""
    return ~sum(body) & 0xFF


# -- host -> board ---------------------------------------------------------------------------------------------
def encode_command(mode: PicoMode | int | str, cooling_speed: int = 0) -> bytes:
    """The 5-byte command ``0xFF | 3 | cooling_speed << 2 | mode | NOT(3 + that byte) & 0xFF | 0xFE`` (mode 0 idle,
    1 nominal (stream), 2 reset IMU (then idle), 3 calibrate; cooling 0..10); raises ValueError for a mode or
    cooling speed the firmware does not define. The firmware reads commands only once per second in NOMINAL mode
    (every ~10 ms in IDLE), the last valid command in its buffer wins, and the rest of the buffer is discarded."""
    mode = PicoMode.parse(mode)
    if not (isinstance(cooling_speed, int | np.integer) and 0 <= cooling_speed <= MAX_COOLING_SPEED):
        raise ValueError(f"cooling_speed must be an integer 0..{MAX_COOLING_SPEED}, got {cooling_speed!r}")
    byte = (int(cooling_speed) << 2) | int(mode)
    return bytes((HEADER, COMMAND_REST_LEN, byte, checksum((COMMAND_REST_LEN, byte)), TRAILER))


def decode_command(packet: bytes) -> tuple[PicoMode, int] | None:
    """(mode, cooling_speed) of one 5-byte command, or None when the firmware would ignore it."""
    if (len(packet) != COMMAND_LEN or packet[0] != HEADER or packet[1] != COMMAND_REST_LEN
            or packet[3] != checksum(packet[1:3]) or packet[4] != TRAILER):
        return None
    return PicoMode(packet[2] & 3), (packet[2] >> 2) & 15


# -- board -> host ---------------------------------------------------------------------------------------------
def contact_byte(contact) -> int:
    """The packet's contact byte for four booleans in FOOT_CONTACT_NAMES order."""
    flags = CONTACT_MARK
    for bit, c in enumerate(contact):
        if c:
            flags |= 1 << bit
    return flags


def encode_packet(accel, gyro, contact=(False,) * 4, *, bias_report: bool = False) -> bytes:
    """The 29-byte packet, 1 kHz, only in NOMINAL mode: ``0xFF | 27 | accel x,y,z float32 LE | gyro x,y,z float32 LE
    | contacts | checksum | 0xFE`` (values rounded to float32, as the board sends them). accel is the specific force
    (+g on the up axis at rest: the firmware's calibration subtracts g from z), gyro bias-corrected by the board.
    contacts: 0x80 | bits 0..3 in FOOT_CONTACT_NAMES order (1 = contact); 0xFF marks a calibration bias report.
    checksum = NOT(sum of bytes 1..26) & 0xFF."""
    flags = BIAS_REPORT_FLAGS if bias_report else contact_byte(contact)
    body = bytearray((PACKET_REST_LEN,))
    body += _FLOATS.pack(*(float(v) for v in accel), *(float(v) for v in gyro))
    body.append(flags)
    return bytes((HEADER, *body, checksum(body), TRAILER))


# Read-only contact arrays for each of the 16 contact patterns, shared by every sample.
_CONTACTS = tuple(np.array([(bits >> k) & 1 for k in range(4)], dtype=bool) for bits in range(16))
for _a in _CONTACTS:
    _a.flags.writeable = False


@dataclass(frozen=True, slots=True, eq=False)
class SenseSample:
    """One decoded packet. Arrays are read-only (shared with whoever holds the sample)."""

    accel: np.ndarray    # (3,) m/s^2, specific force, IMU frame
    gyro: np.ndarray     # (3,) rad/s, IMU frame
    contact: np.ndarray  # (4,) bool, FOOT_CONTACT_NAMES order
    bias_report: bool = False  # a calibration bias report: accel/gyro carry the biases, contact is meaningless


def check_packet(packet: bytes | bytearray | memoryview) -> str | None:
    """Why a 29-byte window is not a valid packet (a reject reason), or None when it is one."""
    if len(packet) != PACKET_LEN:
        return "truncated" if len(packet) < PACKET_LEN else "length"
    if packet[0] != HEADER:
        return "garbage"
    if packet[1] != PACKET_REST_LEN:
        return "length"
    if packet[PACKET_LEN - 1] != TRAILER:
        # A header inside the window means the packet was cut short and the next one began.
        return "truncated" if bytes(packet).find(_HEADER_AND_LENGTH, 1) >= 0 else "trailer"
    if packet[PACKET_LEN - 2] != checksum(packet[1:PACKET_LEN - 2]):
        return "checksum"
    flags = packet[PACKET_LEN - 3]
    if flags != BIAS_REPORT_FLAGS and flags & 0xF0 != CONTACT_MARK:
        return "flags"
    return None


def decode_packet(packet: bytes | bytearray | memoryview, offset: int = 0) -> SenseSample:
    """Decode a packet that `check_packet` accepted (no checks here)."""
    values = np.array(_FLOATS.unpack_from(packet, offset + 2))
    values.flags.writeable = False
    flags = packet[offset + PACKET_LEN - 3]
    bias = flags == BIAS_REPORT_FLAGS
    return SenseSample(accel=values[:3], gyro=values[3:], contact=_CONTACTS[0 if bias else flags & 0x0F],
                       bias_report=bias)


class SenseParser:
    """Incremental parser of the board's byte stream. Never raises on bad bytes: it counts them in `stats`
    and resynchronises on the next header (a failed candidate costs one byte, so a real packet that starts
    inside a false one is still found). Unlike the official host, which flushes its input after one packet, it
    keeps every packet. Reject reasons: "garbage" (bytes outside any packet, counted once per run), "length",
    "trailer", "checksum", "flags" (a contact byte that is neither 0x80..0x8F nor 0xFF), "truncated" (the next
    header appears inside a packet, or the stream stalls mid-packet)."""

    def __init__(self, stats: LinkStats | None = None):
        self.stats = stats if stats is not None else LinkStats()
        self.skipped_bytes = 0
        self._buf = bytearray()
        self._in_bad_run = False  # garbage right after a rejection is part of that rejection, not a new one

    @property
    def pending(self) -> int:
        """Bytes of a packet begun but not yet complete."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray) -> list[SenseSample]:
        buf = self._buf
        buf += data
        out: list[SenseSample] = []
        i, n = 0, len(buf)
        while i < n:
            j = buf.find(HEADER, i)
            if j < 0:
                self._skip(n - i)
                i = n
                break
            if j > i:
                self._skip(j - i)
                i = j
            if n - i < 2:
                break  # wait for the length byte
            if buf[i + 1] != PACKET_REST_LEN:
                self._reject("length")
                i += 1
                continue
            if n - i < PACKET_LEN:
                break  # wait for the rest
            reason = check_packet(buf[i:i + PACKET_LEN])  # a copy: no export pins the buffer
            if reason is not None:
                self._reject(reason)
                i += 1
                continue
            out.append(decode_packet(buf, i))
            self.stats.packets += 1
            self._in_bad_run = False
            i += PACKET_LEN
        del buf[:i]
        return out

    def drop_partial(self) -> None:
        """The rest of a begun packet did not come (the stream stalled): drop it as truncated."""
        if self._buf:
            self._reject("truncated")
            self.skipped_bytes += len(self._buf)
            self._buf.clear()

    def _skip(self, count: int) -> None:
        self.skipped_bytes += count
        if not self._in_bad_run:
            self._reject("garbage")

    def _reject(self, reason: str) -> None:
        self.stats.reject(reason)
        self._in_bad_run = True
