"""Table II's reward terms (training/rl/rewards.py) on hand-made states: each term at its best and worse, the weights,
the total, batches of mixed envs, and BRUCE's constants against the robot model."""

import dataclasses
import math

import numpy as np
import pytest

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from training.rl import rewards
from training.rl.rewards import DOUBLE_SUPPORT, LEFT, REWARD_TERMS, RIGHT, RewardParams, WalkStep, compute, phi

JOINTS = ("r_hip_yaw", "r_hip_pitch", "r_hip_roll", "r_knee", "r_ankle",
          "l_hip_yaw", "l_hip_pitch", "l_hip_roll", "l_knee", "l_ankle")
PARAMS = RewardParams()


def standing_q(n: int) -> np.ndarray:
    q = np.zeros((n, 10))
    q[:, JOINTS.index("r_hip_yaw")], q[:, JOINTS.index("l_hip_yaw")] = PARAMS.hip_yaw_default
    q[:, JOINTS.index("r_hip_roll")], q[:, JOINTS.index("l_hip_roll")] = PARAMS.hip_roll_default
    return q


def make_step(n: int, **fields) -> WalkStep:
    """n envs in the start-up's double support, standing still at BRUCE's standing geometry with a zero command:
    every positive term 1, every penalty 0. `fields` replace any of it."""
    foot_pos = np.zeros((n, 2, 3))
    foot_pos[:, RIGHT, 1], foot_pos[:, LEFT, 1] = -PARAMS.feet_distance / 2, PARAMS.feet_distance / 2
    knee_pos = np.zeros((n, 2, 3))
    knee_pos[:, :, 2] = 0.2
    knee_pos[:, RIGHT, 1], knee_pos[:, LEFT, 1] = -PARAMS.knee_distance / 2, PARAMS.knee_distance / 2
    base_pos = np.zeros((n, 3))
    base_pos[:, 2] = PARAMS.base_height
    v3, v10 = np.zeros((n, 3)), np.zeros((n, 10))
    values = dict(dt=0.01, alive=np.ones(n, bool), base_pos=base_pos, base_euler=v3, base_linvel=v3, base_angvel=v3,
                  base_linvel_prev=v3, base_angvel_prev=v3, command=v3, heading_linvel=v3, foot_pos=foot_pos,
                  foot_vel=np.zeros((n, 2, 3)), foot_contact=np.ones((n, 2), bool), knee_pos=knee_pos,
                  stance_desired=np.full(n, DOUBLE_SUPPORT), swing_height_desired=np.zeros(n), q=standing_q(n),
                  qd=v10, qd_prev=v10, tau=v10, action=v10, action_prev=v10, action_prev2=v10, joint_names=JOINTS)
    values.update({k: np.asarray(v) if k not in ("dt", "joint_names") else v for k, v in fields.items()})
    return WalkStep(**values)


def env(step: WalkStep, i: int) -> WalkStep:
    """Env i of a batch, as a batch of one."""
    return dataclasses.replace(step, **{f.name: getattr(step, f.name)[i:i + 1] for f in dataclasses.fields(step)
                                        if isinstance(getattr(step, f.name), np.ndarray)})


def term(name: str, step: WalkStep, params: RewardParams = PARAMS) -> np.ndarray:
    value = REWARD_TERMS[name][0](step, params)
    assert value.shape == (len(step.alive),)
    return value


def test_phi_is_exp_of_minus_w_times_the_squared_norm_over_the_last_axis():
    np.testing.assert_allclose(phi(2.0, np.array([[3.0, 4.0], [0.0, 0.0], [0.1, 0.0]])),
                               [math.exp(-50.0), 1.0, math.exp(-0.02)])


def test_alive():
    np.testing.assert_array_equal(term("alive", make_step(2, alive=[True, False])), [1.0, 0.0])


def test_swing_foot_height_tracks_the_swing_sole_and_keeps_both_down_in_double_support():
    foot_pos = np.zeros((4, 2, 3))
    foot_pos[0, LEFT, 2] = 0.04              # right stance, left swing at its desired height
    foot_pos[1, RIGHT, 2] = 0.03             # left stance, right swing 1 cm low
    foot_pos[2, :, 2] = (0.01, 0.02)         # double support, both feet up a little
    foot_pos[3, RIGHT, 2] = 0.05             # right stance but the stance foot is up: not this term's business
    foot_pos[3, LEFT, 2] = 0.04
    step = make_step(4, foot_pos=foot_pos, stance_desired=[RIGHT, LEFT, DOUBLE_SUPPORT, RIGHT],
                     swing_height_desired=[0.04, 0.04, 0.0, 0.04])
    np.testing.assert_allclose(term("swing_foot_height", step),
                               [1.0, math.exp(-1000 * 0.01 ** 2), math.exp(-1000 * (0.01 ** 2 + 0.02 ** 2)), 1.0])


