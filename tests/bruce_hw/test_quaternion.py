"""The quaternion helpers against MuJoCo's own quaternion functions, on random and edge-case orientations."""

import math

import mujoco
import numpy as np
import pytest

from bruce_hw.quaternion import (
    body_z_in_world,
    cos_tilt_of,
    euler_of,
    euler_rows,
    roll_pitch_quaternion,
    rotate_to_body,
    rotation_entries,
    tilt_of,
    world_z_in_body,
)


def random_quaternions(count: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


QUATERNIONS = [*random_quaternions(20), np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0, 0.0]),
               np.array([0.0, 0.0, 0.0, 1.0]), np.array([math.cos(0.3), 0.0, math.sin(0.3), 0.0])]


def mujoco_matrix(quat: np.ndarray) -> np.ndarray:
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, quat)
    return matrix.reshape(3, 3)


@pytest.mark.parametrize("quat", QUATERNIONS)
def test_rotation_and_its_axes_match_mujoco(quat):
    r = mujoco_matrix(quat)
    np.testing.assert_allclose(np.reshape(rotation_entries(quat), (3, 3)), r, atol=1e-15)
    np.testing.assert_allclose(world_z_in_body(quat), r[2], atol=1e-15)
    np.testing.assert_allclose(body_z_in_world(quat), r[:, 2], atol=1e-15)
    assert cos_tilt_of(quat) == pytest.approx(r[2, 2], abs=1e-15)
    assert tilt_of(quat) == pytest.approx(math.acos(np.clip(r[2, 2], -1.0, 1.0)), abs=1e-7)


@pytest.mark.parametrize("quat", QUATERNIONS)
def test_rotate_to_body_is_the_inverse_rotation(quat):
    v = np.array([0.3, -1.2, 2.5])
    inverse = np.zeros(4)
    mujoco.mju_negQuat(inverse, quat)
    expected = np.zeros(3)
    mujoco.mju_rotVecQuat(expected, v, inverse)
    np.testing.assert_allclose(rotate_to_body(quat, v), expected, atol=1e-14)


@pytest.mark.parametrize("quat", QUATERNIONS)
def test_euler_angles_rebuild_the_orientation(quat):
    """ZYX: R = Rz(yaw) Ry(pitch) Rx(roll), which MuJoCo builds from the intrinsic sequence "zyx" (lower case)."""
    roll, pitch, yaw = euler_of(quat)
    rebuilt = np.zeros(4)
    mujoco.mju_euler2Quat(rebuilt, [yaw, pitch, roll], "zyx")
    np.testing.assert_allclose(mujoco_matrix(rebuilt), mujoco_matrix(quat), atol=1e-7)


def test_tilt_and_euler_of_known_rotations():
    half = 0.5 * 0.4
    rolled = np.array([math.cos(half), math.sin(half), 0.0, 0.0])   # 0.4 rad about x
    np.testing.assert_allclose(euler_of(rolled), [0.4, 0.0, 0.0], atol=1e-15)
    assert tilt_of(rolled) == pytest.approx(0.4, abs=1e-12)
    np.testing.assert_allclose(world_z_in_body(rolled), [0.0, math.sin(0.4), math.cos(0.4)], atol=1e-15)
    yawed = np.array([math.cos(half), 0.0, 0.0, math.sin(half)])    # heading does not tilt
    assert tilt_of(yawed) == 0.0
    np.testing.assert_allclose(euler_of(yawed), [0.0, 0.0, 0.4], atol=1e-15)
    assert tilt_of(np.array([0.0, 1.0, 0.0, 0.0])) == pytest.approx(math.pi)  # upside down


@pytest.mark.parametrize(("roll", "pitch"), [(0.0, 0.0), (0.3, 0.0), (0.0, -0.5), (-0.2, 0.7), (1.2, -1.1)])
def test_roll_pitch_quaternion_is_zyx_with_yaw_zero(roll, pitch):
    quat = roll_pitch_quaternion(roll, pitch)
    assert math.fsum(v * v for v in quat) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(euler_of(quat), [roll, pitch, 0.0], atol=1e-12)


def test_euler_rows_is_euler_of_on_each_row():
    quats = np.stack(QUATERNIONS)
    np.testing.assert_allclose(euler_rows(quats), np.stack([euler_of(q) for q in quats]), atol=1e-12)
