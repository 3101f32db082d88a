"""bruce-train-policy: an interrupted run continued with --resume is the uninterrupted run; the exported ONNX is the
trained actor (with the action map) on recorded observations; the warm start clones a policy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bruce_hw.config import load_config
from runtime.control.inference import OnnxPolicy
from training.rl.env import BruceWalkEnv
from training.rl.export import export_policy
from training.rl.ppo_loop import PolicyTrainer
from training.rl.train_cli import CHECKPOINT
from training.rl.train_cli import main as train_policy
from training.rl.train_config import load_training_config
from training.rl.vec_env import RslVecEnv
from training.rl.warm_start import TransferMismatch, clone_policy, transfer_policy

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
                         config.action_scale, {"seed": 3}, {"vx": (-0.5, 0.8), "vy": (-0.3, 0.3), "wz": (-0.5, 0.5)})
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
    run, split = tmp_path / "warm", tmp_path / "split"
    warm = ["--warm-start", str(load_config().models.policy), "--set", "train.warm_start.samples=1000",
            "--set", "train.warm_start.epochs=2", "--set", "train.warm_start.critic_iterations=1",
            "--set", "train.warm_start.anchor_weight=2.0", "--set", "train.snapshot_every=2"]
    assert train_policy(["--out", str(run), *SHORT, *warm]) == 0
    state = torch.load(run / CHECKPOINT, weights_only=False)
    assert state["history"]["warm_start"]["policy_sha256"] and state["trainer"]["iteration"] == 5  # 1 + 4
    std = state["trainer"]["alg"]["actor_state_dict"]["distribution.std_param"]
    assert torch.allclose(std, torch.full_like(std, 0.2), atol=0.02)  # not the scratch run's 1.0
    sidecar = (run / "policy.onnx.json").read_text()
    assert "--warm-start" in sidecar and "policy_sha256" in sidecar
    assert sorted(p.name for p in (run / "snapshots").glob("*.onnx")) == ["policy_2.onnx", "policy_4.onnx"]
    assert state["trainer"]["anchor"]["weight"] == 2.0
    # The anchor (the clone after the critic fit) and its optimizer survive a resume: the same run.
    assert train_policy(["--out", str(split), "--stop-after", "2", *SHORT, *warm]) == 0
    assert train_policy(["--out", str(split), "--resume", *SHORT, *warm]) == 0
    a, b = _checkpoint_parameters(run), _checkpoint_parameters(split)
    for key in a:
        assert torch.equal(a[key], b[key]), key


def _actor_means(trainer: PolicyTrainer, obs: np.ndarray) -> torch.Tensor:
    from tensordict import TensorDict
    with torch.no_grad():
        return trainer.actor(TensorDict({"policy": torch.from_numpy(obs).float()}, batch_size=[len(obs)]))


def test_the_anchor_holds_the_actor_near_its_policy_at_the_start():
    robot = load_config()
    config = load_training_config(overrides=["env.num_envs=8", "env.nthread=1", "ppo.num_steps_per_env=8",
                                             "ppo.actor.hidden_dims=[32]", "ppo.critic.hidden_dims=[32]",
                                             "ppo.algorithm.schedule=fixed", "ppo.algorithm.learning_rate=3.0e-3"])
    drift = {}
    for weight in (0.0, 50.0):
        env = BruceWalkEnv(robot, config.env, seed=5, reward_weights=config.reward_weights)
        trainer = PolicyTrainer(RslVecEnv(env, config.action_scale, config.reward_scale), config.ppo, seed=5)
        obs = env.get_observations()["policy"].copy()
        trainer.set_anchor(weight)
        start = _actor_means(trainer, obs)
        losses = [trainer.step_iteration().losses for _ in range(6)]
        drift[weight] = float(torch.sqrt(torch.mean((_actor_means(trainer, obs) - start) ** 2)))
        assert ("anchor" in losses[-1]) == (weight > 0)
        env.close()
    assert drift[50.0] < 0.5 * drift[0.0], drift


def test_transfer_takes_the_distilled_policy_exactly_and_keeps_its_input_scaling():
    robot = load_config()
    config = load_training_config(overrides=["env.num_envs=8", "env.nthread=1", "ppo.num_steps_per_env=8"])
    env = BruceWalkEnv(robot, config.env, seed=2, reward_weights=config.reward_weights)
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    trainer = PolicyTrainer(vec, config.warm_start.ppo(config.ppo), seed=2)
    teacher = OnnxPolicy(robot.models.policy, 44, robot.n_joints)
    result = transfer_policy(trainer, vec, robot.models.policy)
    assert result["transfer_max_error_rad"] < 1e-5
    obs = np.concatenate([env.step(np.stack([teacher(o) for o in env.get_observations()["policy"]]))[0]["policy"]
                          for _ in range(5)])
    got = vec.targets(_actor_means(trainer, obs).double().numpy())
    np.testing.assert_allclose(got, np.stack([teacher(o) for o in obs]), atol=1e-5)
    mean = trainer.actor.obs_normalizer.mean
    trainer.step_iteration()  # PPO moves the weights, not the input scaling
    assert torch.equal(trainer.actor.obs_normalizer.mean, mean)
    env.close()
    # An actor of other layers cannot take the weights: said, naming both shapes.
    small = load_training_config(overrides=["env.num_envs=2", "env.nthread=1", "ppo.actor.hidden_dims=[16]"])
    env = BruceWalkEnv(robot, small.env, seed=0, reward_weights=small.reward_weights)
    vec = RslVecEnv(env, small.action_scale, small.reward_scale)
    with pytest.raises(TransferMismatch, match=r"\(256, 44\).*\(16, 44\)"):
        transfer_policy(PolicyTrainer(vec, small.ppo, seed=0), vec, robot.models.policy)
    env.close()


def test_a_transfer_the_actor_cannot_take_is_one_line_naming_the_key(tmp_path, capsys):
    policy = str(load_config().models.policy)
    assert train_policy(["--out", str(tmp_path / "r"), *SHORT, "--warm-start", policy,
                         "--set", "train.warm_start.method=transfer"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "train.warm_start.method transfer" in err and "(16, 44)" in err, err


def test_a_policy_trained_on_another_spec_runs_with_it(tmp_path, capsys):
    """legged_gym's spec at our 100 Hz (other joint order, scaled terms, raw last action, an action map): the
    environment observes it, the export ends in the inverse of its action map, the sidecar carries it, and through
    it the runtime's controller sends the targets the actor was trained to send."""
    import json

    import onnxruntime as ort
    import yaml

    from runtime.control.controllers import build_controller
    from runtime.control.policy_spec import spec_file

    tree = yaml.safe_load(spec_file("legged_gym").read_text())
    del tree["rate_hz"], tree["action"]["clip"]  # training steps at rates.policy_hz and does not clip the output
    spec_path = tmp_path / "lg100.yaml"
    spec_path.write_text(yaml.safe_dump(tree))
    robot = load_config()
    config = load_training_config(overrides=["env.num_envs=4", "env.nthread=1", "ppo.num_steps_per_env=4",
                                             "ppo.actor.hidden_dims=[16]", "ppo.critic.hidden_dims=[16]",
                                             f"env.policy_spec={spec_path}"])
    env = BruceWalkEnv(robot, config.env, seed=1, reward_weights=config.reward_weights)
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    trainer = PolicyTrainer(vec, config.ppo, seed=1)
    trainer.step_iteration()
    obs = env.get_observations()["policy"].copy()
    assert obs.shape == (4, 42)
    path = export_policy(trainer.actor, tmp_path / "lg.onnx", 42, robot.standing_pose, config.action_scale, {},
                         {"vx": (-0.5, 0.8), "vy": (-0.3, 0.3), "wz": (-0.5, 0.5)}, env.spec, tree)
    env.close()
    assert json.loads((tmp_path / "lg.onnx.json").read_text())["policy_spec"] == tree
    controller, name = build_controller(robot, path)
    assert "spec lg.onnx.json" in name and controller.spec.obs_size == 42
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    spec = controller.spec
    for row, targets in zip(obs, vec.targets(_actor_means(trainer, obs).double().numpy()), strict=True):
        raw = session.run(["actions"], {"obs": row[None].astype(np.float32)})[0][0].astype(np.float64)
        sent = np.empty(10)
        sent[spec.order] = spec.action.offset + spec.action.scale * raw
        np.testing.assert_allclose(sent, targets, atol=1e-5)
    # the CLI records the spec; a spec at another rate is refused in one line
    run = tmp_path / "run"
    assert train_policy(["--out", str(run), *SHORT, "--set", "train.iterations=1",
                         "--set", f"env.policy_spec={spec_path}"]) == 0
    assert json.loads((run / "policy.onnx.json").read_text())["policy_spec"] == tree
    assert train_policy(["--out", str(tmp_path / "r50"), *SHORT, "--set", "env.policy_spec=legged_gym"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "env.policy_spec: legged_gym.yaml runs at 50 Hz" in err, err
