"""The PPO walking environment (training/rl/env.py): the runtime's observation of the same states, the mock's physics
under the runtime's Eq. 8, the randomisation's ranges and where they land, the runtime's fall rule, auto-reset, the
PD actuators and the latency, the settings file, and a checkpointed continuation."""

import dataclasses
import math

import numpy as np
import pytest
import yaml

from bruce_hw.mock import MujocoBackend
from bruce_hw.types import FootContacts, GroundTruth, ImuSample, JointCommand, JointState, RobotState
from runtime.control.heading import wrap_angle
from runtime.control.mixing import eq8_torque
from runtime.estimation import GroundTruthEstimator
from runtime.loop.falls import has_fallen
from runtime.observation.builder import ObservationBuilder
from runtime.walking.gait import gait_phase, swing_height
from runtime.walking.teacher import TeacherParams, WalkingTeacher
from training.rl.env import BruceWalkEnv, WalkEnvConfig
from training.rl.randomisation import RandomisationRanges, draw
from training.rl.rewards import DOUBLE_SUPPORT

NO_NOISE = {f"noise_{name}": (0.0, 0.0) for name in ("q_rad", "qd_rads", "linvel_ms", "angvel_rads", "euler_rad")}

# The env section of training/rl/bruce_walk.yaml at the defaults (the layout WalkEnvConfig.from_dict reads).
DEFAULT_YAML = """
env:
  num_envs: 64
  nthread: 2
  episode_s: 20.0
  reset_joint_noise_rad: 0.05
  commands: {vx: [-0.5, 0.8], vy: [-0.3, 0.3], wz: [-0.5, 0.5], zero_share: 0.1, resample_s: [4.0, 8.0]}
  pushes: {interval_s: [2.0, 4.0], impulse_ns: [0.2, 1.2], angular_impulse_nms: [0.0, 0.05], duration_s: 0.1}
  randomisation:
    ground_friction: [0.5, 1.25]
    joint_coulomb_nm: [0.0, 0.3]
    joint_viscous_nms: [0.0, 0.1]
    mass_scale: [0.9, 1.2]
    inertia_scale: [0.9, 1.2]
    armature_scale: [0.8, 1.3]
    armature_add_kgm2: [0.0, 0.0025]
    torque_scale: [0.85, 1.15]
    torque_limit_scale: [0.75, 1.0]
    latency_ticks: [0, 8]
    torque_lag_s: [0.0, 0.006]
    noise: {q_rad: [0.0, 0.003], qd_rads: [0.0, 0.1], linvel_ms: [0.0, 0.05], angvel_rads: [0.0, 0.03],
            euler_rad: [0.0, 0.01]}
"""


def make_env(config, n: int, seed: int = 0, **settings) -> BruceWalkEnv:
    ranges = settings.pop("randomisation", {})
    return BruceWalkEnv(config, WalkEnvConfig(num_envs=n, randomisation=RandomisationRanges(**ranges), **settings),
                        seed=seed)


class TruthOf:
    """A backend stand-in whose ground truth is env i's simulator state, for the runtime's GroundTruthEstimator."""

    def __init__(self, env: BruceWalkEnv, i: int):
        self.env, self.i = env, i

    def ground_truth(self) -> GroundTruth:
        qpos = self.env.state[self.i, self.env._qpos]
        qvel = self.env.state[self.i, self.env._qvel]
        return GroundTruth(sim_time=0.0, base_pos=qpos[:3].copy(), base_quat=qpos[3:7].copy(),
                           base_linvel=qvel[:3].copy(), base_angvel=qvel[3:6].copy())

    def robot_state(self) -> RobotState:
        sim, row = self.env.sim, self.env.state[self.i]
        q, qd = row[self.env._qpos][sim.qpos].copy(), row[self.env._qvel][sim.dofs].copy()
        return RobotState(JointState(q, qd, np.zeros(10), np.zeros(10), 0.0),
                          ImuSample(np.zeros(3), np.zeros(3), None, 0.0), FootContacts(np.zeros(4, bool), 0.0))


