"""Reality-gap profiles (bruce_hw/reality_gap.py) applied by the mock backend: each mechanism against its definition,
the shipped profiles, the errors, and `bruce-run --gap`."""

from __future__ import annotations

import json
import math
from dataclasses import fields, replace

import mujoco
import numpy as np
import pytest

from bruce_hw.mock import CONTACT_THRESHOLD_N, MujocoBackend
from bruce_hw.reality_gap import GapError, RealityGap, SensorGap, load_gap, profile_names
from bruce_hw.types import FootContacts, ImuSample, JointCommand, JointState, RobotState
from runtime.cli import main
from runtime.control.commands import CommandSchedule
from runtime.loop.observers import EachTick
from runtime.loop.run import run_session

KNEE = 3  # r_knee in the config's joint order
# The shipped one-factor profiles (configs/gaps/) and the RealityGap fields each sets.
ONE_FACTOR_KEYS = {"latency_2ms": {"actuator_latency_s"}, "torque_lag_2ms": {"actuator_time_constant_s"},
                   "torque_constant_0p8": {"torque_scale"}, "coulomb_0p2": {"coulomb"}, "viscous_0p05": {"viscous"},
                   "mass_1p2": {"mass_scale", "inertia_scale"}, "armature_add_1bear": {"armature_add"},
                   "sensor_noise_1ms": {"q_noise", "qd_noise", "sensor_latency_s"},
                   "contact_delay_bounce": {"contact_delay_s", "contact_bounce_s"},
                   "imu_latency_3ms": {"imu_latency_s"}, "encoder_quantisation": {"q_resolution"}}


def configured(config, gap: RealityGap | None = None) -> MujocoBackend:
    mock = MujocoBackend(config, gap=gap)
    mock.configure()
    return mock


