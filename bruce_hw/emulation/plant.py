"""Physics behind the emulators (`Plant`): BRUCE's MuJoCo model (the mock backend's, `bruce_hw.mock.MujocoBackend`)
stepped at 1 kHz in real time on a thread, so that the hw backend talks to emulated devices that move like the robot.

`Plant.step`: what the leg actuators were told becomes actuator torques by their kind's law (`LegEmulation.torques`,
bruce_hw/legs/; the BEARs' torque law is there, CAN motors compute their own), then joint torques through the
coupling, the model steps one loop period, and the measured state goes back to the leg emulators, the sense board
and, every 20th step, the Dynamixel emulator. `bruce_hw.emulation.robot.EmulatedRobot` runs it beside the emulators,
in their process or (`PhysicsProcess`, bruce-emulate on the wall clock) in one of its own.
"""

from __future__ import annotations

import math
import os
import threading
import time
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import GroundTruth, JointCommand
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
                 arm_time_constant_s: float = 0.05, lockstep: bool = False, after_step=None):
        self.config = config
        self.after_step = after_step  # called after each step, its measurement published (PhysicsProcess's child)
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
        leave_real_time()
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

    def status(self) -> dict:
        """The counters, whether held, the arms and the ground truth, all of one moment (bruce-emulate's `status`;
        in a process of its own, one answer over the pipe)."""
        with self._lock:
            return {"steps": self.steps, "late_steps": self.late_steps, "skipped_steps": self.skipped_steps,
                    "held": self.held, "arm_q": self.arm_q.copy(), "truth": self.sim.ground_truth(),
                    "nominal_base_height": self.sim.nominal_base_height}

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
        if self.after_step is not None:
            self.after_step()

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



def name_os_thread(name: str) -> None:
    """The calling thread's name as the OS shows it (Linux: 15 characters; elsewhere nothing): Python before 3.14
    names its threads for itself only."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):
        pass


def leave_real_time() -> None:
    """The physics is no device: it runs at normal priority (SCHED_OTHER) whatever the thread that started it had
    (`bruce-emulate --realtime` starts the emulators SCHED_FIFO 40). At real-time priority it left the kernel no time
    on its CPU for the tty worker (the `kworker` that moves every pty byte, at normal priority): a worker preempted
    halfway through a BEAR pty's buffer by the device thread it had just woken then waited 5-10 ms behind the
    physics' steps, and the host's next request sat in the pty (ftrace, docs/results/timing.md). (Lockstep's device
    clock, the devices' watchdog timer, keeps their priority.)"""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # lowering needs no privilege
    except (AttributeError, OSError):  # not Linux
        pass
