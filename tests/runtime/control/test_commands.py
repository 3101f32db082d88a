"""Velocity command schedules: timing, ramps, scenario validation, and the commands a controller gets on the mock."""

import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from support.paths import REPO

from bruce_hw.config import ConfigError
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import GroundTruth
from runtime.control.commands import COMMAND_LIMITS, CommandSchedule
from runtime.control.controllers import build_controller
from runtime.control.standing import StandingController
from runtime.loop.observers import TRACKING_SKIP_S, GroundTruthLog, heading_velocity
from runtime.loop.run import run_session

SCENARIOS = REPO / "configs" / "scenarios"


class CommandRecorder(StandingController):
    """Stands still, recording (stamp, command) for every policy tick."""

    def __init__(self, config):
        self.received: list[tuple[float, np.ndarray]] = []
        super().__init__(config)

    def reset(self, q_measured):
        """A new run (the session also calls the controller once before activation, to check it): start over."""
        self.received.clear()
        super().reset(q_measured)

    def __call__(self, state, base, command):
        self.received.append((state.joints.stamp, command.copy()))
        return super().__call__(state, base, command)


def schedule(*segments, ramp_s=0.0):
    return CommandSchedule([(d, c) for d, c in segments], ramp_s)


def test_steps_at_segment_boundaries_without_a_ramp():
    s = schedule((1.0, (0.4, 0.0, 0.0)), (2.0, (0.0, 0.1, -0.2)))
    assert s.duration == 3.0
    np.testing.assert_array_equal(s.at(-0.5), [0, 0, 0])
    np.testing.assert_array_equal(s.at(0.0), [0.4, 0, 0])
    np.testing.assert_array_equal(s.at(0.999), [0.4, 0, 0])
    np.testing.assert_array_equal(s.at(1.0), [0, 0.1, -0.2])
    np.testing.assert_array_equal(s.at(2.999), [0, 0.1, -0.2])
    np.testing.assert_array_equal(s.at(3.0), [0, 0, 0])  # after the last segment: stand (step in place)
    np.testing.assert_array_equal(s.at(1e6), [0, 0, 0])


def test_ramps_from_zero_between_segments_and_back_to_zero():
    s = schedule((2.0, (0.4, 0.0, 0.0)), (1.0, (0.0, 0.0, 0.5)), ramp_s=0.5)
    for t, expected in [(0.0, [0, 0, 0]), (0.25, [0.2, 0, 0]), (0.5, [0.4, 0, 0]), (1.9, [0.4, 0, 0]),
                        (2.0, [0.4, 0, 0]), (2.25, [0.2, 0, 0.25]), (2.5, [0, 0, 0.5]), (3.0, [0, 0, 0.5]),
                        (3.1, [0, 0, 0.4]), (3.5, [0, 0, 0]), (9.0, [0, 0, 0])]:
        np.testing.assert_allclose(s.at(t), expected, atol=1e-12, err_msg=f"t = {t}")


def test_a_segment_shorter_than_the_ramp_cuts_it_short():
    s = schedule((0.25, (0.4, 0.0, 0.0)), (1.0, (0.0, 0.0, 0.0)), ramp_s=0.5)
    np.testing.assert_allclose(s.at(0.25), [0.2, 0, 0])  # half way up when the next segment starts
    np.testing.assert_allclose(s.at(0.5), [0.1, 0, 0])   # ... and ramps down from there
    np.testing.assert_allclose(s.at(0.75), [0, 0, 0], atol=1e-12)


def test_constant_command_holds_for_ever():
    s = CommandSchedule.constant(0.3, -0.1, 0.2)
    assert s.duration == math.inf
    np.testing.assert_allclose(s.at(0.25), [0.15, -0.05, 0.1])
    np.testing.assert_allclose(s.at(1e6), [0.3, -0.1, 0.2])


def test_at_returns_a_fresh_array():
    s = CommandSchedule.constant(0.3, 0.0, 0.0)
    s.at(10.0)[0] = 99.0
    s.at(-1.0)[0] = 99.0
    assert s.at(10.0)[0] == 0.3 and s.at(-1.0)[0] == 0.0


