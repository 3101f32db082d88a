import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bruce_hw.config import ConfigError, load_config

LEG = ("hip_yaw", "hip_pitch", "hip_roll", "knee", "ankle")


def test_default_config_follows_the_hardware_order_and_the_paper(config):
    assert config.joints == tuple(f"{side}_{j}" for side in ("r", "l") for j in LEG)
    ankle = np.zeros(config.n_joints, dtype=bool)
    ankle[config.joint_indices("ankle")] = True
    assert [config.joints[i] for i in config.joint_indices("ankle")] == ["r_ankle", "l_ankle"]
    assert np.all(config.eq8.kp[ankle] == 2.5) and np.all(config.eq8.kd[ankle] == 0.35)
    assert np.all(config.eq8.kp[~ankle] == 20.0) and np.all(config.eq8.kd[~ankle] == 0.7)
    assert np.all(config.eq9.kp[ankle] == 10.0) and np.all(config.eq9.kd[ankle] == 1.0)
    assert np.all(config.eq9.kp[~ankle] == 60.0) and np.all(config.eq9.kd[~ankle] == 2.0)
    assert (config.loop_hz, config.policy_hz, config.policy_decimation) == (1000, 100, 10)
    assert config.actuator_torque_limit == 10.5
    assert config.buses.bear.baud == 8_000_000 and config.buses.bear.ids == tuple(range(1, 11))
    assert config.buses.dynamixel.baud == 2_000_000 and config.buses.dynamixel.ids == tuple(range(11, 17))
    assert config.buses.sense.port and config.buses.can.interface and config.buses.can.channel
    assert len(config.arms.names) == 6 and config.arms.hold_pose.shape == (6,)
    assert np.all((config.standing_pose > config.q_lower) & (config.standing_pose < config.q_upper))


def test_coupling_matches_bruces_published_maps(config):
    m = np.arange(1.0, 11.0) / 10.0  # BEAR positions, IDs 1..10
    q = config.coupling.joint_positions(m)
    expected = [-m[0], 0.5 * (m[1] - m[2]), -0.5 * (m[1] + m[2]), -m[3], m[3] + m[4],
                -m[5], 0.5 * (m[6] - m[7]), -0.5 * (m[6] + m[7]), m[8], -m[8] - m[9]]
    np.testing.assert_allclose(q, expected)
    # hip pitch alone is driven by two BEARs: tau_pitch = tau_m2 - tau_m3
    tau_m = np.zeros(10)
    tau_m[1], tau_m[2] = 10.5, -10.5
    assert config.coupling.joint_torques(tau_m)[1] == pytest.approx(21.0)


vectors = st.lists(st.floats(-3, 3, allow_nan=False), min_size=10, max_size=10).map(np.array)


@settings(max_examples=50, deadline=None)
@given(q=vectors, qd=vectors, tau=vectors)
def test_coupling_round_trips_and_conserves_power(config, q, qd, tau):
    c = config.coupling
    np.testing.assert_allclose(c.joint_positions(c.actuator_positions(q)), q, atol=1e-12)
    np.testing.assert_allclose(c.joint_torques(c.actuator_torques(tau)), tau, atol=1e-12)
    # the same power flows through joints and actuators
    assert tau @ qd == pytest.approx(c.actuator_torques(tau) @ c.actuator_positions(qd), abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(tau=st.lists(st.floats(-60, 60, allow_nan=False), min_size=10, max_size=10).map(np.array))
def test_saturation_keeps_every_actuator_inside_its_limit(config, tau):
    c = config.coupling
    limited = c.saturate(tau, config.actuator_torque_limit)
    assert np.all(np.abs(c.actuator_torques(limited)) <= config.actuator_torque_limit + 1e-9)


def _expect_error(write_config, tree, *fragments):
    path = write_config(tree)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_missing_key_is_named(raw_config, write_config):
    del raw_config["gains"]["eq8"]["kd"]
    _expect_error(write_config, raw_config, "gains.eq8.kd", "missing key")


def test_wrong_type_is_named(raw_config, write_config):
    raw_config["rates"]["loop_hz"] = "fast"
    _expect_error(write_config, raw_config, "rates.loop_hz", "expected an integer", "'fast'")


def test_wrong_length_is_named(raw_config, write_config):
    raw_config["coupling"]["joint_from_actuator"][3] = [0.0] * 9
    _expect_error(write_config, raw_config, "coupling.joint_from_actuator[3]", "10 numbers", "9 entries")


def test_wrong_length_of_a_limit_pair_is_named(raw_config, write_config):
    raw_config["joints"]["position_limits"]["l_knee"] = [-2.5]
    _expect_error(write_config, raw_config, "joints.position_limits.l_knee", "2 numbers")


def test_unknown_joint_is_named(raw_config, write_config):
    raw_config["joints"]["standing_pose"]["r_toe"] = 0.1
    _expect_error(write_config, raw_config, "joints.standing_pose.r_toe", "unknown joint")


def test_missing_joint_is_named(raw_config, write_config):
    del raw_config["gains"]["eq9"]["kp"]["l_ankle"]
    _expect_error(write_config, raw_config, "gains.eq9.kp.l_ankle", "missing joint")


def test_unknown_key_is_named(raw_config, write_config):
    raw_config["buses"]["bear"]["prot"] = "/dev/ttyUSB0"
    _expect_error(write_config, raw_config, "buses.bear.prot", "unknown key")


def test_wrong_number_of_bus_ids_is_named(raw_config, write_config):
    raw_config["buses"]["bear"]["ids"] = [1, 2, 3]
    _expect_error(write_config, raw_config, "buses.bear.ids", "10 IDs")


def test_missing_model_file_is_named(raw_config, write_config):
    raw_config["mjcf"] = "no_such_robot.xml"
    _expect_error(write_config, raw_config, "mjcf", "no_such_robot.xml", "not found")


def test_set_overrides_dotted_keys_with_yaml_values():
    config = load_config(overrides=["buses.bear.port=/dev/ttyUSB3", "buses.can.channel=vcan0",
                                    "safety.damping_kd=2.5"])
    assert config.buses.bear.port == "/dev/ttyUSB3"
    assert config.buses.can.channel == "vcan0"
    assert config.safety.damping_kd == 2.5


def test_set_rejects_a_key_that_does_not_exist():
    with pytest.raises(ConfigError, match=r"buses\.bear\.prot: no such key"):
        load_config(overrides=["buses.bear.prot=/dev/ttyUSB3"])


def test_set_value_is_validated_like_the_file():
    with pytest.raises(ConfigError, match=r"rates\.policy_hz: expected a divisor"):
        load_config(overrides=["rates.policy_hz=300"])


def test_default_config_is_found_from_any_directory(tmp_path):
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert load_config().name == "bruce"
    finally:
        os.chdir(cwd)


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="robot config file not found"):
        load_config(tmp_path / "nope.yaml")