def test_the_actor_observation_is_the_runtime_builders_of_the_same_states(config):
    """Three envs driven by recorded actions through falls, time-outs and command changes: each observation equals
    what the runtime's ObservationBuilder makes of the same state (through GroundTruthEstimator), command and last
    action; the gait the rewards use is the scalar gait's."""
    env = make_env(config, 3, episode_s=0.45, command_resample_s=(0.05, 0.15), randomisation=NO_NOISE)
    builders = [ObservationBuilder(config) for _ in range(3)]
    truths = [TruthOf(env, i) for i in range(3)]
    actions = config.standing_pose + np.random.default_rng(4).normal(0.0, 0.05, size=(100, 3, 10))
    apex, landing = TeacherParams().swing_apex, TeacherParams().swing_landing
    obs, ends, checked_phases = env.get_observations(), 0, 0
    for t in range(len(actions) + 1):
        for i, (builder, truth) in enumerate(zip(builders, truths, strict=True)):
            expected = builder.build(env.command[i], truth.robot_state(), GroundTruthEstimator(truth).estimate(),
                                     env.last_action[i])
            np.testing.assert_allclose(obs["policy"][i], expected, rtol=0.0, atol=1e-9)
        np.testing.assert_array_equal(obs["critic"][:, :obs["policy"].shape[1]], obs["policy"])
        np.testing.assert_array_equal(obs["critic"][:, obs["policy"].shape[1]:][:, :10], env.tau)
        if t == len(actions):
            break
        obs, _, terminated, time_out, info = env.step(actions[t])
        walk = info["walk_step"]
        for i, builder in enumerate(builders):
            phase = gait_phase(float(builder.clock.cycles), float(builder.clock.period))  # after this step's tick
            assert walk.stance_desired[i] == (DOUBLE_SUPPORT if phase.starting else phase.stance)
            wanted = 0.0 if phase.starting else swing_height(phase.t_in_step / phase.step_time, apex, landing)
            assert walk.swing_height_desired[i] == pytest.approx(wanted, abs=1e-12)
            checked_phases += not phase.starting
            if terminated[i] or time_out[i]:
                builder.reset()
                ends += 1
    assert ends >= 3 and checked_phases > 0  # restarts and single stance were both exercised


def test_without_randomisation_the_env_steps_as_the_mock_under_the_runtimes_eq8(config):
    """Tick for tick, the env's physics is the mock's when the runtime's Eq. 8 turns the same a_t into torques every
    1 ms (the walking teacher, 0.5 s at 0.3 m/s while turning)."""
    nominal = {**NO_NOISE, "ground_friction": (1.0, 1.0), "joint_coulomb_nm": (0.0, 0.0),
               "joint_viscous_nms": (0.0, 0.0), "mass_scale": (1.0, 1.0), "inertia_scale": (1.0, 1.0),
               "armature_scale": (1.0, 1.0), "armature_add_kgm2": (0.0, 0.0), "torque_scale": (1.0, 1.0),
               "torque_limit_scale": (1.0, 1.0), "latency_ticks": (0, 0), "torque_lag_s": (0.0, 0.0)}
    env = make_env(config, 1, push_impulse_ns=(0.0, 0.0), push_angular_impulse_nms=(0.0, 0.0), randomisation=nominal)
    mock = MujocoBackend(config)
    mock.configure()
    mock.activate()
    state = mock.read()
    env.state[0, env._qpos], env.state[0, env._qvel] = mock.data.qpos, mock.data.qvel
    env.state[0, env._act] = state.joints.q
    teacher, truth = WalkingTeacher(config), GroundTruthEstimator(mock)
    for _ in range(50):
        a = teacher(state, truth.estimate(), np.array([0.3, 0.0, 0.2]))
        ticks = []
        for _ in range(env.decimation):
            mock.write(JointCommand(tau_ff=eq8_torque(a, state.joints.q, state.joints.qd, config.eq8)))
            state = mock.read()
            ticks.append(np.r_[mock.data.qpos, mock.data.qvel])
        env.step(a[None])
        physics = env.physics_states[0]
        np.testing.assert_allclose(np.c_[physics[:, env._qpos], physics[:, env._qvel]], ticks, rtol=0.0, atol=1e-12)
    assert mock.data.qpos[0] > 0.02 and not env.truth().fallen[0]  # it walked


