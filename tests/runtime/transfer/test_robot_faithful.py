"""A robot-faithful run: the control path (controller, estimator, every transfer scheme, the nominal twin) sees only
what a robot measures, never the simulator's truth, and the twin schemes that need nothing more run on `--backend hw`
against the emulated robot.

The mock's truth is sealed while anything but the observers runs (`Backend.truth_sealed`): a read raises
`TruthSealed`, so a scheme that finished its run did not read it."""

import json
import subprocess
import sys

import mujoco
import numpy as np
import pytest
from support.emulated_robot import WALL_CLOCK_SLACK
from support.pacing import completed_or_skipped

from bruce_hw.backend import TruthSealed
from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import load_gap
from runtime.control.commands import CommandSchedule
from runtime.estimation import BaseEstimate
from runtime.estimation.kinematic import KinematicEstimator
from runtime.loop.exit import ExitCode
from runtime.loop.observers import TickObserver
from runtime.loop.run import run_session
from runtime.transfer import twin as twin_scheme
from runtime.transfer.reference_models import foot_spheres, lowest_point, nominal_model, place_from_estimate
from runtime.transfer.twin_runner import ThreadTwinRunner

WALK = CommandSchedule.constant(0.4, 0.0, 0.0)


class TruthReads(TickObserver):
    """An observer reading the truth every tick (as the evaluation does): allowed in a sealed run."""

    def __init__(self):
        self.heights: list[float] = []

    def on_tick(self, view) -> None:
        self.heights.append(float(view.truth.base_pos[2]))


class SentTorques(TickObserver):
    def __init__(self):
        self.tau: list[np.ndarray] = []

    def on_tick(self, view) -> None:
        self.tau.append(view.tau.copy())


@pytest.fixture(scope="module")
def config():
    return load_config()


@pytest.mark.parametrize("scheme", ["direct", "eq9", "shadow", "observer", "twin", "shadow_twin"])
def test_no_scheme_reads_the_truth_in_a_robot_faithful_run(config, scheme):
    backend = MujocoBackend(config, gap=load_gap("default"))
    truth = TruthReads()
    summary = run_session(backend, config, duration=1.0, realtime=False, transfer=scheme, estimator="kinematic",
                          commands=WALK, observers=[truth])
    assert summary.robot_faithful
    assert summary.error is None and summary.stop_cause == "duration reached", summary.stop_cause
    assert len(truth.heights) == 1000 and min(truth.heights) > 0.3  # the observers did read it, every tick
    assert not backend.truth_sealed  # opened again after the run


def test_perfect_model_control_reads_no_truth_either(config):
    backend = MujocoBackend(config, gap=load_gap("default"))
    perfect = load_config(overrides=["transfer.reference_model=nominal"])
    summary = run_session(backend, perfect, duration=1.0, realtime=False, transfer="shadow_twin",
                          estimator="kinematic", commands=WALK)
    assert summary.error is None and summary.stop_cause == "duration reached"


def test_a_truth_read_in_the_control_path_is_caught(config):
    """The seal is what the tests above rely on: an estimator that peeks at the truth ends the run."""
    backend = MujocoBackend(config, gap=load_gap("default"))
    inner = KinematicEstimator(config)

    class Peeking:
        def reset(self, state):
            inner.reset(state)

        def update(self, state):
            inner.update(state)

        def estimate(self) -> BaseEstimate:
            backend.ground_truth()
            return inner.estimate()

    with pytest.raises(TruthSealed, match="control path of a robot-faithful run"):
        run_session(backend, config, duration=0.5, realtime=False, estimator=Peeking(), commands=WALK)


def test_truth_fed_runs_are_labelled_diagnostics(config):
    summary = run_session(MujocoBackend(config), config, duration=0.2, realtime=False, estimator="truth")
    assert not summary.robot_faithful
    assert summary.to_json()["robot_faithful"] is False


def test_the_twin_on_its_own_thread_gives_the_same_torques(config, monkeypatch):
    """The threaded runner, told to wait for the lagged tick, reproduces the inline one bit for bit."""
    def run() -> np.ndarray:
        sent = SentTorques()
        run_session(MujocoBackend(config, gap=load_gap("default")), config, duration=2.5, realtime=False,
                    transfer="shadow_twin", estimator="kinematic", commands=WALK, observers=[sent])
        return np.array(sent.tau)

    inline = run()
    monkeypatch.setattr(twin_scheme, "InlineTwinRunner",
                        lambda integral, lag: ThreadTwinRunner(integral, lag, wait=True))
    threaded = run()
    assert inline.shape == threaded.shape == (2500, config.n_joints)
    np.testing.assert_array_equal(inline, threaded)
    # and the integral did act (the twin schemes' torque differs from the shadow's alone after the first resync)
    shadow = SentTorques()
    run_session(MujocoBackend(config, gap=load_gap("default")), config, duration=2.5, realtime=False,
                transfer="shadow", estimator="kinematic", commands=WALK, observers=[shadow])
    assert np.abs(inline[2100:] - np.array(shadow.tau)[2100:]).max() > 1e-3


