"""The legs on MIT-protocol CAN motors (`buses.can`), the same `bruce_hw.leg_bus.LegBus` as the BEAR legs."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from bruce_hw.bus_startup import StartupError, ids_text
from bruce_hw.config import RobotConfig
from bruce_hw.leg_bus import LegReading, silence

log = logging.getLogger("bruce_hw.hw")

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
        raise StartupError([f"{self.name}: no reply from CAN motor ID(s) {ids_text(silent)} after {self.ping_rounds} "
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

    def silence(self, reading: LegReading, now: float, stalled=None) -> str | None:
        return silence(self.ids, reading, now, self.config.dt, self.config.safety.max_sensor_age_s, stalled)

    def summary(self) -> str:
        span = self.last_cycle - self.first_cycle if self.cycles > 1 else math.nan
        rate = (self.cycles - 1) / span if span > 0 else math.nan
        timeouts = sum(s.timeouts for s in self.group.stats.values()) if self.group is not None else 0
        return f"{self.name}: {self.cycles} cycles in {span:.2f} s ({rate:.0f} Hz), {timeouts} timeouts"