@pytest.mark.parametrize("axis, index", [("vx", 0), ("vy", 1), ("wz", 2)])
def test_constant_command_out_of_range_names_the_limit(axis, index):
    low, high = COMMAND_LIMITS[axis]
    cmd = [0.0, 0.0, 0.0]
    cmd[index] = high + 0.1
    with pytest.raises(ValueError, match=rf"{axis} = .* outside the supported range \[{low:g}, {high:g}\]"):
        CommandSchedule.constant(*cmd)


def test_example_scenario_walks_then_turns():
    s = CommandSchedule.from_yaml(SCENARIOS / "walk_then_turn.yaml")
    assert s.duration == 15.0
    np.testing.assert_allclose(s.at(5.0), [0.4, 0, 0])
    np.testing.assert_allclose(s.at(12.0), [0, 0, 0.5])
    np.testing.assert_allclose(s.at(16.0), [0, 0, 0])


@pytest.mark.parametrize("text, problem", [
    ("segments: []", "segments: expected a non-empty list"),
    ("[1, 2]", "<top>: expected a mapping"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]}]\nramp: 0.5", "ramp: unknown key"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]}]\nramp_s: -1", "ramp_s: expected a number in [0, 10] s"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]}]\nramp_s: .nan", "ramp_s: expected a number in [0, 10] s"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]}, {cmd: [0, 0, 0]}]", "segments[1].duration: missing key"),
    ("segments: [{duration: 1.0}]", "segments[0].cmd: missing key"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0], speed: 2}]", "segments[0].speed: unknown key"),
    ("segments: [{duration: -1.0, cmd: [0, 0, 0]}]", "segments[0].duration: expected a number in (0, 3600] s"),
    ("segments: [{duration: soon, cmd: [0, 0, 0]}]", "segments[0].duration: expected a number in (0, 3600] s"),
    ("segments: [{duration: .inf, cmd: [0, 0, 0]}]", "), got inf"),
    ("segments: [{duration: 1.0e+9, cmd: [0, 0, 0]}]", "segments[0].duration: expected a number in (0, 3600] s"),
    ("segments: [{duration: 1e-3, cmd: [0, 0, 0]}]", "(YAML reads 1e-3 as text: write 1.0e-3)"),
    ("segments: [{duration: 1.0, cmd: [0.4, 0]}]", "segments[0].cmd: expected [vx, vy, wz] (3 numbers)"),
    ("segments: [{duration: 1.0, cmd: 0.4}]", "segments[0].cmd: expected [vx, vy, wz] (3 numbers)"),
    ("segments: [{duration: 1.0, cmd: [0.4, fast, 0]}]", "segments[0].cmd.vy: expected a number in [-0.3, 0.3] m/s"),
    ("segments: [{duration: 1.0, cmd: [true, 0, 0]}]", "segments[0].cmd.vx: expected a number in [-0.5, 1] m/s"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]}, {duration: 1.0, cmd: [1.2, 0, 0]}]",
     "segments[1].cmd.vx: expected a number in [-0.5, 1] m/s (the walking controllers' range), got 1.2"),
    ("segments: [{duration: 1.0, cmd: [0, 0, -0.6]}]",
     "segments[0].cmd.wz: expected a number in [-0.5, 0.5] rad/s (the walking controllers' range), got -0.6"),
    ("segments: [{duration: 1.0, cmd: [0, .nan, 0]}]",
     "segments[0].cmd.vy: expected a number in [-0.3, 0.3] m/s (the walking controllers' range), got nan"),
    ("segments: [{duration: 1.0, cmd: [0, 0, 0]]", "not valid YAML"),
])
def test_scenario_errors_name_the_file_the_segment_and_the_problem(tmp_path, text, problem):
    path = tmp_path / "scenario.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        CommandSchedule.from_yaml(path)
    assert str(error.value).startswith(f"{path}: ")
    assert problem in str(error.value)


def test_missing_scenario_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match=f"{tmp_path / 'none.yaml'}: cannot read the scenario"):
        CommandSchedule.from_yaml(tmp_path / "none.yaml")


def test_controller_gets_the_scheduled_command_on_every_policy_tick(config):
    recorder = CommandRecorder(config)
    commands = schedule((0.05, (0.4, 0.0, 0.0)), (0.05, (0.0, 0.1, 0.2)))
    summary = run_session(MujocoBackend(config), config, duration=0.2, realtime=False, commands=commands,
                          controller=recorder)
    assert summary.error is None and summary.ticks == 200
    stamps = np.array([stamp for stamp, _ in recorder.received])
    np.testing.assert_allclose(np.diff(stamps), 1.0 / config.policy_hz)
    # The mock's clock steps on read: policy tick k sees t = 1 ms + 10 k ms since activation.
    expected = [[0.4, 0, 0]] * 5 + [[0, 0.1, 0.2]] * 5 + [[0, 0, 0]] * 10
    np.testing.assert_array_equal([command for _, command in recorder.received], expected)


