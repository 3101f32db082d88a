"""The `hw` backend: BRUCE's real buses, composed from the drivers in `drivers/` by the robot config.

Legs: ten Koala BEARs on RS-485 (`buses.bear`), or MIT-mode CAN motors when `buses.can.motors` is set; arms: six
Dynamixels (`buses.dynamixel`) held at `arms.hold_pose`; IMU and foot contacts: the sense board (`buses.sense`).
Joint <-> actuator through `coupling` (q = B m, qd = B md, tau_q = B^-T tau_m, tau_m = B^T tau_q), BEAR current
iq = tau_m / `actuators.torque_per_amp`.

Start-up (`configure`, research notes §5.3): open and ping every device of every bus, retrying the missing ones
(`ping_rounds` at `ping_retry_s`, BRUCE: about 7 at 0.5 s) and failing with one message that names every missing
device; BEARs: torque disabled (this leaves a previous run's damping), errors cleared a bounded number of times
(an E-stop bit is refused with "release the E-stop"), then mode, current limit, position limits and the PID
gains written with torque disabled and read back. Homing offsets are per-robot calibration kept in the BEARs'
flash (§1.4): read, never written. Arms: set up with torque off; sense board: stream on and the official IMU
check. `activate` enables the legs (and checks they took it) and ramps the arms to their hold pose.

One tick: the runtime calls read() then write() (runtime/run.py). While active, the legs' bulk cycles run on a thread
of their own (`bruce_hw.bus_thread`, as BRUCE-OP's bear thread): write() hands it the goal currents and starts a
cycle, which writes them and reads present position, velocity and current; read() takes the newest complete reading
and never waits for the bus, so a slow or jittery bus makes the data older (the data-age check judges it), not the
tick longer. Inactive and in damping, read() runs a read-only cycle itself. Once the loop has SCHED_FIFO, the
runtime puts every other thread of the process one real-time priority step above it on its CPU
(`bruce_hw.io_priority`).
BEAR mode: torque (mode 0, goal_iq): the runtime sends joint torques (JointCommand.tau_ff); a command that carries
PD terms is evaluated here on this tick's measured state (JointCommand.torque), because a joint-space PD through
the differential hip is not a per-motor PD, so BEAR force mode could not carry it exactly. Every 100th cycle one
BEAR's temperatures and voltage are read as well (each BEAR once a second, as BRUCE's bear thread does).
The sense board and the arms (50 Hz) run on their own threads, so the 1 kHz tick never waits for them.
ImuSample.orientation: the board measures none, so the backend fills it from an attitude filter
(`bruce_hw.attitude.MahonyAttitude`, gyro + gravity direction): the runtime's tilt check and standing controller use
the orientation when there is one and the raw accelerometer's direction otherwise, which the motors' reaction forces
swing by tens of degrees.

Lost replies: a BEAR reply lost or corrupted within a cycle is not a fault. The bus thread's cycle never retries
(the next cycle asks again a millisecond later); the actuator keeps its last sample, whose stamp ages
(JointState.stamp is the oldest actuator's). Lost replies are counted per ID (`link_report`, the run's stats).

Fault paths (each lands in damping, `_on_fault`: BEAR torque_enable = 3 on every reachable actuator, CAN motors a
damping-only command, the arms keep holding):
- a BEAR whose newest sample is older than `safety.max_sensor_age_s` (silence), a BEAR that lost more than
  `safety.reply_loss_max` of its replies over `safety.reply_loss_window_s`, a silent CAN motor, a fault bit in a
  BEAR's error byte, an arm bus with no good cycle for 0.3 s or a servo error: the backend goes to damping at once
  and read() raises BackendError naming the bus, the IDs and the figure; the runtime ends the session with that
  message (a reading without the legs' data cannot go on to the controller);
- the E-stop (BEAR error bit 3): damping at once, and the reading says `estop`, which trips the safety stage;
- a stopped IMU stream: damping once its newest sample is older than `safety.max_sensor_age_s` (after waiting up
  to IMU_WAIT_S for a newer one), naming the port; the reading keeps the old stamp, so the safety stage's
  sensor-age check trips in the same tick. Each self-inflicted fault while active is either raised or makes the
  safety stage trip on the same reading: a loop that went on would have its next write() refused.
Motor-side watchdogs: a killed process or an unplugged bus cannot send damping, so the motors must stop by
themselves. Start-up writes the BEARs' `watchdog_timeout` (`buses.bear.watchdog_s` in counts of
`buses.bear.watchdog_unit_s`; in torque mode, enabled, a BEAR that hears nothing for that long enters damping) with
torque disabled and reads it back, and the arm driver sets the Dynamixels' Bus Watchdog (`buses.dynamixel.watchdog_s`).
BRUCE-OP sets neither.
Shutdown (every exit path through Backend.shutdown, and at interpreter exit if nobody called it): damping, the BEARs'
watchdog cleared (torque disabled for the write, then damping again), then the ports are closed; arms torque off
(watchdog cleared) and the sense board to idle, as BRUCE-OP's threads do on exit (§5.4).
"""

from __future__ import annotations

import atexit
import importlib.util
import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from bruce_hw.attitude import MahonyAttitude
from bruce_hw.backend import Backend, BackendError, LifecycleState
from bruce_hw.bus_thread import BusThread
from bruce_hw.config import ASSUMED_BEAR_WATCHDOG_UNIT_S, RobotConfig
from bruce_hw.types import JointCommand, JointState, RobotState

