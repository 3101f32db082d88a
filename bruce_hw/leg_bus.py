"""What the hw backend needs of a leg bus (BEARs on RS-485 or CAN motors): one reading type, one interface
(`LegBus`), and the helpers both buses share (the silence rule, pinging with retries)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from bruce_hw.bus_startup import ids_text

log = logging.getLogger("bruce_hw.hw")


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


class LegBus(Protocol):
    """A leg bus as the backend drives it: start-up (`open`, `configure`), `enable`/`disable`/`damp`, one `cycle`
    per tick (torques out, a `LegReading` back; None: read only), the silence rule, link figures, `close`."""

    name: str
    ids: tuple[int, ...]

    def open(self) -> None: ...
    def configure(self) -> None: ...
    def enable(self) -> None: ...
    def disable(self) -> None: ...
    def damp(self) -> None: ...
    def clear_watchdog(self) -> None: ...
    def close(self) -> None: ...
    def cycle(self, torque: np.ndarray | None, damping: bool = False, retry: bool = False) -> LegReading: ...
    def silence(self, reading: LegReading, now: float, stalled=None) -> str | None: ...
    def link_report(self) -> dict: ...
    def summary(self) -> str: ...


def silence(ids: tuple[int, ...], reading: LegReading, now: float, dt: float, max_age_s: float,
            stalled=None) -> str | None:
    """The actuators whose kept sample is too old at `now`. Judged one tick ahead: a sample that will be too old when
    the safety stage looks at it is silence here, where the bus and the IDs are known (the safety stage's own age
    check could only say "stale joint data"). The age is the time the process ran since the sample: `stalled(t0,
    t1)`, the seconds of [t0, t1] in which it was not run (`bruce_hw.host_witness`), is left out: in a host stall
    nobody asked the devices anything, so it is not their silence."""
    ages = now - reading.stamps
    if stalled is not None and np.any(ages + dt > max_age_s):
        ages = ages - np.array([stalled(float(t), now) for t in reading.stamps])
    stale = np.flatnonzero(ages + dt > max_age_s)
    if stale.size:
        age = float(ages[stale].max())
        return (f"no reply from ID(s) {ids_text(ids[k] for k in stale)} for {1e3 * age:.1f} ms "
                f"({1e3 * (age + dt):.1f} ms at the next tick > safety.max_sensor_age_s {1e3 * max_age_s:.1f} ms)")
    return None
