"""MIT-mode CAN motors (mini cheetah protocol, see drivers/can_motor_codec.py) on a python-can bus.

`CanMotorEmulator(channel, motor_ids)` hosts motors that behave like the reference firmware: each listens to
standard frames whose arbitration ID is its motor ID (others are ignored, as on a shared bus) and answers every one
with a 6-byte reply on the host's arbitration ID. Physics adapter (thread-safe, motor units): `set_measured` /
`set_state` in, `commanded_torque` / `torques` out. Faults for tests: `silence(ids)`, `inject_garbage(ids, kind)`,
`send_raw`. Use `interface="virtual"` inside one process; across processes socketcan's `vcan` or python-can's
`udp_multicast` interface.
"""

from __future__ import annotations

import random
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.can_motor_codec import (
    AK80_9_V1P1,
    COMMAND_LENGTH,
    MitCommand,
    MitRanges,
    check_motor_ids,
    decode_command,
    encode_reply,
    ranges_by_id,
    special_kind,
)
from drivers.errors import DriverError, LinkStats

ZERO_COMMAND = MitCommand(0.0, 0.0, 0.0, 0.0, 0.0)
GARBAGE_KINDS = ("length", "motor_id", "arbitration", "extended", "error_frame", "random")


@dataclass
class _Motor:
    ranges: MitRanges
    motor_mode: bool = False
    command: MitCommand = ZERO_COMMAND
    zero: float = 0.0
    position: float = 0.0  # measured, motor units, before `zero`
    velocity: float = 0.0
    torque: float | None = None  # measured torque to report; None: report the commanded torque
    silent: bool = False
    garbage: list[tuple[str, bool]] = field(default_factory=list)  # pending (kind, replace) per reply

    def commanded_torque(self) -> float:
        """clamp(kp (p_des - p) + kd (v_des - v) + t_ff, t_min, t_max) from the last command and the latest measured
        state, p measured from the zero set by SET_ZERO (also what the motor reports); 0 outside motor mode."""
        if not self.motor_mode:
            return 0.0
        p_des, v_des, kp, kd, t_ff = self.command
        tau = kp * (p_des - (self.position - self.zero)) + kd * (v_des - self.velocity) + t_ff
        return min(max(tau, self.ranges.t[0]), self.ranges.t[1])


