"""The `hw` backend: BRUCE's real buses, composed from the drivers in `drivers/` by the robot config.

Legs: the leg bus of the kind the config uses (`bruce_hw.leg_kinds`): ten Koala BEARs on RS-485 (`buses.bear`,
`bruce_hw.bear_legs`), or MIT-mode CAN motors when `buses.can.motors` is set (`bruce_hw.can_legs`); arms: six
Dynamixels held at `arms.hold_pose` (`bruce_hw.arm_holder`); IMU and foot contacts: the sense board
(`buses.sense`). Joint <-> actuator through `coupling` (q = B m, qd = B md, tau_q = B^-T tau_m, tau_m = B^T tau_q).
`make_hw_backend(config)` refuses to start with one line per missing module or device. While active, the legs' bulk
cycles run on a thread of their own (`bruce_hw.bus_thread`), as do the sense board's reader and the arms (50 Hz), so
the 1 kHz tick never waits for a bus (docs/timing.md). What ends in damping, the motors' own watchdogs and shutdown:
docs/safety.md.
"""

from __future__ import annotations

import atexit
import importlib.util
import logging
import os
import re
import sys
import time

import numpy as np

from bruce_hw.arm_holder import ArmHolder
from bruce_hw.attitude import MahonyAttitude
from bruce_hw.backend import Backend, BackendError, LifecycleState
from bruce_hw.bus_startup import StartupError, ids_text
from bruce_hw.bus_thread import BusThread
from bruce_hw.config import RobotConfig
from bruce_hw.host_witness import HostWitness, stalled_union
from bruce_hw.leg_bus import LegBus, LegReading, LegStartup
from bruce_hw.leg_kinds import leg_kind_of
from bruce_hw.types import FootContacts, ImuSample, JointCommand, JointState, RobotState
from drivers.sense_codec import FIRMWARE_GRAVITY

log = logging.getLogger("bruce_hw.hw")

# driver or package -> what it is needed for, beside the leg kind's own (LegKind.modules)
REQUIRED_MODULES = {
    "drivers.dynamixel": "Dynamixel arm servos (buses.dynamixel)",
    "drivers.sense": "sense board IMU and foot contacts (buses.sense)",
    "serial": "the serial buses (package pyserial)",
    "dynamixel_sdk": "the arm bus (package dynamixel-sdk)",
}
# The I/O threads (sense reader, arms, the emulators in a test) must get the GIL within a fraction of
# safety.max_sensor_age_s; CPython's default switch interval (5 ms) lets a busy thread hold them off that long.
GIL_SWITCH_INTERVAL_S = 0.0005
# How long a stale-looking IMU sample may wait for a newer one (see _newer_sense_sample): short, since the reader
# thread runs above the loop once it has SCHED_FIFO; it adds to the time a stopped stream takes to reach damping.
IMU_WAIT_S = 0.0005
# After a host stall, the first read waits at most this long for one bus cycle (and one IMU sample) that began after
# the stall, instead of acting on the stale reading or tripping on it (docs/safety.md, "Host stalls").
POST_STALL_WAIT_S = 0.002
BUS_STOP_TIMEOUT_S = 0.05   # the longest a bus cycle can take (reply timeout, host's hold) with a margin


def _modules_missing(modules: dict[str, str]) -> list[str]:
    return [f"module {name} for {what} is not installed" for name, what in modules.items()
            if importlib.util.find_spec(name) is None]


def missing_for_hw(config: RobotConfig) -> list[str]:
    """Everything that stops the hw backend from starting here, one line each."""
    legs = leg_kind_of(config)
    missing = _modules_missing({**legs.modules, **REQUIRED_MODULES})
    ports = [*legs.ports(config), ("buses.dynamixel.port", config.buses.dynamixel.port),
             ("buses.sense.port", config.buses.sense.port)]
    for key, port in ports:
        if not os.path.exists(port):
            missing.append(f"device {port} ({key}) does not exist; set another with --set {key}=PATH")
    return missing


def make_hw_backend(config: RobotConfig, **options) -> HwBackend:
    missing = missing_for_hw(config)
    if missing:
        raise BackendError("backend 'hw' cannot start:\n  - " + "\n  - ".join(missing))
    return HwBackend(config, **options)


