"""The walking policy as the nominal controller (`PolicyController`): observation (paper Table I) -> ONNX -> a_t at
100 Hz.

The observation is built here and only here (`ObservationBuilder`, layout `observation_layout`), so training and
the runtime cannot disagree on it.
"""

from __future__ import annotations

import math

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import RobotState
from runtime.estimation import BaseEstimate
from runtime.heading import HeadingReference
from runtime.inference import OnnxPolicy
from runtime.walking.gait import GaitClock


def observation_layout(n_joints: int) -> tuple[tuple[str, int], ...]:
    """(name, width) in order; SI units, joint arrays in the config's joint order, no normalisation (a policy folds
    its own into its graph):

    | slice            | dims | what                                                   |
    |------------------|------|--------------------------------------------------------|
    | clock            | 2    | sin, cos of the gait phase (2 pi t / C_T at a constant C_T; `GaitClock`) |
    | command          | 3    | commanded vx, vy (m/s, heading frame), yaw rate (rad/s), rate-limited (`GaitClock`) |
    | q                | n    | joint positions (rad)                                  |
    | qd               | n    | joint velocities (rad/s)                               |
    | base_linvel      | 3    | base linear velocity, base frame (m/s)                 |
    | base_angvel      | 3    | base angular velocity, base frame (rad/s)              |
    | euler            | 3    | base roll, pitch (rad); yaw minus the commanded heading (rad) |
    | last_action      | n    | a_{t-1} (rad)                                          |
    """
    return (("clock", 2), ("command", 3), ("q", n_joints), ("qd", n_joints), ("base_linvel", 3),
            ("base_angvel", 3), ("euler", 3), ("last_action", n_joints))


class ObservationBuilder:
    """The third Euler entry is not the absolute yaw, which a policy cannot generalise over (walking does not depend
    on where north is), but the yaw's error to the heading the command asks for (`runtime.heading`), the state the
    walking teacher steers with: a student that sees it can learn the teacher's heading correction. The clock is the
    teacher's `GaitClock`. The builder keeps the reference and the clock, so it is built once per policy tick, in
    order, and reset at the start of a run. With `num_envs` it builds a batch of simulated robots' observations at
    once (`observe` on arrays with a leading robot axis; training/rl), with the same arithmetic."""

    def __init__(self, config: RobotConfig, num_envs: int | None = None):
        self.slices: dict[str, slice] = {}
        start = 0
        for name, width in observation_layout(config.n_joints):
            self.slices[name] = slice(start, start + width)
            start += width
        self.size = start
        self.heading_reference = HeadingReference(1.0 / config.policy_hz, num_envs=num_envs)
        self.clock = GaitClock(config.models.gait_period_s, 1.0 / config.policy_hz, num_envs)

    def reset(self, envs=...) -> None:
        """Start a run (of the robots `envs` selects: a mask or indices into the batch)."""
        self.heading_reference.reset(envs)
        self.clock.reset(envs)

    def build(self, command: np.ndarray, state: RobotState, base: BaseEstimate,
              last_action: np.ndarray) -> np.ndarray:
        return self.observe(command, state.joints.q, state.joints.qd, base.linvel, base.angvel, base.euler,
                            last_action)

    def observe(self, command: np.ndarray, q: np.ndarray, qd: np.ndarray, base_linvel: np.ndarray,
                base_angvel: np.ndarray, euler: np.ndarray, last_action: np.ndarray) -> np.ndarray:
        """The observation (size,) of one robot, or (num_envs, size) of a batch (every argument with a leading
        robot axis); `euler` is (roll, pitch, yaw), the builder turns the yaw into the heading error."""
        phase = 2.0 * math.pi * self.clock.tick(command)
        command = self.clock.command  # the rate-limited command, the one the gait follows
        s = self.slices
        obs = np.empty((*np.shape(phase), self.size))
        obs[..., s["clock"].start] = np.sin(phase)
        obs[..., s["clock"].start + 1] = np.cos(phase)
        obs[..., s["command"]] = command
        obs[..., s["q"]] = q
        obs[..., s["qd"]] = qd
        obs[..., s["base_linvel"]] = base_linvel
        obs[..., s["base_angvel"]] = base_angvel
        yaw = euler[..., 2]
        self.heading_reference.update(yaw, command[..., 2])
        obs[..., s["euler"].start:s["euler"].start + 2] = euler[..., :2]
        obs[..., s["euler"].start + 2] = self.heading_reference.error(yaw)
        obs[..., s["last_action"]] = last_action
        return obs


class PolicyController:
    """The nominal-controller interface: reset(q) at start, then a_t = controller(state, base, command) at the
    policy rate, with `command` = (vx, vy, yaw rate) in the heading frame."""

    def __init__(self, config: RobotConfig, policy: OnnxPolicy):
        self.builder = ObservationBuilder(config)
        self.policy = policy
        self.reset(config.standing_pose)

    def reset(self, q_measured: np.ndarray) -> None:
        self.builder.reset()
        self.last_action = np.array(q_measured, dtype=float)

    def __call__(self, state: RobotState, base: BaseEstimate, command: np.ndarray) -> np.ndarray:
        obs = self.builder.build(command, state, base, self.last_action)
        a = self.policy(obs)
        self.last_action = a
        return a
