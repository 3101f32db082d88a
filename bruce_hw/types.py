"""Joint-space data exchanged with every backend. Arrays are float64 in the robot config's joint order."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FOOT_CONTACT_NAMES = ("r_toe", "r_heel", "l_toe", "l_heel")  # the sense board's contact bit order
GRAVITY = 9.81  # m/s^2, the simulated world's (MuJoCo's default, which the robot's MJCF keeps)


def all_finite(*arrays: np.ndarray) -> bool:
    """No NaN or inf in any of the (small, 1-D) arrays; a dot product per array, the cheapest check for 10
    elements (it also rejects magnitudes beyond 1e154, which no sensor, torque or model output has)."""
    return all(math.isfinite(a @ a) for a in arrays)


@dataclass(slots=True)
class JointState:
    q: np.ndarray            # rad
    qd: np.ndarray           # rad/s
    tau: np.ndarray          # Nm, measured (motor current x torque constant, through the coupling)
    temperature: np.ndarray  # deg C, per joint (hottest actuator driving it)
    stamp: float             # s, monotonic clock of the backend (simulated time in the mock)


@dataclass(slots=True)
class ImuSample:
    gyro: np.ndarray                # rad/s, IMU frame
    accel: np.ndarray               # m/s^2, specific force in the IMU frame (+g up when at rest)
    orientation: np.ndarray | None  # quaternion (w, x, y, z) IMU -> world, when the device provides one
    stamp: float


@dataclass(slots=True)
class FootContacts:
    contact: np.ndarray  # bool, FOOT_CONTACT_NAMES order
    stamp: float


@dataclass(slots=True)
class JointCommand:
    """Feed-forward torque plus an optional motor-side PD: tau = tau_ff + kp (q_ref - q) + kd (qd_ref - qd).

    A field left None is not used, so a pure torque command is `JointCommand(tau_ff)`; backends whose
    motors run the PD themselves (BEAR force mode, CAN MIT mode) forward q_ref/qd_ref/kp/kd unchanged.
    """

    tau_ff: np.ndarray
    q_ref: np.ndarray | None = None
    qd_ref: np.ndarray | None = None
    kp: np.ndarray | None = None
    kd: np.ndarray | None = None

    def torque(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """The joint torque this command asks for at state (q, qd)."""
        tau = self.tau_ff
        if self.kp is not None and self.q_ref is not None:
            tau = tau + self.kp * (self.q_ref - q)
        if self.kd is not None:
            tau = tau + self.kd * ((0.0 if self.qd_ref is None else self.qd_ref) - qd)
        return tau


@dataclass(slots=True)
class RobotState:
    """Everything one read returns: what the robot's sensors report."""

    joints: JointState
    imu: ImuSample
    contacts: FootContacts
    estop: bool = False  # an emergency-stop input is asserted (sense board button, wireless stop)


@dataclass(slots=True)
class GroundTruth:
    """Simulator-only truth for evaluation; a real robot has none."""

    sim_time: float
    base_pos: np.ndarray      # m, world
    base_quat: np.ndarray     # (w, x, y, z), base -> world
    base_linvel: np.ndarray   # m/s, world
    base_angvel: np.ndarray   # rad/s, base frame
    # Joint angles and velocities as simulated (config order), free of any reality gap's encoder noise or latency.
    joint_q: np.ndarray | None = None
    joint_qd: np.ndarray | None = None
