import math

import numpy as np
import pytest
from support.safety_fixtures import robot, running_stage

from runtime.loop.safety import SafetyStage, SafetyState


def roll_quaternion(deg):
    half = math.radians(deg) / 2
    return (math.cos(half), math.sin(half), 0.0, 0.0)


def test_output_is_within_joint_and_actuator_limits(config):
    stage = running_stage(config)
    rng = np.random.default_rng(0)
    for _ in range(200):
        tau = stage.filter(rng.normal(0, 40, config.n_joints), robot(config))
        assert np.all(np.abs(tau) <= config.tau_limit + 1e-9)
        assert np.all(np.abs(config.coupling.actuator_torques(tau)) <= config.actuator_torque_limit + 1e-9)


def test_rate_of_change_is_limited(config):
    stage = running_stage(config)
    step = config.safety.max_torque_rate * config.dt
    first = stage.filter(np.full(config.n_joints, 8.0), robot(config))
    np.testing.assert_allclose(first, step)  # from zero, one tick moves at most max_torque_rate * dt
    second = stage.filter(np.full(config.n_joints, 8.0), robot(config))
    np.testing.assert_allclose(second, 2 * step)


def test_no_torque_pushes_further_past_a_position_soft_limit(config):
    stage = running_stage(config)
    knee = config.joints.index("r_knee")
    q = config.standing_pose.copy()
    q[knee] = config.q_upper[knee] - config.safety.position_margin / 2  # inside the margin, near the top stop
    tau = np.zeros(config.n_joints)
    tau[knee] = 1.0
    assert stage.filter(tau, robot(config, q=q))[knee] == 0.0  # further up: removed
    tau[knee] = -1.0
    assert stage.filter(tau, robot(config, q=q))[knee] < 0.0  # back towards the range: kept


def test_no_torque_accelerates_beyond_the_velocity_limit(config):
    stage = running_stage(config)
    qd = np.zeros(config.n_joints)
    qd[0] = config.qd_limit[0] * 1.1
    out = stage.filter(np.array([1.0] + [0.0] * 9), robot(config, qd=qd))
    assert out[0] == 0.0
    out = stage.filter(np.array([-1.0] + [0.0] * 9), robot(config, qd=qd))
    assert out[0] < 0.0  # braking is allowed


def test_soft_start_ramps_torques_in(config):
    stage = SafetyStage(config)
    small = np.full(config.n_joints, 0.5)
    outputs = [stage.filter(small, robot(config))[0] for _ in range(stage.ramp_ticks + 5)]
    assert outputs[0] == pytest.approx(0.5 / stage.ramp_ticks)
    assert np.all(np.diff(outputs[: stage.ramp_ticks]) > 0)
    assert outputs[-1] == pytest.approx(0.5)
    assert stage.state is SafetyState.RUNNING


def test_non_finite_command_trips_to_damping_torque(config):
    stage = running_stage(config)
    tau = np.zeros(config.n_joints)
    tau[3] = np.nan
    qd = np.linspace(-1, 1, config.n_joints)
    out = stage.filter(tau, robot(config, qd=qd))
    assert stage.tripped and "r_knee" in stage.cause
    np.testing.assert_allclose(out, -config.safety.damping_kd * qd)


def test_tilt_must_persist_for_the_configured_ticks(config):
    stage = running_stage(config)
    ticks = config.safety.tilt_ticks
    tilted = robot(config, orientation=roll_quaternion(config.safety.tilt_limit_deg + 5))
    for _ in range(ticks - 1):
        stage.check(tilted, now=0.0)
    stage.check(robot(config), now=0.0)  # one upright reading restarts the count
    for _ in range(ticks - 1):
        stage.check(tilted, now=0.0)
    assert not stage.tripped
    stage.check(tilted, now=0.0)
    assert stage.tripped and "tilt" in stage.cause