class CanMotorEmulator:
    def __init__(self, channel: str, motor_ids: Sequence[int], ranges: Any = AK80_9_V1P1, *,
                 interface: str = "virtual", host_id: int = 0, bus: Any = None, seed: int = 0, **bus_kwargs: Any):
        self.channel = str(channel)
        self.motor_ids = check_motor_ids(motor_ids, host_id, f"emulator {self.channel}")
        self.host_id = host_id
        self._motors = {mid: _Motor(r) for mid, r in ranges_by_id(self.motor_ids, ranges).items()}
        self.stats = LinkStats()  # frames addressed to hosted motors: handled, or rejected by reason
        self.frames_seen = 0  # every frame the emulator received, addressed to it or not
        self._lock = threading.Lock()
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._owns_bus = bus is None
        if bus is None:
            try:
                import can

                bus = can.Bus(interface=interface, channel=self.channel, **bus_kwargs)
            except Exception as exc:  # python-can raises several types for a missing or bad interface
                raise DriverError(f"{self.channel}: cannot open CAN interface {interface!r}: {exc}") from exc
        self._bus = bus
        self._thread = threading.Thread(target=self._serve, name=f"can-motors-{self.channel}", daemon=True)

    # -- lifecycle ---------------------------------------------------------------------------------------------
    def start(self) -> CanMotorEmulator:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        if self._owns_bus and self._bus is not None:
            self._bus.shutdown()
        self._bus = None

    def __enter__(self) -> CanMotorEmulator:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- physics adapter ---------------------------------------------------------------------------------------
    def set_measured(self, motor_id: int, position: float, velocity: float, torque: float | None = None) -> None:
        """Motor units: the output shaft, before the zero offset; `torque` None reports the commanded torque."""
        with self._lock:
            m = self._motors[motor_id]
            m.position, m.velocity, m.torque = float(position), float(velocity), torque

    def set_state(self, positions: Any, velocities: Any) -> None:
        """Measured positions and velocities of every motor, arrays in `motor_ids` order."""
        n = len(self.motor_ids)
        p = np.broadcast_to(np.asarray(positions, dtype=np.float64), (n,))
        v = np.broadcast_to(np.asarray(velocities, dtype=np.float64), (n,))
        with self._lock:
            for k, mid in enumerate(self.motor_ids):
                m = self._motors[mid]
                m.position, m.velocity = float(p[k]), float(v[k])

    def commanded_torque(self, motor_id: int) -> float:
        with self._lock:
            return self._motors[motor_id].commanded_torque()

    def torques(self) -> np.ndarray:
        """Commanded torque of every motor, in `motor_ids` order."""
        with self._lock:
            return np.array([self._motors[mid].commanded_torque() for mid in self.motor_ids])

    def in_motor_mode(self, motor_id: int) -> bool:
        with self._lock:
            return self._motors[motor_id].motor_mode

    def command(self, motor_id: int) -> MitCommand:
        """The last command taken (decoded from the wire, so quantised)."""
        with self._lock:
            return self._motors[motor_id].command

    def zero_offset(self, motor_id: int) -> float:
        with self._lock:
            return self._motors[motor_id].zero

    # -- faults ------------------------------------------------------------------------------------------------
    def silence(self, ids: Iterable[int] | None = None) -> None:
        """Stop answering (all motors when `ids` is None); commands are still taken."""
        self._set_silent(ids, True)

    def resume(self, ids: Iterable[int] | None = None) -> None:
        self._set_silent(ids, False)

    def _set_silent(self, ids: Iterable[int] | None, silent: bool) -> None:
        with self._lock:
            for mid in self.motor_ids if ids is None else ids:
                self._motors[mid].silent = silent

    def inject_garbage(self, ids: Iterable[int], kind: str = "length", count: int = 1, replace: bool = False) -> None:
        """The next `count` replies of each motor in `ids` go out corrupted (`replace`) or preceded by garbage.

        Kinds: "length" (truncated to 4 bytes), "motor_id" (an ID byte no motor here has), "arbitration"
        (sent on a foreign arbitration ID), "extended" (29-bit ID), "error_frame", "random" (random length and
        bytes on the host ID).
        """
        if kind not in GARBAGE_KINDS:
            raise ValueError(f"garbage kind {kind!r}: expected one of {GARBAGE_KINDS}")
        with self._lock:
            for mid in ids:
                self._motors[mid].garbage.extend([(kind, replace)] * count)

    def send_raw(self, arbitration_id: int, data: bytes, *, is_extended_id: bool = False,
                 is_error_frame: bool = False, is_remote_frame: bool = False) -> None:
        import can

        self._send(can.Message(arbitration_id=arbitration_id, data=bytes(data), is_extended_id=is_extended_id,
                               is_error_frame=is_error_frame, is_remote_frame=is_remote_frame))

    # -- the motors --------------------------------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(timeout=0.05)
            except Exception:  # a closed or failing interface: stop quietly when asked, else keep listening
                if self._stop.wait(0.01):
                    return
                continue
            if msg is not None:
                self._handle(msg)

    def _handle(self, msg: Any) -> None:
        self.frames_seen += 1
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        replies: list[Any] = []
        with self._lock:
            motor = self._motors.get(msg.arbitration_id)
            if motor is None:
                return  # another node's frame
            data = bytes(msg.data)
            kind = special_kind(data)
            # Entering or leaving motor mode clears the command: a stale command never acts. Commands are taken only
            # in motor mode.
            if kind == "enter_motor_mode":
                motor.motor_mode, motor.command = True, ZERO_COMMAND
            elif kind == "exit_motor_mode":
                motor.motor_mode, motor.command = False, ZERO_COMMAND
            elif kind == "set_zero":
                motor.zero = motor.position
            elif len(data) == COMMAND_LENGTH:
                if motor.motor_mode:
                    motor.command = decode_command(data, motor.ranges)
            else:
                self.stats.reject("length")
                return
            self.stats.packets += 1
            if not motor.silent:
                replies = self._replies(msg.arbitration_id, motor)
        for reply in replies:
            self._send(reply)

    def _replies(self, motor_id: int, motor: _Motor) -> list[Any]:
        import can

        torque = motor.commanded_torque() if motor.torque is None else motor.torque
        data = encode_reply(motor_id, motor.position - motor.zero, motor.velocity, torque, motor.ranges)
        good = can.Message(arbitration_id=self.host_id, data=data, is_extended_id=False)
        if not motor.garbage:
            return [good]
        kind, replace = motor.garbage.pop(0)
        bad = self._garbage(kind, data)
        return [bad] if replace else [bad, good]

    def _garbage(self, kind: str, data: bytes) -> Any:
        import can

        if kind == "length":
            return can.Message(arbitration_id=self.host_id, data=data[:4], is_extended_id=False)
        if kind == "motor_id":
            unused = next(i for i in range(255, 0, -1) if i not in self._motors and i != self.host_id)
            return can.Message(arbitration_id=self.host_id, data=bytes([unused]) + data[1:], is_extended_id=False)
        if kind == "arbitration":
            return can.Message(arbitration_id=(self.host_id + 0x400) & 0x7FF, data=data, is_extended_id=False)
        if kind == "extended":
            return can.Message(arbitration_id=self.host_id | 0x10000, data=data, is_extended_id=True)
        if kind == "error_frame":
            return can.Message(arbitration_id=self.host_id, data=b"", is_error_frame=True, is_extended_id=False)
        length = self._rng.choice([0, 1, 2, 3, 4, 5, 7])  # never a valid reply length
        return can.Message(arbitration_id=self.host_id, data=bytes(self._rng.randrange(256) for _ in range(length)),
                           is_extended_id=False)

    def _send(self, msg: Any) -> None:
        bus = self._bus
        if bus is None or self._stop.is_set():
            return
        try:
            bus.send(msg, timeout=0.01)
        except Exception:  # a full or closed bus drops the reply, as a real motor's would be lost
            self.stats.reject("send_failed")


def emulators_from_config(can_config: Any, *, interface: str = "virtual", **bus_kwargs: Any) -> dict[str, Any]:
    """One started `CanMotorEmulator` per channel of `RobotConfig.buses.can`, hosting that channel's motors."""
    motors = list(can_config.motors)
    emulators: dict[str, CanMotorEmulator] = {}
    try:
        for channel in dict.fromkeys(m.channel for m in motors):
            mine = [m for m in motors if m.channel == channel]
            ranges: Mapping[int, MitRanges] = {m.id: MitRanges.of(m.ranges) for m in mine}
            emulators[channel] = CanMotorEmulator(channel, [m.id for m in mine], ranges, interface=interface,
                                                  host_id=can_config.host_id, **bus_kwargs).start()
    except Exception:
        for emulator in emulators.values():
            emulator.close()
        raise
    return emulators