def test_tracking_error_of_a_robot_that_stands_still(config):
    summary = run_session(MujocoBackend(config), config, duration=TRACKING_SKIP_S + 0.5, realtime=False,
                          commands=CommandSchedule.constant(0.3, 0.0, 0.0), controller=CommandRecorder(config))
    truth = summary.truth
    assert not truth.fell and truth.tracking.samples == round(0.5 * config.policy_hz)
    assert truth.tracking_error["vx"] == pytest.approx(0.3, abs=0.02)
    assert truth.tracking_error["vy"] < 0.02 and truth.tracking_error["wz"] < 0.05
    assert truth.tracking_rmse["vx"] == pytest.approx(0.3, abs=0.02)
    data = summary.to_json()
    assert data["command_mean"]["vx"] == pytest.approx(0.3) and abs(data["velocity_mean"]["vx"]) < 0.02
    assert data["tracking_error"] == truth.tracking_error and data["tracking_rmse"] == truth.tracking_rmse
    error = truth.tracking_error
    assert f"tracking error |mean(v) - mean(cmd)| {error['vx']:.3f}/{error['vy']:.3f}/{error['wz']:.3f}" \
        in summary.text()


def truth_sample(yaw: float, linvel_world, angvel_body) -> GroundTruth:
    quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    return GroundTruth(sim_time=0.0, base_pos=np.array([0.0, 0.0, 0.42]), base_quat=quat,
                       base_linvel=np.array(linvel_world, dtype=float), base_angvel=np.array(angvel_body, dtype=float))


def test_velocity_is_measured_in_the_heading_frame():
    facing_left = truth_sample(math.pi / 2, [0.0, 0.4, 0.0], [0.0, 0.0, 0.3])  # walking forward, facing +y
    np.testing.assert_allclose(heading_velocity(facing_left), [0.4, 0.0, 0.3], atol=1e-12)
    sideways = truth_sample(math.pi / 2, [0.2, 0.0, 0.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(heading_velocity(sideways), [0.0, -0.2, 0.0], atol=1e-12)


def test_tracking_averages_before_comparing_and_skips_the_start_up():
    log = GroundTruthLog(nominal_base_height=0.42)
    log.track(truth_sample(0.0, [5.0, 0.0, 0.0], [0, 0, 0]), TRACKING_SKIP_S - 0.01, np.zeros(3))  # start-up
    for vx in (0.1, 0.5):  # sways about 0.3 m/s around a command of 0.3 m/s
        log.track(truth_sample(0.0, [vx, 0.0, 0.0], [0, 0, 0]), TRACKING_SKIP_S, np.array([0.3, 0.0, 0.0]))
    assert log.tracking.samples == 2
    assert log.tracking_error == pytest.approx({"vx": 0.0, "vy": 0.0, "wz": 0.0}, abs=1e-12)
    assert log.tracking_rmse == pytest.approx({"vx": 0.2, "vy": 0.0, "wz": 0.0})


def test_no_tracking_figures_before_the_start_up_ends():
    data = GroundTruthLog(nominal_base_height=0.42).to_json()
    assert data["tracking_samples"] == 0 and data["tracking_error"] is None and data["tracking_rmse"] is None


def test_build_controller_kinds(config, monkeypatch):
    assert build_controller(config, None, "standing")[1] == "standing controller"
    teacher = types.ModuleType("runtime.walking.teacher")
    teacher.WalkingTeacher = StandingController  # the plumbing only: the real teacher has its own tests
    monkeypatch.setitem(sys.modules, "runtime.walking.teacher", teacher)
    controller, name = build_controller(config, None, "teacher")
    assert name == "walking teacher" and isinstance(controller, StandingController)
    with pytest.raises(ValueError, match="unknown controller 'walk'"):
        build_controller(config, None, "walk")
    with pytest.raises(ValueError, match="is for the policy controller, not 'standing'"):
        build_controller(config, Path("policy.onnx"), "standing")