def test_batched_angle_wrapping_is_math_remainder():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-20.0, 20.0, 20000), rng.uniform(-1e6, 1e6, 2000),
                        math.pi * np.arange(-41, 42), [0.0, -0.0, math.tau, -math.tau, 3 * math.pi + 1e-15]])
    wrapped = wrap_angle(x)
    np.testing.assert_array_equal(wrapped, [math.remainder(v, math.tau) for v in x])
    assert np.all(np.abs(wrapped) <= math.pi)


def test_randomisation_draws_stay_in_their_ranges():
    ranges = RandomisationRanges(ground_friction=(0.3, 1.1), mass_scale=(0.95, 0.95), latency_ticks=(2, 5),
                                 torque_lag_s=(0.001, 0.004), bias_q_rad=(-0.01, 0.02), bias_angvel_rads=(-0.02, 0.0),
                                 bias_euler_rad=(-0.03, 0.03))
    draws = draw(ranges, np.random.default_rng(1), 20000, 10)
    for f in dataclasses.fields(draws):
        low, high = getattr(ranges, f.name)
        values = getattr(draws, f.name)
        per_joint = ("joint_coulomb_nm", "joint_viscous_nms", "armature_scale", "armature_add_kgm2", "torque_scale",
                     "bias_q_rad")
        per_axis = ("bias_angvel_rads", "bias_euler_rad")
        assert values.shape == ((20000, 10) if f.name in per_joint else (20000, 3) if f.name in per_axis
                                else (20000,))
        assert values.min() >= low and values.max() <= high, f.name
        assert values.min() <= low + 0.01 * (high - low) and values.max() >= high - 0.01 * (high - low), f.name
    assert np.all(draws.mass_scale == 0.95)
    assert set(np.unique(draws.latency_ticks)) == {2, 3, 4, 5}


