"""Unit quaternions in MuJoCo's order (w, x, y, z), rotating a body's frame into the world's, and what the stack
reads from them: the rotation matrix R, the world's up axis in the body, the tilt, ZYX Euler angles.

Scalar results are plain tuples: `rotation_entries` (R row by row) serves the paths that run every 1 kHz tick in
Python floats (the attitude filter, the kinematic estimator).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def rotation_entries(quat: Sequence[float]) -> tuple[float, float, float, float, float, float, float, float, float]:
    """R's entries row by row (r00, r01, r02, r10, ..., r22): column j is the body's axis j in the world, row i
    the world's axis i in the body."""
    w, x, y, z = quat
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


def world_z_in_body(quat: Sequence[float]) -> tuple[float, float, float]:
    """The world's z axis in the body frame (R's last row)."""
    w, x, y, z = quat
    return 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


def body_z_in_world(quat: Sequence[float]) -> tuple[float, float, float]:
    """The body's z axis in the world frame (R's last column)."""
    w, x, y, z = quat
    return 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)


def cos_tilt_of(quat: Sequence[float]) -> float:
    """Cosine of the angle between the body's z axis and the world's (R's r22), in scalar math for per-tick use."""
    _, x, y, _ = quat
    return 1 - 2 * (x * x + y * y)


def tilt_of(quat: Sequence[float]) -> float:
    """Angle between the body's z axis and the world's (rad)."""
    return math.acos(max(-1.0, min(1.0, cos_tilt_of(quat))))


def euler_of(quat: Sequence[float]) -> np.ndarray:
    """(roll, pitch, yaw), ZYX convention (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    w, x, y, z = quat
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))     # atan2(r21, r22)
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))      # asin(-r20)
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))      # atan2(r10, r00)
    return np.array([roll, pitch, yaw])


def euler_rows(quats: np.ndarray) -> np.ndarray:
    """`euler_of` of each row of an (N, 4) array of quaternions: (N, 3), in numpy (a batch of simulations)."""
    w, x, y, z = np.asarray(quats).T
    return np.stack([np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
                     np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)),
                     np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))], axis=1)


def quaternion_rows(eulers: np.ndarray) -> np.ndarray:
    """The inverse of `euler_rows`: (N, 4) unit quaternions (w, x, y, z) of (N, 3) rows of ZYX (roll, pitch, yaw)."""
    half = np.asarray(eulers) / 2
    (cr, cp, cy), (sr, sp, sy) = np.cos(half).T, np.sin(half).T
    return np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=1)


def rotate_to_body(quat: Sequence[float], v_world: np.ndarray) -> np.ndarray:
    """R^T v: a world vector in the body frame."""
    return np.array(rotation_entries(quat)).reshape(3, 3).T @ v_world


def roll_pitch_quaternion(roll: float, pitch: float) -> tuple[float, float, float, float]:
    """The orientation with these roll and pitch and yaw 0 (ZYX): q_y(pitch) q_x(roll)."""
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return cp * cr, cp * sr, sp * cr, -sp * sr
