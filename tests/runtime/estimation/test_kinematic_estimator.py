"""The kinematic base estimator against the mock's ground truth, fed only what a real BRUCE measures."""

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bruce_hw.attitude import MahonyAttitude
from bruce_hw.mock import MujocoBackend
from bruce_hw.quaternion import euler_of, rotate_to_body
from bruce_hw.types import FootContacts, ImuSample, JointCommand, JointState, RobotState
from runtime.control.commands import CommandSchedule
from runtime.control.mixing import eq8_torque
from runtime.control.standing import StandingController
from runtime.estimation import GroundTruthEstimator
from runtime.estimation.kinematic import IMU_DELAY_S, KinematicEstimator, plane_normal
from runtime.loop.run import run_session

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
    first = sensors(state)
    estimator.reset(first)
    # The accelerometer integrated with the IMU's own attitude (the hw backend's filter), no leg odometry: the
    # estimator's attitude is corrected with the odometry, so integrating with it would not be "without".
    imu_attitude = MahonyAttitude(GRAVITY)
    imu_attitude.reset(first.imu.gyro, first.imu.accel, first.imu.stamp)
    naive = np.zeros(3)
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
        imu_quat = np.array(imu_attitude.update(measured.imu.gyro, measured.imu.accel, measured.imu.stamp))
        world_accel = rotate_to_body(imu_quat * (1.0, -1.0, -1.0, -1.0), measured.imu.accel)  # R a
        naive += (world_accel - (0.0, 0.0, GRAVITY)) * config.dt
        if tick % config.policy_decimation == 0:
            truth = backend.ground_truth()
            truth_linvel = rotate_to_body(truth.base_quat, truth.base_linvel)
            velocity_errors.append(estimate.linvel - truth_linvel)
            naive_errors.append(rotate_to_body(imu_quat, naive) - truth_linvel)
            tilt_errors.append(estimate.euler[:2] - euler_of(truth.base_quat)[:2])
            speeds.append(math.hypot(*truth.base_linvel[:2]))

    assert max(speeds) > 0.08  # the pushes moved it (~0.12 m/s), and it stayed up
    assert backend.ground_truth().base_pos[2] > 0.38
    # measured: velocity RMSE 0.0029 m/s (ideal IMU), naive 0.029 m/s; biased, noisy sensors 0.033 m/s, naive 0.79 (it
    # was 0.012 with a 30 ms velocity filter): until the attitude filter has learned the 0.01 rad/s gyro bias (tens
    # of s), it leaves 0.01 / 0.3 rad of tilt error, 0.3 m/s^2 of false acceleration, and the velocity filter's
    # 100-140 ms time constant (for the odometry's errors while walking) lets more of it through.
    np.testing.assert_array_less(np.degrees(np.sqrt(np.mean(np.square(tilt_errors), axis=0))), 2.0)
    assert rms(velocity_errors) < (0.04 if noisy else 0.01)
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
    # what the swinging legs' odometry would have said: 0.98 m/s within the 0.23 s (the velocity filter's time
    # constant is 100 ms with both feet "down"), and growing
    assert np.max(np.abs(wrong_errors)) > 0.5


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
    np.testing.assert_allclose(euler_of(np.array(estimator.attitude.quat)), [roll, pitch, 0.0], atol=1e-12)
    # the estimate is carried forward over the IMU's delay at the measured (body) rate
    carried = np.array(estimator.attitude.quat)
    mujoco.mju_quatIntegrate(carried, np.array([0.01, 0.02, 0.03]), IMU_DELAY_S)
    np.testing.assert_allclose(estimate.euler, euler_of(carried), atol=1e-12)
    assert estimate.euler[2] == pytest.approx(0.031 * IMU_DELAY_S, rel=0.05)  # yaw rate (sin r wy + cos r wz) / cos p
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


