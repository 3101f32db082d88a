"""Torque mixing laws of the paper, in joint space, gains from the robot config."""

from __future__ import annotations

import numpy as np

from bruce_hw.config import PdGains


def eq8_torque(a: np.ndarray, q: np.ndarray, qd: np.ndarray, gains: PdGains) -> np.ndarray:
    """Eq. 8: tau* = Kp (a - q) - Kd qd, the 1 kHz PD that turns the policy's targets a_t into torques."""
    return gains.kp * (a - q) - gains.kd * qd