def test_each_episodes_draw_reaches_its_model_and_the_observation_noise(config):
    noise = {"noise_q_rad": (0.01, 0.01), "noise_qd_rads": (0.2, 0.2), "noise_linvel_ms": (0.05, 0.05),
             "noise_angvel_rads": (0.1, 0.1), "noise_euler_rad": (0.02, 0.02)}
    env = make_env(config, 8, seed=3, randomisation=noise)
    sim, d = env.sim, env.draws
    nominal = sim.nominal
    for i, m in enumerate(env.models):
        np.testing.assert_allclose(m.dof_frictionloss[sim.dofs], nominal["dof_frictionloss"][sim.dofs]
                                   + d.joint_coulomb_nm[i])
        np.testing.assert_allclose(m.dof_damping[sim.dofs], nominal["dof_damping"][sim.dofs] + d.joint_viscous_nms[i])
        np.testing.assert_allclose(m.dof_armature[sim.dofs], nominal["dof_armature"][sim.dofs] * d.armature_scale[i]
                                   + d.armature_add_kgm2[i])
        np.testing.assert_allclose(m.body_mass, nominal["body_mass"] * d.mass_scale[i])
        np.testing.assert_allclose(m.body_inertia, nominal["body_inertia"] * d.inertia_scale[i])
        # the derived constants follow (mj_setConst): the robot's mass
        assert m.body_subtreemass[sim.base_body] == pytest.approx(nominal["body_mass"].sum() * d.mass_scale[i])
        assert m.geom_friction[sim.floor_geom, 0] == d.ground_friction[i]
        np.testing.assert_array_equal(m.geom_friction[sim.foot_geoms, 0], d.ground_friction[i])
        scale = d.torque_scale[i]
        np.testing.assert_allclose(m.actuator_gainprm[sim.acts, 0], sim.kp * scale)
        np.testing.assert_allclose(m.actuator_biasprm[sim.acts, 1:3], -np.c_[sim.kp, sim.kd] * scale[:, None])
        np.testing.assert_allclose(m.actuator_forcerange[sim.acts, 1], sim.torque_limit * d.torque_limit_scale[i]
                                   * scale)
        np.testing.assert_allclose(m.actuator_forcerange[sim.acts, 0], -m.actuator_forcerange[sim.acts, 1])
        np.testing.assert_array_equal(m.actuator_dynprm[sim.acts, 0], d.torque_lag_s[i])
    assert len(set(d.ground_friction)) == 8 and len(set(d.mass_scale)) == 8  # one draw per env
    # The observation carries the truth plus the episode's noise, fresh at every step.
    s = env.builder.slices
    residuals = {name: [] for name in ("q", "qd", "base_linvel", "base_angvel", "roll_pitch")}
    for _ in range(20):
        obs = env.step(np.tile(config.standing_pose, (8, 1)))[0]["policy"]
        truth = env.truth()
        for name, true in (("q", truth.q), ("qd", truth.qd), ("base_linvel", truth.linvel),
                           ("base_angvel", truth.angvel)):
            residuals[name].append(obs[:, s[name]] - true)
        residuals["roll_pitch"].append(obs[:, s["euler"].start:s["euler"].start + 2] - truth.euler[:, :2])
    for name, std in (("q", 0.01), ("qd", 0.2), ("base_linvel", 0.05), ("base_angvel", 0.1), ("roll_pitch", 0.02)):
        r = np.concatenate(residuals[name]).ravel()
        assert np.std(r) == pytest.approx(std, rel=0.12), name
        assert abs(np.mean(r)) < 4 * std / math.sqrt(len(r)), name


def test_sensor_biases_are_constant_offsets_of_the_observation_per_episode(config):
    bias = {"bias_q_rad": (-0.02, 0.02), "bias_angvel_rads": (-0.05, 0.05), "bias_euler_rad": (-0.03, 0.03)}
    env = make_env(config, 6, seed=4, randomisation=bias | NO_NOISE)
    s, d = env.builder.slices, env.draws
    assert np.all(np.abs(d.bias_q_rad) > 0) and len(np.unique(d.bias_q_rad)) == d.bias_q_rad.size
    for _ in range(5):
        obs = env.step(np.tile(config.standing_pose, (6, 1)))[0]["policy"]
        truth = env.truth()
        np.testing.assert_allclose(obs[:, s["q"]] - truth.q, d.bias_q_rad, atol=1e-9)
        np.testing.assert_allclose(obs[:, s["base_angvel"]] - truth.angvel, d.bias_angvel_rads, atol=1e-9)
        np.testing.assert_allclose(obs[:, s["euler"].start:s["euler"].start + 2] - truth.euler[:, :2],
                                   d.bias_euler_rad[:, :2], atol=1e-9)
        np.testing.assert_allclose(obs[:, s["qd"]], truth.qd, atol=1e-9)  # no velocity bias


