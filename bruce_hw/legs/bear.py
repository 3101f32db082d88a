"""Legs on Koala BEARs over RS-485 (`buses.bear`), the default leg bus kind: the hw backend's `BearLegs`
(bruce_hw/bear_legs.py), the byte-exact emulator (drivers/emulators/bear.py) with the BEARs' torque law for the
emulated plant (`BearEmulation`), and bruce-hw-check's diagnosis (bruce_hw/legs/bear_check.py)."""

from __future__ import annotations

import numpy as np

from bruce_hw.bear_legs import DEFAULT_REPLY_TIMEOUT_S, BearLegs
from bruce_hw.bus_report import BusReport
from bruce_hw.config import RobotConfig
from bruce_hw.leg_bus import LegStartup
from bruce_hw.legs.bear_check import check_bear

REGISTER_REFRESH_STEPS = 100  # the BEARs' config registers (gains, current limit) are re-read this often
BEAR_GAIN_REGISTERS = ("limit_i_max", "p_gain_force", "d_gain_force", "p_gain_position", "d_gain_position",
                       "p_gain_velocity")


class BearKind:
    name = "bear"  # as bruce-emulate's fault commands name the bus
    modules = {"drivers.bear": "BEAR actuators over RS-485 (buses.bear)"}
    lockstep = True  # its bulk cycles can be the emulated plant's clock

    def uses(self, config: RobotConfig) -> bool:
        """Every config has a buses.bear section: BEAR legs are the default, the kinds registered after are asked
        first (bruce_hw.leg_kinds.leg_kind_of)."""
        return True

    def ports(self, config: RobotConfig) -> list[tuple[str, str]]:
        return [("buses.bear.port", config.buses.bear.port)]

    def legs(self, config: RobotConfig, startup: LegStartup) -> BearLegs:
        return BearLegs(config, ping_rounds=startup.ping_rounds, ping_retry_s=startup.ping_retry_s,
                        clear_attempts=startup.clear_attempts, reply_timeout_s=startup.reply_timeout_s
                        or config.buses.bear.reply_timeout_s or DEFAULT_REPLY_TIMEOUT_S)

    def emulate(self, config: RobotConfig, **options) -> BearEmulation:
        return BearEmulation(config)

    def diagnose(self, config: RobotConfig, rtt_cycles: int = 0) -> BusReport:
        return check_bear(config, rtt_cycles)