log = logging.getLogger("bruce_hw.hw")

# driver or package -> what it is needed for
REQUIRED_MODULES = {
    "drivers.bear": "BEAR actuators over RS-485 (buses.bear)",
    "drivers.dynamixel": "Dynamixel arm servos (buses.dynamixel)",
    "drivers.sense": "sense board IMU and foot contacts (buses.sense)",
    "serial": "the serial buses (package pyserial)",
    "dynamixel_sdk": "the arm bus (package dynamixel-sdk)",
}
CAN_MODULES = {"drivers.can_motor": "CAN leg motors (buses.can)", "can": "the CAN legs (package python-can)"}

# BRUCE-OP's BEAR settings (research notes §2.5, v0.0.7); the current limit comes from the config.
BEAR_GAINS = {
    "p_gain_id": 0.277, "i_gain_id": 0.061, "d_gain_id": 0.0,
    "p_gain_iq": 0.277, "i_gain_iq": 0.061, "d_gain_iq": 0.0,
    "p_gain_velocity": 1.0, "i_gain_velocity": 0.0, "d_gain_velocity": 0.0,
    "p_gain_position": 60.0, "i_gain_position": 0.0, "d_gain_position": 1.0,
    "p_gain_force": 10.0, "i_gain_force": 0.0, "d_gain_force": 1.0,
}
POSITION_LIMIT_MARGIN = 0.1   # rad beyond the actuator range the joint box reaches, for the BEARs' own limit
MONITOR_EVERY_TICKS = 100     # one BEAR's temperatures and voltage per this many ticks
TEMPERATURE_WARN_C = 75.0     # BRUCE-OP warns above this winding temperature (§5.5) ...
VOLTAGE_WARN_V = 14.5         # ... and below this input voltage
MONITOR_REGISTERS = ("winding_temperature", "powerstage_temperature", "ic_temperature", "input_voltage")
ARM_PERIOD_S = 0.02           # BRUCE runs its arms at 50 Hz
# No good arm cycle for this long counts as a lost arm bus. Single cycles get lost on a loaded host: the driver's
# collect_status tests the SDK's packet timeout before reading what arrived meanwhile, so a thread kept off the CPU
# (or the GIL, e.g. while the runtime compiles its MuJoCo models) past the timeout drops a reply that was there.
ARM_SILENCE_TO_FAULT_S = 0.3
# ... and only after this many failed cycles in a row: a thread that could not run (a long collection holding the
# GIL, a busy machine) fails one cycle, however long it waited; a silent bus fails every cycle of the 0.3 s.
ARM_FAILED_CYCLES_TO_FAULT = 5
STANDARD_GRAVITY = 9.80665    # m/s^2: the sense board reports specific force scaled by it (drivers/sense.py)
# The I/O threads (sense reader, arms, the emulators in a test) must get the GIL within a fraction of
# safety.max_sensor_age_s; CPython's default switch interval (5 ms) lets a busy thread hold them off that long.
GIL_SWITCH_INTERVAL_S = 0.0005
# How long a stale-looking IMU sample may wait for a newer one (see _newer_sense_sample): short, since the reader
# thread runs above the loop once it has SCHED_FIFO; it adds to the time a stopped stream takes to reach damping.
IMU_WAIT_S = 0.0005
DEFAULT_REPLY_TIMEOUT_S = 0.002  # BRUCE-OP's bulk_timeout, when buses.bear.reply_timeout_s is not set
BUS_STOP_TIMEOUT_S = 0.05   # the longest a bus cycle can take (reply timeout, monitor read) with a margin
REQUEST_TRIES = 4             # BEAR requests outside the tick's bulk cycle (see BearLegs.open)
SILENT_TICKS = 3              # a motor over the loss bound whose sample is older than this many ticks is silent


def _modules_missing(modules: dict[str, str]) -> list[str]:
    return [f"module {name} for {what} is not installed" for name, what in modules.items()
            if importlib.util.find_spec(name) is None]


def missing_for_hw(config: RobotConfig) -> list[str]:
    """Everything that stops the hw backend from starting here, one line each."""
    can_legs = bool(config.buses.can.motors)
    missing = _modules_missing(REQUIRED_MODULES) + (_modules_missing(CAN_MODULES) if can_legs else [])
    ports = [("buses.dynamixel.port", config.buses.dynamixel.port), ("buses.sense.port", config.buses.sense.port)]
    if not can_legs:
        ports.insert(0, ("buses.bear.port", config.buses.bear.port))
    for key, port in ports:
        if not os.path.exists(port):
            missing.append(f"device {port} ({key}) does not exist; set another with --set {key}=PATH")
    return missing


def make_hw_backend(config: RobotConfig, **options) -> HwBackend:
    missing = missing_for_hw(config)
    if missing:
        raise BackendError("backend 'hw' cannot start:\n  - " + "\n  - ".join(missing))
    return HwBackend(config, **options)