def test_foot_contact_pattern_scores_each_foot_against_the_desired_stance():
    cases = [  # (desired stance, contacts (right, left), reward)
        (RIGHT, (True, False), 1.0), (RIGHT, (False, True), -0.5), (RIGHT, (True, True), 0.25),
        (RIGHT, (False, False), 0.25), (LEFT, (False, True), 1.0), (LEFT, (True, False), -0.5),
        (DOUBLE_SUPPORT, (True, True), 1.0), (DOUBLE_SUPPORT, (True, False), 0.25),
        (DOUBLE_SUPPORT, (False, False), -0.5)]
    step = make_step(len(cases), stance_desired=[c[0] for c in cases], foot_contact=[c[1] for c in cases])
    np.testing.assert_allclose(term("foot_contact_pattern", step), [c[2] for c in cases])


def test_foot_slip_is_the_squared_horizontal_speed_of_the_feet_in_contact():
    foot_vel = np.zeros((3, 2, 3))
    foot_vel[0, RIGHT] = (0.0, 0.0, 0.5)     # vertical: no slip
    foot_vel[0, LEFT] = (1.0, 0.0, 0.0)      # swinging, not in contact
    foot_vel[1, RIGHT] = (0.3, 0.4, 0.0)
    foot_vel[2, RIGHT], foot_vel[2, LEFT] = (0.1, 0.0, 0.0), (0.0, 0.2, 0.0)
    step = make_step(3, foot_vel=foot_vel, foot_contact=[(True, False), (True, False), (True, True)])
    np.testing.assert_allclose(term("foot_slip", step), [0.0, 0.25, 0.05])


def test_feet_and_knee_distances_are_kept_at_their_desired_values():
    params = RewardParams(feet_distance=0.14, knee_distance=0.15)
    feet = np.zeros((3, 2, 3))
    feet[0, RIGHT], feet[0, LEFT] = (0.0, -0.07, 0.0), (0.0, 0.07, 0.0)
    feet[1, LEFT] = (0.06, 0.08, 0.0)        # 0.10 apart: 4 cm too close
    feet[2, LEFT] = (0.0, 0.0, 0.24)         # 0.24 apart (a foot up counts): 10 cm too far
    knees = np.zeros((3, 2, 3))
    knees[0, RIGHT], knees[0, LEFT] = (0.0, -0.075, 0.2), (0.0, 0.075, 0.2)
    knees[1, LEFT] = (0.3, 0.4, 0.0)         # 0.5 apart
    knees[2, LEFT] = (0.09, 0.12, 0.0)       # 0.15 apart
    step = make_step(3, foot_pos=feet, knee_pos=knees)
    np.testing.assert_allclose(term("feet_distance", step, params), [1.0, math.exp(-10 * 0.04 ** 2), math.exp(-0.1)])
    np.testing.assert_allclose(term("knee_distance", step, params), [1.0, math.exp(-10 * 0.35 ** 2), 1.0])


def test_default_yaw_roll_penalises_hip_yaw_and_roll_offsets_from_the_standing_pose_only():
    q = standing_q(4)
    q[1, JOINTS.index("r_hip_yaw")] += 0.5
    q[2, JOINTS.index("l_hip_roll")] -= 0.2
    q[3, JOINTS.index("l_knee")] = -1.0      # other joints are free
    np.testing.assert_allclose(term("default_yaw_roll", make_step(4, q=q)),
                               [1.0, (math.exp(-4 * 0.25) + 3) / 4, (math.exp(-5 * 0.04) + 3) / 4, 1.0])


def test_linear_velocity_tracking_is_in_the_heading_frame():
    step = make_step(2, command=[(0.3, 0.1, 0.0), (0.3, 0.1, 0.0)],
                     heading_linvel=[(0.3, 0.1, 0.5), (0.5, -0.1, 0.0)],   # vertical velocity is not tracked
                     base_linvel=[(0.0, 0.3, 0.0), (0.3, 0.1, 0.0)])        # nor the base frame's velocity
    np.testing.assert_allclose(term("linvel_tracking", step), [1.0, math.exp(-5 * 0.08)])


def test_angular_velocity_tracking_uses_the_world_z_rate():
    step = make_step(4, command=[(0.0, 0.0, 0.2)] * 4,
                     base_euler=[(0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0), (0.0, math.pi / 2, 0.0)],
                     # level; level 0.3 rad/s too fast; rolled 90 deg: world z is the base's y; pitched 90: -x
                     base_angvel=[(0.0, 0.0, 0.2), (0.0, 0.0, 0.5), (0.0, 0.2, 0.0), (-0.2, 0.0, 0.0)])
    np.testing.assert_allclose(term("angvel_tracking", step), [1.0, math.exp(-7 * 0.09), 1.0, 1.0])