def test_pushes_move_the_base_and_the_critic_sees_them_with_its_privileged_state(config):
    envs = [make_env(config, 4, seed=6, push_impulse_ns=(impulse, impulse), push_angular_impulse_nms=(0.02, 0.02),
                     push_duration_s=0.05) for impulse in (0.0, 1.0)]
    stand = np.tile(config.standing_pose, (4, 1))
    for env in envs:
        env._push_countdown[:] = 0  # every env is pushed from the next step on
    (_, calm), (obs, pushed) = [(env.step(stand)[0], env.truth()) for env in envs]
    p = obs["policy"].shape[1]
    force, torque = obs["critic"][:, p + 13:p + 15], obs["critic"][:, p + 15:p + 18]
    np.testing.assert_allclose(np.linalg.norm(force, axis=1), 1.0 / 0.05)  # N, horizontal, in the heading frame
    np.testing.assert_allclose(np.linalg.norm(torque, axis=1), 0.02 / 0.05)
    gained = np.sum((pushed.heading_linvel - calm.heading_linvel)[:, :2] * force / 20.0, axis=1)
    assert np.all(gained > 0.01)  # m/s along the push
    env = envs[1]
    np.testing.assert_array_equal(obs["critic"][:, p:p + 10], env.tau)
    np.testing.assert_array_equal(obs["critic"][:, p + 10], pushed.pos[:, 2])
    np.testing.assert_array_equal(obs["critic"][:, p + 11], env.draws.ground_friction)
    np.testing.assert_array_equal(obs["critic"][:, p + 12], env.draws.mass_scale)
    for _ in range(4):  # the push lasts 5 policy steps
        obs = env.step(stand)[0]
    np.testing.assert_array_equal(obs["critic"][:, p + 13:], 0.0)


def test_termination_is_the_runtime_fall_rule(config):
    env = make_env(config, 64)
    rng = np.random.default_rng(5)
    nominal = env.sim.nominal_base_height
    for _ in range(4):
        qpos = env.state[:, env._qpos]
        qpos[:, 2] = rng.uniform(0.3, 1.0, 64) * nominal
        tilt = rng.uniform(0.0, 1.4, 64)
        axis = rng.normal(size=(64, 3))
        axis[:, 2] *= rng.uniform(0.0, 1.0, 64)
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        qpos[:, 3:7] = np.c_[np.cos(tilt / 2), np.sin(tilt / 2)[:, None] * axis]
        fallen = env.truth().fallen
        expected = [has_fallen(TruthOf(env, i).ground_truth(), nominal) for i in range(64)]
        np.testing.assert_array_equal(fallen, expected)
        assert 5 < fallen.sum() < 59  # both outcomes, by height and by tilt


def test_auto_reset_restarts_and_rerandomises_only_the_finished_envs(config):
    env = make_env(config, 4, seed=2, episode_s=1.0)
    stand = np.tile(config.standing_pose, (4, 1))
    env.step(stand)
    before = [m.body_mass.copy() for m in env.models], [m.geom_friction.copy() for m in env.models]
    draws_before = env.draws.ground_friction.copy()
    env.state[2, env._qpos][2] = 0.1  # env 2 lies on the floor
    env.episode_length[1] = env.max_episode_length - 1  # env 1's time is up after this step
    obs, reward, terminated, time_out, info = env.step(stand)
    np.testing.assert_array_equal(terminated, [False, False, True, False])
    np.testing.assert_array_equal(time_out, [False, True, False, False])
    np.testing.assert_array_equal(info["episode_length"], [2, env.max_episode_length, 2, 2])
    np.testing.assert_array_equal(env.episode_length, [2, 0, 0, 2])
    assert reward.shape == (4,) and set(info["reward_terms"]) and info["reward_terms"]["alive"][2] == 0.0
    np.testing.assert_array_equal(info["walk_step"].action, stand)  # the step's, not the restart's
    for i in range(4):
        changed = i in (1, 2)
        assert (env.draws.ground_friction[i] != draws_before[i]) == changed
        assert (not np.array_equal(env.models[i].body_mass, before[0][i])) == changed
        assert (not np.array_equal(env.models[i].geom_friction, before[1][i])) == changed
    s = env.builder.slices
    # the restarted envs observe a new episode: the clock at phase 0, standing in their new start pose
    np.testing.assert_allclose(obs["policy"][[1, 2], s["clock"]], [[0.0, 1.0], [0.0, 1.0]])
    assert not np.allclose(obs["policy"][[0, 3], s["clock"]], [[0.0, 1.0], [0.0, 1.0]])
    np.testing.assert_array_equal(obs["policy"][[1, 2], s["last_action"]], env.truth().q[[1, 2]])
    assert env.truth().pos[2, 2] > 0.4


