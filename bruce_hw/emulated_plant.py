"""Physics behind the emulators: BRUCE's MuJoCo model (the mock backend's, `bruce_hw.mock.MujocoBackend`) stepped
at 1 kHz in real time on a thread, so that the hw backend talks to emulated devices that move like the robot.

`Plant.step`: what the leg actuators were told (BEAR or CAN motor emulators) becomes joint torques through the
coupling, the model steps one loop period, and the measured state goes back to the leg emulators, the sense board
and, every 20th step, the Dynamixel emulator. `EmulatedRobot` starts the emulators a config describes with a plant
driving them (`bruce-emulate`, runtime/emulate_cli.py, is its command line); `unplug(bus)`, `set_reply_delay(bus,
fixed, jitter)` and `drain_events()` (every emulator's event log and its own, in time order) serve the tests. The
choices the emulators leave to the adapter are noted at the code that makes them.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import GroundTruth, JointCommand
from drivers.emulators.bear import EventLog
from drivers.sense import FIRMWARE_GRAVITY

REGISTER_REFRESH_STEPS = 100  # the BEARs' config registers (gains, current limit) are re-read this often
ARM_EVERY_STEPS = 20          # the arm bus runs at 50 Hz
# The bring-up stand (`stand on`): the base this far above its standing height (feet clear of the floor), held by a
# spring stiff beside the legs' Eq. 8 gains (mm and tenths of a degree under the legs' swing).
STAND_LIFT_M = 0.05
STAND_KP, STAND_KD = 5000.0, 200.0          # N/m, N s/m
STAND_KP_ROT, STAND_KD_ROT = 500.0, 20.0    # N m/rad, N m s/rad
MAX_CATCH_UP_STEPS = 10       # after a longer stall the lost time is dropped (`skipped_steps`), never run in a burst
BEAR_GAIN_REGISTERS = ("limit_i_max", "p_gain_force", "d_gain_force", "p_gain_position", "d_gain_position",
                       "p_gain_velocity")


class Plant:
    """The MuJoCo model behind the emulators given (any may be None). `start()` steps it in real time on a
    thread; without it, `step()` advances one loop period (for tests that want no thread)."""

    def __init__(self, config: RobotConfig, *, bear=None, dynamixel=None, sense=None, can: dict | None = None,
                 arm_time_constant_s: float = 0.05, lockstep: bool = False):
        self.config = config
        self.bear, self.dynamixel, self.sense = bear, dynamixel, sense
        self.can = dict(can or {})
        self.sim = MujocoBackend(config)
        self.sim.configure()
        self.sim.activate()
        model = self.sim.model
        self._stand_weight = np.array([0.0, 0.0, float(np.sum(model.body_mass)) * -float(model.opt.gravity[2])])
        self._stand_at = np.zeros(3)
        self.dt = config.dt
        self.n = config.n_joints
        self.kt = config.torque_per_amp
        self.damping_kd = config.safety.damping_kd
        self.coupling = config.coupling
        self.bear_ids = list(config.buses.bear.ids)
        self._can_slots = self._can_layout() if self.can else []
        self._registers: dict[str, np.ndarray] = {}
        self.arm_q = np.zeros(len(config.arms.names))
        self.arm_qd = np.zeros_like(self.arm_q)
        self.arm_time_constant_s = arm_time_constant_s
        self.held = True
        self.on_stand = False         # the base held in the air, as on a bring-up stand (`stand`)
        self.steps = 0                # physics steps run
        self.late_steps = 0           # steps started more than one period late
        self.skipped_steps = 0        # steps dropped after stalls
        self.lockstep = lockstep
        # Lockstep: the BEAR emulator's lock is the plant's, since its bulk hook steps the plant with that lock held
        # and every other path (place, ground truth) takes the plant's first: one lock, no order to get wrong.
        self._lock = bear._lock if lockstep and bear is not None else threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._hold()

    # -- lifecycle ---------------------------------------------------------------------------------------------
    def start(self) -> Plant:
        if self.lockstep:
            if self.bear is None:
                raise ValueError("lockstep needs a BEAR bus: its bulk cycles are the plant's clock")
            self.bear.on_bulk = self.step
            target = self._device_clocks
        else:
            target = self._run
        self._thread = threading.Thread(target=target, name="plant", daemon=True)
        self._thread.start()
        return self

    def _device_clocks(self) -> None:
        """Lockstep: the physics waits for the host, the devices' own timers do not. Every millisecond the BEARs'
        and the Dynamixels' watchdogs are checked (a silent host still ends in damping / stopped servos)."""
        while not self._stop.wait(self.dt):
            self.bear.check_watchdogs()
            check = getattr(self.dynamixel, "check_watchdogs", None)
            if check is not None:
                check()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def __enter__(self) -> Plant:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
        next_step = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_step:
                time.sleep(next_step - now)
                continue
            behind = now - next_step
            if behind > self.dt:
                self.late_steps += 1
                if behind > MAX_CATCH_UP_STEPS * self.dt:
                    missed = int(behind / self.dt)
                    self.skipped_steps += missed
                    next_step += missed * self.dt
            self.step()
            next_step += self.dt

    # -- the operator ------------------------------------------------------------------------------------------
    # Until a leg actuator is first enabled the robot is held still at the standing pose, feet on the floor (physics
    # paused, the IMU reads +g, every contact switch closed), as on the stand or in the hands before start-up; once
    # every leg actuator reads disabled again (the next start-up disables them) it is put back there and held. In
    # damping the physics runs: the robot sinks as it would.
    def place(self) -> None:
        """Put the robot back at the standing pose and hold it there until a leg actuator is enabled."""
        with self._lock:
            self._hold()

    def stand(self, on: bool) -> None:
        """On a bring-up stand (on): the base held STAND_LIFT_M above its standing height, level, by a stiff spring on
        its free joint (the stand's force, which the IMU feels as support), the feet in the air; off: free again."""
        with self._lock:
            self.on_stand = on
            self._hold()

    def _hold(self) -> None:
        self.sim.place(self.config.standing_pose)
        data = self.sim.data
        data.qfrc_applied[0:6] = 0.0
        if self.on_stand:
            data.qpos[2] += STAND_LIFT_M
            mujoco.mj_forward(self.sim.model, data)
            self._stand_at = data.qpos[0:3].copy()
        self.held = True
        self._publish_legs(self.config.standing_pose, np.zeros(self.n), np.zeros(self.n))
        if self.sense is not None:
            self.sense.set_measurement(accel=(0.0, 0.0, FIRMWARE_GRAVITY), gyro=(0.0, 0.0, 0.0),
                                       contacts=(not self.on_stand,) * 4)

    def _support_on_stand(self) -> None:
        """The stand's force on the base's free joint: a stiff, damped spring to the held position and to level
        (world-frame force; body-frame torque, as the free joint's rotational DOFs are)."""
        data = self.sim.data
        w, x, y, z = data.qpos[3:7]
        tilt = 2.0 * np.array([w * x + y * z, w * y - z * x, w * z + x * y])  # small-angle rotation from level (body)
        data.qfrc_applied[0:3] = STAND_KP * (self._stand_at - data.qpos[0:3]) - STAND_KD * data.qvel[0:3] + \
            self._stand_weight
        data.qfrc_applied[3:6] = -STAND_KP_ROT * tilt - STAND_KD_ROT * data.qvel[3:6]

    def ground_truth(self) -> GroundTruth:
        with self._lock:
            return self.sim.ground_truth()

    @property
    def nominal_base_height(self) -> float:
        return self.sim.nominal_base_height

    # -- one step ----------------------------------------------------------------------------------------------
    def step(self) -> None:
        with self._lock:
            tau_m, enabled, all_off = self._actuator_torques()
            if self.held:
                if enabled:
                    self.held = False
            elif all_off:
                self._hold()
            if not self.held:
                if self.on_stand:
                    self._support_on_stand()
                self.sim.write(JointCommand(tau_ff=self.coupling.joint_torques(tau_m)))
                state = self.sim.read()  # saturates per actuator through the coupling, steps the model
                q, qd = state.joints.q, state.joints.qd
                applied = self.coupling.actuator_torques(state.joints.tau)
                self._publish_legs(q, qd, applied)
                if self.sense is not None:
                    self.sense.set_measurement(accel=state.imu.accel, gyro=state.imu.gyro,
                                               contacts=state.contacts.contact)
            if self.dynamixel is not None and self.steps % ARM_EVERY_STEPS == 0:
                self._step_arms(ARM_EVERY_STEPS * self.dt)
            if self.lockstep and self.sense is not None:
                self.sense.tick()  # the IMU sample of this step, right behind the BEAR replies
            self.steps += 1

    def _actuator_torques(self) -> tuple[np.ndarray, bool, bool]:
        """Actuator torques (coupling column order), whether any leg actuator is enabled, whether all are off.

        BEAR torque per mode while torque_enable reads 1, gains taken as Nm/rad and Nm s/rad: torque (0)
        kt goal_iq; force (3) p_gain_force (goal_position - m) + d_gain_force (goal_velocity - md) + kt goal_iq;
        position (2) p_gain_position (goal_position - m) - d_gain_position md; velocity (1) p_gain_velocity
        (goal_velocity - md); clipped to kt limit_i_max. Damping (3): -safety.damping_kd md; off (0) or error (2):
        none. Reading the commands every step, held or not, also runs the BEAR watchdogs between packets, so an
        expiry is detected within a step even when the host has gone silent."""
        if self.can:
            return self._can_torques()
        if self.bear is None:
            return np.zeros(self.n), False, True
        if self.steps % REGISTER_REFRESH_STEPS == 0 or not self._registers:
            self._registers = {name: np.array([self.bear.register_value(i, name, "config") for i in self.bear_ids])
                               for name in BEAR_GAIN_REGISTERS}
        c = self.bear.commands(self.bear_ids)
        r = self._registers
        m, md = self._m, self._md
        mode, on = c["mode"], c["torque_enable"]
        tau = np.zeros(self.n)
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

    def _publish_legs(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        m, md = self.coupling.actuator_positions(q), self.coupling.actuator_positions(qd)
        self._m, self._md = m, md  # what the actuators measure, for their own PD (force/position modes)
        if self.bear is not None:
            self.bear.set_measured_many(self.bear_ids, m, md, tau_m / self.kt)
        for slot in self._can_slots:
            slot.emulator.set_state(slot.map.motor_position(m[slot.index]), slot.map.motor_velocity(md[slot.index]))

    # -- CAN legs ----------------------------------------------------------------------------------------------
    def _can_layout(self) -> list[_CanSlots]:
        from drivers.can_motor import ActuatorMap

        motors = list(self.config.buses.can.motors)
        slots = []
        for channel, emulator in self.can.items():
            index = [k for k, motor in enumerate(motors) if motor.channel == channel]
            if [motors[k].id for k in index] != list(emulator.motor_ids):
                raise ValueError(f"CAN emulator on {channel} hosts {emulator.motor_ids}, the config puts "
                                 f"{[motors[k].id for k in index]} there")
            mine = [motors[k] for k in index]
            amap = ActuatorMap.of(len(mine), [m.gear for m in mine], [m.sign for m in mine], [m.offset for m in mine])
            slots.append(_CanSlots(emulator, np.array(index), amap))
        return slots

    def _can_torques(self) -> tuple[np.ndarray, bool, bool]:
        tau = np.zeros(self.n)
        engaged = False
        for slot in self._can_slots:
            tau[slot.index] = slot.map.actuator_torque(slot.emulator.torques())
            engaged |= any(slot.emulator.in_motor_mode(mid) for mid in slot.emulator.motor_ids)
        return tau, engaged, not engaged

    # -- arms --------------------------------------------------------------------------------------------------
    def _step_arms(self, dt: float) -> None:
        """The arms are locked in the model (as in the paper): a servo with torque on follows its goal with a
        first-order lag of `arm_time_constant_s`, from the zero pose."""
        goal = self.dynamixel.goal_joint_positions()
        on = self.dynamixel.torque_enabled_all()
        share = 1.0 - math.exp(-dt / self.arm_time_constant_s)
        step = np.where(on, (goal - self.arm_q) * share, 0.0)
        self.arm_q = self.arm_q + step
        self.arm_qd = step / dt
        self.dynamixel.set_joint_state(self.arm_q, self.arm_qd)


@dataclass
class _CanSlots:
    emulator: object
    index: np.ndarray
    map: object


@dataclass
class EmulatedRobot:
    """Every device a config describes, emulated, with a plant driving them. CAN motors go on python-can's
    `can_interface` (default "virtual": reachable from this process only)."""

    config: RobotConfig
    sense_command_poll_s: float = 0.05
    can_interface: str = "virtual"
    lockstep: bool = False  # the physics steps once per host BULK_COMM (Plant(lockstep)), not on the wall clock
    bear: object = None
    dynamixel: object = None
    sense: object = None
    can: dict = field(default_factory=dict)
    plant: Plant | None = None
    events: EventLog = field(default_factory=EventLog)  # the robot's own: unplug / plug of buses without a log
    unplugged: set[str] = field(default_factory=set)

    def start(self) -> EmulatedRobot:
        from drivers.emulators.dynamixel import DynamixelBusEmulator
        from drivers.emulators.sense import SenseBoardEmulator

        cfg = self.config
        try:
            if cfg.buses.can.motors:
                from drivers.emulators.can_motor import emulators_from_config

                self.can = emulators_from_config(cfg.buses.can, interface=self.can_interface)
            else:
                from drivers.emulators.bear import BearBusEmulator

                self.bear = BearBusEmulator(cfg.buses.bear.ids).start()
            self.dynamixel = DynamixelBusEmulator(cfg.buses.dynamixel.ids, signs=cfg.arms.servo_signs,
                                                  track_goals=False).start()
            # The real firmware reads commands once a second while streaming; a shorter poll keeps repeated
            # start-ups and shutdowns from waiting that second each.
            self.sense = SenseBoardEmulator(command_poll_s=self.sense_command_poll_s, lockstep=self.lockstep).start()
            self.plant = Plant(cfg, bear=self.bear, dynamixel=self.dynamixel, sense=self.sense,
                               can=self.can, lockstep=self.lockstep).start()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        if self.plant is not None:
            self.plant.close()
        for device in (self.bear, self.dynamixel, self.sense, *self.can.values()):
            if device is not None:
                device.close()

    def __enter__(self) -> EmulatedRobot:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def unplug(self, bus: str, unplugged: bool = True) -> None:
        """Cut (`unplugged=False`: mend) a bus's wire: "bear" (BearBusEmulator.unplug: nothing reaches the BEARs,
        nothing is answered), "dynamixel" (every servo silenced: neither answers nor acts; mending it makes every
        servo answer again, as `silence(..., False)` with all IDs), "sense" (the board stops streaming, as
        `set_silent`; mending it resumes the stream). The BEAR emulator logs it itself; the others here."""
        if bus == "bear" and self.bear is not None:
            self.bear.unplug(unplugged)
        elif bus == "dynamixel" and self.dynamixel is not None:
            self.dynamixel.silence(self.config.buses.dynamixel.ids, unplugged)
        elif bus == "sense" and self.sense is not None:
            self.sense.set_silent(unplugged)
        else:
            raise ValueError(f"no emulated bus {bus!r} to unplug (bear, dynamixel or sense, as the config has)")
        if bus != "bear":
            self.events.add(f"{bus} {'unplug' if unplugged else 'plug'}")
        (self.unplugged.add if unplugged else self.unplugged.discard)(bus)

    def set_reply_delay(self, bus: str, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """How late a bus answers from now on: "bear", "dynamixel" (each answer starts fixed + U(0, jitter) s after
        its request arrived) or "sense" (each packet leaves that much later); see drivers/emulators/reply_delay.py.
        Logged as an event (`dynamixel reply delay 2 ms + U(0, 1 ms)`; the BEAR emulator logs its own)."""
        device = {"bear": self.bear, "dynamixel": self.dynamixel, "sense": self.sense}.get(bus)
        if device is None:
            raise ValueError(f"no emulated bus {bus!r} to delay (bear, dynamixel or sense, as the config has)")
        device.set_reply_delay(fixed, jitter, seed)
        if bus != "bear":
            self.events.add(f"{bus} reply delay {device.reply_delay.text()}")

    def reply_delays(self) -> dict[str, list[float]]:
        """{bus: [fixed, jitter]} in seconds, for every bus that has a reply delay setting."""
        return {bus: device.reply_delay.describe() for bus, device in
                (("bear", self.bear), ("dynamixel", self.dynamixel), ("sense", self.sense)) if device is not None}

    def drain_events(self) -> list[tuple[float, str]]:
        """Every emulator's events since the last drain (those with a `drain_events`) and the robot's own, in time
        order: (time.monotonic() stamp, text)."""
        out = self.events.drain()
        for device in (self.bear, self.dynamixel, self.sense, *self.can.values()):
            drain = getattr(device, "drain_events", None)
            if drain is not None:
                out += drain()
        out.sort(key=lambda event: event[0])
        return out

    def port_overrides(self) -> list[str]:
        """`KEY=VALUE` config overrides that point the hw backend at these emulators."""
        out = []
        if self.bear is not None:
            out.append(f"buses.bear.port={self.bear.path}")
        out += [f"buses.dynamixel.port={self.dynamixel.path}", f"buses.sense.port={self.sense.path}"]
        if self.can:
            out.append(f"buses.can.interface={self.can_interface}")
        return out

    def devices(self) -> list[tuple[str, str]]:
        """(what, where) of every emulated device, for people."""
        cfg = self.config
        out = []
        if self.bear is not None:
            out.append((f"BEAR bus (IDs {_ids(cfg.buses.bear.ids)})", self.bear.path))
        for channel, emulator in self.can.items():
            out.append((f"CAN motors (IDs {_ids(emulator.motor_ids)})", f"{self.can_interface} channel {channel}"))
        out.append((f"Dynamixel bus (IDs {_ids(cfg.buses.dynamixel.ids)})", self.dynamixel.path))
        out.append(("sense board", self.sense.path))
        return out


def _ids(ids) -> str:
    return ", ".join(str(i) for i in ids)
