"""Observers of the tick: the mock's ground-truth evaluation, the one fall definition, the twin metric, and DAgger
episodes through the runtime's loop."""

import contextlib
import dataclasses
import io
import math

import mujoco
import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import load_gap
from bruce_hw.types import GroundTruth
from runtime.control.commands import CommandSchedule
from runtime.loop.falls import FALL_HEIGHT_FRACTION, FALL_TILT_RAD, has_fallen
from runtime.loop.observers import (
    TRACKING_SKIP_S,
    TRUTH_PHASE,
    FallStop,
    GroundTruthLog,
    TickObserver,
    TickView,
    ground_truth_observers,
)
from runtime.loop.run import run_session

PUSH_READ = 3200  # the shoved walk: pushed over at 3.2 s, after more than a second of scored tracking


class ShovedMock(MujocoBackend):
    """The mock, pushed sideways hard enough to fall at its PUSH_READ-th read."""

    reads = 0

    def _read(self):
        self.reads += 1
        if self.reads == PUSH_READ:
            self.push(np.array([0.0, 6.0, 0.0]), 0.1)
        return super()._read()


class TickRecorder(TickObserver):
    """Every tick as the observers saw it, and the simulator's truth when the loop ended (a safety trip ends it
    after a read that no observer sees)."""

    def __init__(self):
        self.ticks = []
        self.end_truth: GroundTruth | None = None

    def on_start(self, backend, config):
        self.backend = backend

    def on_tick(self, view):
        self.ticks.append((view.tick, view.now, view.clock0, view.robot, view.command.copy(), view.a.copy(),
                           view.tau_star.copy(), view.tau.copy(), view.truth))

    def on_end(self, summary):
        self.end_truth = self.backend.ground_truth()


@pytest.fixture(scope="module")
def shoved_walk(config):
    """A 5 s walk at 0.4 m/s that falls (and trips the safety stage), every tick recorded by an observer."""
    recorder = TickRecorder()
    backend = ShovedMock(config)
    with contextlib.redirect_stdout(io.StringIO()):
        summary = run_session(backend, config, duration=5.0, realtime=False,
                              commands=CommandSchedule.constant(0.4, 0.0, 0.0), observers=[recorder])
    return summary, recorder, backend.nominal_base_height


def expected_truth(recorder: TickRecorder, nominal_height: float, decimation: int) -> dict:
    """What the ground-truth evaluation must say, computed here from the recorded ticks: sampled on tick
    TRUTH_PHASE of every policy period, plus the state the loop ended in; velocity in the heading frame and the
    world yaw rate, scored from TRACKING_SKIP_S on."""
    ticks = recorder.ticks
    sampled = [t for t in ticks if t[0] % decimation == TRUTH_PHASE]
    truths = [t[-1] for t in sampled] + [recorder.end_truth]
    z = np.array([tr.base_pos[2] for tr in truths])
    quat = np.array([tr.base_quat for tr in truths])
    tilt = np.arccos(np.clip(1 - 2 * (quat[:, 1] ** 2 + quat[:, 2] ** 2), -1, 1))
    yaw_end = math.atan2(2 * (quat[-1, 0] * quat[-1, 3] + quat[-1, 1] * quat[-1, 2]),
                         1 - 2 * (quat[-1, 2] ** 2 + quat[-1, 3] ** 2))
    measured, commanded = [], []
    for _, now, clock0, _, command, *_, truth in sampled:
        if now - clock0 < TRACKING_SKIP_S:
            continue
        rotation = np.zeros(9)
        mujoco.mju_quat2Mat(rotation, truth.base_quat)
        rotation = rotation.reshape(3, 3)
        heading = math.atan2(rotation[1, 0], rotation[0, 0])
        c, s = math.cos(heading), math.sin(heading)
        vx, vy = truth.base_linvel[:2]
        measured.append([c * vx + s * vy, -s * vx + c * vy, (rotation @ truth.base_angvel)[2]])
        commanded.append(command)
    measured, commanded = np.array(measured), np.array(commanded)
    return {"base_height_min": z.min(), "base_height_max": z.max(), "base_xy_start": list(truths[0].base_pos[:2]),
            "base_xy_end": list(truths[-1].base_pos[:2]), "base_yaw_end": yaw_end, "sim_time": truths[-1].sim_time,
            "fell": bool(np.any((z < FALL_HEIGHT_FRACTION * nominal_height) | (tilt > FALL_TILT_RAD))),
            "tracking_samples": len(measured),
            "tracking_error": np.abs(measured.mean(axis=0) - commanded.mean(axis=0)),
            "tracking_rmse": np.sqrt(np.mean((measured - commanded) ** 2, axis=0))}


