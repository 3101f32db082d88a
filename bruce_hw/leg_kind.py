"""What a leg bus kind provides (`LegKind`), and what its emulators give the emulated plant and bruce-emulate
(`LegEmulation`). A kind owns everything about its actuators that the rest does not share: the modules and device
files it needs (`missing_for_hw`), its `LegBus` for the hw backend, its emulators with their torque law, and its
diagnosis for bruce-hw-check. The kinds themselves: bruce_hw/legs/, registered in `bruce_hw.leg_kinds`."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    import numpy as np

    from bruce_hw.bus_report import BusReport
    from bruce_hw.config import RobotConfig
    from bruce_hw.leg_bus import LegBus, LegStartup


class LegKind(Protocol):
    """One kind of leg bus (bruce_hw/legs/<kind>.py), asked by name-free code: the hw backend (`uses`, `modules`,
    `ports`, `legs`), the emulated plant and bruce-emulate (`emulate`, `lockstep`), bruce-hw-check (`diagnose`)."""

    name: str                 # "bear", "can"
    modules: dict[str, str]   # module -> what it is needed for, beside the hw backend's own (hw.REQUIRED_MODULES)
    lockstep: bool            # whether its emulator's bus cycles can clock the plant (bruce-emulate --lockstep)

    def uses(self, config: RobotConfig) -> bool: ...
    def ports(self, config: RobotConfig) -> list[tuple[str, str]]: ...  # (config key, device file) that must exist
    def legs(self, config: RobotConfig, startup: LegStartup) -> LegBus: ...
    def emulate(self, config: RobotConfig, **options) -> LegEmulation: ...  # options: can_interface
    def diagnose(self, config: RobotConfig, rtt_cycles: int = 0) -> BusReport: ...


class LegEmulation(Protocol):
    """A kind's emulators as the emulated plant drives them (bruce_hw/emulation/plant.py) and bruce-emulate's fault
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
