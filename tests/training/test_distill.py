"""DAgger distillation of the walking teacher (training/distill.py) and the committed walking policy."""

import json

import numpy as np
import pytest

from runtime.control.commands import limit_violation
from runtime.control.inference import OnnxPolicy
from runtime.observation.builder import ObservationBuilder
from runtime.walking.gait import GaitClock
from training.distill import DistillSettings, distill, rollout, sample_commands

torch = pytest.importorskip("torch")


def test_sampled_commands_stay_inside_the_runtime_limits():
    settings = DistillSettings(episode_s=60.0)
    rng = np.random.default_rng(5)
    for _ in range(20):
        schedule = sample_commands(settings, rng)
        for t in np.arange(0.0, settings.episode_s, 0.25):
            assert limit_violation(schedule.at(t)) is None


def test_teacher_rollout_is_labelled_at_the_policy_rate(config):
    settings = DistillSettings(episode_s=1.5, push_interval_s=(0.5, 0.6), action_noise_rad=0.0)
    episode = rollout(config, settings, np.random.default_rng(0), beta=1.0, student=None)
    builder = ObservationBuilder(config)
    assert not episode.fell
    assert episode.obs.shape == (150, builder.size) and episode.teacher_actions.shape == (150, config.n_joints)
    # The observation is the runtime's: its clock runs at the policy rate and its last action is the executed one.
    clock = episode.obs[:, builder.slices["clock"]]
    gait_clock = GaitClock(config.models.gait_period_s, 1.0 / config.policy_hz)
    # (its command is the clock's own: rate-limited, so ticking a fresh clock with it reproduces it)
    expected = 2 * np.pi * np.array([gait_clock.tick(c) for c in episode.obs[:, builder.slices["command"]]])
    np.testing.assert_allclose(clock, np.c_[np.sin(expected), np.cos(expected)], atol=1e-9)
    np.testing.assert_allclose(episode.obs[1:, builder.slices["last_action"]], episode.teacher_actions[:-1])


def test_a_small_distillation_exports_the_student(config, tmp_path):
    from training.onnx_export import export_mlp_policy_onnx

    settings = DistillSettings(rounds=1, episodes_per_round=2, episode_s=1.0, epochs=2, hidden=(32, 32))
    student, history = distill(config, settings, log=lambda *_: None)
    assert [h["round"] for h in history] == [0, 1] and history[1]["samples"] > history[0]["samples"]
    builder = ObservationBuilder(config)
    path = export_mlp_policy_onnx(student.eval(), tmp_path / "student.onnx", builder.size, config.n_joints)
    policy = OnnxPolicy(path, builder.size, config.n_joints)
    obs = np.random.default_rng(1).normal(size=builder.size)
    with torch.no_grad():
        expected = student(torch.as_tensor(obs, dtype=torch.float32)[None])[0].numpy()
    np.testing.assert_allclose(policy(obs), expected, atol=1e-4)
    # the yaw input is the heading error, which the student reads (it once had the absolute yaw, masked)
    assert student.obs_scale[builder.slices["euler"].start + 2] > 0


def test_the_committed_policy_is_the_default_and_says_how_to_rebuild_it(config):
    path = config.models.policy
    assert path is not None and path.is_file() and path.stat().st_size < 1_000_000
    record = json.loads(path.with_name(path.name + ".json").read_text())
    assert record["distill"]["command"].startswith("python -m training.distill")
    assert record["distill"]["settings"]["seed"] == 0
    OnnxPolicy(path, ObservationBuilder(config).size, config.n_joints)  # loads and matches the signature
