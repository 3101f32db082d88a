"""Base attitude from the IMU, and the base state the walking controllers observe (paper Table I).

`BaseEstimate` is what a controller needs beyond the joints: the base's orientation, its linear and angular
velocity in its own frame, and its Euler angles. Every estimator follows `Estimator`: the loop calls
`update(state)` on every tick (an IMU-driven filter integrates at the loop rate) and `estimate()` on policy
ticks. `GroundTruthEstimator` reads the simulator's truth; it exists only for the mock, and a backend without
ground truth is refused with a clear error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from bruce_hw.backend import Backend, BackendError
from bruce_hw.quaternion import cos_tilt_of, euler_of, rotate_to_body, world_z_in_body
from bruce_hw.types import ImuSample, RobotState


def world_up_in_body(imu: ImuSample) -> np.ndarray:
    """The world's z axis in the IMU frame (unit): from the orientation when the IMU has one, else from the
    accelerometer's specific force, which points up at rest."""
    if imu.orientation is not None:
        return np.array(world_z_in_body(imu.orientation))
    norm = float(np.linalg.norm(imu.accel))
    return imu.accel / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def cos_tilt(imu: ImuSample) -> float:
    """Cosine of the angle between the base's z axis and the world's: the z component of world_up_in_body, in
    scalar math because the safety stage evaluates it every tick."""
    if imu.orientation is not None:
        return cos_tilt_of(imu.orientation)
    a = imu.accel
    norm = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return a[2] / norm if norm > 0 else 1.0


def tilt_angle(imu: ImuSample) -> float:
    """Angle between the base's z axis and the world's (rad)."""
    return math.acos(max(-1.0, min(1.0, float(cos_tilt(imu)))))


@dataclass(slots=True)
class BaseEstimate:
    quat: np.ndarray    # (w, x, y, z), base -> world (yaw relative to where the estimator started, on a robot)
    linvel: np.ndarray  # m/s, base frame
    angvel: np.ndarray  # rad/s, base frame
    euler: np.ndarray   # rad, (roll, pitch, yaw) of quat


class Estimator(Protocol):
    def reset(self, state: RobotState) -> None:
        """Start from the robot at rest in `state` (called once before the loop)."""

    def update(self, state: RobotState) -> None:
        """Take in one tick's measurements (called every tick, so it must be cheap)."""

    def estimate(self) -> BaseEstimate:
        """The current estimate (called on policy ticks)."""


class GroundTruthEstimator:
    """The simulator's truth as the estimate (mock only: a robot has no ground truth)."""

    def __init__(self, backend: Backend):
        if backend.ground_truth() is None:
            raise BackendError(f"{backend.name} backend: no ground truth, and the policy needs the base velocity; "
                             "use the kinematic estimator (IMU + leg kinematics) instead")
        self.backend = backend

    def reset(self, state: RobotState) -> None:
        pass

    def update(self, state: RobotState) -> None:
        pass  # the truth is read when an estimate is asked for

    def estimate(self) -> BaseEstimate:
        truth = self.backend.ground_truth()
        return BaseEstimate(quat=truth.base_quat, linvel=rotate_to_body(truth.base_quat, truth.base_linvel),
                            angvel=truth.base_angvel, euler=euler_of(truth.base_quat))
