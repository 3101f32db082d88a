"""Legs on MIT-mode CAN motors (`buses.can.motors`): the hw backend's `CanLegs` (bruce_hw/can_legs.py), the motor
emulators on python-can (drivers/emulators/can_motor.py, which compute their own MIT torque) as the emulated plant
drives them (`CanEmulation`), and bruce-hw-check's diagnosis (`check_can`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.bus_report import BusReport
from bruce_hw.bus_startup import ids_text
from bruce_hw.can_legs import CanLegs
from bruce_hw.config import RobotConfig
from bruce_hw.leg_bus import LegStartup


class CanKind:
    name = "can"  # as bruce-emulate's fault commands name the bus
    modules = {"drivers.can_motor": "CAN leg motors (buses.can)", "can": "the CAN legs (package python-can)"}
    lockstep = False  # python-can's threads answer on their own: no bus cycle to clock the plant by

    def uses(self, config: RobotConfig) -> bool:
        """The legs are on CAN when buses.can names a motor per joint."""
        return bool(config.buses.can.motors)

    def ports(self, config: RobotConfig) -> list[tuple[str, str]]:
        return []  # channels of an interface, not device files: CanMotorGroup names a missing one at start-up

    def legs(self, config: RobotConfig, startup: LegStartup) -> CanLegs:
        return CanLegs(config, ping_rounds=startup.ping_rounds, ping_retry_s=startup.ping_retry_s)

    def emulate(self, config: RobotConfig, *, can_interface: str = "virtual", **options) -> CanEmulation:
        return CanEmulation(config, can_interface)

    def diagnose(self, config: RobotConfig, rtt_cycles: int = 0) -> BusReport:
        return check_can(config)


@dataclass
class _Slots:
    """One channel's emulator and the joint slots (coupling columns) of its motors."""

    emulator: object
    index: np.ndarray
    map: object  # drivers.can_motor.ActuatorMap: motor <-> actuator side


class CanEmulation:
    """One CAN motor emulator per channel (`device`: {channel: CanMotorEmulator}) as the emulated plant drives them
    and bruce-emulate's commands reach them."""

    bus = CanKind.name
    lock = None  # no lockstep (CanKind.lockstep)

    def __init__(self, config: RobotConfig, interface: str):
        from drivers.emulators.can_motor import emulators_from_config

        self.interface = interface
        self.device = emulators_from_config(config.buses.can, interface=interface)
        try:
            self._slots = _layout(config, self.device)
        except BaseException:
            self.close()
            raise

    # -- the plant
    def clock(self, step) -> None:
        raise ValueError("CAN legs cannot clock the plant (no lockstep)")

    def check_watchdogs(self) -> None:
        """The MIT protocol has no watchdog."""

    def torques(self, m: np.ndarray, md: np.ndarray) -> tuple[np.ndarray, bool, bool]:
        """Actuator torques from what each motor's emulator computes of its last MIT command; engaged: any motor in
        motor mode."""
        tau = np.zeros(len(m))
        engaged = False
        for slot in self._slots:
            tau[slot.index] = slot.map.actuator_torque(slot.emulator.torques())
            engaged |= any(slot.emulator.in_motor_mode(mid) for mid in slot.emulator.motor_ids)
        return tau, engaged, not engaged

    def publish(self, m: np.ndarray, md: np.ndarray, tau_m: np.ndarray) -> None:
        for slot in self._slots:
            slot.emulator.set_state(slot.map.motor_position(m[slot.index]), slot.map.motor_velocity(md[slot.index]))

    # -- bruce-emulate and the tests
    def close(self) -> None:
        for emulator in self.device.values():
            emulator.close()

    def drain_events(self) -> list[tuple[float, str]]:
        out = []
        for emulator in self.device.values():
            drain = getattr(emulator, "drain_events", None)  # those that keep a log
            if drain is not None:
                out += drain()
        return out

    def silence(self, ids, silent: bool) -> None:
        for emulator in self.device.values():
            mine = [i for i in ids if i in emulator.motor_ids]
            if mine:
                (emulator.silence if silent else emulator.resume)(mine)

    def status(self) -> dict:
        return {channel: {"ids": list(emulator.motor_ids),
                          "motor_mode": [emulator.in_motor_mode(i) for i in emulator.motor_ids],
                          "kd": [emulator.command(i).kd for i in emulator.motor_ids]}
                for channel, emulator in self.device.items()}

    def counters(self) -> str:
        return ""

    def devices(self) -> list[tuple[str, str]]:
        return [(f"CAN motors (IDs {', '.join(map(str, emulator.motor_ids))})", f"{self.interface} channel {channel}")
                for channel, emulator in self.device.items()]

    def port_overrides(self) -> list[str]:
        return [f"buses.can.interface={self.interface}"]

    def hint(self, run_here: str) -> str | None:
        """python-can's `virtual` bus reaches only this process: how to run the stack in it."""
        if self.interface != "virtual":
            return None
        return ("the CAN motors are on python-can's `virtual` bus, which only this process reaches: run the stack "
                f"here with\n  {run_here}\n  (in one process the emulated CAN round trip takes about a millisecond: "
                "add --set buses.can.timeout_s=0.005; 1 kHz needs --can-interface socketcan on vcan channels)")


def _layout(config: RobotConfig, emulators: dict) -> list[_Slots]:
    from drivers.can_motor import ActuatorMap

    motors = list(config.buses.can.motors)
    slots = []
    for channel, emulator in emulators.items():
        index = [k for k, motor in enumerate(motors) if motor.channel == channel]
        if [motors[k].id for k in index] != list(emulator.motor_ids):
            raise ValueError(f"CAN emulator on {channel} hosts {emulator.motor_ids}, the config puts "
                             f"{[motors[k].id for k in index]} there")
        mine = [motors[k] for k in index]
        amap = ActuatorMap.of(len(mine), [m.gear for m in mine], [m.sign for m in mine], [m.offset for m in mine])
        slots.append(_Slots(emulator, np.array(index), amap))
    return slots


def check_can(config: RobotConfig) -> BusReport:
    """One zero command to every motor (ignored in rest mode, answered): position, velocity, torque each."""
    from drivers.can_motor import CanMotorGroup
    from drivers.errors import BusTimeout, DriverError

    can = config.buses.can
    ids = [m.id for m in can.motors]
    report = BusReport(f"CAN {can.interface} {', '.join(can.channels)} (motor IDs {ids_text(ids)})")
    try:
        group = CanMotorGroup.from_config(can)
    except (DriverError, ValueError) as exc:
        report.error = str(exc)
        report.missing = ids
        return report
    with group:
        try:
            state = group.read()  # the all-zero command: ignored in rest mode, answered
        except BusTimeout as exc:
            report.missing = list(exc.silent_ids)
            state = group.state
        for k, (slot, motor_id) in enumerate(zip(config.joints, ids, strict=True)):
            if motor_id in report.missing:
                report.lines.append(f"ID {motor_id} ({slot}): MISSING")
            else:
                report.lines.append(f"ID {motor_id} ({slot}): position {state.position[k]:+.3f} rad, velocity "
                                    f"{state.velocity[k]:+.3f} rad/s, torque {state.torque[k]:+.2f} Nm")
    return report