def test_resync_from_the_estimate_keeps_the_contact_depth(config):
    """Roll, pitch and velocities from the estimate, the height set so the lowest sphere keeps its depth; yaw and
    planar position stay the model's own."""
    robot, data = nominal_model(config)
    model = robot.model
    spheres = foot_spheres(model)
    for _ in range(300):  # settle into contact
        data.ctrl[robot.acts] = 0.0
        mujoco.mj_step(model, data)
    depth, xy, yaw = lowest_point(data, spheres), data.qpos[0:2].copy(), data.qpos[3:7].copy()
    rng = np.random.default_rng(0)
    q = config.standing_pose + rng.normal(0.0, 0.05, config.n_joints)
    estimate = BaseEstimate(quat=np.array([1.0, 0, 0, 0]), linvel=np.array([0.3, -0.05, 0.0]),
                            angvel=np.array([0.1, 0.0, -0.2]), euler=np.array([0.05, -0.08, 1.0]))
    place_from_estimate(robot, data, estimate, q, np.zeros(config.n_joints), spheres)
    assert lowest_point(data, spheres) == pytest.approx(depth, abs=1e-9)
    np.testing.assert_allclose(data.qpos[0:2], xy)
    np.testing.assert_allclose(data.qpos[robot.qpos], q)
    w, x, y, z = data.qpos[3:7]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(2 * (w * y - z * x))
    assert roll == pytest.approx(0.05) and pitch == pytest.approx(-0.08)
    yaw_before = np.arctan2(2 * (yaw[0] * yaw[3] + yaw[1] * yaw[2]), 1 - 2 * (yaw[2] ** 2 + yaw[3] ** 2))
    assert np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)) == pytest.approx(yaw_before, abs=1e-9)
    np.testing.assert_allclose(data.qvel[3:6], estimate.angvel)  # body frame, as the estimate's
    body_linvel = np.array(data.xmat[model.body("base").id]).reshape(3, 3).T @ data.qvel[0:3]
    np.testing.assert_allclose(body_linvel, estimate.linvel, atol=1e-9)


def test_estimator_snapshot_restores_the_same_filter(config):
    backend = MujocoBackend(config)
    backend.configure()
    backend.activate()
    first, second = KinematicEstimator(config), KinematicEstimator(config)
    state = backend.read()
    first.reset(state)
    for _ in range(200):
        state = backend.read()
        first.update(state)
    second.restore(first.snapshot(), state.imu.stamp)
    for _ in range(50):
        state = backend.read()
        first.update(state)
        second.update(state)
    a, b = first.estimate(), second.estimate()
    np.testing.assert_array_equal(a.quat, b.quat)
    np.testing.assert_array_equal(a.linvel, b.linvel)


# The settings with which the rehearsal recommends shadow_twin (docs/results/transfer.md, "The recommended settings")
RECOMMENDED = ["estimator.level_from_feet_s=1", "transfer.twin.resync_s=1.5", "transfer.twin.time_constant_s=3"]


def test_recommended_twin_scheme_runs_on_hw_against_the_emulator(emulator, hw_config, tmp_path):
    """`bruce-run --backend hw --transfer shadow_twin` with the recommended settings: the twin runs on its own thread
    of the robot's process, resynchronised from the hw backend's kinematic estimator, and the robot walks on."""
    stats = tmp_path / "stats.json"
    overrides = emulator.overrides + WALL_CLOCK_SLACK + RECOMMENDED
    argv = ["--backend", "hw", *(w for item in overrides for w in ("--set", item)),
            "--duration", "4", "--cmd", "0.2,0,0", "--transfer", "shadow_twin", "--rerun", "off",
            "--stats", str(stats)]

    def attempt():
        run = subprocess.run([sys.executable, "-c", "from runtime.cli import main; raise SystemExit(main())", *argv],
                             capture_output=True, text=True, timeout=90)
        summary = json.loads(stats.read_text())
        return run.returncode == int(ExitCode.OK), summary["late_share"], (run, summary)

    # On a slow moment of the machine the robot can end at a joint limit, which says nothing about the scheme
    run, summary = completed_or_skipped(attempt, before_again=lambda: emulator.send("place"))
    assert run.returncode == int(ExitCode.OK), run.stdout + run.stderr
    assert summary["error"] is None and summary["stop_cause"] == "duration reached", summary
    assert summary["robot_faithful"] and summary["ticks"] == 4000
    assert summary["twin"]["resyncs"] >= 2 and summary["twin"]["stepped"] >= 3000, summary["twin"]
    plant = emulator.status()["plant"]
    assert abs(plant["base_height"] - plant["nominal_base_height"]) < 0.05, plant  # walking, not fallen
