import math

import numpy as np
import pytest

from bruce_hw.backend import BackendError
from bruce_hw.echo import EchoBackend
from bruce_hw.mock import MujocoBackend
from bruce_hw.quaternion import euler_of, rotate_to_body
from runtime.estimation import BaseEstimate, GroundTruthEstimator
from runtime.observation.builder import ObservationBuilder
from runtime.walking.gait import COMMAND_ACCELERATION, gait_period


def test_observation_follows_table_one(config):
    builder = ObservationBuilder(config)
    assert builder.size == 2 + 3 + 10 + 10 + 3 + 3 + 3 + 10  # the paper's Table I observation
    backend = MujocoBackend(config)
    backend.configure()
    state = backend.read()
    base = BaseEstimate(quat=np.array([1.0, 0.0, 0.0, 0.0]), linvel=np.array([0.1, 0.2, 0.3]),
                        angvel=np.array([-1.0, 0.0, 1.0]), euler=np.array([0.01, 0.02, 0.03]))
    obs = builder.build(np.array([0.4, 0.0, -0.5]), state, base, np.arange(10.0))
    s = builder.slices
    np.testing.assert_allclose(obs[s["clock"]], [0.0, 1.0])  # the gait clock starts at phase 0
    # the command the gait follows: one policy tick of the bounded acceleration toward the command
    followed = COMMAND_ACCELERATION / config.policy_hz * [1.0, 0.0, -1.0]
    np.testing.assert_allclose(obs[s["command"]], followed, rtol=1e-12)
    np.testing.assert_array_equal(obs[s["q"]], state.joints.q)
    np.testing.assert_array_equal(obs[s["qd"]], state.joints.qd)
    np.testing.assert_array_equal(obs[s["base_linvel"]], base.linvel)
    np.testing.assert_array_equal(obs[s["base_angvel"]], base.angvel)
    # roll and pitch as estimated; then the yaw's error to the commanded heading: the reference starts at the
    # measured yaw and has turned at the followed yaw rate for one policy tick
    np.testing.assert_allclose(obs[s["euler"]], [0.01, 0.02, -followed[2] / config.policy_hz], rtol=1e-12)
    np.testing.assert_array_equal(obs[s["last_action"]], np.arange(10.0))


def test_heading_error_integrates_the_command_is_bounded_and_ignores_where_north_is(config):
    def errors(yaw_offset: float, yaw_rates: list[float], yaw_of_tick) -> list[float]:
        builder = ObservationBuilder(config)
        state = MujocoBackend(config)
        state.configure()
        robot = state.read()
        out = []
        for k, wz in enumerate(yaw_rates):
            base = BaseEstimate(quat=np.array([1.0, 0.0, 0.0, 0.0]), linvel=np.zeros(3), angvel=np.zeros(3),
                                euler=np.array([0.0, 0.0, yaw_offset + yaw_of_tick(k)]))
            out.append(builder.build(np.array([0.0, 0.0, wz]), robot, base, np.zeros(10))
                       [builder.slices["euler"].start + 2])
        return out

    dt = 1.0 / config.policy_hz
    rates = np.minimum(0.4, COMMAND_ACCELERATION[2] * dt * np.arange(1, 201))  # the followed yaw rate per tick
    turned = dt * np.cumsum(rates)  # the reference's turn after each tick
    standing = errors(0.0, [0.4] * 200, lambda k: 0.0)  # commanded to turn, the base does not
    np.testing.assert_allclose(standing[:30], -turned[:30], rtol=1e-9)
    assert min(standing) == pytest.approx(-0.3)  # the reference leads the measured yaw by 0.3 rad at most
    # turning as commanded: an error of one tick's turn (the reference is where the yaw should be by the next tick)
    following = errors(0.0, [0.4] * 200, lambda k: turned[k - 1] if k else 0.0)
    np.testing.assert_allclose(following, -rates * dt, rtol=1e-9)
    np.testing.assert_allclose(errors(2.0, [0.4] * 200, lambda k: 0.0), standing, atol=1e-12)  # any start heading
    np.testing.assert_allclose(errors(3.0, [0.4] * 200, lambda k: turned[k - 1] if k else 0.0), -rates * dt,
                               rtol=1e-6)


def test_ground_truth_estimate_is_in_the_base_frame(config):
    yaw = math.pi / 2
    quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    np.testing.assert_allclose(euler_of(quat), [0.0, 0.0, yaw], atol=1e-12)
    # facing +y in the world, moving along world +y is moving forward in the base frame
    np.testing.assert_allclose(rotate_to_body(quat, np.array([0.0, 1.0, 0.0])), [1.0, 0.0, 0.0], atol=1e-12)

    backend = MujocoBackend(config)
    backend.configure()
    backend.data.qvel[0:3] = (0.3, 0.0, 0.0)
    estimate = GroundTruthEstimator(backend).estimate()
    assert estimate.linvel[0] == pytest.approx(0.3)


def test_ground_truth_estimator_refuses_a_backend_without_truth(config):
    echo = EchoBackend(config)
    echo.configure()
    with pytest.raises(BackendError, match="echo backend: no ground truth"):
        GroundTruthEstimator(echo)


def test_the_clock_input_runs_at_the_cadence_of_the_forward_command(config):
    """The clock advances 1/C_T per second, C_T following the (rate-limited) forward command, and resets."""
    state = MujocoBackend(config)
    state.configure()
    robot = state.read()
    base = BaseEstimate(quat=np.array([1.0, 0.0, 0.0, 0.0]), linvel=np.zeros(3), angvel=np.zeros(3),
                        euler=np.zeros(3))
    builder = ObservationBuilder(config)
    dt = 1.0 / config.policy_hz
    period_0 = gait_period(config.models.gait_period_s, 0.0)

    def phases(vx: float, ticks: int) -> np.ndarray:
        clock = [builder.build(np.array([vx, 0.0, 0.0]), robot, base, np.zeros(10))[builder.slices["clock"]]
                 for _ in range(ticks)]
        return np.unwrap(np.arctan2(*np.array(clock).T))

    standing = phases(0.0, 50)
    np.testing.assert_allclose(np.diff(standing), 2 * math.pi * dt / period_0, rtol=1e-9)
    builder.reset()
    fast = phases(0.8, 400)  # 1.6 s to reach 0.8 m/s at the cadence's acceleration, then the fast period
    period_fast = gait_period(config.models.gait_period_s, 0.8)
    assert period_fast < period_0 < gait_period(config.models.gait_period_s, -0.5)
    np.testing.assert_allclose(np.diff(fast)[-50:], 2 * math.pi * dt / period_fast, rtol=1e-9)
    assert np.all(np.diff(np.diff(fast)) >= -1e-12)  # speeds up monotonically: no jump of the phase
    builder.reset()
    np.testing.assert_allclose(phases(0.0, 50), standing, atol=1e-12)
