"""The walking teacher in the mock at 1 kHz, through the runtime (Eq. 8 only), and the kinematic estimator
while it walks."""

import numpy as np
import pytest

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import CommandSchedule
from runtime.estimation import GroundTruthEstimator
from runtime.estimation.kinematic import KinematicEstimator
from runtime.loop.run import run_session
from training.evaluation.walking_eval import GRID, TRACKING_LIMIT


def walk(config, cmd, seconds, estimator=None, controller_kind="teacher", backend=None, controller=None):
    return run_session(backend or MujocoBackend(config), config, duration=seconds, realtime=False,
                       controller_kind=controller_kind, controller=controller,
                       commands=CommandSchedule.constant(*cmd), estimator=estimator)




def assert_walks_and_tracks(summary, cmd):
    truth = summary.truth
    assert not truth.fell and summary.stop_cause == "duration reached", (cmd, summary.stop_cause)
    error = truth.tracking_error
    assert max(error["vx"], error["vy"]) <= TRACKING_LIMIT and error["wz"] <= TRACKING_LIMIT, (cmd, error)


@pytest.mark.parametrize("cmd", GRID)
def test_teacher_walks_the_command_grid(config, cmd):
    assert_walks_and_tracks(walk(config, cmd, 20.0), cmd)


@pytest.mark.parametrize("cmd", GRID)
def test_distilled_policy_walks_the_command_grid(config, cmd):
    assert config.models.policy is not None  # the committed ONNX policy is the default
    assert_walks_and_tracks(walk(config, cmd, 20.0, controller_kind="policy"), cmd)


@pytest.fixture(scope="module")
def rl_config():
    """The robot config with the committed PPO policy (bruce-train-policy; docs/rl.md)."""
    return load_config(overrides=["policy.model=policies/bruce_walk_rl.onnx"])


@pytest.mark.parametrize("cmd", GRID)
def test_ppo_policy_walks_the_command_grid(rl_config, cmd):
    assert rl_config.models.policy.name == "bruce_walk_rl.onnx"
    assert_walks_and_tracks(walk(rl_config, cmd, 20.0, controller_kind="policy"), cmd)


class PushedAt:
    """A nominal controller that pushes the mock's base once, `at_s` after the start."""

    def __init__(self, controller, backend, at_s, impulse, policy_hz):
        self.controller, self.backend, self.at_s, self.impulse = controller, backend, at_s, np.asarray(impulse)
        self.dt = 1.0 / policy_hz

    def reset(self, q):
        self.calls = 0
        self.controller.reset(q)

    def __call__(self, state, base, command):
        if self.calls == round(self.at_s / self.dt):
            self.backend.push(self.impulse, 0.1)
        self.calls += 1
        return self.controller(state, base, command)


@pytest.mark.parametrize("kind", ["teacher", "policy"])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_lateral_push_while_walking_is_survived(config, kind, side):
    from runtime.control.controllers import build_controller

    backend = MujocoBackend(config)
    controller, _ = build_controller(config, None, kind)
    pushed = PushedAt(controller, backend, 6.0, (0.0, side * 1.0, 0.0), config.policy_hz)  # 1 N s, sideways
    summary = walk(config, (0.4, 0.0, 0.0), 12.0, backend=backend, controller=pushed)
    assert pushed.calls > 600 and not summary.truth.fell
    assert summary.truth.tracking.measured_mean["vx"] > 0.2  # and it walks on


class TruthWithKinematicShadow:
    """Controls on the truth and runs the robot-side estimator alongside, recording its velocity error."""

    def __init__(self, backend, config):
        self.backend = backend
        self.kinematic = KinematicEstimator(config)
        self.errors = []

    def reset(self, state):
        self.truth = GroundTruthEstimator(self.backend)  # the backend is configured by now
        self.kinematic.reset(state)

    def update(self, state):
        self.kinematic.update(state)

    def estimate(self):
        truth, estimate = self.truth.estimate(), self.kinematic.estimate()
        self.errors.append(estimate.linvel - truth.linvel)
        return truth


def test_kinematic_estimator_tracks_the_base_velocity_while_walking(config):
    backend = MujocoBackend(config)
    shadow = TruthWithKinematicShadow(backend, config)
    summary = run_session(backend, config, duration=8.0, realtime=False, controller_kind="teacher",
                          commands=CommandSchedule.constant(0.4, 0.0, 0.0), estimator=shadow,
                          privileged=True)  # the teacher walks on the truth the shadow estimator hands it
    assert not summary.truth.fell
    errors = np.array(shadow.errors[100:])  # after the first second
    rmse = float(np.sqrt(np.mean(np.sum(errors[:, :2] ** 2, axis=1))))
    print(f"kinematic estimator while walking at 0.4 m/s: horizontal velocity RMSE {rmse:.3f} m/s")
    assert rmse <= 0.1, rmse
