"""The kinds of leg bus the hw path knows, and which one a robot config uses (`leg_kind_of`).

A kind (`LegKind`, one module under bruce_hw/legs/) owns everything about its actuators that the rest does not
share: the modules and device files it needs (`missing_for_hw`), its `LegBus` for the hw backend, its emulators with
their torque law for the emulated plant (`LegEmulation`), and its diagnosis for bruce-hw-check. The hw backend, the
emulated plant, bruce-hw-check and bruce-emulate look the kind up here instead of naming BEARs or CAN motors.
Adding one: docs/extending_leg_actuator.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from bruce_hw.config import RobotConfig
from bruce_hw.legs.bear import BearKind
from bruce_hw.legs.can import CanKind

if TYPE_CHECKING:
    import numpy as np

    from bruce_hw.bus_report import BusReport
    from bruce_hw.leg_bus import LegBus, LegStartup


class LegEmulation(Protocol):
    """A kind's emulators as the emulated plant drives them (bruce_hw/emulated_plant.py) and bruce-emulate's fault
    commands reach them (`silence`; `unplug`, `set_reply_delay`, `set_reply_loss`, `set_estop` where the kind has
    them). Actuator order: coupling columns."""

    bus: str        # the kind's name: how fault commands and status name the bus
    device: object  # the emulator(s) themselves, for tests
    lock: object    # lockstep: the lock the plant shares with the emulator that clocks it (None: cannot clock)

    def clock(self, step) -> None: ...  # lockstep: call `step` once per host bus cycle, holding `lock`
    def check_watchdogs(self) -> None: ...  # lockstep: the devices' own timers, run every millisecond
    def torques(self, m: np.ndarray, md: np.ndarray) -> tuple[np.ndarray, bool, bool]: ...  # the plant law
    def publish(self, m: np.ndarray, md: np.ndarray, tau_m: np.ndarray) -> None: ...  # what the actuators measure
    def close(self) -> None: ...
    def drain_events(self) -> list[tuple[float, str]]: ...
    def silence(self, ids, silent: bool) -> None: ...
    def status(self) -> dict: ...
    def counters(self) -> str: ...  # for bruce-emulate's last line ("" for none)
    def devices(self) -> list[tuple[str, str]]: ...  # (what, where) for people
    def port_overrides(self) -> list[str]: ...  # the `--set KEY=VALUE`s that point the hw backend at them
    def hint(self, run_here: str) -> str | None: ...  # what a person must know to reach them, if anything


class LegKind(Protocol):
    name: str                 # "bear", "can"
    modules: dict[str, str]   # module -> what it is needed for, beside the hw backend's own (hw.REQUIRED_MODULES)
    lockstep: bool            # whether its emulator's bus cycles can clock the plant (bruce-emulate --lockstep)

    def uses(self, config: RobotConfig) -> bool: ...
    def ports(self, config: RobotConfig) -> list[tuple[str, str]]: ...  # (config key, device file) that must exist
    def legs(self, config: RobotConfig, startup: LegStartup) -> LegBus: ...
    def emulate(self, config: RobotConfig, **options) -> LegEmulation: ...  # options: can_interface
    def diagnose(self, config: RobotConfig, rtt_cycles: int = 0) -> BusReport: ...


LEG_KINDS: dict[str, LegKind] = {}


def register_leg_kind(kind: LegKind) -> LegKind:
    """Make `kind` known; it is asked before every kind registered earlier (`leg_kind_of`)."""
    if kind.name in LEG_KINDS:
        raise ValueError(f"a leg kind named {kind.name!r} is registered already")
    LEG_KINDS[kind.name] = kind
    return kind


def leg_kind_of(config: RobotConfig) -> LegKind:
    """The kind of the config's legs: the last registered one that `uses` it. Asking the newest first lets a kind
    claim configs that an earlier, broader one would take: the BEAR legs take every config (the default)."""
    for kind in reversed(LEG_KINDS.values()):
        if kind.uses(config):
            return kind
    raise ValueError(f"{config.path}: no leg kind uses this config (known: {', '.join(LEG_KINDS)})")


register_leg_kind(BearKind())  # first: the default
register_leg_kind(CanKind())
