"""CAN actuators in MIT mode (the "mini cheetah" protocol of Ben Katz's motor controller, as spoken by T-Motor /
CubeMars AK-series actuators): the frame codec. Each frame's layout is at its encoder; `ReplyDecoder` accepts one
channel's replies and rejects everything else. Classic CAN, 11-bit identifiers. Pure: no I/O. No BRUCE source covers
CAN: where the protocol leaves things open, the choice is noted at the code that makes it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from drivers.errors import LinkStats

# Special 8-byte commands (rest mode: no torque); the motor answers every frame addressed to it with a reply.
ENTER_MOTOR_MODE = bytes([0xFF] * 7 + [0xFC])
EXIT_MOTOR_MODE = bytes([0xFF] * 7 + [0xFD])
SET_ZERO = bytes([0xFF] * 7 + [0xFE])
SPECIAL_FRAMES = {ENTER_MOTOR_MODE: "enter_motor_mode", EXIT_MOTOR_MODE: "exit_motor_mode", SET_ZERO: "set_zero"}

COMMAND_LENGTH = 8
REPLY_LENGTHS = (6, 8)     # the reference's 6; newer CubeMars firmware appends temperature and an error code (ignored)
MAX_MOTOR_ID = 0xFF        # the reply names its motor in one byte


class FrameError(ValueError):
    """A frame that cannot be decoded (wrong length). Raised by the pure decoders only, never out of a driver."""


@dataclass(frozen=True, slots=True)
class MitRanges:
    """The [min, max] that each field of one motor's frames is scaled onto (rad, rad/s, Nm/rad, Nm s/rad, Nm)."""

    p: tuple[float, float]
    v: tuple[float, float]
    kp: tuple[float, float]
    kd: tuple[float, float]
    t: tuple[float, float]

    def __post_init__(self) -> None:
        for name in ("p", "v", "kp", "kd", "t"):
            lo, hi = (float(x) for x in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"MitRanges.{name}: expected finite [min, max] with min < max, got {[lo, hi]}")
            object.__setattr__(self, name, (lo, hi))

    @classmethod
    def of(cls, value: Any) -> MitRanges:
        """From a MitRanges, a mapping {p, v, kp, kd, t} or any object with those attributes (the config's)."""
        if isinstance(value, MitRanges):
            return value
        get = value.__getitem__ if isinstance(value, Mapping) else lambda key: getattr(value, key)
        return cls(**{name: tuple(get(name)) for name in ("p", "v", "kp", "kd", "t")})


# T-Motor AK80-9, firmware V1.1 (MIT mode), as used by the public mini-cheetah-motor-driver-socketcan driver. Other
# firmwares use other ranges, which is why they are configurable per motor.
AK80_9_V1P1 = MitRanges(p=(-12.5, 12.5), v=(-22.5, 22.5), kp=(0.0, 500.0), kd=(0.0, 5.0), t=(-18.0, 18.0))


class MitCommand(NamedTuple):
    position: float
    velocity: float
    kp: float
    kd: float
    torque: float


class MotorReply(NamedTuple):
    motor_id: int
    position: float
    velocity: float
    torque: float


