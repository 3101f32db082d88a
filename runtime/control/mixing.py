"""Torque mixing laws of the paper, in joint space, gains from the robot config (`gains.eq8`, `gains.eq9`).

Eq. 8 is the nominal low-gain PD on the policy's targets a_t. Eq. 9 adds a high-gain PD towards the PINN's
prediction of the simulator's next joint state (q^', qd^'), so the robot tracks what the simulator would
have done under the same tau*. `--transfer direct` sends Eq. 8 alone, `--transfer pinn` (or `eq9`) sends Eq. 9;
the other transfer schemes (runtime/transfer/: shadow.py, observer.py, twin.py) build on these two.
"""

from __future__ import annotations

import numpy as np

from bruce_hw.config import PdGains


def eq8_torque(a: np.ndarray, q: np.ndarray, qd: np.ndarray, gains: PdGains) -> np.ndarray:
    """Eq. 8: tau* = Kp (a - q) - Kd qd, the 1 kHz PD that turns the policy's targets a_t into torques."""
    return gains.kp * (a - q) - gains.kd * qd


def eq9_torque(tau_star: np.ndarray, q_next: np.ndarray, qd_next: np.ndarray, q: np.ndarray, qd: np.ndarray,
               gains: PdGains) -> np.ndarray:
    """Eq. 9: tau = tau* + Kp' (q^' - q) + Kd' (qd^' - qd), with (q^', qd^') the PINN's prediction."""
    return tau_star + gains.kp * (q_next - q) + gains.kd * (qd_next - qd)
