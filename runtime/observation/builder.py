"""The observation a policy spec asks for (`ObservationBuilder`), of one robot (the runtime's `PolicyController`)
or of a batch (training/rl's environment), with the same arithmetic: the clock and the heading reference advance,
then `SpecTerms` builds the spec's terms from the registered term functions."""

from __future__ import annotations

import math

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import RobotState
from runtime.control.heading import HeadingReference
from runtime.control.policy_spec import TABLE_ONE, PolicySpec, load_policy_spec
from runtime.estimation import BaseEstimate
from runtime.observation.inputs import ObservationInputs
from runtime.observation.spec_terms import SpecTerms
from runtime.walking.gait import GaitClock


def advance_references(clock: GaitClock, heading: HeadingReference, command, yaw):
    """One policy tick of the gait clock and the heading reference: (the phase (rad) before the tick, the command
    the gait follows, the yaw's error to the reference heading), of one robot or a batch."""
    phase = 2.0 * math.pi * clock.tick(command)
    followed = clock.command  # the rate-limited command, the one the gait follows
    heading.update(yaw, followed[..., 2])
    return phase, followed, heading.error(yaw)


class ObservationBuilder:
    """The observation of `spec` (default: the paper's Table I, configs/robots/policy_specs/table1.yaml), at the
    spec's rate. The clock is the walking teacher's `GaitClock` and the heading reference the one it steers by; the
    builder keeps them and each term's history, so it is called once per policy tick, in order, and reset at the
    start of a run. Without `num_envs` it builds one robot's observation (`build`); with it, `num_envs` robots' at
    once (`observe`, every argument with a leading robot axis; training/rl)."""

    def __init__(self, config: RobotConfig, spec: PolicySpec | None = None, num_envs: int | None = None):
        self.spec = spec if spec is not None else load_policy_spec(TABLE_ONE, config)
        self.size = self.spec.obs_size
        dt = 1.0 / self.spec.rate_hz
        self.batched = num_envs is not None
        self.heading_reference = HeadingReference(dt, num_envs=num_envs)
        self.clock = GaitClock(config.models.gait_period_s, dt, num_envs)
        self.terms = SpecTerms(self.spec, 1 if num_envs is None else num_envs)
        self.slices: dict[str, slice] = {}  # term -> its values in the observation (its first entry in the spec)
        start = 0
        for term in self.spec.terms:
            self.slices.setdefault(term.term, slice(start, start + term.size))
            start += term.size

    def reset(self, envs=...) -> None:
        """Start a run (of the robots `envs` selects: a mask or indices into the batch)."""
        self.heading_reference.reset(envs)
        self.clock.reset(envs)
        self.terms.reset(envs)

    def build(self, command: np.ndarray, state: RobotState, base: BaseEstimate, last_action: np.ndarray,
              last_raw_action: np.ndarray | None = None) -> np.ndarray:
        """One robot's observation (size,). Joint arrays in the config's joint order; `last_raw_action` None: the
        last action (a policy whose output is its targets)."""
        one = [np.asarray(v).reshape(1, -1) for v in (command, state.joints.q, state.joints.qd, base.linvel,
                                                      base.angvel, base.euler, base.quat, last_action,
                                                      last_action if last_raw_action is None else last_raw_action)]
        return self.observe(*one)[0]

    def observe(self, command: np.ndarray, q: np.ndarray, qd: np.ndarray, base_linvel: np.ndarray,
                base_angvel: np.ndarray, base_euler: np.ndarray, base_quat: np.ndarray, last_action: np.ndarray,
                last_raw_action: np.ndarray) -> np.ndarray:
        """A batch's observations (N, size), every argument with a leading robot axis (N = 1 without `num_envs`)."""
        return self.terms(self.inputs(command, q, qd, base_linvel, base_angvel, base_euler, base_quat, last_action,
                                      last_raw_action))

    def inputs(self, command, q, qd, base_linvel, base_angvel, base_euler, base_quat, last_action,
               last_raw_action) -> ObservationInputs:
        """This tick's term inputs: the references advance one tick."""
        # one robot's clock and reference run on numbers (as the walking teacher's), a batch's on arrays
        batched = self.batched
        yaw = base_euler[:, 2] if batched else base_euler[0, 2]
        phase, followed, heading_error = advance_references(self.clock, self.heading_reference,
                                                            command if batched else command[0], yaw)
        return ObservationInputs(
            phase=np.asarray(phase).reshape(-1), command=followed.reshape(-1, 3), raw_command=command, q=q, qd=qd,
            base_linvel=base_linvel, base_angvel=base_angvel, base_euler=base_euler, base_quat=base_quat,
            heading_error=np.asarray(heading_error).reshape(-1), last_action=last_action,
            last_raw_action=last_raw_action)