def true_joints(mock: MujocoBackend) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions and velocities straight from the simulation (MuJoCo's named access, no backend internals)."""
    data = mock.data
    return (np.array([data.joint(name).qpos[0] for name in mock.config.joints]),
            np.array([data.joint(name).qvel[0] for name in mock.config.joints]))


# -- command path ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("ticks", "time_constant_s"), [(3, 0.0), (2, 0.002), (0, 0.004)])
def test_step_torque_arrives_after_the_latency_then_rises_with_the_time_constant(config, ticks, time_constant_s):
    gap = RealityGap(actuator_latency_s=ticks * config.dt, actuator_time_constant_s=time_constant_s)
    with configured(config, gap) as mock:
        mock.activate()
        for _ in range(10):
            mock.read()
            mock.write(JointCommand(tau_ff=np.zeros(config.n_joints)))
        mock.read()
        step = np.zeros(config.n_joints)
        step[KNEE] = 1.0
        mock.write(JointCommand(tau_ff=step))  # sent now: nominally applied during the next read's physics step
        applied = np.array([mock.read().joints.tau[KNEE] for _ in range(30)])
    m = np.arange(1, 31)  # reads after the write
    after = np.maximum(m - ticks, 0)
    closed_form = 1.0 - np.exp(-after * config.dt / time_constant_s) if time_constant_s else (after > 0) * 1.0
    np.testing.assert_array_equal(applied[:ticks], 0.0)
    np.testing.assert_allclose(applied, closed_form, rtol=1e-9, atol=1e-12)


def test_torque_limit_scale_saturates_each_actuator_lower(config):
    with configured(config, RealityGap(torque_limit_scale=0.8)) as mock:
        mock.activate()
        mock.read()
        mock.write(JointCommand(tau_ff=np.full(config.n_joints, 50.0)))
        tau = mock.read().joints.tau
    per_actuator = np.abs(config.coupling.actuator_torques(tau))
    assert per_actuator.max() == pytest.approx(0.8 * config.actuator_torque_limit)
    assert np.all(per_actuator <= 0.8 * config.actuator_torque_limit + 1e-9)


@pytest.mark.parametrize("torque_scale", [0.8, {"r_knee": 0.8}])
def test_torque_scale_gives_the_joint_that_share_of_the_command(config, torque_scale):
    """A torque-constant error: the joint gets torque_scale x the (saturated) command, every tick, whatever the
    limit; a per-joint mapping leaves the other joints at the command."""
    command = np.linspace(-2.0, 2.0, config.n_joints)  # well inside every limit
    expected_scale = RealityGap(torque_scale=torque_scale).per_joint("torque_scale", config.joints)
    with configured(config, RealityGap(torque_scale=torque_scale)) as scaled, configured(config) as nominal:
        applied = {}
        for name, mock in (("scaled", scaled), ("nominal", nominal)):
            mock.activate()
            mock.read()
            mock.write(JointCommand(tau_ff=command))
            applied[name] = np.array([mock.read().joints.tau for _ in range(5)])
    np.testing.assert_allclose(applied["nominal"], np.broadcast_to(command, (5, config.n_joints)), atol=1e-12)
    np.testing.assert_allclose(applied["scaled"], applied["nominal"] * expected_scale, rtol=1e-12, atol=1e-12)
    assert expected_scale[KNEE] == 0.8 and (isinstance(torque_scale, float) or expected_scale[0] == 1.0)


def test_torque_scale_moves_a_joint_from_rest_with_that_share_of_the_acceleration(config):
    """In the air (no contact), one tick of a knee torque from rest: the knee's velocity change scales with it."""
    step = np.zeros(config.n_joints)
    step[KNEE] = 1.0
    gained = {}
    for scale in (1.0, 0.8):
        with configured(config, RealityGap(torque_scale=scale)) as mock:
            mock.data.qpos[2] += 0.5
            mujoco.mj_forward(mock.model, mock.data)
            mock.activate()
            before = mock.read().joints.qd[KNEE]
            mock.write(JointCommand(tau_ff=step))
            gained[scale] = mock.read().joints.qd[KNEE] - before
    assert gained[1.0] > 0.0
    assert gained[0.8] / gained[1.0] == pytest.approx(0.8, rel=0.02)


# -- friction ----------------------------------------------------------------------------------------------------
def spin_in_the_air(config, gap: RealityGap | None, ticks: int = 40) -> tuple[float, MujocoBackend]:
    """The knee spun at 4 rad/s with the robot 0.5 m up (no contact; a free fall loads no joint) and the motors
    off; its velocity after `ticks` and the backend, left at that state with forces computed."""
    mock = configured(config, gap)
    mock.data.qpos[2] += 0.5
    mock.data.joint("r_knee").qvel[0] = 4.0
    mujoco.mj_forward(mock.model, mock.data)
    for _ in range(ticks):
        qd = mock.read().joints.qd[KNEE]
    mujoco.mj_forward(mock.model, mock.data)  # forces at the state reached
    return qd, mock


def test_coulomb_friction_opposes_motion_and_slows_the_joint(config):
    nominal, _ = spin_in_the_air(config, None)
    slowed, mock = spin_in_the_air(config, RealityGap(coulomb={"r_knee": 0.3}))
    assert 0.0 < slowed < nominal - 0.1
    dof = mock.model.joint("r_knee").dofadr[0]
    assert mock.model.dof_frictionloss[dof] == 0.3
    friction = mock.data.qfrc_constraint[dof]  # in the air only the frictionloss constraint acts on the knee
    assert friction < 0.0 < mock.data.qvel[dof]
    assert friction == pytest.approx(-0.3, rel=0.05)


def test_viscous_friction_opposes_motion_and_slows_the_joint(config):
    nominal, nominal_mock = spin_in_the_air(config, None)
    slowed, mock = spin_in_the_air(config, RealityGap(viscous=0.1))
    assert 0.0 < slowed < nominal - 0.1
    dof = mock.model.joint("r_knee").dofadr[0]
    mjcf_damping = nominal_mock.model.dof_damping[dof]
    assert mock.model.dof_damping[dof] == pytest.approx(mjcf_damping + 0.1)
    assert mock.data.qfrc_damper[dof] == pytest.approx(-(mjcf_damping + 0.1) * mock.data.qvel[dof])
    assert mock.data.qfrc_damper[dof] < 0.0


# -- inertia -----------------------------------------------------------------------------------------------------
def test_scaled_mass_inertia_and_armature_are_in_the_model(config):
    nominal = configured(config).model
    gap = RealityGap(mass_scale=1.1, inertia_scale=1.2, armature_scale=2.0, armature_add={"r_knee": 0.001})
    model = configured(config, gap).model
    assert mujoco.mj_getTotalmass(model) == pytest.approx(1.1 * mujoco.mj_getTotalmass(nominal), rel=1e-12)
    np.testing.assert_allclose(model.body_inertia, 1.2 * nominal.body_inertia, rtol=1e-12)
    base = model.body("base").id
    assert model.body_subtreemass[base] == pytest.approx(1.1 * nominal.body_subtreemass[base], rel=1e-12)
    dofs = [model.joint(name).dofadr[0] for name in config.joints]
    expected = 2.0 * nominal.dof_armature[dofs]
    expected[KNEE] += 0.001
    np.testing.assert_allclose(model.dof_armature[dofs], expected, rtol=1e-12)


def standing_load(config, gap: RealityGap | None) -> tuple[float, float]:
    """(mean vertical ground force over the last 100 of 400 ticks standing on a stiff PD, total mass x g)."""
    kp = np.where(np.isin(np.arange(config.n_joints), config.joint_indices("ankle")), 20.0, 80.0)
    hold = JointCommand(tau_ff=np.zeros(config.n_joints), q_ref=config.standing_pose, kp=kp, kd=0.1 * kp)
    with configured(config, gap) as mock:
        mock.activate()
        loads = []
        for tick in range(400):
            mock.read()
            mock.write(hold)
            if tick >= 300:
                loads.append(mock.data.qfrc_constraint[2])  # the contacts on the base's world-z dof
        weight = mujoco.mj_getTotalmass(mock.model) * -mock.model.opt.gravity[2]
    return float(np.mean(loads)), weight


def test_scaled_mass_loads_the_feet_accordingly(config):
    nominal_load, nominal_weight = standing_load(config, None)
    heavier_load, heavier_weight = standing_load(config, RealityGap(mass_scale=1.15, inertia_scale=1.15))
    assert nominal_load == pytest.approx(nominal_weight, rel=0.02)
    assert heavier_load == pytest.approx(heavier_weight, rel=0.02)
    assert heavier_load / nominal_load == pytest.approx(1.15, rel=0.03)


# -- sensor path -------------------------------------------------------------------------------------------------
def test_encoder_and_imu_noise_have_the_configured_std_and_bias(config):
    q_bias = {"r_knee": 0.01, "l_ankle": -0.02}
    gap = RealityGap(seed=3, q_noise=2e-3, q_bias=q_bias, qd_noise=0.05, qd_bias=-0.01, gyro_noise=0.01,
                     gyro_bias=[0.002, -0.001, 0.0], accel_noise=0.05, accel_bias=0.03)
    n_ticks = 2000
    q_err, qd_err, gyro_err, accel_err = [], [], [], []
    with configured(config, gap) as mock:
        for _ in range(n_ticks):  # inactive: the robot folds up, which does not matter here
            state = mock.read()
            q, qd = true_joints(mock)
            q_err.append(state.joints.q - q)
            qd_err.append(state.joints.qd - qd)
            gyro_err.append(state.imu.gyro - mock.data.sensor("imu_gyro").data)
            accel_err.append(state.imu.accel - mock.data.sensor("imu_accel").data)

    def check(errors, std, bias):
        errors = np.array(errors)
        samples = errors.size
        # Gaussian: the sample std's relative standard error is 1/sqrt(2N), the mean's is std/sqrt(n): 5 sigma.
        assert (errors - bias).std() == pytest.approx(std, rel=5 / math.sqrt(2 * samples))
        np.testing.assert_allclose(errors.mean(axis=0), bias, atol=5 * std / math.sqrt(errors.shape[0]))

    check(q_err, 2e-3, gap.per_joint("q_bias", config.joints))
    check(qd_err, 0.05, -0.01)
    check(gyro_err, 0.01, np.array([0.002, -0.001, 0.0]))
    check(accel_err, 0.05, 0.03)


def noisy_readings(config, seed: int) -> np.ndarray:
    with configured(config, RealityGap(seed=seed, q_noise=1e-3, gyro_noise=0.01, orientation_noise=0.01)) as mock:
        states = [mock.read() for _ in range(20)]
    return np.array([np.concatenate([s.joints.q, s.imu.gyro, s.imu.orientation]) for s in states])


def test_noise_is_reproducible_from_the_seed_and_orientation_stays_unit(config):
    first, again, other = noisy_readings(config, 7), noisy_readings(config, 7), noisy_readings(config, 8)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    np.testing.assert_allclose(np.linalg.norm(first[:, -4:], axis=1), 1.0, rtol=1e-12)


def test_sensor_latency_reports_the_state_measured_n_ticks_ago(config):
    ticks = 3
    with configured(config, RealityGap(sensor_latency_s=ticks * config.dt)) as mock:
        placed_q, _ = true_joints(mock)
        truth_q, truth_gyro, truth_time, reported = [], [], [], []
        for _ in range(40):  # inactive: the robot folds up, so every tick differs
            reported.append(mock.read())
            truth_q.append(true_joints(mock)[0])
            truth_gyro.append(mock.data.sensor("imu_gyro").data.copy())
            truth_time.append(mock.data.time)
            assert mock.ground_truth().sim_time == mock.data.time  # truth is never delayed
    for i, state in enumerate(reported):
        if i < ticks:  # before anything newer came through: the placed state, stamped at placement
            np.testing.assert_array_equal(state.joints.q, placed_q)
            assert state.joints.stamp == state.imu.stamp == 0.0
        else:
            np.testing.assert_array_equal(state.joints.q, truth_q[i - ticks])
            np.testing.assert_array_equal(state.imu.gyro, truth_gyro[i - ticks])
            assert state.joints.stamp == state.imu.stamp == state.contacts.stamp == truth_time[i - ticks]


def test_place_resets_the_delay_lines_and_the_lag(config):
    gap = RealityGap(actuator_latency_s=0.002, actuator_time_constant_s=0.003, sensor_latency_s=0.002)
    with configured(config, gap) as mock:
        mock.activate()
        mock.read()
        mock.write(JointCommand(tau_ff=np.full(config.n_joints, 0.5)))
        for _ in range(20):
            mock.read()
        mock.place(config.standing_pose)  # forgets what was in flight: nothing sent, nothing applied
        placed_q, _ = true_joints(mock)
        first, second, third = mock.read(), mock.read(), mock.read()
    np.testing.assert_array_equal(first.joints.q, placed_q)
    assert first.joints.stamp == second.joints.stamp == 0.0
    np.testing.assert_array_equal(third.joints.tau, 0.0)  # measured at the first tick after placement


# -- sensor path: contacts, IMU latency, quantisation, on hand-made states -------------------------------------
DT = 0.001


def made_state(k: int, contact, n_joints: int) -> RobotState:
    """Tick k's measurement: every value says which tick it is (q = 0.01 k + a per-joint offset, gyro = k, ...),
    stamped k ms; `contact` the 4 switch states."""
    t = k * DT
    return RobotState(
        joints=JointState(q=0.01 * k + 0.1 * np.arange(n_joints), qd=np.full(n_joints, -float(k)),
                          tau=np.zeros(n_joints), temperature=np.zeros(n_joints), stamp=t),
        imu=ImuSample(gyro=np.full(3, float(k)), accel=np.array([0.0, 0.0, 9.81 + k]),
                      orientation=np.array([1.0, 0.0, 0.0, 0.0]), stamp=t),
        contacts=FootContacts(contact=np.array(contact, dtype=bool), stamp=t))


def reported(config, gap: RealityGap, contacts: np.ndarray) -> list[RobotState]:
    """What SensorGap reports for the measurements made_state(1..), contacts[k] at tick k, after a reset at
    made_state(0)."""
    sensors = SensorGap(gap, config.joints, round(gap.sensor_latency_s / DT), dt=DT)
    sensors.reset(lambda: made_state(0, contacts[0], config.n_joints))
    return [sensors.report(made_state(k, contacts[k], config.n_joints)) for k in range(1, len(contacts))]


def switch_pattern(n_ticks: int, seed: int = 0) -> np.ndarray:
    """(n_ticks, 4) switch states that change now and then (12 to 40 ticks apart on each switch)."""
    rng = np.random.default_rng(seed)
    states = np.zeros((n_ticks, 4), dtype=bool)
    for switch in range(4):
        k, value = 0, bool(switch % 2)
        while k < n_ticks:
            run = int(rng.integers(12, 40))
            states[k:k + run, switch] = value
            k, value = k + run, not value
    return states


@pytest.mark.parametrize(("latency", "delay"), [(0, 3), (2, 3), (1, 0), (0, 1)])
def test_contact_delay_reports_the_switches_of_n_ticks_before_the_sample(config, latency, delay):
    truth = switch_pattern(200)
    gap = RealityGap(sensor_latency_s=latency * DT, contact_delay_s=delay * DT)
    states = reported(config, gap, truth)
    for k, state in enumerate(states, start=1):
        np.testing.assert_array_equal(state.contacts.contact, truth[max(k - latency - delay, 0)], err_msg=f"{k}")
        assert state.contacts.stamp == state.joints.stamp == state.imu.stamp == max(k - latency, 0) * DT
        assert state.joints.q[0] == pytest.approx(0.01 * max(k - latency, 0))
    assert sum(not np.array_equal(truth[k], truth[k - 1]) for k in range(1, 200)) > 10  # it did change


def flips(config, seed: int, bounce: int, delay: int = 0, n_ticks: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """(reported != delayed truth, ticks since the delayed truth last changed) per tick and switch."""
    truth = switch_pattern(n_ticks)
    gap = RealityGap(seed=seed, contact_delay_s=delay * DT, contact_bounce_s=bounce * DT)
    got = np.array([s.contacts.contact for s in reported(config, gap, truth)])
    delayed = truth[np.maximum(np.arange(1, n_ticks) - delay, 0)]
    since = np.zeros(delayed.shape, dtype=int)
    last, age = truth[0], np.full(4, 10**6)
    for k, row in enumerate(delayed):
        age = np.where(row != last, 0, age + 1)
        last = row
        since[k] = age
    return got != delayed, since


@pytest.mark.parametrize("delay", [0, 3])
def test_contact_bounce_only_within_the_window_after_each_change_and_a_fair_coin_there(config, delay):
    bounce = 4
    flipped, since = flips(config, seed=5, bounce=bounce, delay=delay)
    inside = since < bounce  # the change's tick and the bounce - 1 after it
    assert not flipped[~inside].any()
    assert inside.sum() > 200
    share = flipped[inside].mean()  # a fair coin: half of the window's ticks differ from the truth
    assert share == pytest.approx(0.5, abs=5 * math.sqrt(0.25 / inside.sum()))
    for age in range(bounce):  # every tick of the window bounces, the change's own included
        assert flipped[since == age].any()


def test_contact_bounce_is_deterministic_per_seed(config):
    first, _ = flips(config, seed=5, bounce=4)
    again, _ = flips(config, seed=5, bounce=4)
    other, _ = flips(config, seed=6, bounce=4)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)


def test_contact_bounce_leaves_steady_switches_and_the_rest_of_the_state_alone(config):
    truth = np.zeros((50, 4), dtype=bool)
    truth[:, 1] = True  # never changes: no bounce, not even at reset
    gap = RealityGap(contact_bounce_s=0.004, q_noise=1e-3, seed=2)
    states = reported(config, gap, truth)
    np.testing.assert_array_equal([s.contacts.contact for s in states], truth[1:])
    without = reported(config, replace(gap, contact_bounce_s=0.0), truth)  # no switch bounced: no draw taken
    np.testing.assert_array_equal([s.joints.q for s in states], [s.joints.q for s in without])


@pytest.mark.parametrize(("latency", "imu"), [(0, 3), (1, 3), (2, 1)])
def test_imu_latency_lags_the_imu_sample_and_its_stamp_behind_the_joints(config, latency, imu):
    gap = RealityGap(sensor_latency_s=latency * DT, imu_latency_s=imu * DT)
    states = reported(config, gap, np.zeros((40, 4), dtype=bool))
    for k, state in enumerate(states, start=1):
        joints_tick, imu_tick = max(k - latency, 0), max(k - latency - imu, 0)
        assert state.joints.stamp == joints_tick * DT and state.joints.q[0] == pytest.approx(0.01 * joints_tick)
        assert state.imu.stamp == imu_tick * DT and state.contacts.stamp == joints_tick * DT
        np.testing.assert_array_equal(state.imu.gyro, np.full(3, float(imu_tick)))
        assert state.imu.accel[2] == 9.81 + imu_tick
        if k > latency + imu:
            assert state.joints.stamp - state.imu.stamp == pytest.approx(imu * DT, abs=1e-12)


@pytest.mark.parametrize("resolution", [2 * math.pi / 4096, 0.01, {"r_knee": 0.004}])
def test_quantised_q_is_a_multiple_of_the_resolution_after_bias_and_noise_and_qd_is_untouched(config, resolution):
    gap = RealityGap(seed=1, q_resolution=resolution, q_noise=1e-3, q_bias=0.02)
    step = gap.per_joint("q_resolution", config.joints)
    unquantised = reported(config, replace(gap, q_resolution=0.0), np.zeros((60, 4), dtype=bool))  # same draws
    for state, raw in zip(reported(config, gap, np.zeros((60, 4), dtype=bool)), unquantised, strict=True):
        q, counts = state.joints.q, state.joints.q / np.where(step > 0, step, 1.0)
        np.testing.assert_allclose(counts[step > 0], np.round(counts[step > 0]), rtol=0, atol=1e-9)
        assert np.all(np.abs(q - raw.joints.q) <= step / 2 + 1e-12)
        np.testing.assert_array_equal(q[step == 0], raw.joints.q[step == 0])
        np.testing.assert_array_equal(state.joints.qd, raw.joints.qd)
    assert isinstance(resolution, float) or set(step) == {0.0, 0.004}


def old_sensor_path(config, gap: RealityGap, contacts: np.ndarray) -> list[RobotState]:
    """The sensor path as it was before the IMU latency, the contacts' delay and bounce and the quantisation: bias,
    then noise in the order q, qd, gyro, accel, orientation from default_rng(seed), then `latency` ticks of delay."""
    rng = np.random.default_rng(gap.seed)
    q_bias, q_noise = gap.per_joint("q_bias", config.joints), gap.per_joint("q_noise", config.joints)
    qd_noise = gap.per_joint("qd_noise", config.joints)

    def corrupt(state: RobotState) -> RobotState:
        state.joints.q += q_bias
        state.imu.gyro += gap.vec3("gyro_bias")
        state.joints.q += q_noise * rng.standard_normal(config.n_joints)
        state.joints.qd += qd_noise * rng.standard_normal(config.n_joints)
        state.imu.gyro += gap.gyro_noise * rng.standard_normal(3)
        mujoco.mju_quatIntegrate(state.imu.orientation, gap.orientation_noise * rng.standard_normal(3), 1.0)
        return state

    latency = round(gap.sensor_latency_s / DT)
    line = [corrupt(made_state(0, contacts[0], config.n_joints)) for _ in range(latency)]
    out = []
    for k in range(1, len(contacts)):
        line.append(corrupt(made_state(k, contacts[k], config.n_joints)))
        out.append(line.pop(0))
    return out


def test_a_profile_without_the_new_keys_reports_bit_identically_to_the_old_sensor_path(config, tmp_path):
    truth = switch_pattern(100)
    path = tmp_path / "old.yaml"
    path.write_text("seed: 11\nencoder:\n  q_noise: 1.0e-3\n  q_bias: 0.01\n  qd_noise: 0.03\nimu:\n"
                    "  gyro_noise: 0.01\n  gyro_bias: [0.001, 0.0, -0.002]\n  orientation_noise: 0.01\n"
                    "sensor:\n  latency_s: 0.002\n")
    gap = load_gap(path, config.joints)
    assert gap == replace(gap, imu_latency_s=0.0, contact_delay_s=0.0, contact_bounce_s=0.0, q_resolution=0.0)
    expected = old_sensor_path(config, gap, truth)
    got = reported(config, gap, truth)
    for a, b in zip(got, expected, strict=True):
        for name in ("q", "qd", "stamp"):
            np.testing.assert_array_equal(getattr(a.joints, name), getattr(b.joints, name))
        for name in ("gyro", "accel", "orientation", "stamp"):
            np.testing.assert_array_equal(getattr(a.imu, name), getattr(b.imu, name))
        np.testing.assert_array_equal(a.contacts.contact, b.contacts.contact)
        assert a.contacts.stamp == b.contacts.stamp


def test_sensor_gap_needs_a_reset_for_the_new_delays(config):
    sensors = SensorGap(RealityGap(imu_latency_s=0.002), config.joints, 0, dt=DT)
    with pytest.raises(ValueError, match="report before reset"):
        sensors.report(made_state(1, [False] * 4, config.n_joints))


def test_mock_reports_the_imu_and_the_contacts_late_by_their_ticks(config):
    """In the mock (which gives SensorGap its physics tick): the IMU sample and the switches lag the joints by the
    configured ticks, the joints keep sensor.latency_s."""
    latency, imu, delay = 1, 3, 2
    gap = RealityGap(sensor_latency_s=latency * config.dt, imu_latency_s=imu * config.dt,
                     contact_delay_s=delay * config.dt)
    touch = ("r_toe", "r_heel", "l_toe", "l_heel")

    def switches(mock: MujocoBackend) -> np.ndarray:
        return np.array([mock.data.sensor(name).data[0] > CONTACT_THRESHOLD_N for name in touch])

    with configured(config, gap) as mock:
        placed_contact, placed_gyro = switches(mock), mock.data.sensor("imu_gyro").data.copy()
        times, gyros, contacts, states = [], [], [], []
        for _ in range(300):  # inactive: the robot folds up and sits down, the switches change
            states.append(mock.read())
            times.append(mock.data.time)
            gyros.append(mock.data.sensor("imu_gyro").data.copy())
            contacts.append(switches(mock))
    assert len({tuple(c) for c in contacts}) > 1
    for i, state in enumerate(states):
        j, m, c = i - latency, i - latency - imu, i - latency - delay
        assert state.joints.stamp == state.contacts.stamp == (times[j] if j >= 0 else 0.0)
        assert state.imu.stamp == (times[m] if m >= 0 else 0.0)
        np.testing.assert_array_equal(state.imu.gyro, gyros[m] if m >= 0 else placed_gyro)
        np.testing.assert_array_equal(state.contacts.contact, contacts[c] if c >= 0 else placed_contact)


# -- the none profile, the shipped profiles ------------------------------------------------------------------------
def walk(config, gap: RealityGap | None) -> tuple[np.ndarray, np.ndarray]:
    """A short walk of the policy at 0.4 m/s (1.5 s): every tick's (q, qd, tau) and the final qpos, qvel."""
    rows = []
    backend = MujocoBackend(config, gap=gap)
    run_session(backend, config, duration=1.5, realtime=False, commands=CommandSchedule.constant(0.4, 0.0, 0.0),
                observers=[EachTick(lambda view: rows.append(np.concatenate([view.q, view.qd, view.tau])))])
    return np.array(rows), np.concatenate([backend.data.qpos, backend.data.qvel])


def test_none_profile_is_bit_identical_to_no_gap_over_a_short_walk(config):
    nominal_ticks, nominal_end = walk(config, None)
    none_ticks, none_end = walk(config, load_gap("none", config.joints))
    assert nominal_ticks.shape == (1500, 3 * config.n_joints)
    np.testing.assert_array_equal(none_ticks, nominal_ticks)
    np.testing.assert_array_equal(none_end, nominal_end)
    assert load_gap("none") == RealityGap()


@pytest.mark.parametrize("name", profile_names())
def test_each_shipped_profile_loads_and_runs(config, name):
    assert name in profile_names()
    gap = load_gap(name, config.joints)
    assert gap.source.endswith(f"{name}.yaml")
    with configured(config, gap) as mock:
        mock.activate()
        for _ in range(100):
            state = mock.read()
            mock.write(JointCommand(tau_ff=np.zeros(config.n_joints), q_ref=config.standing_pose,
                                    kp=np.full(config.n_joints, 20.0)))
    assert np.all(np.isfinite(state.joints.q)) and np.all(np.isfinite(state.imu.accel))


def test_one_factor_profiles_are_the_none_profile_plus_their_one_factor(config):
    none = load_gap("none", config.joints)
    for name, factor in ONE_FACTOR_KEYS.items():
        gap = load_gap(name, config.joints)
        changed = {f.name for f in fields(RealityGap) if f.compare and getattr(gap, f.name) != getattr(none, f.name)}
        assert changed == factor, name


def test_default_profile_has_the_documented_values(config):
    gap = load_gap("default", config.joints)
    assert (gap.actuator_latency_s, gap.actuator_time_constant_s, gap.torque_limit_scale) == (0.002, 0.002, 0.9)
    two_bears = config.joint_indices("hip_pitch", "hip_roll", "knee")
    coulomb = gap.per_joint("coulomb", config.joints)
    assert set(coulomb[two_bears]) == {0.10} and set(np.delete(coulomb, two_bears)) == {0.05}
    armature_add = gap.per_joint("armature_add", config.joints)
    assert set(armature_add[two_bears]) == {0.00182} and set(np.delete(armature_add, two_bears)) == {0.0}
    assert gap.sensor_latency_s == 0.001 and gap.q_noise == 1e-3 and gap.gyro_noise == 0.01


# -- errors ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("text", "message"), [
    ("actuator:\n  latency_s: -1\n", "actuator.latency_s: expected a number in [0, 0.05] s (50 ticks at 1 kHz"),
    ("actuator:\n  latency_s: true\n", "actuator.latency_s: expected a number in [0, 0.05] s"),
    ("actuator:\n  latency_s: 0.2\n", "), got 0.2"),
    ("actuator:\n  time_constant_s: 1.0\n", "actuator.time_constant_s: expected a number in [0, 0.05] s"),
    ("actuator:\n  latncy_s: 0.001\n", "actuator.latncy_s: unknown key (expected one of ['latency_s',"),
    ("actuators:\n  latency_s: 0.001\n", "actuators: unknown key (expected one of ['actuator', 'contacts', 'encoder',"),
    ("actuator:\n  torque_limit_scale: 1.2\n", "actuator.torque_limit_scale: expected a number in [0.5, 1] ("),
    ("actuator:\n  torque_scale: 1.6\n", "actuator.torque_scale: expected a number in [0.5, 1.5] ("),
    ("actuator:\n  torque_scale: {r_knee: 0.2}\n", "actuator.torque_scale.r_knee: expected a number in [0.5, 1.5]"),
    ("inertia:\n  mass_scale: 0\n", "inertia.mass_scale: expected a number in [0.5, 2] ("),
    ("inertia:\n  inertia_scale: 5\n", "inertia.inertia_scale: expected a number in [0.5, 2] ("),
    ("inertia:\n  armature_scale: {r_knee: -2}\n", "inertia.armature_scale.r_knee: expected a number in [0.5, 2]"),
    ("inertia:\n  armature_add: 1.0\n", "inertia.armature_add: expected a number in [0, 0.01] kg·m²"),
    ("friction:\n  coulomb: {r_knee: -0.1}\n", "friction.coulomb.r_knee: expected a number in [0, 1] N·m ("),
    ("friction:\n  viscous: .inf\n", "friction.viscous: expected a number in [0, 0.5] N·m·s/rad"),
    ("friction:\n  coulomb: {r_kne: 0.1}\n", "friction.coulomb.r_kne: unknown joint (expected one of"),
    ("friction: 0.1\n", "friction: expected a mapping with keys among ['coulomb', 'viscous'], got 0.1"),
    ("encoder:\n  q_noise: abc\n", "encoder.q_noise: expected a number in [0, 0.05] rad (3 deg std) or a mapping "
                                   "joint name -> number, got 'abc'"),
    ("encoder:\n  q_bias: {r_knee: 0.5}\n", "encoder.q_bias.r_knee: expected a number in [-0.1, 0.1] rad"),
    ("encoder:\n  q_noise: 1e-3\n", "(YAML reads 1e-3 as text: write 1.0e-3)"),
    ("imu:\n  gyro_bias: [0.1, 0.2]\n", "imu.gyro_bias: expected a list of 3 numbers, got 2 entries"),
    ("imu:\n  gyro_bias: [0.1, .nan, 0.0]\n", "imu.gyro_bias[1]: expected a number in [-0.5, 0.5] rad/s"),
    ("imu:\n  gyro_noise: -0.01\n", "imu.gyro_noise: expected a number in [0, 0.5] rad/s (std per axis), got -0.01"),
    ("imu:\n  accel_bias: 9.81\n", "imu.accel_bias: expected a number in [-2, 2] m/s²"),
    ("imu:\n  orientation_noise: 1\n", "imu.orientation_noise: expected a number in [0, 0.1] rad"),
    ("sensor:\n  latency_s: .nan\n", "sensor.latency_s: expected a number in [0, 0.05] s"),
    ("sensor:\n  latency_s: 1.0e+9\n", "sensor.latency_s: expected a number in [0, 0.05] s"),
    ("seed: -1\n", "seed: expected an integer >= 0, got -1"),
    ("- 1\n", "<top>: expected a mapping with keys among ['actuator', 'contacts', 'encoder', 'friction', 'imu', "
              "'inertia', 'seed', 'sensor'], got [1]"),
    ("contacts:\n  delay_s: 0.1\n", "contacts.delay_s: expected a number in [0, 0.05] s (beyond sensor.latency_s"),
    ("contacts:\n  delay_s: -0.001\n", "contacts.delay_s: expected a number in [0, 0.05] s"),
    ("contacts:\n  bounce_s: 0.05\n", "contacts.bounce_s: expected a number in [0, 0.02] s (chatter after each "
                                      "change"),
    ("contacts:\n  bounce_s: [0.001]\n", "contacts.bounce_s: expected a number in [0, 0.02] s"),
    ("contacts:\n  debounce_s: 0.001\n", "contacts.debounce_s: unknown key (expected one of ['bounce_s', 'delay_s'])"),
    ("contacts: 0.003\n", "contacts: expected a mapping with keys among ['bounce_s', 'delay_s'], got 0.003"),
    ("imu:\n  latency_s: .inf\n", "imu.latency_s: expected a number in [0, 0.05] s (beyond sensor.latency_s"),
    ("imu:\n  latency_s: -0.003\n", "imu.latency_s: expected a number in [0, 0.05] s"),
    ("encoder:\n  q_resolution: 0.1\n", "encoder.q_resolution: expected a number in [0, 0.01] rad (0.6 deg per "
                                        "count"),
    ("encoder:\n  q_resolution: {r_knee: -1.0e-3}\n", "encoder.q_resolution.r_knee: expected a number in [0, "
                                                      "0.01] rad"),
    ("encoder:\n  q_resolution: {knee: 1.0e-3}\n", "encoder.q_resolution.knee: unknown joint (expected one of"),
])
def test_bad_profile_names_the_file_and_the_key(config, tmp_path, text, message):
    path = tmp_path / "foo.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as error:
        load_gap(path, config.joints)
    assert str(error.value).startswith(f"{path}: ") and message in str(error.value)
    assert "\n" not in str(error.value)


