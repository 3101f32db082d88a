"""The walking policy as the nominal controller (`PolicyController`): its observation -> ONNX -> a_t, at the
policy's rate.

What a policy observes, at which rate and in which joint order, and how its output becomes targets, is its spec
(`runtime.control.policy_spec`); ours is the paper's Table I (the shipped spec `table1.yaml`). The observation is
built by `runtime.observation.builder.ObservationBuilder`, the same builder training runs on a batch of simulated
robots, so training and the runtime cannot disagree on it.
"""

from __future__ import annotations

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import RobotState
from runtime.control.inference import OnnxPolicy
from runtime.control.policy_spec import TABLE_ONE, PolicySpec, load_policy_spec
from runtime.estimation import BaseEstimate
from runtime.observation.builder import ObservationBuilder


class PolicyController:
    """The nominal-controller interface: reset(q) at start, then a_t = controller(state, base, command) at the
    loop's policy rate (rates.policy_hz), with `command` = (vx, vy, yaw rate) in the heading frame.

    `spec` (default: Table I) says what the policy sees and does. A policy slower than rates.policy_hz runs on every
    k-th call and its targets are held between (a 50 Hz policy under the 100 Hz tick: every other call). Its output,
    clipped, scaled and offset, is put into the config's joint order. `obs` is the observation it last ran on."""

    def __init__(self, config: RobotConfig, policy: OnnxPolicy, spec: PolicySpec | None = None):
        self.spec = spec if spec is not None else load_policy_spec(TABLE_ONE, config)
        self.builder = ObservationBuilder(config, self.spec)
        self.policy = policy
        self.hold_calls = config.policy_hz // self.spec.rate_hz
        action = self.spec.action
        self._action_steps = (action.clip, bool(np.any(action.scale != 1.0)), bool(np.any(action.offset)))
        self.obs: np.ndarray | None = None
        self.reset(config.standing_pose)

    def reset(self, q_measured: np.ndarray) -> None:
        self.builder.reset()
        self.last_action = q_measured
        self.last_raw_action = np.zeros(len(self.spec.joints))  # legged_gym and Isaac Lab start from no action
        self.calls = 0

    @property
    def last_action(self) -> np.ndarray:
        """a_{t-1}, the targets in force, in the config's joint order."""
        return self.a

    @last_action.setter
    def last_action(self, a: np.ndarray) -> None:
        """Take `a` (config order) as the targets in force and the action memory, the raw output too as far as the
        action map inverts (the nominal twin hands the robot's over at a resync)."""
        self.a = np.array(a, dtype=float)
        self.last_raw_action = self.spec.action.output_of(self.a[self.spec.order])

    def __call__(self, state: RobotState, base: BaseEstimate, command: np.ndarray) -> np.ndarray:
        call, self.calls = self.calls, self.calls + 1
        if call % self.hold_calls:
            return self.a
        last_raw = np.empty(len(self.a))  # the observation takes joint arrays in the config's order
        last_raw[self.spec.order] = self.last_raw_action
        self.obs = self.builder.build(command, state, base, self.a, last_raw)
        raw = self.policy(self.obs)
        clip, scale, offset = self._action_steps
        if clip is not None:
            raw = np.clip(raw, -clip, clip)
        target = raw * self.spec.action.scale if scale else raw
        target = target + self.spec.action.offset if offset else target
        a = np.empty(len(target))
        a[self.spec.order] = target
        self.last_raw_action, self.a = raw, a
        return a
