"""What an observation term reads (`ObservationInputs`): one policy tick of a batch of robots."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class ObservationInputs:
    """Every array has a leading batch axis of N robots (N = 1 in the runtime); joint arrays are (N, n_joints) in
    the robot config's joint order. The gait phase, the followed command and the heading error are the
    `ObservationBuilder`'s clock and heading reference after this tick."""

    phase: np.ndarray            # (N,) gait phase (rad) before the tick: 2 pi t / C_T (runtime.walking.gait.GaitClock)
    command: np.ndarray          # (N, 3) vx, vy (m/s, heading frame), yaw rate (rad/s), rate-limited as the gait
                                 # follows it
    raw_command: np.ndarray      # (N, 3) the same, as commanded (the command schedule's, before the rate limit)
    q: np.ndarray                # (N, n) joint positions (rad)
    qd: np.ndarray               # (N, n) joint velocities (rad/s)
    base_linvel: np.ndarray      # (N, 3) base linear velocity, base frame (m/s)
    base_angvel: np.ndarray      # (N, 3) base angular velocity, base frame (rad/s)
    base_euler: np.ndarray       # (N, 3) roll, pitch, yaw (rad, ZYX), as estimated
    base_quat: np.ndarray        # (N, 4) base orientation (w, x, y, z)
    heading_error: np.ndarray    # (N,) yaw minus the heading the command asks for (rad; runtime.control.heading)
    last_action: np.ndarray      # (N, n) the previous joint targets (rad), after the action map's scale and offset
    last_raw_action: np.ndarray  # (N, n) the previous network output, after action.clip, before scale and offset

    @property
    def batch(self) -> int:
        return len(self.phase)
