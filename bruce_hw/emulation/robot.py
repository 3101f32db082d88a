"""Physics behind the emulators: BRUCE's MuJoCo model (the mock backend's, `bruce_hw.mock.MujocoBackend`) stepped
at 1 kHz in real time on a thread, so that the hw backend talks to emulated devices that move like the robot.

`Plant.step`: what the leg actuators were told becomes actuator torques by their kind's law (`LegEmulation.torques`,
bruce_hw/legs/; the BEARs' torque law is there, CAN motors compute their own), then joint torques through the
coupling, the model steps one loop period, and the measured state goes back to the leg emulators, the sense board
and, every 20th step, the Dynamixel emulator. `EmulatedRobot` starts the emulators a config describes with a plant
driving them (`bruce-emulate`, runtime/emulate_cli.py, is its command line); `unplug(bus)`, `set_reply_delay(bus,
fixed, jitter)` and `drain_events()` (every emulator's event log and its own, in time order) serve the tests. The
choices the emulators leave to the adapter are noted at the code that makes them.
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.leg_kinds import leg_kind_of
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import GroundTruth, JointCommand
from drivers.emulators.bear import EventLog
from drivers.sense_codec import FIRMWARE_GRAVITY

if TYPE_CHECKING:
    from bruce_hw.leg_kind import LegEmulation

ARM_EVERY_STEPS = 20          # the arm bus runs at 50 Hz
# The bring-up stand (`stand on`): the base this far above its standing height (feet clear of the floor), held by a
# spring stiff beside the legs' Eq. 8 gains (mm and tenths of a degree under the legs' swing).
STAND_LIFT_M = 0.05
STAND_KP, STAND_KD = 5000.0, 200.0          # N/m, N s/m
STAND_KP_ROT, STAND_KD_ROT = 500.0, 20.0    # N m/rad, N m s/rad
PHYSICS_THREAD_NAME = "bruce-physics"  # the stepping thread's name in `ps -L` / `top -H` (bruce-emulate runs it apart)
MAX_CATCH_UP_STEPS = 10       # after a longer stall the lost time is dropped (`skipped_steps`), never run in a burst


class Plant:
    """The MuJoCo model behind the emulators given (any may be None). `start()` steps it in real time on a
    thread; without it, `step()` advances one loop period (for tests that want no thread)."""

    def __init__(self, config: RobotConfig, *, legs: LegEmulation | None = None, dynamixel=None, sense=None,
                 arm_time_constant_s: float = 0.05, lockstep: bool = False):
        self.config = config
        self.legs, self.dynamixel, self.sense = legs, dynamixel, sense
        self.sim = MujocoBackend(config)
        self.sim.configure()
        self.sim.activate()
        model = self.sim.model
        self._stand_weight = np.array([0.0, 0.0, float(np.sum(model.body_mass)) * -float(model.opt.gravity[2])])
        self._stand_at = np.zeros(3)
        self.dt = config.dt
        self.n = config.n_joints
        self.coupling = config.coupling
        self.arm_q = np.zeros(len(config.arms.names))
        self.arm_qd = np.zeros_like(self.arm_q)
        self.arm_time_constant_s = arm_time_constant_s
        self.held = True
        self.on_stand = False         # the base held in the air, as on a bring-up stand (`stand`)
        self.steps = 0                # physics steps run
        self.late_steps = 0           # steps started more than one period late
        self.skipped_steps = 0        # steps dropped after stalls
        self.lockstep = lockstep
        # Lockstep: the clocking leg emulator's lock is the plant's, since its bus cycle hook steps the plant with that
        # lock held and every other path (place, ground truth) takes the plant's first: one lock, no order to get wrong.
        clocked = lockstep and legs is not None and legs.lock is not None
        self._lock = legs.lock if clocked else threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._hold()

    # -- lifecycle ---------------------------------------------------------------------------------------------
    def start(self) -> Plant:
        if self.lockstep:
            if self.legs is None or self.legs.lock is None:
                raise ValueError("lockstep needs leg emulators whose bus cycles can be the plant's clock (BEAR legs)")
            self.legs.clock(self.step)
            target = self._device_clocks
        else:
            target = self._run
        self._thread = threading.Thread(target=target, name="plant", daemon=True)
        self._thread.start()
        return self

    def _device_clocks(self) -> None:
        """Lockstep: the physics waits for the host, the devices' own timers do not. Every millisecond the leg
        actuators' and the Dynamixels' watchdogs are checked (a silent host still ends in damping / stopped servos)."""
        while not self._stop.wait(self.dt):
            self.legs.check_watchdogs()
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
        name_os_thread(PHYSICS_THREAD_NAME)
        _leave_real_time()
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
        """Actuator torques (coupling column order), whether any leg actuator is enabled, whether all are off: the
        leg kind's law on what the actuators measure."""
        if self.legs is None:
            return np.zeros(self.n), False, True
        return self.legs.torques(self._m, self._md)

    def _publish_legs(self, q: np.ndarray, qd: np.ndarray, tau_m: np.ndarray) -> None:
        m, md = self.coupling.actuator_positions(q), self.coupling.actuator_positions(qd)
        self._m, self._md = m, md  # what the actuators measure, for their own PD (BEAR force/position modes)
        if self.legs is not None:
            self.legs.publish(m, md, tau_m)

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
class EmulatedRobot:
    """Every device a config describes, emulated, with a plant driving them: the legs' emulators are their kind's
    (`legs`, bruce_hw.leg_kinds). CAN motors go on python-can's `can_interface` (default "virtual": reachable from
    this process only)."""

    config: RobotConfig
    sense_command_poll_s: float = 0.05
    can_interface: str = "virtual"
    lockstep: bool = False  # the physics steps once per host bus cycle (Plant(lockstep)), not on the wall clock
    legs: LegEmulation | None = None
    dynamixel: object = None
    sense: object = None
    plant: Plant | None = None
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


def name_os_thread(name: str) -> None:
    """The calling thread's name as the OS shows it (Linux: 15 characters; elsewhere nothing): Python before 3.14
    names its threads for itself only."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):
        pass


def _leave_real_time() -> None:
    """The physics is no device: it runs at normal priority (SCHED_OTHER) whatever the thread that started it had
    (`bruce-emulate --realtime` starts the emulators SCHED_FIFO 40), below every device thread (pty servers,
    sense-board firmware and sender, CAN motors). At real-time priority it left the kernel no time on its CPU for the
    tty worker (the `kworker` that moves every pty byte, at normal priority): a worker preempted halfway through a
    BEAR pty's buffer by the device thread it had just woken then waited 5-10 ms behind the physics' steps, and no
    other worker may take that buffer meanwhile, so the host's next request sat in the pty and every BEAR went silent
    (ftrace of the runs that ended, docs/results/timing.md). At normal priority the worker shares the CPU with the
    physics (it still waits up to one time slice of it, ~2 ms). Real devices answer whatever the world is doing; the
    physics only runs a little late. (Lockstep's device clock, the devices' watchdog timer, keeps their priority.)"""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # lowering needs no privilege
    except (AttributeError, OSError):  # not Linux
        pass
