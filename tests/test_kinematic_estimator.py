"""The kinematic base estimator against the mock's ground truth, fed only what a real BRUCE measures."""

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from bruce_hw.types import FootContacts, ImuSample, JointCommand, JointState, RobotState
from runtime.estimation import euler_of, rotate_to_body
from runtime.kinematic_estimator import KinematicEstimator
from runtime.mixing import eq8_torque
from runtime.standing import StandingController

GRAVITY = 9.81
# A MEMS IMU after a factory calibration, and encoder-differentiated joint velocities (per 1 kHz sample).
GYRO_BIAS, GYRO_NOISE = np.array([0.01, -0.01, 0.005]), 0.004      # rad/s
ACCEL_BIAS, ACCEL_NOISE = np.array([0.1, -0.1, 0.05]), 0.03        # m/s^2
JOINT_VELOCITY_NOISE = 0.05                                         # rad/s
PUSHES = ((1.0, (5.0, 0.0)), (2.0, (-5.0, 0.0)), (3.0, (0.0, 4.0)), (4.0, (0.0, -4.0)))  # (start s, force N)
PUSH_S = 0.1


class Sensors:
    """What the robot would report: no IMU orientation (the sense board has none) and, when `noisy`, sensor
    biases and white noise, seeded so that the test is deterministic."""

    def __init__(self, noisy: bool, seed: int = 0):
        self.noisy = noisy
        self.rng = np.random.default_rng(seed)

    def __call__(self, state: RobotState, contacts: np.ndarray | None = None) -> RobotState:
        imu, joints = dataclasses.replace(state.imu, orientation=None), state.joints
        if self.noisy:
            imu.gyro = imu.gyro + GYRO_BIAS + self.rng.normal(0.0, GYRO_NOISE, 3)
            imu.accel = imu.accel + ACCEL_BIAS + self.rng.normal(0.0, ACCEL_NOISE, 3)
            joints = dataclasses.replace(joints, qd=joints.qd + self.rng.normal(0.0, JOINT_VELOCITY_NOISE, 10))
        foot = state.contacts if contacts is None else dataclasses.replace(state.contacts, contact=contacts)
        return dataclasses.replace(state, imu=imu, joints=joints, contacts=foot)


def rms(errors: list) -> float:
    """Root mean square of the vectors' norms."""
    return float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))


@pytest.mark.parametrize("noisy", [False, True], ids=["ideal_imu", "biased_noisy_sensors"])
def test_tracks_tilt_and_velocity_of_a_pushed_standing_robot(config, noisy):
    backend = MujocoBackend(config)
    backend.configure()
    backend.activate()
    base = backend.model.body("base").id
    controller = StandingController(config)
    sensors = Sensors(noisy)
    state = backend.read()
    controller.reset(state.joints.q)
    estimator = KinematicEstimator(config)
    estimator.reset(sensors(state))
    naive = np.zeros(3)  # the accelerometer integrated with the estimator's attitude, no leg odometry
    velocity_errors, naive_errors, tilt_errors, speeds = [], [], [], []
    for tick in range(6000):
        t = tick * config.dt
        if tick % config.policy_decimation == 0:
            a = controller(state)
        backend.write(JointCommand(eq8_torque(a, state.joints.q, state.joints.qd, config.eq8)))
        backend.data.xfrc_applied[base, 0:2] = next((f for t0, f in PUSHES if t0 <= t < t0 + PUSH_S), (0.0, 0.0))
        state = backend.read()
        measured = sensors(state)
        estimator.update(measured)
        estimate = estimator.estimate()
        world_accel = rotate_to_body(estimate.quat * (1.0, -1.0, -1.0, -1.0), measured.imu.accel)  # R a
        naive += (world_accel - (0.0, 0.0, GRAVITY)) * config.dt
        if tick % config.policy_decimation == 0:
            truth = backend.ground_truth()
            truth_linvel = rotate_to_body(truth.base_quat, truth.base_linvel)
            velocity_errors.append(estimate.linvel - truth_linvel)
            naive_errors.append(rotate_to_body(estimate.quat, naive) - truth_linvel)
            tilt_errors.append(estimate.euler[:2] - euler_of(truth.base_quat)[:2])
            speeds.append(math.hypot(*truth.base_linvel[:2]))

    assert max(speeds) > 0.08  # the pushes moved it (~0.12 m/s), and it stayed up
    assert backend.ground_truth().base_pos[2] > 0.38
    # measured (attitude gain 0.3): velocity RMSE 0.0034 m/s (ideal IMU), naive 0.029 m/s; with the biased, noisy
    # sensors the naive integration is far worse
    np.testing.assert_array_less(np.degrees(np.sqrt(np.mean(np.square(tilt_errors), axis=0))), 2.0)
    assert rms(velocity_errors) < 0.02
    assert rms(naive_errors) > 5 * rms(velocity_errors)