def assert_log_matches(log: GroundTruthLog, expected: dict) -> None:
    data = log.to_json()
    for key in ("base_height_min", "base_height_max", "base_yaw_end", "sim_time"):
        assert data[key] == pytest.approx(expected[key], abs=1e-12), key
    for key in ("base_xy_start", "base_xy_end"):
        np.testing.assert_allclose(data[key], expected[key], atol=1e-12, err_msg=key)
    assert data["fell"] == expected["fell"] and data["tracking_samples"] == expected["tracking_samples"]
    for key in ("tracking_error", "tracking_rmse"):
        np.testing.assert_allclose(list(data[key].values()), expected[key], atol=1e-9, err_msg=key)


def test_the_ground_truth_observers_score_a_recorded_run_as_computed_from_its_ticks(config, shoved_walk):
    summary, recorder, nominal = shoved_walk
    expected = expected_truth(recorder, nominal, config.policy_decimation)
    assert summary.exit_code == 3 and expected["fell"] and expected["tracking_samples"] >= 100  # the run covers both
    assert summary.truth.nominal_base_height == nominal
    assert_log_matches(summary.truth, expected)
    assert summary.to_json()["fell"] is True and "fell: yes" in summary.text()


class ReplayedMock:
    """Hands the observers the recorded truth of the tick being replayed."""

    name = "replay"

    def __init__(self, nominal_base_height: float):
        self.nominal_base_height = nominal_base_height
        self.current: GroundTruth | None = None

    def ground_truth(self) -> GroundTruth:
        return self.current


def test_the_same_observers_fed_the_recorded_ticks_give_the_same_numbers(config, shoved_walk):
    summary, recorder, nominal = shoved_walk
    ticks = recorder.ticks
    backend = ReplayedMock(nominal)
    log = GroundTruthLog(nominal_base_height=nominal)
    observers = ground_truth_observers(log)
    for observer in observers:
        observer.on_start(backend, config)
    view = TickView(backend, ticks[0][2])
    for tick, now, _, robot, command, a, tau_star, tau, truth in ticks:
        backend.current = truth
        view.fill(tick, now, robot, command, a, tau_star, tau)
        assert not any(observer.on_tick(view) for observer in observers)  # evaluation never ends a run
    backend.current = recorder.end_truth
    for observer in observers:
        observer.on_end(summary)
    assert_log_matches(log, expected_truth(recorder, nominal, config.policy_decimation))
    assert log.to_json() == summary.truth.to_json()


def truth_at(height: float, tilt: float) -> GroundTruth:
    """The base at `height`, tilted by `tilt` about a horizontal axis (pitch, then a roll, mixed)."""
    axis = np.array([math.cos(0.3), math.sin(0.3), 0.0])
    quat = np.r_[math.cos(tilt / 2), math.sin(tilt / 2) * axis]
    return GroundTruth(sim_time=0.0, base_pos=np.array([0.1, -0.2, height]), base_quat=quat,
                       base_linvel=np.zeros(3), base_angvel=np.zeros(3))


def test_fell_is_below_a_share_of_the_standing_height_or_tilted_past_the_limit():
    nominal = 0.42
    low = FALL_HEIGHT_FRACTION * nominal
    assert not has_fallen(truth_at(nominal, 0.0), nominal)
    assert not has_fallen(truth_at(low + 1e-6, FALL_TILT_RAD - 1e-3), nominal)
    assert has_fallen(truth_at(low - 1e-6, 0.0), nominal)
    assert has_fallen(truth_at(nominal, FALL_TILT_RAD + 1e-3), nominal)
    assert has_fallen(truth_at(nominal, math.pi), nominal)  # upside down


def test_fall_stop_ends_the_run_on_the_tick_it_fell(config):
    fall = FallStop()
    backend = ShovedMock(config)
    with contextlib.redirect_stdout(io.StringIO()):
        summary = run_session(backend, config, duration=5.0, realtime=False,
                              commands=CommandSchedule.constant(0.4, 0.0, 0.0), observers=[fall])
    assert fall.fell_at is not None and summary.ticks == fall.fell_at + 1
    assert summary.stop_cause.startswith(f"fell at {fall.fell_at * config.dt:.3f} s") and summary.exit_code == 0
    assert summary.truth.fell  # the summary's own fall observer agrees at the end


# -- the twin metric -------------------------------------------------------------------------------------------
def twin_run(gap_name: str | None, seconds: float = TRACKING_SKIP_S + 0.5):
    from training.evaluation.transfer_runs import RunSpec, run_one

    gap = dataclasses.replace(load_gap(gap_name), seed=0) if gap_name else None
    with contextlib.redirect_stdout(io.StringIO()):
        return run_one(RunSpec("tracking", (0.4, 0.0, 0.0), seconds, "direct" if gap else "nominal", gap))


