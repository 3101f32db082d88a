"""Our observation terms: the paper's Table I (configs/robots/policy_specs/table1.yaml) and what legged_gym's and
Isaac Lab's policies observe (legged_gym.yaml). Each is one function of `ObservationInputs` (batch N) -> (N, width),
in registration order (the order a bad spec's error lists them in)."""

from __future__ import annotations

import numpy as np

from bruce_hw.quaternion import world_z_in_body
from runtime.observation.inputs import ObservationInputs
from runtime.observation.registry import PER_JOINT, register_term


def clock(x: ObservationInputs) -> np.ndarray:
    """sin, cos of the gait phase."""
    out = np.empty((len(x.phase), 2))  # filled by column: np.stack costs one robot's policy tick several times this
    out[:, 0] = np.sin(x.phase)  # on the contiguous phase, as np.stack had it
    out[:, 1] = np.cos(x.phase)
    return out


def euler(x: ObservationInputs) -> np.ndarray:
    """Roll, pitch, and instead of the yaw, which a policy cannot generalise over (walking does not depend on where
    north is), the yaw's error to the commanded heading: the state the walking teacher steers with."""
    out = np.empty((len(x.phase), 3))
    out[:, :2] = x.base_euler[:, :2]
    out[:, 2] = x.heading_error
    return out


def projected_gravity(x: ObservationInputs) -> np.ndarray:
    """The unit gravity vector (0, 0, -1) in the base frame."""
    return np.negative(np.stack(world_z_in_body(x.base_quat.T), axis=-1))


register_term("clock", 2, clock)
register_term("command", 3, lambda x: x.command)
register_term("raw_command", 3, lambda x: x.raw_command)
register_term("q", PER_JOINT, lambda x: x.q, joint_angles=True)
register_term("qd", PER_JOINT, lambda x: x.qd)
register_term("base_linvel", 3, lambda x: x.base_linvel)
register_term("base_angvel", 3, lambda x: x.base_angvel)
register_term("euler", 3, euler)
register_term("projected_gravity", 3, projected_gravity)
register_term("last_action", PER_JOINT, lambda x: x.last_action, joint_angles=True)
register_term("last_raw_action", PER_JOINT, lambda x: x.last_raw_action)