def test_velocity_mismatch_penalises_vertical_velocity_and_roll_pitch_rates():
    step = make_step(3, heading_linvel=[(0.5, 0.0, 0.0), (0.0, 0.0, 0.2), (0.0, 0.0, 0.0)],
                     base_angvel=[(0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.3, 0.4, 5.0)])
    np.testing.assert_allclose(term("velocity_mismatch", step),
                               [1.0, (math.exp(-25 * 0.04) + 1) / 2, (1 + math.exp(-2 * 0.25)) / 2])


def test_orientation_penalises_roll_and_pitch_not_yaw():
    step = make_step(2, base_euler=[(0.0, 0.0, 1.0), (0.1, 0.2, 0.0)])
    np.testing.assert_allclose(term("orientation", step), [1.0, math.exp(-5 * 0.05)])


def test_base_height_tracks_the_target():
    step = make_step(2, base_pos=[(1.0, 2.0, 0.42), (0.0, 0.0, 0.32)])
    np.testing.assert_allclose(term("base_height", step, RewardParams(base_height=0.42)), [1.0, math.exp(-5 * 0.01)])


def test_base_acceleration_smoothness_penalises_velocity_changes():
    step = make_step(2, base_linvel=[(0.5, 0.0, 0.0), (0.6, 0.0, 0.0)], base_linvel_prev=[(0.5, 0.0, 0.0)] * 2,
                     base_angvel=[(0.0, 0.0, 0.3), (0.0, 0.2, 0.3)], base_angvel_prev=[(0.0, 0.0, 0.3)] * 2)
    np.testing.assert_allclose(term("base_acceleration_smoothness", step), [1.0, math.exp(-0.05)])


def test_action_smoothness_is_the_squared_second_difference():
    step = make_step(2, action=[[0.2] * 10, [0.0] * 10], action_prev=[[0.1] * 10] * 2, action_prev2=[[0.0] * 10] * 2)
    np.testing.assert_allclose(term("action_smoothness", step), [0.0, 10 * 0.2 ** 2])


def test_torque_velocity_is_squared_torque_plus_ten_times_squared_velocity():
    step = make_step(2, tau=[[0.0] * 10, [2.0] * 10], qd=[[0.0] * 10, [1.0] * 10])
    np.testing.assert_allclose(term("torque_velocity", step), [0.0, 10 * 4.0 + 10 * 10 * 1.0])


def test_joint_acceleration_is_the_squared_velocity_change_per_policy_period():
    qd = np.zeros((3, 10))
    qd[1, 0] = 0.01                          # 1 rad/s^2 over 10 ms
    qd[2, 3:5] = -0.02                       # 2 rad/s^2 on two joints
    np.testing.assert_allclose(term("joint_acceleration", make_step(3, qd=qd)), [0.0, 1.0, 8.0])


def test_the_terms_are_table_ii_with_its_weights():
    assert {name: weight for name, (_, weight) in REWARD_TERMS.items()} == {
        "alive": 0.15, "swing_foot_height": 1.0, "foot_contact_pattern": 1.0, "foot_slip": -0.05,
        "feet_distance": 1.0, "knee_distance": 1.0, "default_yaw_roll": 0.5, "linvel_tracking": 2.0,
        "angvel_tracking": 1.0, "velocity_mismatch": 0.5, "orientation": 1.0, "base_height": 0.5,
        "base_acceleration_smoothness": 0.05, "action_smoothness": -0.002, "torque_velocity": -5e-6,
        "joint_acceleration": -5e-7}


def test_the_ideal_state_earns_every_positive_weight_and_a_terminated_env_loses_alive():
    total, terms = compute(make_step(2, alive=[True, False]))
    assert list(terms) == list(REWARD_TERMS)
    np.testing.assert_allclose(total, [9.7, 9.55])   # 0.15 + 1 + 1 + 1 + 1 + 0.5 + 2 + 1 + 0.5 + 1 + 0.5 + 0.05
    for name, (_, weight) in REWARD_TERMS.items():
        np.testing.assert_allclose(terms[name], [max(weight, 0.0), 0.0 if name == "alive" else max(weight, 0.0)])


