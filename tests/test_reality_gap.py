"""Reality-gap profiles (bruce_hw/reality_gap.py) applied by the mock backend: each mechanism against its definition,
the shipped profiles, the errors, and `bruce-run --gap`."""

from __future__ import annotations

import json
import math
from dataclasses import fields, replace

import mujoco
import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import GapError, RealityGap, load_gap, profile_names
from bruce_hw.types import JointCommand
from runtime.cli import main
from runtime.commands import CommandSchedule
from runtime.observers import EachTick
from runtime.run import run_session

KNEE = 3  # r_knee in the config's joint order
# The shipped one-factor profiles (configs/gaps/) and the RealityGap fields each sets.
ONE_FACTOR_KEYS = {"latency_2ms": {"actuator_latency_s"}, "torque_lag_2ms": {"actuator_time_constant_s"},
                   "torque_constant_0p8": {"torque_scale"}, "coulomb_0p2": {"coulomb"}, "viscous_0p05": {"viscous"},
                   "mass_1p2": {"mass_scale", "inertia_scale"}, "armature_add_1bear": {"armature_add"},
                   "sensor_noise_1ms": {"q_noise", "qd_noise", "sensor_latency_s"}}


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
    ("actuators:\n  latency_s: 0.001\n", "actuators: unknown key (expected one of ['actuator', 'encoder',"),
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
    ("- 1\n", "<top>: expected a mapping with keys among ['actuator', 'encoder', 'friction', 'imu', 'inertia', "
              "'seed', 'sensor'], got [1]"),
])
def test_bad_profile_names_the_file_and_the_key(config, tmp_path, text, message):
    path = tmp_path / "foo.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as error:
        load_gap(path, config.joints)
    assert str(error.value).startswith(f"{path}: ") and message in str(error.value)


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
