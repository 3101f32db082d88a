"""The legs on ten Koala BEARs over RS-485 (`buses.bear`): start-up with read-back, the bulk cycle (with the
temperatures and voltages now and then), lost-reply accounting. Driven by the hw backend through
`bruce_hw.leg_bus.LegBus`."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from bruce_hw.backend import BackendError
from bruce_hw.bus_startup import StartupError, ids_text, ping_all
from bruce_hw.config import ASSUMED_BEAR_WATCHDOG_UNIT_S, RobotConfig
from bruce_hw.host_witness import StallLog
from bruce_hw.leg_bus import LegReading, silence

log = logging.getLogger("bruce_hw.hw")

POSITION_LIMIT_MARGIN = 0.1   # rad beyond the actuator range the joint box reaches, for the BEARs' own limit
MONITOR_EVERY_TICKS = 100     # every BEAR's temperatures and voltage, read in the bulk cycle, once per this many
TEMPERATURE_WARN_C = 75.0     # BRUCE-OP warns above this winding temperature ...
VOLTAGE_WARN_V = 14.5         # ... and below this input voltage
MONITOR_REGISTERS = ("winding_temperature", "powerstage_temperature", "ic_temperature", "input_voltage")
DEFAULT_REPLY_TIMEOUT_S = 0.002  # BRUCE-OP's bulk_timeout, when buses.bear.reply_timeout_s is not set
REQUEST_TRIES = 4             # BEAR requests outside the tick's bulk cycle (see BearLegs.open)
SILENT_TICKS = 3              # a motor over the loss bound whose sample is older than this many ticks is silent


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

    def came_late(self, rows: np.ndarray) -> None:
        """Replies of the last cycle added that came after all (`BulkReply.late`): not lost."""
        last = (self._k - 1) % self.window
        rows = rows[self._ring[last, rows] > 0]
        self._ring[last, rows] = 0
        self._in_window[rows] -= 1
        self.total[rows] -= 1

    def share(self) -> np.ndarray:
        return self._in_window / self.window

    def over(self) -> np.ndarray:
        """Actuators over the bound (indices)."""
        return np.flatnonzero(self._in_window > self.max_share * self.window)


# -- legs on BEARs --------------------------------------------------------------------------------------------
class BearLegs:
    """The ten BEARs: start-up, one bulk cycle per tick, damping. Actuator order = buses.bear.ids order."""

    def __init__(self, config: RobotConfig, *, ping_rounds: int, ping_retry_s: float, clear_attempts: int,
                 reply_timeout_s: float, turn_order: bool = True):
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
        self.temperature = np.full(len(self.ids), np.nan)  # hottest sensor, per actuator (read in the bulk cycle)
        self.monitor_count = 0
        self.voltage = np.full(len(self.ids), np.nan)
        self.homing_offset = np.full(len(self.ids), np.nan)
        self.cycles = 0
        self.late_replies = 0  # replies taken after their cycle's deadline (BulkReply.late)
        self._row = {device_id: k for k, device_id in enumerate(self.ids)}
        # the bulk request's order each cycle (see `cycle`; `turn_order` False: IDs in config order every cycle, the
        # order before the turning one, for comparison): actuator rows, the IDs in that order, and where each
        # actuator's reply is in it
        turns = len(self.ids) if turn_order else 1
        self._rotation = [np.roll(np.arange(len(self.ids)), -k) for k in range(turns)]
        self._orders = [tuple(self.ids[k] for k in rows) for rows in self._rotation]
        self._reply_rows = [np.argsort(rows) for rows in self._rotation]
        self.first_cycle = self.last_cycle = math.nan
        self.low_latency = "not opened"
        self._monitor_tick = 0
        safety = config.safety
        self.max_age_s = safety.max_sensor_age_s
        self.host_stall_max_s = safety.host_stall_max_s
        self.dt = config.dt
        # The time the host held this port's own I/O (BearBus.on_host_stall): the kernel's tty work for the port not
        # run, so a request not sent or a reply not handed over. Not the BEARs' silence; the hw backend leaves it out
        # of the joint data's age, up to safety.host_stall_max_s (`silence`).
        self.port_stalls = StallLog(open_since=self._held_since)
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
        from drivers.bear import BearBus
        from drivers.bear_registers import FAULT_BITS, BearError, Mode
        from drivers.errors import DriverError

        self._torque_mode = Mode.TORQUE
        self._fault_bits = int(FAULT_BITS & ~BearError.WATCHDOG_ESTOP)  # bit 3 (E-stop, damping): handled apart
        try:
            # Requests outside the tick (start-up, enabling) ask up to REQUEST_TRIES times: at 1 %
            # lost replies, 2 tries would fail one start-up in a thousand. The tick's bulk cycle never retries.
            self.bus = BearBus(self.port, self.config.buses.bear.baud, reply_timeout_s=self.reply_timeout_s,
                               tries=REQUEST_TRIES)
        except DriverError as exc:
            raise StartupError([f"{self.name}: {exc}"]) from exc
        self.low_latency = self.bus.low_latency
        self.bus.on_host_stall = self.port_stalls.record
        log.info("%s: %s", self.name, self.low_latency)
        missing = ping_all(self.bus.ping, self.ids, self.ping_rounds, self.ping_retry_s)
        if missing:
            raise StartupError([f"{self.name}: no reply from BEAR ID(s) {ids_text(missing)} after {self.ping_rounds} "
                                f"ping rounds"])

    def configure(self) -> None:
        """Torque off, errors cleared, limits and gains written with torque disabled (BRUCE's run_bear)."""
        from drivers.bear_registers import Mode, TorqueEnable
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
        from drivers.bear_registers import RATED_CURRENT_A

        if self.i_max <= RATED_CURRENT_A * (1 + 1e-9):  # 10.5 / 0.35 is 30 A give or take a rounding
            self.i_max = min(self.i_max, RATED_CURRENT_A)
        else:
            raise StartupError([f"{self.name}: actuators.torque_limit / actuators.torque_per_amp = {self.i_max:.1f} A "
                                f"is beyond the Koala BEAR's rated {RATED_CURRENT_A:g} A: nothing written"])
        low, high = actuator_position_limits(self.config)
        for k, device_id in enumerate(self.ids):
            settings = {"mode": int(Mode.TORQUE), "limit_i_max": self.i_max, "limit_position_min": float(low[k]),
                        "limit_position_max": float(high[k]), "watchdog_timeout": self.watchdog_count,
                        **dict(self.config.buses.bear.gains)}
            try:
                bus.write_config(device_id, settings, verify=True)  # torque is disabled: read back, or it raises
                # per-robot calibration kept in the BEARs' flash (as BRUCE-OP treats it): read, never written
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
        self._seed()

    def _seed(self) -> None:
        """Every actuator's first sample and temperatures, with retries (before the loop, a lost reply may be asked
        for again)."""
        reply = self.bus.bulk_cycle(self.ids, None, extra_reads=MONITOR_REGISTERS)
        answered = np.ones(len(self.ids), dtype=bool)
        self._keep(answered, reply, answered, time.monotonic())
        self._monitored(reply, answered)

    def _keep(self, rows: np.ndarray, reply, taken: np.ndarray, stamp: float) -> None:
        """The samples `reply` brought in its rows `taken` become the kept ones of actuators `rows`, as of `stamp`."""
        self._position[rows] = reply.position[taken]
        self._velocity[rows] = reply.velocity[taken]
        self._iq[rows] = reply.iq[taken]
        self._stamps[rows] = stamp

    def clear_watchdog(self) -> None:
        """watchdog_timeout back to 0 (a clean shutdown leaves the BEARs as other software expects them): config
        registers take writes only with torque disabled, so disable, write and read back, then damping again.
        Best effort: it runs on the shutdown path."""
        from drivers.bear_registers import TorqueEnable
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
        from drivers.bear_registers import TorqueEnable

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
        from drivers.bear_registers import TorqueEnable

        self.bus.set_torque_enable(self.ids, TorqueEnable.DISABLED)

    def damp(self) -> None:
        """torque_enable = 3 to every BEAR; a write that fails is skipped (the others still get theirs)."""
        from drivers.bear_registers import TorqueEnable
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
        """One bulk cycle: goal currents for `torque` (actuator Nm; None: read only), present values back; every
        MONITOR_EVERY_TICKS cycles the same request also reads every BEAR's temperatures and voltage (a request of
        their own would hold the bus for another reply's wait, and the cycle's reading with it). In damping the
        BEARs damp by themselves: `damping` changes nothing here. A lost reply keeps that actuator's last sample
        (its stamp ages); `problem` is set when a sample is older than `safety.max_sensor_age_s` or an actuator lost
        more than `safety.reply_loss_max` of its replies over the window. `retry` (outside the loop's ticks: before
        the first command) asks again for lost replies and raises BusTimeout for silent IDs."""
        self._monitor_tick += 1
        monitor = MONITOR_REGISTERS if self._monitor_tick >= MONITOR_EVERY_TICKS else ()
        # The BEARs answer in request order, and the driver ends a cycle once the last ID's reply is in (the newest
        # taken); a lost last reply alone costs the reply gap (drivers.bear.REPLY_GAP_S). The order turns by one ID
        # a cycle, so that cost falls on each ID in turn: at a fixed order, three replies of the last ID lost in a
        # row (1 % loss: about one 30-s run in thirty) aged its sample past safety.max_sensor_age_s.
        first = self.cycles % len(self._rotation)
        rows = self._rotation[first]
        order = self._orders[first]
        if torque is None:
            reply = self.bus.bulk_cycle(order, None, partial=not retry, extra_reads=monitor)
        else:
            goal_iq = np.minimum(np.maximum(torque / self.kt, -self.i_max), self.i_max)
            reply = self.bus.bulk_cycle(order, self._torque_mode, goal_iq=goal_iq[rows], partial=True,
                                        extra_reads=monitor)
        reply = reply.in_order(self.ids, self._reply_rows[first])
        stamp = time.monotonic()
        self.cycles += 1
        if self.cycles == 1:
            self.first_cycle = stamp
        self.last_cycle = stamp
        estop = reply.estop_ids()
        faults = {}
        late = reply.late
        if late is not None:  # the last cycle's lost replies, come after its deadline: its samples, not lost
            rows = np.array([self._row[i] for i in late.ids])
            self.loss.came_late(rows)
            older = self._stamps[rows] < late.sent_at  # never in place of a newer sample
            self._keep(rows[older], late, older, late.sent_at)
            self.late_replies += len(late.ids)
            estop = tuple(sorted(set(estop) | set(late.estop_ids())))
            faults.update(self._faults(late))
        answered = np.ones(len(self.ids), dtype=bool) if reply.answered is None else reply.answered
        self._keep(answered, reply, answered, stamp)
        self.loss.add(~answered)
        faults.update(self._faults(reply))
        if monitor:
            self._monitor_tick = 0
            self._monitored(reply, answered)
        return LegReading(self._position.copy(), self._velocity.copy(), self._iq * self.kt,
                          float(self._stamps.min()), self._stamps.copy(), estop, faults,
                          self._loss_problem(stamp))

    def _faults(self, reply) -> dict[int, tuple[str, ...]]:
        """ID -> flags of the replies reporting a fault bit (the E-stop bit apart)."""
        return {i: reply.flags(i) for i, error in zip(reply.ids, reply.error.tolist(), strict=True)
                if error & self._fault_bits}

    def silence(self, reading: LegReading, now: float, stalled=None) -> str | None:
        """The silence rule (`bruce_hw.leg_bus.silence`, with `stalled` the backend's joint_stalled_between, which
        leaves this port's held time out); but a port call the host held longer than safety.host_stall_max_s, or
        holds still, is a fault of its own: the motors held their last current that long."""
        oldest = float(reading.stamps.min())
        if now - oldest > self.host_stall_max_s:  # only then can a hold since the oldest sample be that long
            held = self.port_stalls.intervals(oldest, now)
            worst = max((end - start for start, end in held), default=0.0)
            if worst > self.host_stall_max_s:
                return (f"the host held its port {1e3 * worst:.1f} ms (requests not sent, replies not handed over: "
                        f"the kernel's tty work for the port not run) > safety.host_stall_max_s "
                        f"{1e3 * self.host_stall_max_s:g} ms")
        return silence(self.ids, reading, now, self.dt, self.max_age_s, stalled, oldest)

    def _held_since(self, now: float) -> float | None:
        """Since when the host has held the port call in progress, if it has (drivers.bear's `held_since`)."""
        bus = self.bus
        return bus.held_since(now) if bus is not None else None

    def _loss_problem(self, now: float) -> str | None:
        ages = now - self._stamps
        over = self.loss.over()
        if over.size:
            share = self.loss.share()
            text = (f"reply loss {', '.join(f'ID {self.ids[k]} {100 * share[k]:.1f} %' for k in over)} over the last "
                    f"{self.loss.window} cycles > safety.reply_loss_max {100 * self.loss.max_share:g} %")
            silent = [k for k in over if ages[k] > SILENT_TICKS * self.dt]
            if silent:  # a motor gone silent reaches the loss bound before the age bound when that one is wide
                return (f"no reply from ID(s) {ids_text(self.ids[k] for k in silent)} for "
                        f"{1e3 * float(ages[silent].max()):.1f} ms: {text}")
            return text
        return None

    def link_report(self) -> dict:
        """Cycles and lost replies per ID, for the run's summary and stats."""
        lost = {str(i): int(n) for i, n in zip(self.ids, self.loss.total.tolist(), strict=True)}
        total = int(self.loss.total.sum())
        return {"bus": self.name, "cycles": self.cycles, "replies_lost": lost, "replies_lost_total": total,
                "reply_loss_share": total / (self.cycles * len(self.ids)) if self.cycles else 0.0,
                "replies_late": self.late_replies,
                "watchdog_timeout": self.watchdog_count, "adapter": self.low_latency,
                "host_stalls": self.bus.stats.host_stalls if self.bus is not None else 0,
                "port_held": self.port_stalls.report()}

    def _monitored(self, reply, answered: np.ndarray) -> None:
        """The temperatures and voltages a bulk cycle brought (a BEAR that did not answer keeps its last ones).
        Warnings only, as BRUCE-OP."""
        hottest = np.max([reply.column(name) for name in MONITOR_REGISTERS[:3]], axis=0)
        voltage = reply.column("input_voltage")
        for k in np.flatnonzero(answered):
            device_id = self.ids[k]
            if hottest[k] > TEMPERATURE_WARN_C and not self.temperature[k] > TEMPERATURE_WARN_C:
                log.warning("%s: ID %d at %.0f C (> %.0f C)", self.name, device_id, hottest[k], TEMPERATURE_WARN_C)
            if voltage[k] < VOLTAGE_WARN_V and not self.voltage[k] < VOLTAGE_WARN_V:
                log.warning("%s: ID %d input %.1f V (< %.1f V)", self.name, device_id, voltage[k], VOLTAGE_WARN_V)
        self.temperature[answered] = hottest[answered]
        self.voltage[answered] = voltage[answered]
        self.monitor_count += 1

    def summary(self) -> str:
        span = self.last_cycle - self.first_cycle if self.cycles > 1 else math.nan
        rate = (self.cycles - 1) / span if span > 0 else math.nan
        stats = self.bus.stats if self.bus is not None else None
        lost = int(self.loss.total.sum())
        link = "" if stats is None else (f", {lost} replies lost, {self.late_replies} taken late, "
                                         f"{stats.retries} retries, "
                                         f"{stats.rejected_total} bytes/packets rejected, "
                                         f"{stats.host_stalls} sends or reads the host held "
                                         f"(worst {self.port_stalls.worst_s * 1e3:.1f} ms)")
        return f"{self.name}: {self.cycles} bulk cycles in {span:.2f} s ({rate:.0f} Hz){link}"


def actuator_position_limits(config: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per actuator, the range the joint box (joints.position_limits) reaches through the coupling, widened by
    POSITION_LIMIT_MARGIN: the BEARs' own position limits (their error bit 4 is the last line behind ours)."""
    a = config.coupling.actuator_from_joint
    mid, half = (config.q_upper + config.q_lower) / 2, (config.q_upper - config.q_lower) / 2
    center, reach = a @ mid, np.abs(a) @ half
    return center - reach - POSITION_LIMIT_MARGIN, center + reach + POSITION_LIMIT_MARGIN
