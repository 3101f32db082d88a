"""What the hw backend needs of a leg bus (BEARs on RS-485, CAN motors, any kind in `bruce_hw.leg_kinds`): one
reading type, one interface (`LegBus`), the start-up options every kind is built with (`LegStartup`), and the
helpers the buses share (the silence rule)."""

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


@dataclass(frozen=True)
class LegStartup:
    """The hw backend's start-up options for its leg bus (HwBackend's keywords); a kind takes those it has use for."""

    ping_rounds: int = 7
    ping_retry_s: float = 0.5
    clear_attempts: int = 6               # BEAR: tries at clearing a device's latched errors
    reply_timeout_s: float | None = None  # BEAR: a bulk cycle's reply wait; None: the config's, else the driver's


class LegBus(Protocol):
    """A leg bus as the backend drives it: start-up (`open`, `configure`), `enable`/`disable`/`damp`, one `cycle`
    per tick (torques out, a `LegReading` back; None: read only), the silence rule, link figures, `close`.
    Optional: `port_stalls`, a `bruce_hw.host_witness.StallLog` of the time the host held the bus's own I/O (a
    serial port's flush waiting in the kernel): the backend leaves it out of the joint data's age."""

    kind: str                 # what the bus is, for messages that name it without its port ("BEAR bus")
    name: str                 # the bus and where it is ("BEAR bus /dev/ttyUSB0")
    ids: tuple[int, ...]      # actuator order: coupling columns
    temperature: np.ndarray   # hottest sensor per actuator (NaN: not measured), refreshed ...
    monitor_count: int        # ... whenever this count moves on

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
            stalled=None, oldest: float | None = None) -> str | None:
    """The actuators whose kept sample is too old at `now`. Judged one tick ahead: a sample that will be too old when
    the safety stage looks at it is silence here, where the bus and the IDs are known (the safety stage's own age
    check could only say "stale joint data"). The age is the time the process ran since the sample: `stalled(t0,
    t1)`, the seconds of [t0, t1] in which it was not run (`bruce_hw.host_witness`), is left out: in a host stall
    nobody asked the devices anything, so it is not their silence. `oldest`: the oldest stamp, if the caller has it."""
    oldest = float(reading.stamps.min()) if oldest is None else oldest
    if now - oldest + dt <= max_age_s:  # every tick but a silent one: no sample can be stale (stalls only shorten ages)
        return None
    ages = now - reading.stamps
    if stalled is not None:  # the oldest is past the bound: the stalls decide
        ages = ages - np.array([stalled(float(t), now) for t in reading.stamps])
    stale = np.flatnonzero(ages + dt > max_age_s)
    if stale.size:
        age = float(ages[stale].max())
        return (f"no reply from ID(s) {ids_text(ids[k] for k in stale)} for {1e3 * age:.1f} ms "
                f"({1e3 * (age + dt):.1f} ms at the next tick > safety.max_sensor_age_s {1e3 * max_age_s:.1f} ms)")
    return None