def test_gravity_less_the_base_acceleration_is_unbiased_where_the_faded_specific_force_is_not():
    """A level base swaying sideways and bobbing at a step's frequency, in phase (the lateral and vertical
    accelerations of walking are correlated). Both average to zero, so the specific force's mean is g, straight up;
    but fading it by |a| and normalising it weighs the phases unequally and the faded filter settles tilted. Given
    the base's acceleration, the filter takes gravity in linearly and stays level, also with a noisy acceleration."""
    faded, compensated = MahonyAttitude(GRAVITY), MahonyAttitude(GRAVITY)
    rng = np.random.default_rng(0)
    omega = 2.0 * math.pi * 1.6
    rate = np.zeros(3)
    for tick in range(30000):
        t = tick * 0.001
        sway = math.sin(omega * t)
        linear = np.array([0.0, 2.0 * sway, 2.5 * sway])  # m/s^2, world = base (it does not turn)
        accel = linear + (0.0, 0.0, GRAVITY)
        if tick == 0:
            faded.reset(rate, accel, t)
            compensated.reset(rate, accel, t)
        faded.update(rate, accel, t)
        compensated.update(rate, accel, t, tuple(linear + rng.normal(0.0, 0.5, 3)))
    assert abs(math.degrees(euler_of(np.array(faded.quat))[0])) > 0.5  # measured 0.92 deg
    np.testing.assert_array_less(np.abs(np.degrees(euler_of(np.array(compensated.quat))[:2])), 0.1)


def _errors(estimate, truth):
    """Linear velocity (base frame), roll/pitch and yaw errors of an estimate against the mock's truth."""
    euler = euler_of(truth.base_quat)
    return (estimate.linvel - rotate_to_body(truth.base_quat, truth.base_linvel), estimate.euler[:2] - euler[:2],
            math.remainder(estimate.euler[2] - euler[2], math.tau))


class KinematicWithErrors:
    """The kinematic estimator as the controller's base state (`drive`), or beside the truth that drives it,
    its errors against the simulator's truth recorded at every policy tick."""

    def __init__(self, backend, config, drive: bool):
        self.backend, self.drive = backend, drive
        self.kinematic = KinematicEstimator(config)
        self.velocity, self.tilt, self.yaw = [], [], []

    def reset(self, state):
        self.kinematic.reset(state)

    def update(self, state):
        self.kinematic.update(state)

    def estimate(self):
        estimate, truth = self.kinematic.estimate(), self.backend.ground_truth()
        velocity, tilt, yaw = _errors(estimate, truth)
        self.velocity.append(velocity)
        self.tilt.append(np.degrees(tilt))
        self.yaw.append(math.degrees(yaw))
        return estimate if self.drive else GroundTruthEstimator(self.backend).estimate()


def _walk(config, controller_kind, cmd, seconds, drive):
    backend = MujocoBackend(config)
    estimator = KinematicWithErrors(backend, config, drive)
    # privileged: the estimator here is instrumented with the simulator's truth to score itself
    summary = run_session(backend, config, duration=seconds, realtime=False, controller_kind=controller_kind,
                          commands=CommandSchedule.constant(*cmd), estimator=estimator, privileged=True)
    return summary, estimator


def test_the_estimate_tracks_tilt_and_velocity_while_the_teacher_walks_on_the_truth(config):
    """Open loop (the teacher walks on the truth): the README's velocity figure, and the tilt it did not measure.
    With the specific force faded by |a| as the attitude's gravity, the roll error grew while walking, to 2.1 deg
    within 20 s (RMS 1.5 deg; 3.7 deg after 30 s under the policy), and the horizontal velocity RMSE was 0.051 m/s;
    now under 0.1 deg RMS and 0.016 m/s."""
    summary, estimator = _walk(config, "teacher", (0.4, 0.0, 0.0), 20.0, drive=False)
    assert not summary.truth.fell
    tilt = np.array(estimator.tilt[100:])  # after the first second
    velocity = np.array(estimator.velocity[100:])
    print(f"open loop: tilt RMS {np.sqrt(np.mean(tilt ** 2, axis=0))} deg, max {np.abs(tilt).max(axis=0)} deg, "
          f"velocity RMSE {np.sqrt(np.mean(velocity ** 2, axis=0))} m/s")
    np.testing.assert_array_less(np.sqrt(np.mean(tilt ** 2, axis=0)), 0.3)
    np.testing.assert_array_less(np.abs(tilt[-500:].mean(axis=0)), 0.2)  # no drift: the last 5 s
    assert rms(velocity[:, :2]) < 0.03


