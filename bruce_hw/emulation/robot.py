"""The emulated robot (`EmulatedRobot`): every device a config describes, emulated, with a plant driving them
(`bruce_hw.emulation.plant.Plant`, on a thread here or in a process of its own, `PhysicsProcess`); `bruce-emulate`
(runtime/emulate_cli.py) is its command line. `unplug(bus)`, `set_reply_delay(bus, fixed, jitter)` and
`drain_events()` (every emulator's event log and its own, in time order) serve the tests. The choices the emulators
leave to the adapter are noted at the code that makes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from bruce_hw.config import RobotConfig
from bruce_hw.emulation.plant import Plant
from bruce_hw.leg_kinds import leg_kind_of
from drivers.emulators.bear import EventLog

if TYPE_CHECKING:
    from bruce_hw.emulation.physics_process import PhysicsProcess
    from bruce_hw.leg_kind import LegEmulation


@dataclass
class EmulatedRobot:
    """Every device a config describes, emulated, with a plant driving them: the legs' emulators are their kind's
    (`legs`, bruce_hw.leg_kinds). CAN motors go on python-can's `can_interface` (default "virtual": reachable from
    this process only)."""

    config: RobotConfig
    sense_command_poll_s: float = 0.05
    can_interface: str = "virtual"
    lockstep: bool = False  # the physics steps once per host bus cycle (Plant(lockstep)), not on the wall clock
    physics_process: bool = False  # on the wall clock, the physics in a child process (PhysicsProcess), not a thread
    legs: LegEmulation | None = None
    dynamixel: object = None
    sense: object = None
    plant: Plant | PhysicsProcess | None = None
    events: EventLog = field(default_factory=EventLog)  # the robot's own: unplug / plug of buses without a log
    unplugged: set[str] = field(default_factory=set)

    def start(self) -> EmulatedRobot:
        from drivers.emulators.dynamixel import DynamixelBusEmulator
        from drivers.emulators.sense import SenseBoardEmulator

        cfg = self.config
        try:
            self.legs = leg_kind_of(cfg).emulate(cfg, can_interface=self.can_interface)
            self.dynamixel = DynamixelBusEmulator(cfg.buses.dynamixel.ids, signs=cfg.arms.servo_signs,
                                                  track_goals=False).start()
            # The real firmware reads commands once a second while streaming; a shorter poll keeps repeated
            # start-ups and shutdowns from waiting that second each.
            self.sense = SenseBoardEmulator(command_poll_s=self.sense_command_poll_s, lockstep=self.lockstep).start()
            if self.physics_process and not self.lockstep:
                from bruce_hw.emulation.physics_process import PhysicsProcess

                self.plant = PhysicsProcess(cfg, legs=self.legs, dynamixel=self.dynamixel, sense=self.sense).start()
            else:
                self.plant = Plant(cfg, legs=self.legs, dynamixel=self.dynamixel, sense=self.sense,
                                   lockstep=self.lockstep).start()
        except BaseException:
            self.close()
            raise
        return self

    # The legs' emulators under the names the tests and tools reach them by: the BEAR bus emulator (None when the
    # legs are of another kind), the CAN motor emulators by channel ({} when they are not).
    @property
    def bear(self):
        return self.legs.device if self.legs is not None and self.legs.bus == "bear" else None

    @property
    def can(self) -> dict:
        return self.legs.device if self.legs is not None and self.legs.bus == "can" else {}

    def close(self) -> None:
        if self.plant is not None:
            self.plant.close()
        for device in (self.legs, self.dynamixel, self.sense):
            if device is not None:
                device.close()

    def __enter__(self) -> EmulatedRobot:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _leg_bus(self, bus: str, what: str):
        """The legs' emulation when `bus` names it and it can do `what` (a method name); else None."""
        legs = self.legs
        return legs if legs is not None and legs.bus == bus and hasattr(legs, what) else None

    def unplug(self, bus: str, unplugged: bool = True) -> None:
        """Cut (`unplugged=False`: mend) a bus's wire: the legs' where their kind can ("bear": BearBusEmulator.unplug,
        nothing reaches the BEARs, nothing is answered), "dynamixel" (every servo silenced: neither answers nor acts;
        mending it makes every servo answer again, as `silence(..., False)` with all IDs), "sense" (the board stops
        streaming, as `set_silent`; mending it resumes the stream). The legs' emulator logs it itself; the others
        here."""
        legs = self._leg_bus(bus, "unplug")
        if legs is not None:
            legs.unplug(unplugged)
        elif bus == "dynamixel" and self.dynamixel is not None:
            self.dynamixel.silence(self.config.buses.dynamixel.ids, unplugged)
        elif bus == "sense" and self.sense is not None:
            self.sense.set_silent(unplugged)
        else:
            raise ValueError(f"no emulated bus {bus!r} to unplug (bear, dynamixel or sense, as the config has)")
        if legs is None:
            self.events.add(f"{bus} {'unplug' if unplugged else 'plug'}")
        (self.unplugged.add if unplugged else self.unplugged.discard)(bus)

    def _delayable(self) -> dict:
        """{bus: device} of every bus that has a reply delay setting."""
        legs = self.legs if self.legs is not None and hasattr(self.legs, "set_reply_delay") else None
        return {bus: device for bus, device in ((getattr(legs, "bus", None), legs), ("dynamixel", self.dynamixel),
                                                ("sense", self.sense)) if device is not None}

    def set_reply_delay(self, bus: str, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """How late a bus answers from now on: the legs' where their kind can ("bear"), "dynamixel" (each answer
        starts fixed + U(0, jitter) s after its request arrived) or "sense" (each packet leaves that much later);
        see drivers/emulators/reply_delay.py. Logged as an event (`dynamixel reply delay 2 ms + U(0, 1 ms)`; the
        legs' emulator logs its own)."""
        device = self._delayable().get(bus)
        if device is None:
            raise ValueError(f"no emulated bus {bus!r} to delay (bear, dynamixel or sense, as the config has)")
        device.set_reply_delay(fixed, jitter, seed)
        if device is not self.legs:
            self.events.add(f"{bus} reply delay {device.reply_delay.text()}")

    def reply_delays(self) -> dict[str, list[float]]:
        """{bus: [fixed, jitter]} in seconds, for every bus that has a reply delay setting."""
        return {bus: device.reply_delay.describe() for bus, device in self._delayable().items()}

    def drain_events(self) -> list[tuple[float, str]]:
        """Every emulator's events since the last drain (those with a `drain_events`) and the robot's own, in time
        order: (time.monotonic() stamp, text)."""
        out = self.events.drain()
        for device in (self.legs, self.dynamixel, self.sense):
            drain = getattr(device, "drain_events", None)
            if drain is not None:
                out += drain()
        out.sort(key=lambda event: event[0])
        return out

    def port_overrides(self) -> list[str]:
        """`KEY=VALUE` config overrides that point the hw backend at these emulators."""
        return [*self.legs.port_overrides(), f"buses.dynamixel.port={self.dynamixel.path}",
                f"buses.sense.port={self.sense.path}"]

    def devices(self) -> list[tuple[str, str]]:
        """(what, where) of every emulated device, for people."""
        return [*self.legs.devices(), (f"Dynamixel bus (IDs {_ids(self.config.buses.dynamixel.ids)})",
                                       self.dynamixel.path), ("sense board", self.sense.path)]


def _ids(ids) -> str:
    return ", ".join(str(i) for i in ids)
