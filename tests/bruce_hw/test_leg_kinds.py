"""A leg bus kind added the way docs/extending.md ("Adding a leg actuator") says: this one file and its registration
(`register_leg_kind`). Its actuators are ideal torque motors reached inside this process (no driver, no wire),
chosen by a buses.bear.port of `inproc:NAME` (a test cannot add a section to the YAML). The hw backend builds its
legs (`make_hw_backend`), the emulated plant steps in lockstep with its bus cycles and takes the actuator torques from
its law, bruce-hw-check reports its diagnosis; BEAR and CAN configs still get their own kinds."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from support.emulated_robot import drive_torques

from bruce_hw.bus_report import BusReport
from bruce_hw.bus_startup import StartupError
from bruce_hw.config import RobotConfig, load_config
from bruce_hw.leg_bus import LegReading, LegStartup, silence
from bruce_hw.leg_kinds import LEG_KINDS, leg_kind_of, register_leg_kind

PORT = "inproc:legs"
WIRES: dict[str, IdealMotors] = {}  # port -> the motors there: this kind's wire


# -- the emulator (drivers/emulators/ for a real actuator) ------------------------------------------------------
class IdealMotors:
    """Motors that apply what they are told: the commanded torque while on, -kd md while damping, none while off."""

    def __init__(self, port: str, n: int):
        self.port, self.lock, self.on_cycle = port, threading.RLock(), None
        self.state, self.commanded, self.cycles = "off", np.zeros(n), 0
        self.m, self.md, self.tau = np.zeros(n), np.zeros(n), np.zeros(n)
        WIRES[port] = self

    def set_state(self, state: str) -> None:
        with self.lock:
            self.state = state

    def exchange(self, torque: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One bus cycle: the command in, the measured values out; then the plant steps (lockstep)."""
        with self.lock:
            if torque is not None:
                self.commanded = np.array(torque, dtype=float)
            reply = (self.m.copy(), self.md.copy(), self.tau.copy())
            self.cycles += 1
            if self.on_cycle is not None:
                self.on_cycle()
            return reply


# -- the LegBus (bruce_hw/<kind>_legs.py for a real actuator) --------------------------------------------------
class IdealLegs:
    kind = "ideal torque bus"

    def __init__(self, config: RobotConfig):
        self.config, self.port, self.ids = config, config.buses.bear.port, tuple(config.buses.bear.ids)
        self.name = f"{self.kind} {self.port}"
        self.temperature, self.monitor_count = np.full(len(self.ids), np.nan), 0
        self.wire: IdealMotors | None = None
        self.cycles = 0

    def open(self) -> None:
        self.wire = WIRES.get(self.port)
        if self.wire is None:
            raise StartupError([f"{self.name}: nothing on the wire"])

    def configure(self) -> None:
        self.wire.set_state("off")

    def enable(self) -> None:
        self.wire.exchange(np.zeros(len(self.ids)))  # no stale command acts on enable
        self.wire.set_state("on")

    def disable(self) -> None:
        self.wire.set_state("off")

    def damp(self) -> None:
        if self.wire is not None:
            self.wire.set_state("damping")

    def clear_watchdog(self) -> None:
        """No watchdog."""

    def close(self) -> None:
        self.wire = None

    def cycle(self, torque, damping: bool = False, retry: bool = False) -> LegReading:
        m, md, tau = self.wire.exchange(torque)
        self.cycles += 1
        stamp = time.monotonic()
        return LegReading(m, md, tau, stamp, np.full(len(self.ids), stamp))

    def silence(self, reading: LegReading, now: float, stalled=None) -> str | None:
        return silence(self.ids, reading, now, self.config.dt, self.config.safety.max_sensor_age_s, stalled)

    def link_report(self) -> dict:
        return {"bus": self.name, "cycles": self.cycles}

    def summary(self) -> str:
        return f"{self.name}: {self.cycles} cycles"


