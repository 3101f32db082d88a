"""A live nominal twin of the robot (`NominalTwin`): the simulator's own closed loop, run beside the robot and
resynchronised to it.

The twin is the nominal MuJoCo model under a second instance of the nominal controller on the robot's command, with
its own ground truth as its base estimate and its torques through its own safety stage (the simulator's went through
one). Every `resync_ticks` it is set to the robot's state (measured joints; the base from `base_state`, the mock's
ground truth) and its controller takes the robot's target and action memory; between resyncs it rolls on by itself,
in phase (the gait clock is a function of the command history). `resync_requested` asks for one at the next policy
tick, e.g. after a push the twin did not feel. Without a gap the twin reproduces the robot to rounding; with one,
the posture offset between them over seconds is what no prediction over a few ticks sees
(docs/transfer_twin_notes.md). Mock only: a robot does not measure its full base state.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.quaternion import euler_of, rotate_to_body
from bruce_hw.types import FootContacts, GroundTruth, ImuSample, JointState, RobotState
from runtime.estimation import BaseEstimate
from runtime.inference import ModelError
from runtime.mixing import eq8_torque
from runtime.reference_models import nominal_backend, set_state
from runtime.safety import SafetyStage


class NominalTwin:
    """The nominal model under the nominal controller, resynchronised to the robot every `resync_ticks`."""

    def __init__(self, config: RobotConfig, base_state: Callable[[], GroundTruth | None], resync_ticks: int,
                 controller):
        nominal = nominal_backend(config, base_state, "the nominal twin needs the robot's full state (base and "
                                  "joints), which only the mock backend has (simulator ground truth); it is not "
                                  "available on the robot")
        self.model, self.data = nominal.model, nominal.data
        self._qpos, self._dofs, self._acts = nominal._qpos, nominal._dofs, nominal._acts
        self.controller = controller
        self.safety = SafetyStage(config)
        self.eq8 = config.eq8
        self.decimation = config.policy_decimation
        self.resync_ticks = resync_ticks
        self.base_state = base_state
        self._n = config.n_joints
        self.reset()

    def reset(self) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.safety.reset()
        self.tick = 0
        self.resync_requested = False  # resync at the next policy tick, out of turn
        self.a: np.ndarray | None = None
        self.q: np.ndarray | None = None  # the twin's joint posture at the robot's coming tick

    def advance(self, a_robot: np.ndarray, q: np.ndarray, qd: np.ndarray, command: np.ndarray,
                last_torque: np.ndarray | None) -> None:
        """One tick, after the robot's controller gave `a_robot` on this tick from the measured joints (q, qd):
        resync when due (to the measured joints: what the twin is compared with, and all a robot has; the base from
        `base_state`), then the twin's own controller (on policy ticks), Eq. 8, its safety filter and one step.
        `last_torque` is the torque the robot was sent last tick (the rate limit starts from it at a resync)."""
        data = self.data
        policy_tick = self.tick % self.decimation == 0
        resync = self.tick % self.resync_ticks == 0 or (self.resync_requested and policy_tick)
        if resync:
            self.resync_requested = False
            truth = self.base_state()
            if truth is None:
                raise ModelError("nominal twin: the robot's full state is gone (mock backend only)")
            set_state(data, self._qpos, self._dofs, truth, q, qd)
            mujoco.mj_forward(self.model, data)
            if last_torque is not None:
                self.safety.previous = np.array(last_torque, dtype=float)
        state, base = self._reading()
        if self.tick == 0:
            self.controller.reset(state.joints.q)
        if policy_tick:
            a = self.controller(state, base, command)  # also advances its gait clock and heading reference
            if resync:  # the robot's controller state: its target now is the action memory of both
                a = np.array(a_robot, dtype=float)
                self.controller.last_action = a
            self.a = a
        tau = self.safety.filter(eq8_torque(self.a, state.joints.q, state.joints.qd, self.eq8), state)
        data.ctrl[self._acts] = tau
        mujoco.mj_step(self.model, data)
        self.tick += 1
        self.q = data.qpos[self._qpos].copy()

    def _reading(self) -> tuple[RobotState, BaseEstimate]:
        """The twin's joints as a reading and its ground truth as the base estimate."""
        data = self.data
        t = float(data.time)
        quat = data.qpos[3:7].copy()
        angvel = data.qvel[3:6].copy()
        joints = JointState(q=data.qpos[self._qpos].copy(), qd=data.qvel[self._dofs].copy(), tau=np.zeros(self._n),
                            temperature=np.zeros(self._n), stamp=t)
        state = RobotState(joints=joints, imu=ImuSample(gyro=angvel, accel=np.zeros(3), orientation=quat, stamp=t),
                           contacts=FootContacts(contact=np.zeros(4, dtype=bool), stamp=t), estop=False)
        base = BaseEstimate(quat=quat, linvel=rotate_to_body(quat, data.qvel[0:3]), angvel=angvel,
                            euler=euler_of(quat))
        return state, base