class StartupError(Exception):
    """One bus's start-up problems, one line each."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("; ".join(problems))


@dataclass
class LegReading:
    """One bus cycle of the legs, actuator order (coupling columns)."""

    position: np.ndarray   # rad
    velocity: np.ndarray   # rad/s
    torque: np.ndarray     # Nm, actuator output
    stamp: float           # time.monotonic() when the oldest actuator's sample came in (a lost reply keeps its last)
    stamps: np.ndarray     # per actuator, time.monotonic() when its kept sample came in
    estop_ids: tuple[int, ...] = ()
    faults: dict[int, tuple[str, ...]] = field(default_factory=dict)  # ID -> fault flags other than the E-stop
    problem: str | None = None  # silence or a loss rate past the config's bound: the backend faults with this text


class ReplyLoss:
    """Lost replies per actuator over a sliding window of bus cycles, and since the start.

    A lost or corrupt reply is not a fault: the actuator's last sample is kept and its age counts. Too many lost
    over the window (`safety.reply_loss_max` of `safety.reply_loss_window_s`) is one: the share is taken over the
    whole window, so the first cycles of a run cannot trip it on one or two losses."""

    def __init__(self, n: int, window_cycles: int, max_share: float):
        self.window = max(1, window_cycles)
        self.max_share = max_share
        self._ring = np.zeros((self.window, n), dtype=np.int32)
        self._in_window = np.zeros(n, dtype=np.int64)
        self.total = np.zeros(n, dtype=np.int64)
        self._k = 0

    def add(self, lost: np.ndarray) -> None:
        """One cycle's lost mask (True: no reply)."""
        row = lost.astype(np.int32)
        self._in_window += row - self._ring[self._k]
        self._ring[self._k] = row
        self._k = (self._k + 1) % self.window
        self.total += row

    def share(self) -> np.ndarray:
        return self._in_window / self.window

    def over(self) -> np.ndarray:
        """Actuators over the bound (indices)."""
        return np.flatnonzero(self._in_window > self.max_share * self.window)