class BearEmulation:
    """The BEAR bus emulator (`device`) as the emulated plant drives it and bruce-emulate's commands reach it."""

    bus = BearKind.name

    def __init__(self, config: RobotConfig):
        from drivers.emulators.bear import BearBusEmulator

        self.ids = list(config.buses.bear.ids)
        self.kt = config.torque_per_amp
        self.damping_kd = config.safety.damping_kd
        self.device = BearBusEmulator(self.ids).start()
        # Lockstep: the plant takes this lock for its own paths too, since the bulk hook steps the plant with it
        # held: one lock, no order to get wrong.
        self.lock = self.device._lock
        self._registers: dict[str, np.ndarray] = {}
        self._steps = 0

    # -- the plant
    def clock(self, step) -> None:
        """Lockstep: `step` runs once per host bulk cycle, after the replies are out."""
        self.device.on_bulk = step

    def check_watchdogs(self) -> None:
        self.device.check_watchdogs()

    def torques(self, m: np.ndarray, md: np.ndarray) -> tuple[np.ndarray, bool, bool]:
        """Actuator torques (coupling column order), whether any BEAR is enabled, whether all are off; called once
        per plant step with what the actuators measure (m, md).

        Torque per mode while torque_enable reads 1, gains taken as Nm/rad and Nm s/rad: torque (0) kt goal_iq;
        force (3) p_gain_force (goal_position - m) + d_gain_force (goal_velocity - md) + kt goal_iq; position (2)
        p_gain_position (goal_position - m) - d_gain_position md; velocity (1) p_gain_velocity (goal_velocity - md);
        clipped to kt limit_i_max. Damping (3): -safety.damping_kd md; off (0) or error (2): none. Reading the
        commands every step, held or not, also runs the BEAR watchdogs between packets, so an expiry is detected
        within a step even when the host has gone silent."""
        if self._steps % REGISTER_REFRESH_STEPS == 0 or not self._registers:
            self._registers = {name: np.array([self.device.register_value(i, name, "config") for i in self.ids])
                               for name in BEAR_GAIN_REGISTERS}
        self._steps += 1
        c = self.device.commands(self.ids)
        r = self._registers
        mode, on = c["mode"], c["torque_enable"]
        tau = np.zeros(len(self.ids))
        for value in set(mode.tolist()):  # only the modes in use are computed (the physics runs this every step)
            if value == 0:
                mode_tau = self.kt * c["goal_iq"]
            elif value == 3:
                mode_tau = (r["p_gain_force"] * (c["goal_position"] - m) + r["d_gain_force"] * (c["goal_velocity"] - md)
                            + self.kt * c["goal_iq"])
            elif value == 2:
                mode_tau = r["p_gain_position"] * (c["goal_position"] - m) - r["d_gain_position"] * md
            elif value == 1:
                mode_tau = r["p_gain_velocity"] * (c["goal_velocity"] - md)
            else:
                continue
            tau = np.where(mode == value, mode_tau, tau)
        limit = self.kt * r["limit_i_max"]
        tau = np.minimum(np.maximum(tau, -limit), limit)  # np.clip and np.nan_to_num cost ~20 us at this size
        tau[np.isnan(tau)] = 0.0
        tau = np.where(on == 1, tau, np.where(on == 3, -self.damping_kd * md, 0.0))
        return tau, bool(np.any(on == 1)), bool(np.all(on == 0))

    def publish(self, m: np.ndarray, md: np.ndarray, tau_m: np.ndarray) -> None:
        """What the BEARs measure: actuator positions, velocities and torques (as currents)."""
        self.device.set_measured_many(self.ids, m, md, tau_m / self.kt)

    # -- bruce-emulate and the tests
    def close(self) -> None:
        self.device.close()

    def drain_events(self) -> list[tuple[float, str]]:
        return self.device.drain_events()

    def silence(self, ids, silent: bool) -> None:
        self.device.silence(ids, silent)

    def unplug(self, unplugged: bool) -> None:
        self.device.unplug(unplugged)  # logged by the emulator

    def set_reply_delay(self, fixed: float, jitter: float, seed=None) -> None:
        self.device.set_reply_delay(fixed, jitter, seed)  # logged by the emulator

    @property
    def reply_delay(self):
        return self.device.reply_delay

    def set_reply_loss(self, drop: float, corrupt: float, seed: int | None = None) -> None:
        self.device.set_reply_loss(drop, corrupt, seed)

    def set_estop(self, on: bool) -> None:
        self.device.set_estop(on)

    def status(self) -> dict:
        c = self.device.commands(self.ids)
        return {"ids": list(self.ids), "mode": c["mode"].tolist(), "torque_enable": c["torque_enable"].tolist(),
                "error": c["error"].tolist(), "bulk_comm": self.device.requests["BULK_COMM"],
                "replies": self.device.replies, "reply_losses": dict(self.device.reply_losses)}

    def counters(self) -> str:
        text = f"BEAR bus: {self.device.requests['BULK_COMM']} BULK_COMM"
        losses = self.device.reply_losses
        if losses:
            text += (f", {sum(losses.values())} of {self.device.replies} replies spoiled ("
                     + ", ".join(f"{n} {kind}" for kind, n in sorted(losses.items())) + ")")
        return text

    def devices(self) -> list[tuple[str, str]]:
        return [(f"BEAR bus (IDs {', '.join(map(str, self.ids))})", self.device.path)]

    def port_overrides(self) -> list[str]:
        return [f"buses.bear.port={self.device.path}"]

    def hint(self, run_here: str) -> str | None:
        """Nothing to add: the BEAR bus is a pseudo-terminal that any process opens."""
        return None