def test_no_foot_on_the_ground_velocity_from_the_imu_alone(config):
    """Dropped from 0.3 m with the legs swinging: every contact switch open, so the leg odometry (which then
    describes the legs' swing, not the base's motion) must be ignored and the velocity follows the IMU."""
    backend = MujocoBackend(config)
    backend.configure()
    backend.activate()
    backend.data.qpos[2] += 0.3
    mujoco.mj_forward(backend.model, backend.data)
    sensors = Sensors(noisy=False)
    state = backend.read()
    in_air, wrongly_on_ground = KinematicEstimator(config), KinematicEstimator(config)
    all_closed = np.ones(4, dtype=bool)
    in_air.reset(sensors(state))
    wrongly_on_ground.reset(sensors(state, all_closed))
    swing = np.zeros(config.n_joints)
    swing[config.joint_indices("hip_pitch", "knee")] = 0.4
    errors, wrong_errors = [], []
    for tick in range(230):  # the feet touch the floor after ~0.25 s
        a = config.standing_pose + swing * math.sin(2 * math.pi * 4.0 * tick * config.dt)
        backend.write(JointCommand(eq8_torque(a, state.joints.q, state.joints.qd, config.eq8)))
        state = backend.read()
        assert not state.contacts.contact.any()
        in_air.update(sensors(state))
        wrongly_on_ground.update(sensors(state, all_closed))
        truth = backend.ground_truth()
        truth_linvel = rotate_to_body(truth.base_quat, truth.base_linvel)
        estimate = in_air.estimate()
        assert all(np.all(np.isfinite(v)) for v in (estimate.quat, estimate.linvel, estimate.angvel, estimate.euler))
        errors.append(estimate.linvel - truth_linvel)
        wrong_errors.append(wrongly_on_ground.estimate().linvel - truth_linvel)

    assert backend.ground_truth().base_linvel[2] < -2.0  # falling, not held
    assert np.max(np.abs(errors)) < 0.03  # measured 0.013 (0.0098 of it: reset assumes rest, 1 ms into the fall)
    assert np.max(np.abs(wrong_errors)) > 1.0  # what the swinging legs' odometry would have said


def rest_state(t: float, roll: float = 0.0, pitch: float = 0.0, gyro=(0.0, 0.0, 0.0), contact=(True,) * 4,
               q: np.ndarray | None = None, qd: np.ndarray | None = None) -> RobotState:
    """A state with the base tilted by (roll, pitch) and not accelerating (specific force = g up)."""
    accel = GRAVITY * np.array([-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)])
    zeros = np.zeros(10)
    return RobotState(
        joints=JointState(q=zeros if q is None else q, qd=zeros if qd is None else qd, tau=zeros,
                          temperature=zeros, stamp=t),
        imu=ImuSample(gyro=np.array(gyro, dtype=float), accel=accel, orientation=None, stamp=t),
        contacts=FootContacts(contact=np.array(contact), stamp=t))


def test_reset_starts_at_rest_with_yaw_zero_and_the_measured_tilt(config):
    estimator = KinematicEstimator(config)
    estimator.reset(rest_state(0.0, contact=(False,) * 4))
    for tick in range(1, 500):  # spinning, and accelerating sideways in the air
        moving = rest_state(tick * config.dt, gyro=(0.0, 0.0, 1.0), contact=(False,) * 4)
        moving.imu.accel[1] += 2.0
        estimator.update(moving)
    moved = estimator.estimate()
    assert moved.euler[2] == pytest.approx(0.5, abs=0.01) and np.linalg.norm(moved.linvel) > 0.5

    roll, pitch = 0.05, -0.08
    estimator.reset(rest_state(1.0, roll, pitch, gyro=(0.01, 0.02, 0.03)))
    estimate = estimator.estimate()
    np.testing.assert_array_equal(estimate.linvel, 0.0)
    np.testing.assert_allclose(estimate.euler, [roll, pitch, 0.0], atol=1e-12)
    np.testing.assert_allclose(estimate.angvel, [0.01, 0.02, 0.03])

    # a specific force far from g (the mock's first tick, as its contacts settle) says nothing about tilt
    falling = rest_state(0.0, roll, pitch)
    falling.imu.accel *= 0.1
    estimator.reset(falling)
    np.testing.assert_allclose(estimator.estimate().euler, 0.0, atol=1e-12)


def test_a_foot_that_just_touched_down_is_trusted_less_than_a_settled_one(config):
    """The same odometry (legs moving, base at rest by the IMU) from a foot down since reset and from a foot
    whose switches just closed: the settled foot pulls the velocity much harder on the first tick."""
    qd = np.zeros(10)
    qd[config.joint_indices("knee")] = 1.0
    settled, touching_down = KinematicEstimator(config), KinematicEstimator(config)
    settled.reset(rest_state(0.0, q=config.standing_pose))
    touching_down.reset(rest_state(0.0, q=config.standing_pose, contact=(False,) * 4))
    for estimator in (settled, touching_down):
        estimator.update(rest_state(config.dt, q=config.standing_pose, qd=qd))
    first_settled = np.linalg.norm(settled.estimate().linvel)
    first_touchdown = np.linalg.norm(touching_down.estimate().linvel)
    assert first_touchdown < 0.05 * first_settled
    for tick in range(2, 300):  # once the touchdown window is over, both follow the odometry
        for estimator in (settled, touching_down):
            estimator.update(rest_state(tick * config.dt, q=config.standing_pose, qd=qd))
    np.testing.assert_allclose(touching_down.estimate().linvel, settled.estimate().linvel, rtol=0.01, atol=1e-3)
    assert np.linalg.norm(settled.estimate().linvel) > 0.1