# Walking on the estimate, as on the robot: with the specific force faded by |a| as the attitude's gravity (its
# roll 2-3 deg off), a 30 ms velocity filter and no carrying forward over the IMU's delay, the policy fell at 8.3 s
# (0.4, 0, 0) and 8.1 s (0.4, 0, 0.3), and the teacher's targets left their range at 4.3 s and 8.8 s.
@pytest.mark.parametrize("cmd", [(0.4, 0.0, 0.0), (0.4, 0.0, 0.3)], ids=["straight", "turning"])
@pytest.mark.parametrize("controller_kind", ["policy", "teacher"])
def test_walks_on_the_kinematic_estimate(config, controller_kind, cmd):
    summary, estimator = _walk(config, controller_kind, cmd, 20.0, drive=True)
    assert summary.exit_code == 0 and not summary.truth.fell, summary.stop_cause
    assert summary.truth.tracking_error["vx"] < 0.1
    velocity, tilt, yaw = np.array(estimator.velocity[100:]), np.array(estimator.tilt[100:]), np.array(estimator.yaw)
    # measured over 30 s: velocity RMSE <= 0.008 m/s forward, 0.015 lateral; tilt <= 0.2 deg; yaw <= 0.15 deg
    np.testing.assert_array_less(np.sqrt(np.mean(velocity[:, :2] ** 2, axis=0)), 0.03)
    np.testing.assert_array_less(np.abs(tilt).max(axis=0), 0.5)
    assert np.abs(yaw).max() < 1.0


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), off_plane=st.floats(0.0, 0.002), length=st.floats(0.03, 0.12),
       width=st.floats(0.03, 0.2))
def test_the_feet_planes_normal_is_the_svds_to_round_off(seed, off_plane, length, width):
    """Four toe and heel centres in their order around the feet (right toe, right heel, left heel, left toe), a few
    cm apart and up to 2 mm off one plane, anywhere and at any attitude: `plane_normal` (scalar math, for the
    control thread) gives the least-squares plane's normal that the SVD of the centred points gives."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, rng.normal(size=3))
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    corners = [(length / 2, -width / 2), (-length / 2, -width / 2), (-length / 2, width / 2), (length / 2, width / 2)]
    centre = rng.normal(size=3)
    points = np.array([centre + (x + rng.uniform(-0.01, 0.01)) * u + (y + rng.uniform(-0.01, 0.01)) * v
                       + off_plane * rng.normal() * normal for x, y in corners])
    expected = np.linalg.svd(points - points.mean(axis=0))[2][-1]
    got = np.array(plane_normal(*points.tolist()))
    assert abs(np.linalg.norm(got) - 1.0) < 1e-12
    assert np.linalg.norm(np.cross(got, expected)) < 1e-12  # sin of the angle between them


def _levelled_bias(accel_bias, seconds=1.5, level_s=1.0):
    """The horizontal accelerometer bias a levelling estimator learns while the standing controller holds the mock
    whose accelerometer reads `accel_bias` off, and its bias at the end of levelling and at the end of the run."""
    from bruce_hw.config import load_config
    from bruce_hw.reality_gap import parse_gap

    config = load_config(overrides=[f"estimator.level_from_feet_s={level_s}"])
    gap = parse_gap({"imu": {"accel_bias": list(accel_bias)}}, "test")
    estimator = KinematicEstimator(config)
    seen = []

    class Watch:
        def on_start(self, backend, config):
            pass

        def on_tick(self, view):
            seen.append(estimator.accel_bias)

        def on_end(self, summary):
            pass

    run_session(MujocoBackend(config, gap=gap), config, duration=seconds, realtime=False, controller_kind="standing",
                estimator=estimator, observers=[Watch()])
    return np.array(seen)


def test_levelling_from_the_feet_learns_the_accelerometers_horizontal_bias_then_holds_it():
    biased = _levelled_bias((0.05, -0.05, 0.0))
    clean = _levelled_bias((0.0, 0.0, 0.0))
    # what the feet say about gravity, less what the accelerometer reads: the injected bias, to a few mm/s^2 (the
    # clean robot's own value is what the feet plane and the IMU disagree on without any bias)
    np.testing.assert_allclose(biased[999] - clean[999], [0.05, -0.05], atol=0.005)
    assert np.array_equal(biased[1000], biased[-1])  # learned only in the first level_from_feet_s
    off = _levelled_bias((0.05, -0.05, 0.0), seconds=0.3, level_s=0.0)
    assert not off.any()  # off by default: the estimator as it was