def test_unknown_profile_and_missing_file_are_named(tmp_path):
    with pytest.raises(GapError, match=r"unknown reality-gap profile 'nope': expected a YAML path or one of \["):
        load_gap("nope")
    with pytest.raises(GapError, match="missing.yaml: reality-gap profile file not found"):
        load_gap(tmp_path / "missing.yaml")


def test_gap_built_in_code_is_checked_too(config):
    with pytest.raises(GapError, match=r"^RealityGap: actuator.latency_s: expected a number in \[0, 0.05\] s .*, "
                                       r"got -0.001"):
        RealityGap(actuator_latency_s=-0.001)
    with pytest.raises(GapError, match=r"friction.viscous.knee: unknown joint"):
        configured(config, RealityGap(viscous={"knee": 0.1}))
    with pytest.raises(GapError, match=r"^RealityGap: contacts.bounce_s: expected a number in \[0, 0.02\] s .*, "
                                       r"got 0.5$"):
        RealityGap(contact_bounce_s=0.5)
    assert replace(load_gap("default"), seed=5).seed == 5


# -- bruce-run ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["mild", "torque_constant_0p8"])
def test_bruce_run_mock_with_a_gap(tmp_path, capsys, name):
    stats = tmp_path / "stats.json"
    assert main(["--backend", "mock", "--gap", name, "--gap-seed", "4", "--duration", "0.5", "--rerun", "off",
                 "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert data["ticks"] == 500 and data["stop_cause"] == "duration reached" and data["fell"] is False
    out = capsys.readouterr().out
    assert "reality gap " in out and f"{name}.yaml (seed 4)" in out


def test_bruce_run_gap_is_for_the_mock_only(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--backend", "echo", "--gap", "mild"])
    assert exit_.value.code == 2
    assert "--gap is for --backend mock (a simulated robot), not echo" in capsys.readouterr().err


def test_bruce_run_bad_gap_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("actuator:\n  latency_s: -1\n")
    assert main(["--gap", str(bad), "--duration", "0.1", "--rerun", "off"]) == 2
    err = capsys.readouterr().err
    assert f"bruce-run: {bad}: actuator.latency_s: expected a number in [0, 0.05] s" in err and "got -1" in err