# -- legs on BEARs --------------------------------------------------------------------------------------------
class BearLegs:
    """The ten BEARs: start-up, one bulk cycle per tick, damping. Actuator order = buses.bear.ids order."""

    def __init__(self, config: RobotConfig, *, ping_rounds: int, ping_retry_s: float, clear_attempts: int,
                 reply_timeout_s: float):
        self.config = config
        self.ids = tuple(config.buses.bear.ids)
        self.port = config.buses.bear.port
        self.kind = "BEAR bus"
        self.name = f"{self.kind} {self.port}"
        self.kt = config.torque_per_amp
        self.i_max = config.actuator_torque_limit / config.torque_per_amp
        self.ping_rounds, self.ping_retry_s, self.clear_attempts = ping_rounds, ping_retry_s, clear_attempts
        self.reply_timeout_s = reply_timeout_s
        self.bus = None
        self.temperature = np.full(len(self.ids), np.nan)  # hottest sensor, per actuator (the monitor reads)
        self.monitor_count = 0
        self.voltage = np.full(len(self.ids), np.nan)
        self.homing_offset = np.full(len(self.ids), np.nan)
        self.cycles = 0
        self.first_cycle = self.last_cycle = math.nan
        self.low_latency = "not opened"
        self._monitor_tick = 0
        self._monitor_next = 0
        safety = config.safety
        self.max_age_s = safety.max_sensor_age_s
        self.dt = config.dt
        self.loss = ReplyLoss(len(self.ids), round(safety.reply_loss_window_s * config.loop_hz), safety.reply_loss_max)
        n = len(self.ids)
        self._position, self._velocity, self._iq = np.zeros(n), np.zeros(n), np.zeros(n)
        self._stamps = np.full(n, -math.inf)  # when each actuator's kept sample came in
        bus = config.buses.bear
        # The register's count for the configured time (its unit is undocumented: bus.watchdog_unit_s is assumed
        # until `bruce-hw-check --probe-watchdog` measures it); 0: no watchdog.
        self.watchdog_count = max(1, round(bus.watchdog_s / bus.watchdog_unit_s)) if bus.watchdog_s > 0 else 0

    # -- start-up
    def open(self) -> None:
        from drivers.bear import FAULT_BITS, BearBus, BearError, Mode
        from drivers.errors import DriverError

        self._torque_mode = Mode.TORQUE
        self._fault_bits = int(FAULT_BITS & ~BearError.WATCHDOG_ESTOP)  # bit 3 (E-stop, damping): handled apart
        try:
            # Requests outside the tick (start-up, enabling, the monitor) ask up to REQUEST_TRIES times: at 1 %
            # lost replies, 2 tries would fail one start-up in a thousand. The tick's bulk cycle never retries.
            self.bus = BearBus(self.port, self.config.buses.bear.baud, reply_timeout_s=self.reply_timeout_s,
                               tries=REQUEST_TRIES)
        except DriverError as exc:
            raise StartupError([f"{self.name}: {exc}"]) from exc
        self.low_latency = self.bus.low_latency
        log.info("%s: %s", self.name, self.low_latency)
        missing = ping_all(self.bus.ping, self.ids, self.ping_rounds, self.ping_retry_s)
        if missing:
            raise StartupError([f"{self.name}: no reply from BEAR ID(s) {_ids(missing)} after {self.ping_rounds} "
                                f"ping rounds"])

    def configure(self) -> None:
        """Torque off, errors cleared, limits and gains written with torque disabled (BRUCE's run_bear)."""
        from drivers.bear import Mode, TorqueEnable
        from drivers.errors import DeviceFault, DriverError

        bus = self.bus
        problems = []
        bus.set_torque_enable(self.ids, TorqueEnable.DISABLED)  # also leaves a previous run's damping
        for device_id in self.ids:
            try:
                bus.clear_errors(device_id, attempts=self.clear_attempts)
            except DeviceFault as exc:
                problems.append(f"{self.name}: {exc}")
            except DriverError as exc:
                problems.append(f"{self.name}: ID {device_id}: clearing errors: {exc}")
        if problems:
            raise StartupError(problems)
        from drivers.bear import RATED_CURRENT_A

        if self.i_max <= RATED_CURRENT_A * (1 + 1e-9):  # 10.5 / 0.35 is 30 A give or take a rounding
            self.i_max = min(self.i_max, RATED_CURRENT_A)
        else:
            raise StartupError([f"{self.name}: actuators.torque_limit / actuators.torque_per_amp = {self.i_max:.1f} A "
                                f"is beyond the Koala BEAR's rated {RATED_CURRENT_A:g} A: nothing written"])
        low, high = actuator_position_limits(self.config)
        for k, device_id in enumerate(self.ids):
            settings = {"mode": int(Mode.TORQUE), "limit_i_max": self.i_max, "limit_position_min": float(low[k]),
                        "limit_position_max": float(high[k]), "watchdog_timeout": self.watchdog_count, **BEAR_GAINS}
            try:
                bus.write_config(device_id, settings, verify=True)  # torque is disabled: read back, or it raises
                self.homing_offset[k] = bus.read_config(device_id, "homing_offset")["homing_offset"]
            except DriverError as exc:
                problems.append(f"{self.name}: ID {device_id}: writing limits, gains and watchdog: {exc}")
        if problems:
            raise StartupError(problems)
        if self.watchdog_count:
            cfg = self.config.buses.bear
            log.info("%s: BEAR watchdog_timeout %d (%.0f ms at %g s per count%s), read back from every BEAR",
                     self.name, self.watchdog_count, 1e3 * self.watchdog_count * cfg.watchdog_unit_s,
                     cfg.watchdog_unit_s, "; the unit is assumed until `bruce-hw-check --probe-watchdog` measures it"
                     if cfg.watchdog_unit_s == ASSUMED_BEAR_WATCHDOG_UNIT_S else "")
        for _ in self.ids:
            self.monitor()
        self._seed()

    def _seed(self) -> None:
        """Every actuator's first sample, with retries (before the loop, a lost reply may be asked for again)."""
        reply = self.bus.bulk_cycle(self.ids, None)
        self._keep(reply, np.ones(len(self.ids), dtype=bool), time.monotonic())

    def _keep(self, reply, answered: np.ndarray, stamp: float) -> None:
        self._position[answered] = reply.position[answered]
        self._velocity[answered] = reply.velocity[answered]
        self._iq[answered] = reply.iq[answered]
        self._stamps[answered] = stamp

    def clear_watchdog(self) -> None:
        """watchdog_timeout back to 0 (a clean shutdown leaves the BEARs as other software expects them): config
        registers take writes only with torque disabled, so disable, write and read back, then damping again.
        Best effort: it runs on the shutdown path."""
        from drivers.bear import TorqueEnable
        from drivers.errors import DriverError

        if self.bus is None or not self.watchdog_count:
            return
        try:
            self.bus.set_torque_enable(self.ids, TorqueEnable.DISABLED)
            for device_id in self.ids:
                self.bus.write_config(device_id, {"watchdog_timeout": 0}, verify=True)
        except DriverError as exc:
            log.warning("%s: clearing watchdog_timeout: %s (the BEARs keep it until power-off)", self.name, exc)
        finally:
            self.damp()

    # -- lifecycle
    def enable(self) -> None:
        from drivers.bear import TorqueEnable

        bus = self.bus
        for device_id in self.ids:
            bus.write_status(device_id, {"goal_iq": 0.0})  # no stale goal acts on enable
        bus.set_torque_enable(self.ids, TorqueEnable.ENABLED)
        refused = {}
        for device_id in self.ids:
            value = int(bus.read_status(device_id, "torque_enable")["torque_enable"])
            if value != TorqueEnable.ENABLED:
                refused[device_id] = value
        if refused:
            hint = " (3: damping or the E-stop is pressed; 2: a device error)"
            raise BackendError(f"{self.name}: torque_enable did not take: " + ", ".join(
                f"ID {i} reads {v}" for i, v in refused.items()) + hint)

    def disable(self) -> None:
        from drivers.bear import TorqueEnable

        self.bus.set_torque_enable(self.ids, TorqueEnable.DISABLED)

    def damp(self) -> None:
        """torque_enable = 3 to every BEAR; a write that fails is skipped (the others still get theirs)."""
        from drivers.bear import TorqueEnable
        from drivers.errors import DriverError

        if self.bus is None:
            return
        for device_id in self.ids:
            try:
                self.bus.set_torque_enable([device_id], TorqueEnable.DAMPING)
            except DriverError:
                pass

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
            self.bus = None

    # -- per tick
    def cycle(self, torque: np.ndarray | None, damping: bool = False, retry: bool = False) -> LegReading:
        """One bulk cycle: goal currents for `torque` (actuator Nm; None: read only), present values back. In
        damping the BEARs damp by themselves: `damping` changes nothing here. A lost reply keeps that actuator's
        last sample (its stamp ages); `problem` is set when a sample is older than `safety.max_sensor_age_s` or
        an actuator lost more than `safety.reply_loss_max` of its replies over the window. `retry` (outside the
        loop's ticks: before the first command) asks again for lost replies and raises BusTimeout for silent IDs."""
        if torque is None:
            reply = self.bus.bulk_cycle(self.ids, None, partial=not retry)
        else:
            goal_iq = np.minimum(np.maximum(torque / self.kt, -self.i_max), self.i_max)
            reply = self.bus.bulk_cycle(self.ids, self._torque_mode, goal_iq=goal_iq, partial=True)
        stamp = time.monotonic()
        self.cycles += 1
        if self.cycles == 1:
            self.first_cycle = stamp
        self.last_cycle = stamp
        answered = np.ones(len(self.ids), dtype=bool) if reply.answered is None else reply.answered
        self._keep(reply, answered, stamp)
        self.loss.add(~answered)
        faults = {}
        for device_id, error in zip(self.ids, reply.error.tolist(), strict=True):
            if error & self._fault_bits:
                faults[device_id] = reply.flags(device_id)
        reading = LegReading(self._position.copy(), self._velocity.copy(), self._iq * self.kt,
                             float(self._stamps.min()), self._stamps.copy(), reply.estop_ids(), faults,
                             self._loss_problem(stamp))
        self._monitor_tick += 1
        if self._monitor_tick >= MONITOR_EVERY_TICKS:
            self._monitor_tick = 0
            self.monitor()
        return reading

    def silence(self, reading: LegReading, now: float) -> str | None:
        return silence(self.ids, reading, now, self.dt, self.max_age_s)

    def _loss_problem(self, now: float) -> str | None:
        ages = now - self._stamps
        over = self.loss.over()
        if over.size:
            share = self.loss.share()
            text = (f"reply loss {', '.join(f'ID {self.ids[k]} {100 * share[k]:.1f} %' for k in over)} over the last "
                    f"{self.loss.window} cycles > safety.reply_loss_max {100 * self.loss.max_share:g} %")
            silent = [k for k in over if ages[k] > SILENT_TICKS * self.dt]
            if silent:  # a motor gone silent reaches the loss bound before the age bound when that one is wide
                return (f"no reply from ID(s) {_ids(self.ids[k] for k in silent)} for "
                        f"{1e3 * float(ages[silent].max()):.1f} ms: {text}")
            return text
        return None

    def link_report(self) -> dict:
        """Cycles and lost replies per ID, for the run's summary and stats."""
        lost = {str(i): int(n) for i, n in zip(self.ids, self.loss.total.tolist(), strict=True)}
        total = int(self.loss.total.sum())
        return {"bus": self.name, "cycles": self.cycles, "replies_lost": lost, "replies_lost_total": total,
                "reply_loss_share": total / (self.cycles * len(self.ids)) if self.cycles else 0.0,
                "watchdog_timeout": self.watchdog_count, "adapter": self.low_latency,
                "host_stalls": self.bus.stats.host_stalls if self.bus is not None else 0}

    def monitor(self) -> None:
        """Temperatures and voltage of the next BEAR in turn; a BEAR that does not answer is left to the next
        bulk cycle to report. Warnings only, as BRUCE-OP (§5.5)."""
        from drivers.errors import BusTimeout

        k = self._monitor_next
        self._monitor_next = (k + 1) % len(self.ids)
        device_id = self.ids[k]
        try:
            reply = self.bus.read_status(device_id, MONITOR_REGISTERS, tries=1)
        except BusTimeout:  # one lost reply is not worth a retry in the tick: the next round asks again
            return
        hottest = max(reply[name] for name in MONITOR_REGISTERS[:3])
        if hottest > TEMPERATURE_WARN_C and not self.temperature[k] > TEMPERATURE_WARN_C:
            log.warning("%s: ID %d at %.0f C (> %.0f C)", self.name, device_id, hottest, TEMPERATURE_WARN_C)
        if reply["input_voltage"] < VOLTAGE_WARN_V and not self.voltage[k] < VOLTAGE_WARN_V:
            log.warning("%s: ID %d input %.1f V (< %.1f V)", self.name, device_id, reply["input_voltage"],
                        VOLTAGE_WARN_V)
        self.temperature[k] = hottest
        self.voltage[k] = reply["input_voltage"]
        self.monitor_count += 1

    def summary(self) -> str:
        span = self.last_cycle - self.first_cycle if self.cycles > 1 else math.nan
        rate = (self.cycles - 1) / span if span > 0 else math.nan
        stats = self.bus.stats if self.bus is not None else None
        lost = int(self.loss.total.sum())
        link = "" if stats is None else (f", {lost} replies lost, {stats.retries} retries, "
                                         f"{stats.rejected_total} bytes/packets rejected, "
                                         f"{stats.host_stalls} reads the host was late for")
        return f"{self.name}: {self.cycles} bulk cycles in {span:.2f} s ({rate:.0f} Hz){link}"


