import numpy as np
import pytest

from bruce_hw.config import PdGains
from runtime.control.mixing import eq8_torque, eq9_torque


def test_eq8_by_hand():
    gains = PdGains(kp=np.array([20.0, 2.5]), kd=np.array([0.7, 0.35]))
    tau = eq8_torque(np.array([0.5, -0.2]), np.array([0.4, 0.0]), np.array([1.0, -2.0]), gains)
    # 20 * 0.1 - 0.7 * 1 = 1.3 ; 2.5 * -0.2 - 0.35 * -2 = -0.5 + 0.7 = 0.2
    np.testing.assert_allclose(tau, [1.3, 0.2], atol=1e-12)


def test_eq9_by_hand():
    gains = PdGains(kp=np.array([60.0, 10.0, 60.0]), kd=np.array([2.0, 1.0, 2.0]))
    tau_star = np.array([1.0, -2.0, 0.0])
    q, qd = np.array([0.0, 0.3, 1.0]), np.array([0.5, -0.5, 0.0])
    q_next, qd_next = np.array([0.1, 0.2, 1.0]), np.array([1.0, -1.0, 0.0])
    tau = eq9_torque(tau_star, q_next, qd_next, q, qd, gains)
    # 1 + 60 * 0.1 + 2 * 0.5 = 8 ; -2 + 10 * -0.1 + 1 * -0.5 = -3.5 ; a perfect prediction adds nothing: 0
    np.testing.assert_allclose(tau, [8.0, -3.5, 0.0], atol=1e-12)


def test_eq9_uses_the_configs_eq9_gains(config):
    n = config.n_joints
    q, qd = config.standing_pose, np.zeros(n)
    q_next = q + 0.01
    tau = eq9_torque(np.zeros(n), q_next, qd, q, qd, config.eq9)
    assert tau == pytest.approx(0.01 * config.eq9.kp)
    knee = config.joints.index("r_knee")
    assert tau[knee] == pytest.approx(0.01 * config.raw["gains"]["eq9"]["kp"]["r_knee"])
