import math

import numpy as np
import pytest

from bruce_hw.backend import BackendError
from bruce_hw.echo import EchoBackend
from bruce_hw.mock import MujocoBackend
from runtime.estimation import BaseEstimate, GroundTruthEstimator, euler_of, rotate_to_body
from runtime.policy import ObservationBuilder


def test_observation_follows_table_one(config):
    builder = ObservationBuilder(config)
    assert builder.size == 2 + 3 + 10 + 10 + 3 + 3 + 3 + 10  # the paper's Table I observation
    backend = MujocoBackend(config)
    backend.configure()
    state = backend.read()
    base = BaseEstimate(quat=np.array([1.0, 0.0, 0.0, 0.0]), linvel=np.array([0.1, 0.2, 0.3]),
                        angvel=np.array([-1.0, 0.0, 1.0]), euler=np.array([0.01, 0.02, 0.03]))
    t = 0.125 * config.models.gait_period_s
    obs = builder.build(t, np.array([0.4, 0.0, -0.5]), state, base, np.arange(10.0))
    s = builder.slices
    np.testing.assert_allclose(obs[s["clock"]], [math.sin(math.pi / 4), math.cos(math.pi / 4)])
    np.testing.assert_array_equal(obs[s["command"]], [0.4, 0.0, -0.5])
    np.testing.assert_array_equal(obs[s["q"]], state.joints.q)
    np.testing.assert_array_equal(obs[s["qd"]], state.joints.qd)
    np.testing.assert_array_equal(obs[s["base_linvel"]], base.linvel)
    np.testing.assert_array_equal(obs[s["base_angvel"]], base.angvel)
    np.testing.assert_array_equal(obs[s["euler"]], base.euler)
    np.testing.assert_array_equal(obs[s["last_action"]], np.arange(10.0))


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