# -- legs on CAN ----------------------------------------------------------------------------------------------
class CanLegs:
    """MIT-mode CAN motors, one per joint slot (buses.can.motors in joints.names order = coupling columns)."""

    def __init__(self, config: RobotConfig, *, ping_rounds: int, ping_retry_s: float):
        self.config = config
        self.can = config.buses.can
        self.ids = tuple(m.id for m in self.can.motors)
        self.kind = "CAN bus"
        self.name = f"{self.kind} {', '.join(self.can.channels)} ({self.can.interface})"
        self.ping_rounds, self.ping_retry_s = ping_rounds, ping_retry_s
        self.damping_kd = config.safety.damping_kd
        self.group = None
        self.temperature = np.full(len(self.ids), np.nan)  # the MIT reply carries none
        self.monitor_count = 0
        self.cycles = 0
        self.first_cycle = self.last_cycle = math.nan

    def open(self) -> None:
        from drivers.can_motor import CanMotorGroup
        from drivers.errors import BusTimeout, DriverError

        try:
            self.group = CanMotorGroup.from_config(self.can)
        except (DriverError, ValueError) as exc:
            raise StartupError([f"{self.name}: {exc}"]) from exc
        silent: tuple[int, ...] = ()
        for attempt in range(self.ping_rounds):
            if attempt:
                time.sleep(self.ping_retry_s)
            try:
                self.group.read()  # the all-zero command: ignored in rest mode, answered
                return
            except BusTimeout as exc:
                silent = exc.silent_ids
        raise StartupError([f"{self.name}: no reply from CAN motor ID(s) {_ids(silent)} after {self.ping_rounds} "
                            "rounds"])

    def configure(self) -> None:
        """Rest mode (no torque): the MIT protocol carries gains in every frame, there is nothing to write."""
        self.group.exit_motor_mode()

    def enable(self) -> None:
        self.group.enter_motor_mode()  # clears the command: zero torque until the first cycle

    def disable(self) -> None:
        self.group.exit_motor_mode()

    def damp(self) -> None:
        """A damping-only command (tau = -kd v); the firmware keeps applying it until told otherwise, the CAN
        counterpart of BEAR damping mode."""
        from drivers.errors import DriverError

        if self.group is None:
            return
        try:
            self.group.damp(self.damping_kd)
        except DriverError:
            pass  # the silent ones are what we are damping around

    def close(self) -> None:
        if self.group is not None:
            self.group.close()
            self.group = None

    def clear_watchdog(self) -> None:
        """The MIT protocol has no watchdog register to clear."""

    def link_report(self) -> dict:
        timeouts = sum(s.timeouts for s in self.group.stats.values()) if self.group is not None else 0
        return {"bus": self.name, "cycles": self.cycles, "timeouts": timeouts}

    def cycle(self, torque: np.ndarray | None, damping: bool = False, retry: bool = False) -> LegReading:
        if damping:
            state = self.group.damp(self.damping_kd)
        elif torque is None:
            state = self.group.read()
        else:
            state = self.group.exchange(0.0, 0.0, 0.0, 0.0, torque)
        stamp = time.monotonic()
        self.cycles += 1
        if self.cycles == 1:
            self.first_cycle = stamp
        self.last_cycle = stamp
        return LegReading(state.position, state.velocity, state.torque, stamp, np.full(len(self.ids), stamp))

    def silence(self, reading: LegReading, now: float) -> str | None:
        return silence(self.ids, reading, now, self.config.dt, self.config.safety.max_sensor_age_s)

    def summary(self) -> str:
        span = self.last_cycle - self.first_cycle if self.cycles > 1 else math.nan
        rate = (self.cycles - 1) / span if span > 0 else math.nan
        timeouts = sum(s.timeouts for s in self.group.stats.values()) if self.group is not None else 0
        return f"{self.name}: {self.cycles} cycles in {span:.2f} s ({rate:.0f} Hz), {timeouts} timeouts"


