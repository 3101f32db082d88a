"""CAN actuators in MIT mode: a per-tick bus driver over python-can. The frame codec (the frame layouts, their
encoders and decoders, and the reply parser) is in `drivers.can_motor_codec`.

`CanMotorBus` drives the motors of one channel, `CanMotorGroup` several channels as one (it sends on all before
collecting from any). The driver speaks actuator-output units (the columns of the robot's coupling matrix) and maps
them to motor units per motor (`ActuatorMap`). No BRUCE source covers CAN: where the protocol leaves things open, the
choice is noted at the code that makes it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from drivers.can_motor_codec import (
    AK80_9_V1P1,
    ENTER_MOTOR_MODE,
    EXIT_MOTOR_MODE,
    SET_ZERO,
    MitRanges,
    MotorReply,
    ReplyDecoder,
    check_motor_ids,
    encode_command,
    ranges_by_id,
    special_kind,
)
from drivers.errors import BusTimeout, DriverError, LinkStats


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