def float_to_uint(x: float, lo: float, hi: float, bits: int) -> int:
    """Clamp x to [lo, hi] and scale it onto 0 .. 2^bits - 1 (truncating, as the reference does): uint = trunc((x -
    lo) (2^bits - 1) / (hi - lo)); `uint_to_float` inverts it, so a round trip is exact to one step."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot encode a non-finite value ({x})")
    top = (1 << bits) - 1
    x = min(max(x, lo), hi)
    return min(int((x - lo) * top / (hi - lo)), top)


def uint_to_float(value: int, lo: float, hi: float, bits: int) -> float:
    return value * (hi - lo) / ((1 << bits) - 1) + lo


def step(lo: float, hi: float, bits: int) -> float:
    """One quantisation step of a field: the round-trip error bound."""
    return (hi - lo) / ((1 << bits) - 1)


def encode_command(command: MitCommand | Sequence[float], ranges: MitRanges) -> bytes:
    """Host -> motor, arbitration ID = motor ID, 8 bytes, fields most significant bit first: ``[p15..8] [p7..0]
    [v11..4] [v3..0|kp11..8] [kp7..0] [kd11..4] [kd3..0|t11..8] [t7..0]``; the motor applies ``tau = kp (p -
    p_meas) + kd (v - v_meas) + t``. A command with every field at full scale would alias a special frame (torque
    0xFFC = enter motor mode): its torque field is lowered by one step instead."""
    p_des, v_des, kp, kd, t_ff = command
    p = float_to_uint(p_des, *ranges.p, 16)
    v = float_to_uint(v_des, *ranges.v, 12)
    kp_i = float_to_uint(kp, *ranges.kp, 12)
    kd_i = float_to_uint(kd, *ranges.kd, 12)
    t = float_to_uint(t_ff, *ranges.t, 12)
    if p == 0xFFFF and v == kp_i == kd_i == 0xFFF and 0xFFC <= t <= 0xFFE:
        t = 0xFFB  # would read as enter/exit motor mode or set zero
    return bytes([p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (kp_i >> 8), kp_i & 0xFF,
                  kd_i >> 4, ((kd_i & 0xF) << 4) | (t >> 8), t & 0xFF])


def decode_command(data: bytes, ranges: MitRanges) -> MitCommand:
    if len(data) != COMMAND_LENGTH:
        raise FrameError(f"command frame has {len(data)} bytes, expected {COMMAND_LENGTH}")
    p = (data[0] << 8) | data[1]
    v = (data[2] << 4) | (data[3] >> 4)
    kp = ((data[3] & 0xF) << 8) | data[4]
    kd = (data[5] << 4) | (data[6] >> 4)
    t = ((data[6] & 0xF) << 8) | data[7]
    return MitCommand(uint_to_float(p, *ranges.p, 16), uint_to_float(v, *ranges.v, 12),
                      uint_to_float(kp, *ranges.kp, 12), uint_to_float(kd, *ranges.kd, 12),
                      uint_to_float(t, *ranges.t, 12))


def special_kind(data: bytes) -> str | None:
    """'enter_motor_mode', 'exit_motor_mode', 'set_zero' for the special frames, else None."""
    return SPECIAL_FRAMES.get(bytes(data))


def encode_reply(motor_id: int, position: float, velocity: float, torque: float, ranges: MitRanges) -> bytes:
    """Motor -> host, arbitration ID = host ID (the firmware's CAN_MASTER, 0 by default), 6 bytes:
    ``[motor ID] [p15..8] [p7..0] [v11..4] [v3..0|t11..8] [t7..0]``."""
    if not 0 <= motor_id <= MAX_MOTOR_ID:
        raise ValueError(f"motor ID {motor_id} does not fit the reply's ID byte")
    p = float_to_uint(position, *ranges.p, 16)
    v = float_to_uint(velocity, *ranges.v, 12)
    t = float_to_uint(torque, *ranges.t, 12)
    return bytes([motor_id, p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (t >> 8), t & 0xFF])


def decode_reply(data: bytes, ranges: MitRanges) -> MotorReply:
    if len(data) not in REPLY_LENGTHS:
        raise FrameError(f"reply frame has {len(data)} bytes, expected one of {REPLY_LENGTHS}")
    p = (data[1] << 8) | data[2]
    v = (data[3] << 4) | (data[4] >> 4)
    t = ((data[4] & 0xF) << 8) | data[5]
    return MotorReply(data[0], uint_to_float(p, *ranges.p, 16), uint_to_float(v, *ranges.v, 12),
                      uint_to_float(t, *ranges.t, 12))


def ranges_by_id(motor_ids: Sequence[int], ranges: Any) -> dict[int, MitRanges]:
    """Per-motor ranges from one MitRanges (all motors), a sequence (motor order) or a mapping by ID."""
    if isinstance(ranges, Mapping) and set(ranges) - {"p", "v", "kp", "kd", "t"}:
        return {i: MitRanges.of(ranges[i]) for i in motor_ids}
    if isinstance(ranges, Sequence) and not isinstance(ranges, str):
        if len(ranges) != len(motor_ids):
            raise ValueError(f"{len(ranges)} ranges for {len(motor_ids)} motors")
        return {i: MitRanges.of(r) for i, r in zip(motor_ids, ranges, strict=True)}
    one = MitRanges.of(ranges)
    return dict.fromkeys(motor_ids, one)


def check_motor_ids(motor_ids: Iterable[int], host_id: int, where: str) -> tuple[int, ...]:
    ids = tuple(int(i) for i in motor_ids)
    if not ids or len(set(ids)) != len(ids):
        raise ValueError(f"{where}: expected unique motor IDs, got {list(ids)}")
    bad = [i for i in ids if not 1 <= i <= MAX_MOTOR_ID or i == host_id]
    if bad:
        raise ValueError(f"{where}: motor IDs must be 1..{MAX_MOTOR_ID} and differ from the host ID {host_id}, "
                         f"got {bad}")
    return ids


def worst_case_cycle_s(n_motors: int, bitrate: int) -> float:
    """Bus time of one command and one reply per motor, with worst-case bit stuffing (classic CAN, 11-bit IDs): ~250
    bit times per motor, so at 1 Mbit/s one channel carries at most 3 motors at 1 kHz (configs/robots/bruce_can.yaml
    puts BRUCE's ten leg motors on four channels)."""

    def frame_bits(n_data: int) -> int:
        stuffed = 34 + 8 * n_data  # SOF .. CRC, where stuff bits can be inserted
        return stuffed + (stuffed - 1) // 4 + 13  # + CRC delimiter, ACK, EOF, intermission

    return n_motors * (frame_bits(COMMAND_LENGTH) + frame_bits(6)) / bitrate


class ReplyDecoder:
    """Accepts the replies of one channel's motors and rejects everything else (wrong length, other arbitration ID,
    extended ID, remote or error frame, unknown motor ID; the bus adds a second reply in one tick and one left over
    from an earlier tick), counting why; it never raises."""

    def __init__(self, ranges: Mapping[int, MitRanges], host_id: int = 0, stats: LinkStats | None = None):
        self.ranges = dict(ranges)
        self.host_id = host_id
        self.stats = stats if stats is not None else LinkStats()

    def classify(self, arbitration_id: int, data: bytes, *, is_extended_id: bool = False,
                 is_remote_frame: bool = False, is_error_frame: bool = False) -> MotorReply | str:
        """The decoded reply, or the reason for rejecting the frame. Pure: counts nothing, never raises."""
        if is_error_frame:
            return "error_frame"
        if is_remote_frame:
            return "remote"
        if is_extended_id or arbitration_id != self.host_id:
            return "foreign"
        if len(data) not in REPLY_LENGTHS:
            return "length"
        ranges = self.ranges.get(data[0])
        if ranges is None:
            return "unknown_id"
        return decode_reply(bytes(data), ranges)

    def classify_message(self, msg: Any) -> MotorReply | str:
        return self.classify(msg.arbitration_id, bytes(msg.data), is_extended_id=bool(msg.is_extended_id),
                             is_remote_frame=bool(msg.is_remote_frame), is_error_frame=bool(msg.is_error_frame))

    def decode(self, arbitration_id: int, data: bytes, **flags: bool) -> MotorReply | None:
        """The decoded reply (counted as a packet), or None (counted as a rejection by reason)."""
        result = self.classify(arbitration_id, data, **flags)
        if isinstance(result, str):
            self.stats.reject(result)
            return None
        self.stats.packets += 1
        return result
