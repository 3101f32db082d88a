"""CAN actuators in MIT mode (the "mini cheetah" protocol of Ben Katz's motor controller, as spoken by T-Motor /
CubeMars AK-series actuators): pure frame encoders/decoders, and a per-tick bus driver over python-can.

`CanMotorBus` drives the motors of one channel, `CanMotorGroup` several channels as one (it sends on all before
collecting from any). Classic CAN, 11-bit identifiers; each frame's layout is at its encoder. The driver speaks
actuator-output units (the columns of the robot's coupling matrix) and maps them to motor units per motor
(`ActuatorMap`). No BRUCE source covers CAN: where the protocol leaves things open, the choice is noted at the code
that makes it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from drivers.errors import BusTimeout, DriverError, LinkStats

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


class MotorState(NamedTuple):
    """Measured state of a set of motors, in actuator units and motor order; `stamp` is time.monotonic()."""

    position: np.ndarray
    velocity: np.ndarray
    torque: np.ndarray
    stamp: float


@dataclass(frozen=True)
class ActuatorMap:
    """Actuator-output units <-> motor units per motor: p = gear sign (m - offset), t = sign tau / gear."""

    gear: np.ndarray
    sign: np.ndarray
    offset: np.ndarray

    @classmethod
    def of(cls, n: int, gear: Any = 1.0, sign: Any = 1.0, offset: Any = 0.0) -> ActuatorMap:
        gear, sign, offset = (np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)).copy()
                              for x in (gear, sign, offset))
        if np.any(gear <= 0) or not np.all(np.isin(sign, (-1.0, 1.0))) or not np.all(np.isfinite(offset)):
            raise ValueError(f"ActuatorMap: expected gear > 0, sign +-1, finite offset; got {gear}, {sign}, {offset}")
        return cls(gear, sign, offset)

    def motor_position(self, m: Any) -> np.ndarray:
        return self.gear * self.sign * (np.asarray(m, dtype=np.float64) - self.offset)

    def motor_velocity(self, md: Any) -> np.ndarray:
        return self.gear * self.sign * np.asarray(md, dtype=np.float64)

    def motor_torque(self, tau: Any) -> np.ndarray:
        return self.sign * np.asarray(tau, dtype=np.float64) / self.gear

    def motor_gain(self, k: Any) -> np.ndarray:
        return np.asarray(k, dtype=np.float64) / self.gear**2

    def actuator_position(self, p: Any) -> np.ndarray:
        return self.sign * np.asarray(p, dtype=np.float64) / self.gear + self.offset

    def actuator_velocity(self, v: Any) -> np.ndarray:
        return self.sign * np.asarray(v, dtype=np.float64) / self.gear

    def actuator_torque(self, t: Any) -> np.ndarray:
        return self.sign * self.gear * np.asarray(t, dtype=np.float64)


class CanMotorBus:
    """The MIT-mode motors on one CAN channel. Every call is bounded in time; silence raises `BusTimeout`.

    Per tick: `exchange(position, velocity, kp, kd, torque)` (actuator units, arrays in `motor_ids` order or
    scalars) sends every command frame, then collects the replies until all motors answered or `timeout_s` ran out,
    and returns a `MotorState`. `send_commands` + `collect` are the two halves, for sending on several channels
    before collecting (`CanMotorGroup`). `bus` may be an already open python-can bus (it is then not owned).
    No retry inside a tick: a silent motor costs the tick (`BusTimeout` naming it), since the next tick is 1 ms later
    and a re-sent command would be stale; the start-up frames (enter/exit motor mode, set zero) are retried.
    """

    def __init__(self, channel: str, motor_ids: Sequence[int], ranges: Any = AK80_9_V1P1, *,
                 interface: str = "socketcan", bitrate: int | None = None, host_id: int = 0,
                 timeout_s: float = 0.001, gear: Any = 1.0, sign: Any = 1.0, offset: Any = 0.0,
                 bus: Any = None, **bus_kwargs: Any):
        self.channel = str(channel)
        self.motor_ids = check_motor_ids(motor_ids, host_id, self.channel)
        if not timeout_s > 0:
            raise ValueError(f"{self.channel}: timeout_s must be > 0, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self.ranges = ranges_by_id(self.motor_ids, ranges)
        self.actuators = ActuatorMap.of(len(self.motor_ids), gear, sign, offset)
        self.stats = LinkStats()
        self.decoder = ReplyDecoder(self.ranges, host_id, self.stats)
        self.host_id = host_id
        self._index = {mid: k for k, mid in enumerate(self.motor_ids)}
        n = len(self.motor_ids)
        self._motor_p, self._motor_v, self._motor_t = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        self.reply_time = np.full(n, -np.inf)  # time.monotonic() of each motor's last accepted reply
        self._pending: set[int] = set()
        self._send_failed: dict[int, str] = {}
        self._deadline = 0.0
        self._owns_bus = bus is None
        self._bus = bus if bus is not None else self._open(interface, bitrate, bus_kwargs)

    def _open(self, interface: str, bitrate: int | None, bus_kwargs: dict) -> Any:
        try:
            import can
        except ImportError as exc:
            raise DriverError(f"{self.channel}: python-can is not installed ({exc})") from exc
        if bitrate is not None:
            bus_kwargs = {**bus_kwargs, "bitrate": bitrate}
        try:
            return can.Bus(interface=interface, channel=self.channel, **bus_kwargs)
        except (can.CanError, OSError, ValueError, NotImplementedError) as exc:
            raise DriverError(f"{self.channel}: cannot open CAN interface {interface!r}: {exc}") from exc

    # -- per tick ----------------------------------------------------------------------------------------------
    def exchange(self, position: Any, velocity: Any, kp: Any, kd: Any, torque: Any) -> MotorState:
        self.send_commands(position, velocity, kp, kd, torque)
        return self.collect()

    def read(self) -> MotorState:
        """The state, sending the all-zero command: ignored in rest mode, zero torque in motor mode."""
        return self.exchange(0.0, 0.0, 0.0, 0.0, 0.0)

    def damp(self, kd: Any) -> MotorState:
        """Damping only: tau = -kd v, computed by the motors themselves."""
        return self.exchange(0.0, 0.0, 0.0, kd, 0.0)

    def send_commands(self, position: Any, velocity: Any, kp: Any, kd: Any, torque: Any,
                      deadline: float | None = None) -> None:
        """Encode and send one command per motor; replies are collected by `collect` until `deadline`."""
        fields = [self._vector(name, x) for name, x in
                  (("position", position), ("velocity", velocity), ("kp", kp), ("kd", kd), ("torque", torque))]
        a = self.actuators
        motor = np.stack([a.motor_position(fields[0]), a.motor_velocity(fields[1]), a.motor_gain(fields[2]),
                          a.motor_gain(fields[3]), a.motor_torque(fields[4])], axis=1)
        frames = [(mid, encode_command(row, self.ranges[mid])) for mid, row in zip(self.motor_ids, motor, strict=True)]
        self._start(frames, deadline)

    def collect(self, deadline: float | None = None) -> MotorState:
        """Replies to the frames just sent, until every motor answered or the deadline passed."""
        deadline = self._deadline if deadline is None else deadline
        # Past the deadline, frames already queued are still read (another channel's collection may have used up
        # the shared deadline while these arrived), but only so many: a flooding bus must not hold the tick.
        late_budget = 16 * len(self.motor_ids) + 16
        while self._pending:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                late_budget -= 1
                if late_budget < 0:
                    break
            msg = self._recv(max(remaining, 0.0))
            if msg is None:
                if remaining <= 0:
                    break
                continue
            result = self.decoder.classify_message(msg)
            if isinstance(result, str):
                self.stats.reject(result)
            elif result.motor_id not in self._pending:
                self.stats.reject("duplicate")
            else:
                self.stats.packets += 1
                self._store(result)
        silent = [mid for mid in self.motor_ids if mid in self._pending or mid in self._send_failed]
        send_failed, self._send_failed = self._send_failed, {}
        self._pending.clear()
        if silent:
            self.stats.timeouts += 1
            failed = "; ".join(f"send to ID {mid} failed: {why}" for mid, why in send_failed.items())
            raise BusTimeout(self.channel, silent, failed or f"within {self.timeout_s * 1e3:.3g} ms")
        return self.state

    @property
    def state(self) -> MotorState:
        """The last accepted reply of every motor (NaN before the first), in actuator units."""
        a = self.actuators
        stamp = float(np.max(self.reply_time)) if np.isfinite(self.reply_time).any() else float("nan")
        return MotorState(a.actuator_position(self._motor_p), a.actuator_velocity(self._motor_v),
                          a.actuator_torque(self._motor_t), stamp)

    # -- start-up ----------------------------------------------------------------------------------------------
    def enter_motor_mode(self, attempts: int = 3) -> MotorState:
        return self._special(ENTER_MOTOR_MODE, attempts)

    def exit_motor_mode(self, attempts: int = 3) -> MotorState:
        return self._special(EXIT_MOTOR_MODE, attempts)

    def set_zero(self, attempts: int = 3) -> MotorState:
        """Make every motor's present position its zero (the firmware stores it)."""
        return self._special(SET_ZERO, attempts)

    def _special(self, frame: bytes, attempts: int) -> MotorState:
        ids = list(self.motor_ids)
        last = BusTimeout(self.channel, ids)
        for attempt in range(max(1, attempts)):
            if attempt:
                self.stats.retries += 1
            self._start([(mid, frame) for mid in ids], None)
            try:
                return self.collect()
            except BusTimeout as exc:
                ids = [mid for mid in ids if mid in exc.silent_ids]
                last = exc
        raise BusTimeout(self.channel, last.silent_ids, f"{special_kind(frame)} after {max(1, attempts)} attempts")

    # -- internals ---------------------------------------------------------------------------------------------
    def _vector(self, name: str, value: Any) -> np.ndarray:
        try:
            v = np.broadcast_to(np.asarray(value, dtype=np.float64), (len(self.motor_ids),))
        except ValueError as exc:
            raise ValueError(f"{self.channel}: {name}: expected {len(self.motor_ids)} values ({exc})") from exc
        if not np.all(np.isfinite(v)):
            bad = [mid for mid, x in zip(self.motor_ids, v, strict=True) if not math.isfinite(x)]
            raise ValueError(f"{self.channel}: non-finite {name} command for ID(s) {bad}")
        return v

    def _start(self, frames: list[tuple[int, bytes]], deadline: float | None) -> None:
        import can

        self._drain()
        self._deadline = time.monotonic() + self.timeout_s if deadline is None else deadline
        self._send_failed = {}
        self._pending = set()
        for mid, data in frames:
            msg = can.Message(arbitration_id=mid, data=data, is_extended_id=False)
            try:
                self._bus.send(msg, timeout=max(self._deadline - time.monotonic(), 1e-4))
            except (can.CanError, OSError) as exc:
                self._send_failed[mid] = str(exc) or type(exc).__name__
            else:
                self._pending.add(mid)

    def _drain(self) -> None:
        """Discard what arrived since the last tick (late replies, other traffic), counting it; bounded."""
        for _ in range(16 * len(self.motor_ids) + 16):
            msg = self._recv(0.0)
            if msg is None:
                return
            result = self.decoder.classify_message(msg)
            self.stats.reject(result if isinstance(result, str) else "stale")

    def _recv(self, timeout: float) -> Any:
        import can

        try:
            return self._bus.recv(timeout=timeout)
        except (can.CanError, OSError):
            self.stats.reject("receive_error")
            if timeout > 0:
                time.sleep(min(timeout, 1e-4))  # an erroring interface must not spin the deadline loop
            return None

    def _store(self, reply: MotorReply) -> None:
        k = self._index[reply.motor_id]
        self._motor_p[k], self._motor_v[k], self._motor_t[k] = reply.position, reply.velocity, reply.torque
        self.reply_time[k] = time.monotonic()
        self._pending.discard(reply.motor_id)

    def close(self) -> None:
        if self._owns_bus and self._bus is not None:
            self._bus.shutdown()
        self._bus = None

    def __enter__(self) -> CanMotorBus:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class CanMotorGroup:
    """Several `CanMotorBus` (one per channel) driven as one: arrays in `motor_ids` order (e.g. the coupling's
    actuator columns). A tick sends on every channel before collecting from any, so the channels run in parallel.
    """

    def __init__(self, buses: Sequence[CanMotorBus], motor_ids: Sequence[int] | None = None):
        self.buses = tuple(buses)
        all_ids = [mid for bus in self.buses for mid in bus.motor_ids]
        if len(set(all_ids)) != len(all_ids):
            raise ValueError(f"motor IDs must be unique across channels, got {all_ids}")
        self.motor_ids = tuple(all_ids if motor_ids is None else motor_ids)
        if sorted(self.motor_ids) != sorted(all_ids):
            raise ValueError(f"motor_ids {list(self.motor_ids)} do not match the buses' motors {all_ids}")
        # _slots[b][k]: the group index of bus b's k-th motor
        self._slots = [np.array([self.motor_ids.index(mid) for mid in bus.motor_ids]) for bus in self.buses]

    @classmethod
    def from_config(cls, can_config: Any, *, interface: str | None = None, timeout_s: float | None = None,
                    **bus_kwargs: Any) -> CanMotorGroup:
        """From `RobotConfig.buses.can` (one bus per channel, motors in the config's joint-slot order)."""
        motors = list(can_config.motors)
        if not motors:
            raise ValueError("buses.can describes no motors")
        channels = list(dict.fromkeys(m.channel for m in motors))
        buses: list[CanMotorBus] = []
        try:
            for channel in channels:
                mine = [m for m in motors if m.channel == channel]
                buses.append(CanMotorBus(
                    channel, [m.id for m in mine], [MitRanges.of(m.ranges) for m in mine],
                    interface=interface or can_config.interface, bitrate=can_config.bitrate,
                    host_id=can_config.host_id,
                    timeout_s=timeout_s or can_config.timeout_s or 0.001,
                    gear=[m.gear for m in mine], sign=[m.sign for m in mine], offset=[m.offset for m in mine],
                    **bus_kwargs))
        except Exception:
            for bus in buses:
                bus.close()
            raise
        return cls(buses, [m.id for m in motors])

    @property
    def stats(self) -> dict[str, LinkStats]:
        return {bus.channel: bus.stats for bus in self.buses}

    def exchange(self, position: Any, velocity: Any, kp: Any, kd: Any, torque: Any) -> MotorState:
        n = len(self.motor_ids)
        fields = [np.broadcast_to(np.asarray(x, dtype=np.float64), (n,)) for x in (position, velocity, kp, kd, torque)]
        bad = sorted({self.motor_ids[i] for f in fields for i in np.flatnonzero(~np.isfinite(f))})
        if bad:
            raise ValueError(f"{', '.join(b.channel for b in self.buses)}: non-finite command for ID(s) {bad}")
        deadline = time.monotonic() + max(bus.timeout_s for bus in self.buses)
        for bus, slots in zip(self.buses, self._slots, strict=True):
            bus.send_commands(*(f[slots] for f in fields), deadline=deadline)
        return self._collect_all(lambda bus: bus.collect(deadline))

    def read(self) -> MotorState:
        return self.exchange(0.0, 0.0, 0.0, 0.0, 0.0)

    def damp(self, kd: Any) -> MotorState:
        return self.exchange(0.0, 0.0, 0.0, kd, 0.0)

    def enter_motor_mode(self, attempts: int = 3) -> MotorState:
        return self._collect_all(lambda bus: bus.enter_motor_mode(attempts))

    def exit_motor_mode(self, attempts: int = 3) -> MotorState:
        return self._collect_all(lambda bus: bus.exit_motor_mode(attempts))

    def set_zero(self, attempts: int = 3) -> MotorState:
        return self._collect_all(lambda bus: bus.set_zero(attempts))

    @property
    def state(self) -> MotorState:
        return self._merge([bus.state for bus in self.buses])

    def _collect_all(self, call: Any) -> MotorState:
        states, timeouts = [], []
        for bus in self.buses:
            try:
                states.append(call(bus))
            except BusTimeout as exc:
                timeouts.append(exc)
                states.append(bus.state)
        if timeouts:
            silent = [mid for mid in self.motor_ids if any(mid in exc.silent_ids for exc in timeouts)]
            raise BusTimeout(", ".join(exc.bus for exc in timeouts), silent,
                             "; ".join(str(exc) for exc in timeouts))
        return self._merge(states)

    def _merge(self, states: list[MotorState]) -> MotorState:
        n = len(self.motor_ids)
        out = [np.full(n, np.nan) for _ in range(3)]
        for state, slots in zip(states, self._slots, strict=True):
            for k in range(3):
                out[k][slots] = state[k]
        stamps = [s.stamp for s in states if math.isfinite(s.stamp)]
        return MotorState(*out, max(stamps) if stamps else float("nan"))

    def close(self) -> None:
        for bus in self.buses:
            bus.close()

    def __enter__(self) -> CanMotorGroup:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