# -- the kind (bruce_hw/legs/<kind>.py) ------------------------------------------------------------------------
class IdealEmulation:
    bus = "ideal"

    def __init__(self, config: RobotConfig):
        self.device = IdealMotors(config.buses.bear.port, config.n_joints)
        self.lock = self.device.lock
        self.kd = config.safety.damping_kd

    def clock(self, step) -> None:
        self.device.on_cycle = step

    def check_watchdogs(self) -> None:
        """No watchdog."""

    def torques(self, m, md):
        state = self.device.state
        if state == "on":
            return self.device.commanded.copy(), True, False
        if state == "damping":
            return -self.kd * md, False, False
        return np.zeros(len(m)), False, True

    def publish(self, m, md, tau_m) -> None:
        self.device.m, self.device.md, self.device.tau = m, md, tau_m

    def close(self) -> None:
        WIRES.pop(self.device.port, None)

    def drain_events(self) -> list:
        return []

    def silence(self, ids, silent: bool) -> None:
        raise ValueError("ideal motors never fall silent")

    def status(self) -> dict:
        return {"state": self.device.state, "cycles": self.device.cycles}

    def counters(self) -> str:
        return f"ideal motors: {self.device.cycles} cycles"

    def devices(self) -> list[tuple[str, str]]:
        return [("ideal torque motors", self.device.port)]

    def port_overrides(self) -> list[str]:
        return [f"buses.bear.port={self.device.port}"]

    def hint(self, run_here: str) -> str | None:
        return f"the ideal motors are reached in this process only: {run_here}"


class IdealKind:
    name = "ideal"
    modules: dict[str, str] = {}
    lockstep = True

    def uses(self, config: RobotConfig) -> bool:
        return config.buses.bear.port.startswith("inproc:")

    def ports(self, config: RobotConfig) -> list[tuple[str, str]]:
        return []  # no device file

    def legs(self, config: RobotConfig, startup: LegStartup) -> IdealLegs:
        return IdealLegs(config)

    def emulate(self, config: RobotConfig, **options) -> IdealEmulation:
        return IdealEmulation(config)

    def diagnose(self, config: RobotConfig, rtt_cycles: int = 0) -> BusReport:
        wire = WIRES.get(config.buses.bear.port)
        report = BusReport(f"ideal torque bus {config.buses.bear.port}")
        if wire is None:
            report.error, report.missing = "nothing on the wire", list(config.buses.bear.ids)
        else:
            report.lines.append(f"{len(wire.commanded)} motors, {wire.state}")
        return report


@pytest.fixture
def ideal_kind():
    kind = register_leg_kind(IdealKind())
    yield kind
    del LEG_KINDS[kind.name]


def test_the_newest_kind_that_uses_a_config_is_its_kind(ideal_kind):
    assert leg_kind_of(load_config(overrides=[f"buses.bear.port={PORT}"])) is ideal_kind
    assert leg_kind_of(load_config()).name == "bear"
    assert leg_kind_of(load_config("configs/robots/bruce_can.yaml")).name == "can"
    with pytest.raises(ValueError, match="registered already"):
        register_leg_kind(IdealKind())


@pytest.mark.slow
def test_a_registered_kind_is_built_driven_and_diagnosed(ideal_kind):
    from bruce_hw.emulation.robot import EmulatedRobot
    from bruce_hw.hw import make_hw_backend, missing_for_hw
    from bruce_hw.hw_check import check

    base = load_config(overrides=[f"buses.bear.port={PORT}"])
    with EmulatedRobot(base, lockstep=True) as robot:
        assert robot.legs.bus == "ideal" and robot.bear is None and robot.can == {}
        # In-process, the emulators share the GIL with the host: slack on the IMU's age.
        config = load_config(overrides=[*robot.port_overrides(), "safety.max_sensor_age_s=0.05"])
        assert missing_for_hw(config) == []  # the kind names no device file; the others' are the emulators'
        wire = WIRES[PORT]
        backend = make_hw_backend(config, check_imu=False, switch_interval_s=None)
        assert isinstance(backend.legs, IdealLegs)
        backend.configure()
        try:
            tau, state = drive_torques(backend)
            assert np.all(np.isfinite(state.joints.q))
            np.testing.assert_allclose(wire.commanded, config.coupling.actuator_torques(tau), atol=1e-9)
            assert not robot.plant.held  # enabled by the kind's law: the physics runs
            backend.fault("test")
            assert wire.state == "damping"
            damping, _, _ = robot.legs.torques(np.zeros(config.n_joints), np.ones(config.n_joints))
            np.testing.assert_allclose(damping, -config.safety.damping_kd)
        finally:
            backend.shutdown()
        assert robot.plant.steps == wire.cycles > 20  # lockstep: the plant stepped once per bus cycle, no more
        legs, *others = check(config)
        assert legs.name == f"ideal torque bus {PORT}" and legs.ok, legs.text()
        assert [r.name.split()[0] for r in others] == ["Dynamixel", "sense"]