# -- arms -----------------------------------------------------------------------------------------------------
class ArmSilence:
    """When the arm bus counts as lost: no good cycle for ARM_SILENCE_TO_FAULT_S and at least
    ARM_FAILED_CYCLES_TO_FAULT failed cycles in a row."""

    def __init__(self, now: float):
        self.last_good = now
        self.failed_in_row = 0

    def good(self, now: float) -> None:
        self.last_good, self.failed_in_row = now, 0

    def failed(self, now: float) -> float | None:
        """Count a failed cycle; the silence so far (s) when the bus counts as lost, else None."""
        self.failed_in_row += 1
        silent_s = now - self.last_good
        if silent_s > ARM_SILENCE_TO_FAULT_S and self.failed_in_row >= ARM_FAILED_CYCLES_TO_FAULT:
            return silent_s
        return None


class ArmHolder:
    """The arms on their own thread at 50 Hz: a sync read every cycle and, once asked to hold, goal positions
    ramped from the measured pose to arms.hold_pose. A servo error, or no good cycle for `ARM_SILENCE_TO_FAULT_S`,
    sets `error` (the backend faults on it). The port belongs to the thread once it runs."""

    def __init__(self, config: RobotConfig, *, ping_rounds: int, ping_retry_s: float, ramp_s: float = 1.0,
                 period_s: float = ARM_PERIOD_S):
        self.config = config
        self.name = f"Dynamixel bus {config.buses.dynamixel.port}"
        self.ping_rounds, self.ping_retry_s = ping_rounds, ping_retry_s
        self.ramp_s, self.period_s = ramp_s, period_s
        self.arms = None
        self.error: str | None = None
        self.q = self.qd = None
        self.stamp = -math.inf
        self.cycles = 0
        self.failed_cycles = 0
        self._hold = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        from drivers.dynamixel import DynamixelArms
        from drivers.errors import BusTimeout, DriverError

        missing: tuple[int, ...] = ()
        for attempt in range(self.ping_rounds):
            if attempt:
                time.sleep(self.ping_retry_s)
            try:
                self.arms = DynamixelArms.from_config(self.config)  # ping all, set up with torque off
                return
            except BusTimeout as exc:
                missing = exc.silent_ids
            except DriverError as exc:
                raise StartupError([f"{self.name}: {exc}"]) from exc
        raise StartupError([f"{self.name}: no reply from Dynamixel ID(s) {_ids(missing)} after "
                            f"{self.ping_rounds} ping rounds"])

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="hw-arms", daemon=True)
        self._thread.start()

    @property
    def thread(self) -> threading.Thread | None:
        return self._thread

    def hold(self) -> None:
        """Torque on and ramp to the hold pose (done by the thread)."""
        self._hold.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        if self.arms is not None:
            self.arms.close()  # torque off, as BRUCE-OP's run_dxl on exit
            self.arms = None

    def _run(self) -> None:
        from drivers.errors import DeviceFault

        arms, target = self.arms, self.config.arms.hold_pose
        start = None
        ramp_t0 = 0.0
        silence = ArmSilence(time.monotonic())
        deadline = time.monotonic()
        while not self._stop.wait(max(0.0, deadline - time.monotonic())):
            deadline = max(deadline + self.period_s, time.monotonic())
            try:
                if self._hold.is_set():
                    if start is None:
                        measured = arms.read()[0]
                        arms.write_positions(measured)  # goal = measured before torque on: no jump
                        arms.enable_torque()
                        start, ramp_t0 = measured, time.monotonic()
                    share = min(1.0, (time.monotonic() - ramp_t0) / self.ramp_s) if self.ramp_s > 0 else 1.0
                    arms.write_positions(start + (target - start) * share)
                self.q, self.qd = arms.read()
                self.stamp = time.monotonic()
                silence.good(self.stamp)
                self.cycles += 1
            except DeviceFault as exc:
                self.error = self.error or f"arm bus {exc}"
            except Exception as exc:  # DriverError, and whatever a vanished port raises (termios.error, OSError)
                self.failed_cycles += 1
                log.debug("arms: %s", exc)
                silent_s = silence.failed(time.monotonic())
                if silent_s is not None:
                    self.error = self.error or f"arm bus {exc} (no good cycle for {1e3 * silent_s:.0f} ms)"