def test_tilt_from_the_accelerometer_when_there_is_no_orientation(config):
    stage = running_stage(config)
    state = robot(config, orientation=None)
    state.imu.accel = np.array([0.0, 9.81, 0.0])  # lying on its side
    for _ in range(config.safety.tilt_ticks):
        stage.check(state, now=0.0)
    assert stage.tripped and "tilt 90 deg" in stage.cause


@pytest.mark.parametrize("which", ["joint", "IMU"])
def test_stale_sensor_data_trips(config, which):
    stage = running_stage(config)
    age = config.safety.max_sensor_age_s
    old = robot(config, stamp=1.0, imu_stamp=1.0 + age) if which == "joint" else \
        robot(config, stamp=1.0 + age, imu_stamp=1.0)
    stage.check(old, now=1.0 + 0.999 * age)  # just inside the limit: fine (1.0 + age - 1.0 may round above it)
    assert not stage.tripped
    stage.check(old, now=1.0 + 1.5 * age)
    assert stage.tripped and f"stale {which} data" in stage.cause


def test_estop_trips(config):
    stage = running_stage(config)
    stage.check(robot(config, estop=True), now=0.0)
    assert stage.tripped and "e-stop" in stage.cause


@pytest.mark.parametrize("not_run", [True, False], ids=["a stall beyond the bound", "a slow window"])
def test_an_estop_is_named_before_a_slow_window_but_not_before_a_long_stall(config, not_run):
    """The first tick after a gap may find the E-stop bit together with a rate below the floor (the process run,
    slowly): the press is the cause a person needs to read. Found with a stall beyond the bound (the process not
    run), the bit is the BEARs' own watchdog as likely as a press (the same error bit 3), and the stall is named.
    Without the bit the same tick trips on the other cause."""
    causes = []
    for estop in (True, False):
        stage = SafetyStage(config, stalled=(lambda t0, t1: t1 - t0) if not_run else None)
        stage.state = SafetyState.RUNNING
        now = 0.0
        for _ in range(stage.rate_ticks):
            now += config.dt
            stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
        assert not stage.tripped, stage.cause
        now += 2 * max(config.safety.host_stall_max_s, config.safety.rate_window_s)
        stage.check(robot(config, estop=estop, stamp=now, imu_stamp=now), now=now)
        causes.append(stage.cause)
    other = "host stall" if not_run else "below safety.min_rate_hz"
    assert other in causes[1], causes
    assert other in causes[0] if not_run else causes[0] == "e-stop input asserted", causes


def test_rate_floor_trips_on_a_slow_window_not_on_one_late_tick(config):
    """A late tick is not a fault; fewer than safety.min_rate_hz ticks over safety.rate_window_s is one."""
    cfg = config.safety
    stage = running_stage(config)
    now, dt = 0.0, config.dt
    for _ in range(3 * stage.rate_ticks):  # on time
        now += dt
        stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
    now += 0.4 * cfg.rate_window_s  # one stall of 20 ms: the window still holds enough ticks
    for _ in range(2 * stage.rate_ticks):
        stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
        now += dt
    assert not stage.tripped, stage.cause
    slow = 1.0 / (0.8 * cfg.min_rate_hz)  # steadily below the floor
    for _ in range(stage.rate_ticks + 1):
        now += slow
        stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
        if stage.tripped:
            break
    assert stage.tripped and f"loop ran {stage.rate_ticks} ticks in" in stage.cause
    assert "below safety.min_rate_hz 500 Hz over safety.rate_window_s 50 ms" in stage.cause


def test_damping_is_sticky_and_keeps_the_first_cause(config):
    stage = running_stage(config)
    stage.trip("first")
    stage.trip("second")
    stage.check(robot(config, estop=True), now=0.0)
    out = stage.filter(np.full(config.n_joints, 5.0), robot(config, qd=np.ones(config.n_joints)))
    assert stage.cause == "first"
    np.testing.assert_allclose(out, -config.safety.damping_kd)
    assert [text for _, text in stage.transitions][-1].endswith("first")