_PER_DEVICE = re.compile(r"^(?P<bus>.*?): ID (?P<id>\d+): (?P<what>.*)$")


def grouped(problems: list[str]) -> list[str]:
    """Start-up problems with the devices that share one named together, in order: "BEAR bus P: ID(s) 2, 3, 4:
    write failed: ..." for what would be a line per device (a vanished port fails every device behind it)."""
    out: dict[tuple[str, str], list[str]] = {}
    for problem in problems:
        match = _PER_DEVICE.match(problem)
        key = (match["bus"], match["what"]) if match else (problem, "")
        out.setdefault(key, []).extend([match["id"]] if match else [])
    return [f"{bus}: ID{'s' if len(ids) > 1 else ''} {', '.join(ids)}: {what}" if ids else bus
            for (bus, what), ids in out.items()]


# -- the backend ----------------------------------------------------------------------------------------------
class HwBackend(Backend):
    name = "hw"
    host_witness = True

    def __init__(self, config: RobotConfig, *, check_imu: bool = True, check_contact: bool = False,
                 ping_rounds: int = 7, ping_retry_s: float = 0.5, clear_attempts: int = 6,
                 bear_reply_timeout_s: float | None = None, arm_ramp_s: float = 1.0,
                 switch_interval_s: float | None = GIL_SWITCH_INTERVAL_S):
        super().__init__(config)
        self.check_imu, self.check_contact = check_imu, check_contact
        self.switch_interval_s = switch_interval_s
        self.legs: LegBus = leg_kind_of(config).legs(config, LegStartup(
            ping_rounds=ping_rounds, ping_retry_s=ping_retry_s, clear_attempts=clear_attempts,
            reply_timeout_s=bear_reply_timeout_s))
        self.arms = ArmHolder(config, ping_rounds=ping_rounds, ping_retry_s=ping_retry_s, ramp_s=arm_ramp_s)
        self.sense = None
        self.sense_port = config.buses.sense.port
        self.fault_stamp: float | None = None  # time.monotonic() when damping was entered
        self.damped_by_bus_thread = False  # the bus thread damped on the cycle that brought an E-stop or fault
        cpl = config.coupling
        self._b = cpl.joint_from_actuator
        self._tau_q_from_m = cpl.actuator_from_joint.T.copy()  # tau_q = B^-T tau_m
        self._tau_m_from_q = cpl.joint_from_actuator.T.copy()  # tau_m = B^T tau_q
        # joint i's temperature is that of the hottest actuator it moves with or takes torque from
        self._drives = (np.abs(cpl.joint_from_actuator) > 1e-12) | (np.abs(cpl.actuator_from_joint.T) > 1e-12)
        self.max_sensor_age = config.safety.max_sensor_age_s
        self.torque_limit = config.actuator_torque_limit
        self._torque: np.ndarray | None = None  # actuator torques of the last write(), sent by the next read()
        self._last: RobotState | None = None
        self._temperature: np.ndarray | None = None
        self._temperature_count = -1
        # The board measures no orientation: this filter fills ImuSample.orientation, which the tilt check and the
        # standing controller use (the raw accelerometer's direction swings by tens of degrees with the motors'
        # reaction forces).
        self._attitude = MahonyAttitude(FIRMWARE_GRAVITY)
        self._saved_switch_interval: float | None = None
        self._bus: BusThread | None = None    # the legs' cycles while active (bruce_hw.bus_thread)
        # When the process was not run (bruce_hw.host_witness): ages are judged on the time the host ran, and a
        # stall up to safety.host_stall_max_s is ridden through.
        self.witness = HostWitness()
        # The joints' readings are also held back when the host holds the leg bus's own port calls (a kind that
        # keeps a log of them: `port_stalls`): left out of their age like a stall of the process.
        port_stalls = getattr(self.legs, "port_stalls", None)
        self._port_stalls = port_stalls
        self._joint_stalled = (self.witness.stalled_between if port_stalls is None
                               else stalled_union(self.witness, port_stalls))
        self.host_stall_max_s = config.safety.host_stall_max_s
        self._last_read_at: float | None = None  # time.monotonic() of the last active read
        self.bus_cycle_us: dict | None = None  # its cycle-time percentiles, once it has ended

    # -- lifecycle -------------------------------------------------------------------------------------------
    def _on_configure(self) -> None:
        """Start-up, as BRUCE-OP v0.0.7's `Play/bootup.sh` starts the robot: open and ping every device of every bus,
        retrying the missing ones (`ping_rounds` at `ping_retry_s`), and fail with one message naming every missing
        device; the legs set up with torque disabled and read back (`LegBus.configure`); the arms with torque off;
        the sense board streaming after the official IMU check."""
        if self.switch_interval_s is not None:
            self._saved_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(self.switch_interval_s)
        problems: list[str] = []
        # BRUCE-OP's order: arms, legs, then the sense board; every bus is tried so that one message names
        # everything that is missing.
        for start in (self._start_arms, self._start_legs, self._start_sense):
            try:
                start()
            except StartupError as exc:
                problems += exc.problems
            except Exception as exc:
                problems.append(f"{type(exc).__name__}: {exc}")
        if problems:
            self._close_all()
            self._restore_switch_interval()
            raise BackendError("hw backend: start-up failed: " + "; ".join(grouped(problems)))
        # Levels itself on the first sample (the robot is still after the IMU check).
        self._attitude = MahonyAttitude(FIRMWARE_GRAVITY)
        self.witness.start()  # like the threads below, before the loop asks for real-time scheduling
        self.arms.start()  # before the loop asks for real-time scheduling: threads inherit the caller's
        self._bus = self._new_bus_thread()  # created now, cycling from activate() on
        atexit.register(self.shutdown)  # an interpreter exit that skipped shutdown() still ends in damping
        log.info("hw backend: configured: %s ID(s) %s, Dynamixel ID(s) %s, sense board %s",
                 self.legs.name, ids_text(self.legs.ids), ids_text(self.config.buses.dynamixel.ids), self.sense_port)

    def _start_arms(self) -> None:
        self.arms.open()

    def _start_legs(self) -> None:
        self.legs.open()
        self.legs.configure()

    def _start_sense(self) -> None:
        from drivers.errors import DriverError
        from drivers.sense import SenseBoard

        try:
            self.sense = SenseBoard(self.sense_port, self.config.buses.sense.baud)
            self.sense.start(check_imu=self.check_imu)
            if self.check_contact:
                self.sense.wait_for_contact()
        except DriverError as exc:
            raise StartupError([f"sense board {exc}"]) from exc

    def _on_activate(self) -> None:
        from drivers.errors import DriverError

        self._torque = None  # zero goal until the first write
        self._last_read_at = None
        activated = time.monotonic()
        self.witness.reset_counts(activated)  # the run's stalls: from activation on
        if self._port_stalls is not None:
            self._port_stalls.reset_counts(activated)
        try:
            self.legs.enable()
        except DriverError as exc:
            self.legs.damp()
            raise BackendError(f"hw backend: enabling {self.legs.name}: {exc}") from exc
        except BackendError:
            self.legs.damp()
            raise
        # From here the legs' cycles run on their own thread; the first reading is taken here so read() never waits.
        first = self.legs.cycle(None, retry=True)
        if self._bus is None or not self._bus.thread.is_alive():  # activated again after a deactivate
            self._bus = self._new_bus_thread()
        self._bus.begin(first)
        self.arms.hold()

    def _new_bus_thread(self) -> BusThread:
        bus = BusThread("hw-legs", self.legs.cycle, period_s=self.config.dt, hold_s=self.max_sensor_age,
                        halt=self._damp_on_device_fault, stalled=self.witness.stalled_between)
        bus.start()
        return bus

    def _damp_on_device_fault(self, reading: LegReading) -> str | None:
        """On the bus thread, right after the cycle that brought it: an E-stop or a device fault damps every actuator
        at once instead of on the next tick (a tick and a cycle sooner). The control thread then faults on the same
        reading, with this moment as the fault's time; it damps again (idempotent)."""
        if not (reading.estop_ids or reading.faults):
            return None
        self.legs.damp()
        return f"E-stop or fault flags on ID(s) {ids_text(sorted({*reading.estop_ids, *reading.faults}))}"

    def _stop_bus(self) -> None:
        """End the legs' bus thread (after its cycle in flight): the caller owns the port from here."""
        bus, self._bus = self._bus, None
        if bus is None:
            return
        if not bus.stop(BUS_STOP_TIMEOUT_S):
            log.error("hw backend: %s: the bus thread did not end within %.0f ms", self.legs.name,
                      1e3 * BUS_STOP_TIMEOUT_S)
        if bus.cycles:
            self.bus_cycle_us = bus.cycle_us()

    def _on_deactivate(self) -> None:
        self._stop_bus()
        self._torque = None
        self.legs.disable()

    def _on_fault(self) -> None:
        """Damping on every reachable actuator; must not raise (it runs on the error paths)."""
        bus = self._bus
        halted_at = bus.halted_at if bus is not None else None  # the bus thread damped already
        self.fault_stamp = halted_at if halted_at is not None else time.monotonic()
        self.damped_by_bus_thread = halted_at is not None
        self._torque = None
        try:
            self._stop_bus()
            self.legs.damp()
        except Exception as exc:  # best effort by design: this runs on the error paths
            log.error("hw backend: damping %s failed: %s", self.legs.name, exc)

    def _on_reset(self) -> None:
        self.legs.disable()  # BEAR: torque_enable 0 also clears latched errors

    def _on_shutdown(self) -> None:
        """Every exit path, and interpreter exit if nobody called shutdown(): damping, the legs' watchdog cleared
        (then damping again), ports closed; the arms torque off (watchdog cleared), the sense board to idle."""
        atexit.unregister(self.shutdown)
        try:
            self._stop_bus()
            self.legs.damp()
            self.legs.clear_watchdog()  # and damping again
        finally:
            log.info("hw backend: %s", self.link_summary())
            self._close_all()
            self._restore_switch_interval()

    def _restore_switch_interval(self) -> None:
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None

    def _close_all(self) -> None:
        self._stop_bus()
        self.witness.stop()
        for close in (self.arms.close, self.legs.close, self._close_sense):
            try:
                close()
            except Exception as exc:  # every port gets its close
                log.error("hw backend: closing: %s", exc)

    def _close_sense(self) -> None:
        if self.sense is not None:
            self.sense.close()  # board to IDLE
            self.sense = None

    def link_report(self) -> dict:
        """Per-bus link figures for the run's stats: leg cycles and lost replies per ID, arm cycles."""
        legs = self.legs.link_report()
        bus = self._bus
        cycle = bus.cycle_us() if bus is not None and bus.cycles else self.bus_cycle_us
        if cycle is not None:
            legs["bus_cycle_us"] = cycle
        report = {"legs": legs,
                  "arms": {"bus": self.arms.name, "cycles": self.arms.cycles, "failed_cycles": self.arms.failed_cycles},
                  "host_stalls": self.witness.report()}
        if self.sense is not None:
            report["sense"] = {"port": self.sense_port, "samples": self.sense.sample_count,
                               "stalls": self.sense.stats.timeouts, "rejected": self.sense.stats.rejected_total}
        return report

    def link_summary(self) -> str:
        stalls = self.witness.report()
        parts = [self.legs.summary(), f"Dynamixel: {self.arms.cycles} arm cycles, {self.arms.failed_cycles} failed",
                 f"host: {stalls['count']} stalls (worst {stalls['worst_ms']:.1f} ms, {stalls['total_ms']:.0f} ms in "
                 f"all; ridden through up to safety.host_stall_max_s {1e3 * self.host_stall_max_s:g} ms)"]
        if self.sense is not None:
            parts.append(f"sense board {self.sense_port}: {self.sense.sample_count} samples, "
                         f"{self.sense.stats.timeouts} stalls, {self.sense.stats.rejected_total} rejected")
        return "; ".join(parts)

    # -- per tick --------------------------------------------------------------------------------------------
    def _fail(self, cause: str) -> BackendError:
        """Damping now (unless already), and the error that read() raises."""
        if self._state is not LifecycleState.FAULT:
            self.fault(cause)
        return BackendError(f"hw backend: {cause}")

    def _read(self) -> RobotState:
        """The newest legs reading (active: the bus thread's; inactive or damping: a cycle of our own), the arms'
        state and the newest sense sample. A lost reply is not a fault: the actuator keeps its last sample, whose
        stamp ages (JointState.stamp is the oldest actuator's). A silent or lossy actuator, a fault flag, an arm bus
        error or a stopped IMU stream goes to damping and raises BackendError naming the bus, the IDs and the figure;
        an E-stop (BEAR error bit 3) goes to damping and the reading says `estop`."""
        from drivers.errors import BusTimeout, DriverError

        state = self._state
        bus = self._bus
        if bus is not None and bus.cycling and bus.error is None and state is LifecycleState.ACTIVE:
            self._ride_through(bus)
        try:
            if bus is not None and bus.cycling:  # active: the newest reading of the bus thread, never waited for
                if bus.error is not None:
                    raise bus.error
                reading = bus.latest
            else:  # inactive (lost replies are asked again) or damping: a cycle of our own
                reading = self.legs.cycle(None, damping=state is LifecycleState.FAULT,
                                          retry=state is not LifecycleState.FAULT)
        except BusTimeout as exc:
            raise self._fail(f"{self.legs.kind} {exc}") from exc  # names the port (channels) and the silent IDs
        except DriverError as exc:
            raise self._fail(f"{self.legs.name}: {exc}") from exc
        except Exception as exc:  # whatever a vanished port raises on the bus thread (termios.error, OSError)
            raise self._fail(f"{self.legs.name}: {type(exc).__name__}: {exc}") from exc
        problem = reading.problem or self.legs.silence(reading, time.monotonic(), self._joint_stalled)
        if problem and state is not LifecycleState.FAULT:
            raise self._fail(f"{self.legs.name}: {problem}")
        if reading.faults and state is not LifecycleState.FAULT:
            raise self._fail(f"{self.legs.name}: " + "; ".join(
                f"ID {i} reports {', '.join(flags)}" for i, flags in reading.faults.items()))
        if self.arms.error and state is not LifecycleState.FAULT:
            raise self._fail(self.arms.error)
        try:
            sense, stamp = self.sense.read()
            if self._stale_at_next_tick(self._age(stamp)):
                sense, stamp = self._newer_sense_sample(stamp)
        except BusTimeout as exc:
            raise self._fail(f"sense board {exc}") from exc
        imu = ImuSample(gyro=sense.gyro, accel=sense.accel, stamp=stamp,
                        orientation=np.array(self._attitude.update(sense.gyro, sense.accel, stamp)))
        contacts = FootContacts(contact=sense.contact, stamp=stamp)
        joints = JointState(q=self._b @ reading.position, qd=self._b @ reading.velocity,
                            tau=self._tau_q_from_m @ reading.torque, temperature=self._joint_temperature(),
                            stamp=reading.stamp)
        robot = RobotState(joints=joints, imu=imu, contacts=contacts, estop=bool(reading.estop_ids))
        if state is not LifecycleState.FAULT:
            if reading.estop_ids and state is LifecycleState.ACTIVE:
                self.fault(f"{self.legs.name}: E-stop (error bit 3) on ID(s) {ids_text(reading.estop_ids)}")
            elif not reading.estop_ids:
                age = self._age(imu.stamp)
                if self._stale_at_next_tick(age):
                    cause = (f"sense board {self.sense_port}: IMU stream stopped: last packet {1e3 * age:.1f} ms "
                             f"ago ({1e3 * (age + self.config.dt):.1f} ms at the next tick > safety.max_sensor_age_s "
                             f"{1e3 * self.max_sensor_age:.1f} ms)")
                    if state is LifecycleState.INACTIVE:
                        raise self._fail(cause)
                    # the safety stage's age check ends the run on the same reading, or, where it judged the
                    # moment a little apart, the loop's refused write does (runtime.loop.run)
                    self.fault(cause)
        self._last = robot
        return robot

    def stalled_between(self, t0: float, t1: float) -> float:
        return self.witness.stalled_between(t0, t1)

    def joint_stalled_between(self, t0: float, t1: float) -> float:
        return self._joint_stalled(t0, t1)

    def _stale_at_next_tick(self, age: float) -> bool:
        """An IMU sample this old is a stopped stream: judged one tick ahead, as the legs' silence
        (bruce_hw.leg_bus.silence), so damping falls within the bound's reach of the last packet instead of a tick
        (and a wait for a newer sample) after it."""
        return age + self.config.dt > self.max_sensor_age

    def _age(self, stamp: float) -> float:
        """How long the process has run since `stamp`: its age less the host stalls in between."""
        now = time.monotonic()
        return now - stamp - self.witness.stalled_between(stamp, now)

    def _ride_through(self, bus: BusThread) -> None:
        """A read after a host stall: wait (at most POST_STALL_WAIT_S) for a bus cycle and an IMU sample that began
        after it, so the tick acts on fresh data instead of the stale reading; after the host held the leg bus's
        port (and no longer does), for a bus cycle. A stall longer than safety.host_stall_max_s damps at once (the
        motors held their last current that long); the safety stage trips on the same stall, naming its
        length, and where it measured a moment shorter, the loop ends the run on this cause."""
        now = time.monotonic()
        last, self._last_read_at = self._last_read_at, now
        witness = self.witness
        if last is None:
            return
        # the witness wakes every millisecond: a silent witness is a stall that has just ended and is not yet recorded
        host = bool(witness.stalled_between(last, now)) or now - witness.last_wake > witness.tolerance_s
        # the port held longer than a stall the witness counts (a read pass a little late is not worth a wait), and
        # no longer held now
        port = (self._port_stalls is not None and self._port_stalls.stalled_between(last, now) > witness.tolerance_s
                and not self._port_stalls.holding(now))
        if not (host or port):
            return
        deadline = now + POST_STALL_WAIT_S
        _, imu_stamp = self.sense.latest() if self.sense is not None and host else (None, None)
        while time.monotonic() < deadline:
            fresh_legs = bus.last_start is not None and bus.last_start >= now and bus.last_end >= bus.last_start
            fresh_imu = imu_stamp is None or (self.sense.latest()[1] or 0.0) > now
            if fresh_legs and fresh_imu and (not host or witness.last_wake >= now):
                break
            time.sleep(0.0001)
        self._last_read_at = time.monotonic()
        stalled = witness.stalled_between(last, self._last_read_at)
        if stalled > self.host_stall_max_s:  # damping at once; the safety stage trips on the same stall
            self.fault(f"host stall: this process was not run for {1e3 * stalled:.1f} ms > "
                       f"safety.host_stall_max_s {1e3 * self.host_stall_max_s:g} ms")

    def _newer_sense_sample(self, stamp: float) -> tuple:
        """A stale-looking sample gets IMU_WAIT_S to be superseded: the reader thread may only have been kept off
        the GIL or the CPU for a moment, and sleeping here lets it run."""
        deadline = time.monotonic() + IMU_WAIT_S
        while time.monotonic() < deadline:
            time.sleep(0.0002)
            _, newest = self.sense.latest()
            if newest is not None and newest > stamp:
                break
        return self.sense.read()

    def _joint_temperature(self) -> np.ndarray:
        """Per joint, the hottest actuator it moves with or takes torque from; recomputed when new temperatures came."""
        if self._temperature_count != self.legs.monitor_count or self._temperature is None:
            t = self.legs.temperature
            self._temperature = np.where(self._drives, t[None, :], -np.inf).max(axis=1)
            self._temperature_count = self.legs.monitor_count
        return self._temperature.copy()

    def _write(self, command: JointCommand) -> None:
        """Joint torques to the actuators (BEAR torque mode, goal_iq). A command with PD terms is evaluated here on
        this tick's measured state: a joint-space PD through the differential hip is not a per-motor PD, so the
        BEARs' own force mode could not carry it exactly."""
        tau = command.tau_ff
        if (command.kp is not None or command.kd is not None) and self._last is not None:
            last = self._last.joints
            tau = command.torque(last.q, last.qd)  # the motor-side PD, on this tick's measured state
        tau_m = self._tau_m_from_q @ tau
        if not np.all(np.isfinite(tau_m)):
            raise self._fail("non-finite torque command (nothing sent)")
        self._torque = np.minimum(np.maximum(tau_m, -self.torque_limit), self.torque_limit)
        if self._bus is not None and self._bus.cycling:
            self._bus.post(self._torque)