# -- the backend ----------------------------------------------------------------------------------------------
class HwBackend(Backend):
    name = "hw"

    def __init__(self, config: RobotConfig, *, check_imu: bool = True, check_contact: bool = False,
                 ping_rounds: int = 7, ping_retry_s: float = 0.5, clear_attempts: int = 6,
                 bear_reply_timeout_s: float | None = None, arm_ramp_s: float = 1.0,
                 switch_interval_s: float | None = GIL_SWITCH_INTERVAL_S):
        super().__init__(config)
        self.check_imu, self.check_contact = check_imu, check_contact
        self.switch_interval_s = switch_interval_s
        if config.buses.can.motors:
            self.legs = CanLegs(config, ping_rounds=ping_rounds, ping_retry_s=ping_retry_s)
        else:
            self.legs = BearLegs(config, ping_rounds=ping_rounds, ping_retry_s=ping_retry_s,
                                 clear_attempts=clear_attempts, reply_timeout_s=bear_reply_timeout_s
                                 or config.buses.bear.reply_timeout_s or DEFAULT_REPLY_TIMEOUT_S)
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
        self._attitude = MahonyAttitude(STANDARD_GRAVITY)
        self._saved_switch_interval: float | None = None
        self._bus: BusThread | None = None    # the legs' cycles while active (bruce_hw.bus_thread)
        self.bus_cycle_us: dict | None = None  # its cycle-time percentiles, once it has ended

    # -- lifecycle -------------------------------------------------------------------------------------------
    def _on_configure(self) -> None:
        if self.switch_interval_s is not None:
            self._saved_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(self.switch_interval_s)
        problems: list[str] = []
        # BRUCE's order (§5.3): arms, legs, then the sense board; every bus is tried so that one message names
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
            raise BackendError("hw backend: start-up failed:\n  - " + "\n  - ".join(problems))
        # Levels itself on the first sample (the robot is still after the IMU check).
        self._attitude = MahonyAttitude(STANDARD_GRAVITY)
        self.arms.start()  # before the loop asks for real-time scheduling: threads inherit the caller's
        self._bus = self._new_bus_thread()  # created now, cycling from activate() on
        atexit.register(self.shutdown)  # an interpreter exit that skipped shutdown() still ends in damping
        log.info("hw backend: configured: %s BEAR/CAN ID(s) %s, Dynamixel ID(s) %s, sense board %s",
                 self.legs.name, _ids(self.legs.ids), _ids(self.config.buses.dynamixel.ids), self.sense_port)

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
                        halt=self._damp_on_device_fault)
        bus.start()
        return bus

    def _damp_on_device_fault(self, reading: LegReading) -> str | None:
        """On the bus thread, right after the cycle that brought it: an E-stop or a device fault damps every actuator
        at once instead of on the next tick (a tick and a cycle sooner). The control thread then faults on the same
        reading, with this moment as the fault's time; it damps again (idempotent)."""
        if not (reading.estop_ids or reading.faults):
            return None
        self.legs.damp()
        return f"E-stop or fault flags on ID(s) {_ids(sorted({*reading.estop_ids, *reading.faults}))}"

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
                  "arms": {"bus": self.arms.name, "cycles": self.arms.cycles, "failed_cycles": self.arms.failed_cycles}}
        if self.sense is not None:
            report["sense"] = {"port": self.sense_port, "samples": self.sense.sample_count,
                               "stalls": self.sense.stats.timeouts, "rejected": self.sense.stats.rejected_total}
        return report

    def link_summary(self) -> str:
        parts = [self.legs.summary(), f"Dynamixel: {self.arms.cycles} arm cycles, {self.arms.failed_cycles} failed"]
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
        from drivers.errors import BusTimeout, DriverError

        state = self._state
        bus = self._bus
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
        problem = reading.problem or self.legs.silence(reading, time.monotonic())
        if problem and state is not LifecycleState.FAULT:
            raise self._fail(f"{self.legs.name}: {problem}")
        if reading.faults and state is not LifecycleState.FAULT:
            raise self._fail(f"{self.legs.name}: " + "; ".join(
                f"ID {i} reports {', '.join(flags)}" for i, flags in reading.faults.items()))
        if self.arms.error and state is not LifecycleState.FAULT:
            raise self._fail(self.arms.error)
        try:
            imu, contacts = self.sense.read()
            if time.monotonic() - imu.stamp > self.max_sensor_age:
                imu, contacts = self._newer_sense_sample(imu.stamp)
        except BusTimeout as exc:
            raise self._fail(f"sense board {exc}") from exc
        imu.orientation = np.array(self._attitude.update(imu.gyro, imu.accel, imu.stamp))
        joints = JointState(q=self._b @ reading.position, qd=self._b @ reading.velocity,
                            tau=self._tau_q_from_m @ reading.torque, temperature=self._joint_temperature(),
                            stamp=reading.stamp)
        robot = RobotState(joints=joints, imu=imu, contacts=contacts, estop=bool(reading.estop_ids))
        if state is not LifecycleState.FAULT:
            if reading.estop_ids and state is LifecycleState.ACTIVE:
                self.fault(f"{self.legs.name}: E-stop (error bit 3) on ID(s) {_ids(reading.estop_ids)}")
            elif not reading.estop_ids:
                age = time.monotonic() - imu.stamp
                if age > self.max_sensor_age:
                    cause = (f"sense board {self.sense_port}: IMU stream stopped: last packet {1e3 * age:.1f} ms "
                             f"ago > safety.max_sensor_age_s {1e3 * self.max_sensor_age:.1f} ms")
                    if state is LifecycleState.INACTIVE:
                        raise self._fail(cause)
                    self.fault(cause)  # the safety stage's age check trips on the same reading
        self._last = robot
        return robot

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
        """Per joint, the hottest actuator it moves with or takes torque from; recomputed after monitor reads."""
        if self._temperature_count != self.legs.monitor_count or self._temperature is None:
            t = self.legs.temperature
            self._temperature = np.where(self._drives, t[None, :], -np.inf).max(axis=1)
            self._temperature_count = self.legs.monitor_count
        return self._temperature.copy()

    def _write(self, command: JointCommand) -> None:
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