def mixed_batch() -> WalkStep:
    """Five envs, every field different across them."""
    rng = np.random.default_rng(0)
    n = 5
    return make_step(
        n, alive=[True, True, False, True, True], base_pos=rng.normal([0.0, 0.0, 0.42], 0.03, (n, 3)),
        base_euler=rng.normal(0, 0.1, (n, 3)), base_linvel=rng.normal(0, 0.3, (n, 3)),
        base_angvel=rng.normal(0, 0.3, (n, 3)), base_linvel_prev=rng.normal(0, 0.3, (n, 3)),
        base_angvel_prev=rng.normal(0, 0.3, (n, 3)), command=rng.uniform(-0.5, 0.5, (n, 3)),
        heading_linvel=rng.normal(0, 0.3, (n, 3)), foot_pos=rng.normal(0, 0.1, (n, 2, 3)),
        foot_vel=rng.normal(0, 0.2, (n, 2, 3)), foot_contact=rng.random((n, 2)) < 0.5,
        knee_pos=rng.normal(0, 0.1, (n, 2, 3)), stance_desired=[RIGHT, LEFT, DOUBLE_SUPPORT, LEFT, RIGHT],
        swing_height_desired=[0.03, 0.01, 0.0, 0.04, 0.02], q=rng.normal(0, 0.3, (n, 10)),
        qd=rng.normal(0, 2, (n, 10)), qd_prev=rng.normal(0, 2, (n, 10)), tau=rng.normal(0, 3, (n, 10)),
        action=rng.normal(0, 0.3, (n, 10)), action_prev=rng.normal(0, 0.3, (n, 10)),
        action_prev2=rng.normal(0, 0.3, (n, 10)))


def test_compute_weights_the_terms_and_sums_them():
    step = mixed_batch()
    total, terms = compute(step)
    for name, (function, weight) in REWARD_TERMS.items():
        np.testing.assert_allclose(terms[name], weight * function(step, PARAMS))
    np.testing.assert_allclose(total, sum(terms.values()))
    assert total.shape == (5,)
    assert len({round(float(t), 9) for t in total}) == 5


def test_compute_uses_exactly_the_given_weights_and_refuses_unknown_terms():
    step = mixed_batch()
    total, terms = compute(step, {"alive": 2.0, "foot_slip": -1.0})
    assert set(terms) == {"alive", "foot_slip"}
    np.testing.assert_allclose(total, 2.0 * rewards.alive(step, PARAMS) - rewards.foot_slip(step, PARAMS))
    with pytest.raises(ValueError, match=r"unknown reward terms \['alvie'\]"):
        compute(step, {"alvie": 1.0})


def test_compute_on_a_batch_equals_compute_on_each_env_alone():
    step = mixed_batch()
    params = RewardParams(feet_distance=0.12, knee_distance=0.1, base_height=0.4)
    total, terms = compute(step, params=params)
    for i in range(5):
        total_i, terms_i = compute(env(step, i), params=params)
        np.testing.assert_allclose(total_i, total[i:i + 1], rtol=1e-12)
        for name in terms:
            np.testing.assert_allclose(terms_i[name], terms[name][i:i + 1], rtol=1e-12)


def test_the_default_params_are_bruce_standing_geometry():
    config = load_config()
    backend = MujocoBackend(config)
    backend.configure()               # places the robot in the standing pose, soles on the floor
    data = backend.data
    soles = [data.site(f"{side}_sole").xpos for side in "rl"]
    knees = [data.body(f"{side}_shank").xpos for side in "rl"]
    assert PARAMS.feet_distance == pytest.approx(np.linalg.norm(soles[1] - soles[0]), abs=5e-5)
    assert PARAMS.knee_distance == pytest.approx(np.linalg.norm(knees[1] - knees[0]), abs=5e-5)
    assert PARAMS.base_height == pytest.approx(backend.nominal_base_height, abs=5e-5)
    pose = dict(zip(config.joints, config.standing_pose, strict=True))
    assert PARAMS.hip_yaw_default == (pose["r_hip_yaw"], pose["l_hip_yaw"])
    assert PARAMS.hip_roll_default == (pose["r_hip_roll"], pose["l_hip_roll"])
    assert tuple(config.joints) == JOINTS


def test_added_terms_score_the_mean_velocity_and_the_heading():
    from training.rl.rewards import ADDED_TERMS, PAPER_WEIGHTS, heading_tracking, mean_velocity_tracking

    command = np.array([[0.4, 0.0, 0.2]] * 3)
    mean = command + np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.1]])
    step = make_step(3, command=command, mean_velocity=mean, heading_error=np.array([0.0, 0.1, -0.3]))
    params = RewardParams()
    np.testing.assert_allclose(mean_velocity_tracking(step, params), [1.0, np.exp(-0.2), np.exp(-0.4)])
    np.testing.assert_allclose(heading_tracking(step, params), [1.0, np.exp(-0.1), np.exp(-0.9)])
    assert all(weight == 0.0 for _, weight in ADDED_TERMS.values())  # off unless a config weights them
    total, terms = compute(step, {**PAPER_WEIGHTS, "heading_tracking": 2.0})
    assert set(terms) == set(PAPER_WEIGHTS) | {"heading_tracking"}
    np.testing.assert_allclose(terms["heading_tracking"], 2.0 * heading_tracking(step, params))