def test_pinn_lookahead_is_optional_and_checked(config, raw_config, write_config):
    assert config.models.pinn_lookahead_ticks == 0  # the paper's one-step reference by default
    raw_config["pinn"]["lookahead_ticks"] = 2
    assert load_config(write_config(raw_config)).models.pinn_lookahead_ticks == 2
    raw_config["pinn"]["lookahead_ticks"] = -1
    _expect_error(write_config, raw_config, "pinn.lookahead_ticks", "an integer in [0, 50] ticks", "got -1")


def test_gait_period_is_a_number_or_a_cadence_table(config, raw_config, write_config):
    assert config.models.gait_period_s == ((-0.5, 0.40), (0.0, 0.36), (0.8, 0.26))
    raw_config["policy"]["gait_period_s"] = 0.4
    assert load_config(write_config(raw_config)).models.gait_period_s == ((0.0, 0.4),)  # a constant C_T
    raw_config["policy"]["gait_period_s"] = [[0.0, 0.36], [-0.5, 0.44]]
    _expect_error(write_config, raw_config, "policy.gait_period_s", "increasing vx")
    raw_config["policy"]["gait_period_s"] = [[0.0, 0.0]]
    _expect_error(write_config, raw_config, "policy.gait_period_s[0][1]", "a number in (0.1, 2] s", "got 0.0")
    raw_config["policy"]["gait_period_s"] = [0.0, 0.36]
    _expect_error(write_config, raw_config, "policy.gait_period_s[0]", "a [vx (m/s), period (s)] pair", "got 0.0")


def test_arm_servo_signs_come_from_the_config_and_are_plus_or_minus_one(raw_config, write_config):
    from bruce_hw.config import ConfigError, load_config

    config = load_config()
    assert config.arms.servo_signs.tolist() == [1.0, 1.0, -1.0, 1.0, 1.0, -1.0]  # BRUCE-OP's flipped elbows
    raw_config["arms"]["servo_signs"]["r_elbow"] = 0
    with pytest.raises(ConfigError, match=r"arms\.servo_signs\.r_elbow: expected \+1 or -1, got 0\.0"):
        load_config(write_config(raw_config))


def test_bear_gains_come_from_the_config_and_every_gain_register_is_required(raw_config, write_config):
    from bruce_hw.config import BEAR_GAIN_REGISTERS, ConfigError, load_config

    gains = dict(load_config().buses.bear.gains)
    assert set(gains) == set(BEAR_GAIN_REGISTERS) and gains["p_gain_iq"] == 0.277  # BRUCE-OP v0.0.7's
    del raw_config["buses"]["bear"]["gains"]["d_gain_force"]
    with pytest.raises(ConfigError, match=r"buses\.bear\.gains\.d_gain_force: expected a value for every BEAR gain"):
        load_config(write_config(raw_config))
    raw_config["buses"]["bear"]["gains"]["d_gain_force"] = -1.0
    with pytest.raises(ConfigError, match=r"buses\.bear\.gains\.d_gain_force"):
        load_config(write_config(raw_config))