@pytest.mark.parametrize("delays", [{"latency_ticks": (0, 3), "torque_lag_s": (0.0, 0.006)},
                                    {"latency_ticks": (0, 0), "torque_lag_s": (0.0, 0.0)}])
def test_the_pd_actuator_is_eq8_clamped_with_the_episodes_gains_lag_and_latency(config, delays):
    """At the first physics step of a policy step: tau = clip(s kp (a' - q) - s kd qd, +-s limit), s the
    torque-constant scale, a' the PD target after the first-order lag (a'' = a_{t-1} while the latency lasts)."""
    env = make_env(config, 16, seed=7, randomisation=delays)
    rng = np.random.default_rng(8)
    env.step(config.standing_pose + rng.normal(0.0, 0.2, (16, 10)))  # moving joints
    sim, d = env.sim, env.draws
    row = env.state.copy()
    q, qd, act = row[:, env._qpos][:, sim.qpos], row[:, env._qvel][:, sim.dofs], row[:, env._act]
    previous = env.last_action.copy()
    a = config.standing_pose + rng.normal(0.0, 1.0, (16, 10))
    env.step(a)
    target = np.where(d.latency_ticks[:, None] > 0, previous, a)
    lag = d.torque_lag_s[:, None]
    alpha = np.where(lag > 0, -np.expm1(-0.001 / np.where(lag > 0, lag, 1.0)), 1.0)
    filtered = act + alpha * (target - act)
    s, limit = d.torque_scale, sim.torque_limit * d.torque_limit_scale[:, None] * d.torque_scale
    expected = np.clip(s * sim.kp * (filtered - q) - s * sim.kd * qd, -limit, limit)
    np.testing.assert_allclose(env.sensordata[:, 0, sim.tau], expected, rtol=0.0, atol=1e-9)
    if delays["latency_ticks"][1]:
        assert len(set(d.latency_ticks)) > 1 and np.any(d.torque_lag_s > 0.003)
    else:
        assert np.any(np.abs(expected) == limit) and np.any(np.abs(expected) < limit)  # clamped and free joints


def test_the_target_switches_after_the_latency(config):
    env = make_env(config, 64, seed=9, randomisation={"latency_ticks": (0, 9), "torque_lag_s": (0.0, 0.0)})
    rng = np.random.default_rng(10)
    previous = env.last_action.copy()
    a = config.standing_pose + rng.normal(0.0, 0.1, (64, 10))
    env.step(a)
    applied = env.physics_states[:, :, env._act]  # the PD target of each physics step (no lag: the control)
    late = np.arange(env.decimation)[None, :] < env.draws.latency_ticks[:, None]
    np.testing.assert_allclose(applied, np.where(late[:, :, None], previous[:, None, :], a[:, None, :]),
                               rtol=0.0, atol=1e-12)
    assert set(env.draws.latency_ticks) >= {0, 9}


