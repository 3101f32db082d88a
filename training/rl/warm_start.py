"""Warm start: the actor cloned from an ONNX policy (the distilled one), then the critic fitted with the actor held.

Cloning is DAgger over the training environment (randomisation and pushes included): round 0 lets the ONNX policy
act, later rounds the clone, and the ONNX policy labels every visited observation; the actor's mean is fitted by
mean squared error in network units. Its observation normaliser is set from the visited observations first, so it
starts where PPO's running statistics will be.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from runtime.inference import OnnxPolicy
from training.rl.ppo_loop import IterationStats, PolicyTrainer
from training.rl.vec_env import RslVecEnv

ROUNDS = 4


def clone_policy(trainer: PolicyTrainer, vec: RslVecEnv, policy_path: Path, samples: int, epochs: int,
                 seed: int, progress: Callable[[str], None] = lambda text: None) -> dict[str, float]:
    """Fit the trainer's actor to `policy_path`'s actions; the final training loss and the clone's held-out error
    (rad, RMS over joints) on the last round's data."""
    env = vec.walk
    obs_dim = env.get_observations()["policy"].shape[1]
    teacher = OnnxPolicy(policy_path, obs_dim, env.num_actions)
    actor = trainer.actor
    rng = torch.Generator().manual_seed(seed)
    per_round = max(1, samples // (ROUNDS * env.num_envs))
    observations: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    result: dict[str, float] = {}
    for round_ in range(ROUNDS):
        round_obs, round_labels = [], []
        env.reset()
        for _ in range(per_round):
            obs = env.get_observations()
            policy_obs = obs["policy"]
            targets = np.stack([teacher(row) for row in policy_obs])
            round_obs.append(policy_obs.copy())
            round_labels.append(vec.output_of(targets))
            if round_ == 0:
                executed = targets
            else:
                with torch.no_grad():
                    out = actor(TensorDict({"policy": torch.from_numpy(policy_obs).float()},
                                           batch_size=[env.num_envs]))
                executed = vec.targets(out.double().numpy())
            env.step(executed)
        if round_ == ROUNDS - 1 and observations:
            result["held_out_rms_rad"] = _error(actor, np.concatenate(round_obs), np.concatenate(round_labels),
                                                vec.action_scale)
        observations += round_obs
        labels += round_labels
        x = torch.from_numpy(np.concatenate(observations)).float()
        y = torch.from_numpy(np.concatenate(labels)).float()
        if round_ == 0:
            actor.obs_normalizer.train()
            actor.update_normalization(TensorDict({"policy": x}, batch_size=[len(x)]))
        result["loss"] = _fit(actor, x, y, epochs, rng)
        progress(f"warm start: round {round_ + 1}/{ROUNDS}, {len(x)} samples, loss {result['loss']:.4g}")
    env.reset()
    return result


def _fit(actor: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, epochs: int, rng: torch.Generator,
         batch: int = 4096) -> float:
    actor.obs_normalizer.eval()
    optimizer = torch.optim.Adam(actor.mlp.parameters(), lr=1e-3)
    loss = torch.tensor(0.0)
    for _ in range(epochs):
        order = torch.randperm(len(x), generator=rng)
        for start in range(0, len(x), batch):
            idx = order[start:start + batch]
            out = actor.mlp(actor.obs_normalizer(x[idx]))
            loss = torch.mean((out - y[idx]) ** 2)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return float(loss.detach())


def _error(actor: torch.nn.Module, x: np.ndarray, y: np.ndarray, action_scale: float) -> float:
    with torch.no_grad():
        out = actor.mlp(actor.obs_normalizer(torch.from_numpy(x).float())).double().numpy()
    return float(np.sqrt(np.mean(((out - y) * action_scale) ** 2)))


def fit_critic(trainer: PolicyTrainer, iterations: int,
               report: Callable[[IterationStats], None] = lambda stats: None) -> None:
    """PPO iterations that move only the critic (the actor's parameters and its noise held).

    The learning rate is held too: with the actor still, the KL between its old and new policy is 0, and the
    adaptive schedule would raise the rate to its ceiling for the first update that moves the actor.
    """
    alg = trainer.alg
    held = [p for p in trainer.actor.parameters() if p.requires_grad]
    schedule, learning_rate = alg.schedule, alg.learning_rate
    for p in held:
        p.requires_grad_(False)
    alg.schedule = "fixed"
    try:
        for _ in range(iterations):
            report(trainer.step_iteration())
    finally:
        for p in held:
            p.requires_grad_(True)
        alg.schedule, alg.learning_rate = schedule, learning_rate
        for group in alg.optimizer.param_groups:
            group["lr"] = learning_rate
