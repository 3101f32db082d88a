"""The walking policy as the nominal controller (`PolicyController`): its observation -> ONNX -> a_t, at the
policy's rate.

What a policy observes, at which rate and in which joint order, and how its output becomes targets, is its spec
(`runtime.policy_spec`); ours is the paper's Table I (`observation_layout`, the shipped spec `table1.yaml`).
`ObservationBuilder` builds the Table I observation, also for batches of simulated robots (training), and
`SpecObservation` builds a spec's; both take the clock, the followed command and the heading error from
`advance_references`, and tests/runtime/test_policy_spec.py holds them equal on Table I, so training and the runtime
cannot disagree on it.
"""

from __future__ import annotations

import math

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.quaternion import world_z_in_body
from bruce_hw.types import RobotState
from runtime.estimation import BaseEstimate
from runtime.heading import HeadingReference
from runtime.inference import OnnxPolicy
from runtime.policy_spec import TABLE_ONE, PolicySpec, load_policy_spec
from runtime.walking.gait import GaitClock


def advance_references(clock: GaitClock, heading: HeadingReference, command, yaw):
    """One policy tick of the gait clock and the heading reference: (the phase (rad) before the tick, the command
    the gait follows, the yaw's error to the reference heading), of one robot or a batch."""
    phase = 2.0 * math.pi * clock.tick(command)
    followed = clock.command  # the rate-limited command, the one the gait follows
    heading.update(yaw, followed[..., 2])
    return phase, followed, heading.error(yaw)


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
        phase, command, heading_error = advance_references(self.clock, self.heading_reference, command,
                                                           euler[..., 2])
        s = self.slices
        obs = np.empty((*np.shape(phase), self.size))
        obs[..., s["clock"].start] = np.sin(phase)
        obs[..., s["clock"].start + 1] = np.cos(phase)
        obs[..., s["command"]] = command
        obs[..., s["q"]] = q
        obs[..., s["qd"]] = qd
        obs[..., s["base_linvel"]] = base_linvel
        obs[..., s["base_angvel"]] = base_angvel
        obs[..., s["euler"].start:s["euler"].start + 2] = euler[..., :2]
        obs[..., s["euler"].start + 2] = heading_error
        obs[..., s["last_action"]] = last_action
        return obs


class SpecObservation:
    """The observation a spec asks for (runtime.policy_spec.PolicySpec), built once per policy tick of its own rate,
    in order, and reset at the start of a run. Joint-space terms are in the spec's joint order; a term with history
    keeps its last frames, all equal to the first one after a reset (as Isaac Lab's history buffers start)."""

    def __init__(self, config: RobotConfig, spec: PolicySpec):
        self.spec = spec
        self.size = spec.obs_size
        self.heading_reference = HeadingReference(1.0 / spec.rate_hz)
        self.clock = GaitClock(config.models.gait_period_s, 1.0 / spec.rate_hz)
        # Per term: whether offset, clip and scale change anything (an identity costs nothing and stays exact).
        self._steps = [(bool(np.any(t.offset)), t.clip, bool(np.any(t.scale != 1.0))) for t in spec.terms]
        self._frames = [np.zeros((t.history, t.width)) if t.history > 1 else None for t in spec.terms]
        self._started = False

    def reset(self) -> None:
        self.heading_reference.reset()
        self.clock.reset()
        self._started = False

    def build(self, command: np.ndarray, state: RobotState, base: BaseEstimate, last_action: np.ndarray,
              last_raw_action: np.ndarray) -> np.ndarray:
        """The observation (size,); `last_action` and `last_raw_action` in the spec's joint order."""
        phase, followed, heading_error = advance_references(self.clock, self.heading_reference, command,
                                                            base.euler[2])
        order = self.spec.order
        values = {
            "clock": (np.sin(phase), np.cos(phase)), "command": followed, "raw_command": command,
            "q": state.joints.q[order], "qd": state.joints.qd[order], "base_linvel": base.linvel,
            "base_angvel": base.angvel, "euler": (base.euler[0], base.euler[1], heading_error),
            "projected_gravity": np.negative(world_z_in_body(base.quat)), "last_action": last_action,
            "last_raw_action": last_raw_action,
        }
        obs = np.empty(self.size)
        start = 0
        for term, (offset, clip, scale), frames in zip(self.spec.terms, self._steps, self._frames, strict=True):
            x = values[term.term]
            if offset:
                x = np.subtract(x, term.offset)
            if clip is not None:
                x = np.clip(x, -clip, clip)
            if scale:
                x = np.multiply(x, term.scale)
            if frames is not None:
                if self._started:
                    frames[1:] = frames[:-1]  # newest in row 0
                    frames[0] = x
                else:
                    frames[:] = x
                x = (frames if term.newest_first else frames[::-1]).ravel()
            obs[start:start + term.size] = x
            start += term.size
        self._started = True
        if self.spec.obs_clip is not None:
            np.clip(obs, -self.spec.obs_clip, self.spec.obs_clip, out=obs)
        return obs


class PolicyController:
    """The nominal-controller interface: reset(q) at start, then a_t = controller(state, base, command) at the
    loop's policy rate (rates.policy_hz), with `command` = (vx, vy, yaw rate) in the heading frame.

    `spec` (default: Table I) says what the policy sees and does. A policy slower than rates.policy_hz runs on every
    k-th call and its targets are held between (a 50 Hz policy under the 100 Hz tick: every other call). Its output,
    clipped, scaled and offset, is put into the config's joint order. `obs` is the observation it last ran on."""

    def __init__(self, config: RobotConfig, policy: OnnxPolicy, spec: PolicySpec | None = None):
        self.spec = spec if spec is not None else load_policy_spec(TABLE_ONE, config)
        self.builder = SpecObservation(config, self.spec)
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
        self._last_target = self.a[self.spec.order]
        action = self.spec.action
        self.last_raw_action = np.divide(self._last_target - action.offset, action.scale,
                                         out=np.zeros(len(action.scale)), where=action.scale != 0.0)

    def __call__(self, state: RobotState, base: BaseEstimate, command: np.ndarray) -> np.ndarray:
        call, self.calls = self.calls, self.calls + 1
        if call % self.hold_calls:
            return self.a
        self.obs = self.builder.build(command, state, base, self._last_target, self.last_raw_action)
        raw = self.policy(self.obs)
        clip, scale, offset = self._action_steps
        if clip is not None:
            raw = np.clip(raw, -clip, clip)
        target = raw * self.spec.action.scale if scale else raw
        target = target + self.spec.action.offset if offset else target
        a = np.empty(len(target))
        a[self.spec.order] = target
        self.last_raw_action, self._last_target, self.a = raw, target, a
        return a