# -- attitude -------------------------------------------------------------------------------------------------
# -- helpers --------------------------------------------------------------------------------------------------
def _ids(ids) -> str:
    return ", ".join(str(i) for i in ids) or "none"


def silence(ids: tuple[int, ...], reading: LegReading, now: float, dt: float, max_age_s: float) -> str | None:
    """The actuators whose kept sample is too old at `now`. Judged one tick ahead: a sample that will be too old when
    the safety stage looks at it is silence here, where the bus and the IDs are known (the safety stage's own age
    check could only say "stale joint data")."""
    ages = now - reading.stamps
    stale = np.flatnonzero(ages + dt > max_age_s)
    if stale.size:
        age = float(ages[stale].max())
        return (f"no reply from ID(s) {_ids(ids[k] for k in stale)} for {1e3 * age:.1f} ms ({1e3 * (age + dt):.1f} ms "
                f"at the next tick > safety.max_sensor_age_s {1e3 * max_age_s:.1f} ms)")
    return None


def ping_all(ping, ids, rounds: int, retry_s: float) -> list[int]:
    """Ping every ID, then the silent ones again, `rounds` times in all, `retry_s` apart; the IDs still silent."""
    from drivers.errors import BusTimeout

    missing = list(ids)
    for attempt in range(max(1, rounds)):
        if attempt:
            time.sleep(retry_s)
        still = []
        for device_id in missing:
            try:
                ping(device_id)
            except BusTimeout:
                still.append(device_id)
        missing = still
        if not missing:
            break
    return missing


def actuator_position_limits(config: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per actuator, the range the joint box (joints.position_limits) reaches through the coupling, widened by
    POSITION_LIMIT_MARGIN: the BEARs' own position limits (their error bit 4 is the last line behind ours)."""
    a = config.coupling.actuator_from_joint
    mid, half = (config.q_upper + config.q_lower) / 2, (config.q_upper - config.q_lower) / 2
    center, reach = a @ mid, np.abs(a) @ half
    return center - reach - POSITION_LIMIT_MARGIN, center + reach + POSITION_LIMIT_MARGIN
