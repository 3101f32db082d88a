"""Joint <-> actuator maps of BRUCE's differential hip and knee/ankle linkage.

Positions and velocities: q = B m (B = `joint_from_actuator`), m = A q with A = B^-1.
Torques follow from power balance (tau_q . qd = tau_m . md): tau_q = A^T tau_m and tau_m = B^T tau_q.
"""

from __future__ import annotations

import numpy as np


class Coupling:
    def __init__(self, joint_from_actuator: np.ndarray):
        self.joint_from_actuator = np.array(joint_from_actuator, dtype=np.float64)
        self.actuator_from_joint = np.linalg.inv(self.joint_from_actuator)
        # Torque maps, precomputed because the 1 kHz loop uses them every tick.
        self._tau_joint_from_actuator = self.actuator_from_joint.T.copy()
        self._tau_actuator_from_joint = self.joint_from_actuator.T.copy()

    def joint_positions(self, actuator_positions: np.ndarray) -> np.ndarray:
        """Joint angles (or velocities) from actuator angles (or velocities)."""
        return self.joint_from_actuator @ actuator_positions

    def actuator_positions(self, joint_positions: np.ndarray) -> np.ndarray:
        """Actuator angles (or velocities) from joint angles (or velocities)."""
        return self.actuator_from_joint @ joint_positions

    def joint_torques(self, actuator_torques: np.ndarray) -> np.ndarray:
        return self._tau_joint_from_actuator @ actuator_torques

    def actuator_torques(self, joint_torques: np.ndarray) -> np.ndarray:
        return self._tau_actuator_from_joint @ joint_torques

    def saturate(self, joint_torques: np.ndarray, actuator_limit: float) -> np.ndarray:
        """Joint torques after each actuator saturates at +-actuator_limit, as the motors themselves do."""
        tau_m = np.minimum(np.maximum(self.actuator_torques(joint_torques), -actuator_limit), actuator_limit)
        return self.joint_torques(tau_m)
