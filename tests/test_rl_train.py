"""bruce-train-policy: an interrupted run continued with --resume is the uninterrupted run; the exported ONNX is the
trained actor (with the action map) on recorded observations; the warm start clones a policy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bruce_hw.config import load_config
from runtime.inference import OnnxPolicy
from training.rl.env import BruceWalkEnv
from training.rl.export import export_policy
from training.rl.ppo_loop import PolicyTrainer
from training.rl.train_cli import CHECKPOINT
from training.rl.train_cli import main as train_policy
from training.rl.train_config import load_training_config
from training.rl.vec_env import RslVecEnv
from training.rl.warm_start import clone_policy

SHORT = ["--set", "env.num_envs=6", "--set", "ppo.num_steps_per_env=6", "--set", "train.iterations=4",
         "--set", "train.checkpoint_every=1", "--set", "env.episode_s=0.3", "--set", "ppo.actor.hidden_dims=[16]",
         "--set", "ppo.critic.hidden_dims=[16]", "--set", "env.nthread=1", "--no-progress"]


def _checkpoint_parameters(run) -> dict[str, torch.Tensor]:
    state = torch.load(run / CHECKPOINT, weights_only=False)["trainer"]
    return {**{f"actor.{k}": v for k, v in state["alg"]["actor_state_dict"].items()},
            **{f"critic.{k}": v for k, v in state["alg"]["critic_state_dict"].items()}}


def test_resume_continues_exactly_as_the_uninterrupted_run(tmp_path):
    whole, split = tmp_path / "whole", tmp_path / "split"
    assert train_policy(["--out", str(whole), *SHORT]) == 0
    assert train_policy(["--out", str(split), "--stop-after", "1", *SHORT]) == 0
    assert not (split / "policy.onnx").exists()  # stopped early: no export yet
    assert train_policy(["--out", str(split), "--stop-after", "2", "--resume", *SHORT]) == 0
    assert train_policy(["--out", str(split), "--resume", *SHORT]) == 0
    a, b = _checkpoint_parameters(whole), _checkpoint_parameters(split)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    obs = np.random.default_rng(0).normal(size=(20, 44))
    pa, pb = (OnnxPolicy(run / "policy.onnx", 44, 10) for run in (whole, split))
    assert all(np.array_equal(pa(o), pb(o)) for o in obs)
    # ... and the run has moved: the trained actor is not the initial one.
    first = torch.load(whole / CHECKPOINT, weights_only=False)["trainer"]["iteration"]
    assert first == 4


def test_resume_refuses_other_settings(tmp_path, capsys):
    run = tmp_path / "run"
    assert train_policy(["--out", str(run), "--stop-after", "1", *SHORT]) == 0
    assert train_policy(["--out", str(run), "--resume", *SHORT, "--set", "train.action_scale=0.3"]) == 2
    assert "the run was started with other settings" in capsys.readouterr().err
    assert train_policy(["--out", str(run), *SHORT]) == 2  # not over an existing run without --resume
    # A longer run is the same run: it may be extended.
    assert train_policy(["--out", str(run), "--resume", *SHORT, "--set", "train.iterations=5"]) == 0
    assert torch.load(run / CHECKPOINT, weights_only=False)["trainer"]["iteration"] == 5


@pytest.fixture(scope="module")
def small_trainer():
    robot = load_config()
    config = load_training_config(overrides=["env.num_envs=8", "env.nthread=1", "ppo.num_steps_per_env=8",
                                             "ppo.actor.hidden_dims=[32, 32]", "ppo.critic.hidden_dims=[32]"])
    env = BruceWalkEnv(robot, config.env, seed=3, reward_weights=config.reward_weights)
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    trainer = PolicyTrainer(vec, config.ppo, seed=3)
    trainer.step_iteration()
    yield robot, config, vec, trainer
    env.close()


def test_exported_policy_is_the_trained_actor_on_recorded_observations(small_trainer, tmp_path):
    robot, config, vec, trainer = small_trainer
    recorded = []
    for _ in range(20):
        recorded.append(vec.walk.get_observations()["policy"].copy())
        vec.walk.step(np.tile(robot.standing_pose, (vec.num_envs, 1)))
    recorded = np.concatenate(recorded)
    path = export_policy(trainer.actor, tmp_path / "p.onnx", recorded.shape[1], robot.standing_pose,
                         config.action_scale, {"seed": 3})
    onnx_policy = OnnxPolicy(path, recorded.shape[1], robot.n_joints)
    trainer.alg.eval_mode()
    from tensordict import TensorDict
    with torch.no_grad():
        torch_out = trainer.actor(TensorDict({"policy": torch.from_numpy(recorded).float()},
                                             batch_size=[len(recorded)])).double().numpy()
    expected = vec.targets(torch_out)
    got = np.stack([onnx_policy(o) for o in recorded])
    assert np.max(np.abs(got - expected)) < 1e-5
    assert np.std(got, axis=0).max() > 1e-4  # the observations move the action: not a constant graph


def test_warm_start_clones_the_policy(tmp_path):
    robot = load_config()
    config = load_training_config(overrides=["env.num_envs=16", "env.nthread=1", "ppo.num_steps_per_env=8"])
    env = BruceWalkEnv(robot, config.env, seed=0, reward_weights=config.reward_weights)
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    trainer = PolicyTrainer(vec, config.ppo, seed=0)
    teacher_path = robot.models.policy
    teacher = OnnxPolicy(teacher_path, 44, robot.n_joints)
    obs = env.get_observations()["policy"]

    def error() -> float:
        from tensordict import TensorDict
        with torch.no_grad():
            out = trainer.actor(TensorDict({"policy": torch.from_numpy(obs).float()}, batch_size=[len(obs)]))
        return float(np.sqrt(np.mean((vec.targets(out.double().numpy()) - np.stack([teacher(o) for o in obs])) ** 2)))

    before = error()
    result = clone_policy(trainer, vec, teacher_path, samples=16 * 4 * 50, epochs=30, seed=0)
    after = error()
    env.close()
    assert after < 0.2 * before, (before, after)
    assert after < 0.05, after  # rad, RMS over joints
    assert result["held_out_rms_rad"] < 0.08


def test_a_warm_started_run_clones_then_trains_with_the_warm_start_settings(tmp_path):
    run = tmp_path / "warm"
    policy = str(load_config().models.policy)
    assert train_policy(["--out", str(run), *SHORT, "--warm-start", policy, "--set", "train.warm_start.samples=1000",
                         "--set", "train.warm_start.epochs=2", "--set", "train.warm_start.critic_iterations=1"]) == 0
    state = torch.load(run / CHECKPOINT, weights_only=False)
    assert state["history"]["warm_start"]["policy_sha256"] and state["trainer"]["iteration"] == 5  # 1 + 4
    std = state["trainer"]["alg"]["actor_state_dict"]["distribution.std_param"]
    assert torch.allclose(std, torch.full_like(std, 0.2), atol=0.02)  # not the scratch run's 1.0
    sidecar = (run / "policy.onnx.json").read_text()
    assert "--warm-start" in sidecar and "policy_sha256" in sidecar