def test_settings_read_from_yaml_with_errors_naming_the_file_and_key():
    tree = yaml.safe_load(DEFAULT_YAML)
    assert WalkEnvConfig.from_dict(tree["env"], "bruce_walk.yaml") == WalkEnvConfig()
    tree["env"]["commands"]["vx"] = [-0.3, 0.8]
    tree["env"]["randomisation"]["noise"]["q_rad"] = [0.001, 0.002]
    tree["env"]["randomisation"]["bias"] = {"angvel_rads": [-0.01, 0.02]}
    custom = WalkEnvConfig.from_dict(tree["env"], "bruce_walk.yaml")
    assert custom.command_vx == (-0.3, 0.8) and custom.randomisation.noise_q_rad == (0.001, 0.002)
    assert custom.randomisation.bias_angvel_rads == (-0.01, 0.02) and custom.randomisation.bias_q_rad == (0.0, 0.0)
    assert WalkEnvConfig.from_dict({"num_envs": 8}, "x.yaml", key="") == WalkEnvConfig(num_envs=8)
    for change, message in (
            (("commands", "vx", [-0.8, 0.5]), r"bruce_walk.yaml: env.commands.vx\[0\]: expected a number in \[-0.5, 1"),
            (("commands", "wz", [0.5, -0.5]), r"env.commands.wz: expected \[low, high\] with low <= high"),
            (("pushes", "impulse", 1.0), r"env.pushes.impulse: unknown key"),
            (("randomisation", "latency_ticks", [0, 12]), r"env.randomisation.latency_ticks\[1\]: expected an integer"),
            (("randomisation", "mass_scale", 1.1), r"env.randomisation.mass_scale: expected \[low, high\]"),
            (("randomisation", "bias", {"gyro": [0.0, 0.1]}), r"env.randomisation.bias.gyro: unknown key"),
            (("randomisation", "bias", {"q_rad": [0.0, 0.5]}), r"env.randomisation.bias.q_rad\[1\]: expected a number"),
            (("num_envs", None, 0), r"env.num_envs: expected an integer in \[1, 65536\]")):
        broken = yaml.safe_load(DEFAULT_YAML)
        section, name, value = change
        if name is None:
            broken["env"][section] = value
        else:
            broken["env"][section][name] = value
        with pytest.raises(ValueError, match=message):
            WalkEnvConfig.from_dict(broken["env"], "bruce_walk.yaml")
    with pytest.raises(ValueError, match=r"x.yaml: env: expected a mapping"):
        WalkEnvConfig.from_dict([1, 2], "x.yaml")


def test_a_restored_state_continues_exactly(config):
    env = make_env(config, 6, seed=11, episode_s=0.3)
    rng = np.random.default_rng(12)
    actions = config.standing_pose + rng.normal(0.0, 0.1, (40, 6, 10))
    for a in actions[:15]:
        env.step(a)
    saved = env.get_state()
    tail = [env.step(a) for a in actions[15:]]
    other = make_env(config, 6, seed=99, episode_s=0.3)
    other.set_state(saved)
    for a, (obs, reward, terminated, time_out, _) in zip(actions[15:], tail, strict=True):
        obs2, reward2, terminated2, time_out2, _ = other.step(a)
        np.testing.assert_array_equal(obs2["critic"], obs["critic"])
        np.testing.assert_array_equal(reward2, reward)
        np.testing.assert_array_equal(terminated2 | time_out2, terminated | time_out)
    assert any(t.any() for _, _, t, o, _ in tail) or any(o.any() for _, _, t, o, _ in tail)


def test_the_added_tracking_inputs_follow_the_velocity_and_the_heading(config):
    from training.rl.env import MEAN_VELOCITY_S
    from training.rl.rewards import world_yaw_rate

    env = make_env(config, 3, seed=4, nthread=1)
    try:
        truths, steps = [], []
        for _ in range(30):
            reference = env.builder.heading_reference.heading.copy()  # what the last observation was built with
            _, _, fell, time_out, info = env.step(np.tile(config.standing_pose, (3, 1)))
            assert not (fell.any() or time_out.any())
            truths.append(env.truth())
            steps.append(info["walk_step"])
        # The low-pass of each step's heading-frame velocity and world yaw rate, from zero at the episode's start.
        expected = np.zeros((3, 3))
        for truth in truths:
            v = np.concatenate([truth.heading_linvel[:, :2], world_yaw_rate(truth.euler, truth.angvel)[:, None]], 1)
            expected += env.dt / MEAN_VELOCITY_S * (v - expected)
        np.testing.assert_allclose(steps[-1].mean_velocity, expected, atol=1e-12)
        from runtime.control.heading import wrap_angle
        np.testing.assert_allclose(steps[-1].heading_error, wrap_angle(truths[-1].euler[:, 2] - reference),
                                   atol=1e-12)
        env._reset(np.array([1]))
        assert np.all(env.mean_velocity[1] == 0.0) and np.any(env.mean_velocity[0] != 0.0)
    finally:
        env.close()