def test_the_twin_metric_is_zero_when_the_robot_is_the_simulator_and_not_with_a_gap():
    from training.evaluation.transfer_metrics import run_metrics
    from training.evaluation.transfer_runs import EXPERIMENTS

    same = twin_run("none")
    assert same.twin_rmse_per_joint.shape == (10,) and np.all(same.twin_rmse_per_joint < 1e-9)
    gapped = twin_run("default")
    assert not gapped.fell and np.all(gapped.twin_rmse_per_joint > 1e-5)
    metrics = run_metrics(gapped, same, EXPERIMENTS[0])
    assert metrics["twin_rmse"] == pytest.approx(np.mean(gapped.twin_rmse_per_joint))
    assert metrics["twin_rmse_per_joint"] == gapped.twin_rmse_per_joint.tolist()


def test_the_twin_metric_scores_only_after_the_start_up(config):
    from runtime.transfer.twin_metric import TwinMetric

    early, late = TwinMetric(skip_s=TRACKING_SKIP_S), TwinMetric(skip_s=0.0)
    with contextlib.redirect_stdout(io.StringIO()):
        run_session(MujocoBackend(config, gap=load_gap("default")), config, duration=TRACKING_SKIP_S - 0.5,
                    realtime=False, commands=CommandSchedule.constant(0.4, 0.0, 0.0), observers=[early, late])
    assert early.windows == 0 and np.isnan(early.rmse)
    # one window ends on every policy period after the first
    assert late.windows == round((TRACKING_SKIP_S - 0.5) * config.policy_hz) - 1 and late.rmse > 0


# -- DAgger through the loop -----------------------------------------------------------------------------------
torch = pytest.importorskip("torch")


class StudentGoingWild(torch.nn.Module):
    """Stands (targets: the standing pose) for `calm` calls, then asks for targets far outside the joint range."""

    def __init__(self, standing_pose: np.ndarray, calm: int):
        super().__init__()
        self.pose, self.calm, self.calls = torch.as_tensor(standing_pose)[None], calm, 0

    def forward(self, obs):
        self.calls += 1
        return self.pose if self.calls <= self.calm else self.pose + 100.0


def test_a_dagger_episode_runs_the_safety_stage(config):
    from training.distill import DistillSettings, rollout

    settings = DistillSettings(episode_s=1.0, action_noise_rad=0.0)
    calm = 20  # policy ticks (the low Eq. 8 gains alone hold the pose that long); the warm-up check is one more call
    student = StudentGoingWild(config.standing_pose, calm + 1)
    episode = rollout(config, settings, np.random.default_rng(0), beta=0.0, student=student)
    assert "controller target" in episode.stop_cause and "outside" in episode.stop_cause  # the safety trip
    assert episode.seconds == pytest.approx(calm * config.policy_decimation * config.dt, abs=2 * config.dt)
    assert not episode.fell and len(episode.obs) == max(0, calm + 1 - round(settings.fall_trim_s * config.policy_hz))


def test_a_dagger_episode_pushes_and_the_student_may_see_the_kinematic_estimate(config, monkeypatch):
    import training.distill as distill
    from runtime.observation.builder import ObservationBuilder

    pushes = []

    class CountingMock(MujocoBackend):
        def push(self, impulse, duration=0.1):
            pushes.append((float(self.data.time), np.linalg.norm(impulse)))
            super().push(impulse, duration)

    monkeypatch.setattr(distill, "MujocoBackend", CountingMock)
    settings = distill.DistillSettings(episode_s=0.6, push_interval_s=(0.2, 0.25), action_noise_rad=0.01)
    episodes = {}
    for observe in ("truth", "kinematic"):
        episodes[observe] = distill.rollout(config, dataclasses.replace(settings, observe=observe),
                                            np.random.default_rng(3), beta=1.0, student=None)
    assert len(pushes) == 2 * 2 and all(settings.push_impulse_ns[0] <= p <= settings.push_impulse_ns[1]
                                        for _, p in pushes)
    s = ObservationBuilder(config).slices
    truth, kinematic = episodes["truth"], episodes["kinematic"]
    # the teacher acts on the truth in both, so the robot moves the same; only what the student sees differs
    np.testing.assert_array_equal(truth.obs[:, s["q"]], kinematic.obs[:, s["q"]])
    np.testing.assert_array_equal(truth.teacher_actions, kinematic.teacher_actions)
    assert np.abs(truth.obs[:, s["base_linvel"]] - kinematic.obs[:, s["base_linvel"]]).max() > 1e-4
