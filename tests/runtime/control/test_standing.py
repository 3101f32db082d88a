import numpy as np
import pytest

from bruce_hw import make_backend
from runtime.control.standing import StandingController
from runtime.loop.run import run_session


def test_mock_stands_for_10_s_within_2_cm_of_the_nominal_height(config, tmp_path):
    backend = make_backend("mock", config)
    summary = run_session(backend, config, duration=10.0, realtime=False, stats_path=tmp_path / "s.json",
                          controller_kind="standing")
    truth = summary.truth
    assert summary.ticks == 10_000 and truth.sim_time == pytest.approx(10.0, abs=0.002)
    assert not truth.fell
    assert truth.nominal_base_height == pytest.approx(0.424, abs=0.002)
    assert truth.base_height_min > truth.nominal_base_height - 0.02
    assert truth.base_height_max < truth.nominal_base_height + 0.02
    drift = np.hypot(*np.subtract(truth.base_xy_end, truth.base_xy_start))
    assert drift < 0.05


def test_soft_start_ramps_from_the_measured_pose(config):
    controller = StandingController(config)
    backend = make_backend("echo", config, initial_q=config.standing_pose - 0.2)
    backend.configure()
    state = backend.read()
    controller.reset(state.joints.q)
    first = controller(state)
    # ankles and hip rolls carry balance feedback; the other joints follow the ramp alone
    legs = np.ones(config.n_joints, dtype=bool)
    legs[config.joint_indices("ankle", "hip_roll")] = False
    np.testing.assert_allclose(first[legs], state.joints.q[legs])  # no jump at the start
    halfway = [controller(state) for _ in range(controller.ramp_steps // 2 - 1)][-1]
    assert np.all(np.abs(halfway[legs] - state.joints.q[legs]) > 0.05)
    for _ in range(controller.ramp_steps):
        last = controller(state)
    yaw = config.joint_indices("hip_yaw")
    np.testing.assert_allclose(last[yaw], config.standing_pose[yaw])  # ends on the pose (+ integral elsewhere)
