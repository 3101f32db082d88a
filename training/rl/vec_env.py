"""`BruceWalkEnv` as rsl-rl's `VecEnv`: torch tensors, observation groups, time-outs and the reward terms' log.

The reward is the Table II sum times `reward_scale` (the values a critic must learn stay near 1). The network's output
is scaled about the standing pose, a_t = q_stand + action_scale * output, so a fresh network
starts near standing with unit-scale outputs; the exported policy folds this map in (training/rl/export.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from training.rl.env import BruceWalkEnv


class RslVecEnv(VecEnv):
    def __init__(self, env: BruceWalkEnv, action_scale: float, reward_scale: float = 1.0):
        self.walk = env
        self.action_scale = float(action_scale)
        self.reward_scale = float(reward_scale)
        self.standing = env.robot.standing_pose.copy()
        self.num_envs = env.num_envs
        self.num_actions = env.num_actions
        self.max_episode_length = env.max_episode_length
        self.device = "cpu"
        self.cfg = {"env": repr(env.config)}
        self.dt = env.dt

    @property
    def episode_length_buf(self) -> torch.Tensor:
        return torch.from_numpy(self.walk.episode_length)

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.walk.episode_length[:] = value.numpy()

    def targets(self, output: np.ndarray) -> np.ndarray:
        """Network output -> PD targets a_t (rad)."""
        return self.standing + self.action_scale * output

    def output_of(self, targets: np.ndarray) -> np.ndarray:
        """PD targets -> the network output that gives them (the inverse of `targets`)."""
        return (targets - self.standing) / self.action_scale

    def get_observations(self) -> TensorDict:
        return _tensordict(self.walk.get_observations(), self.num_envs)

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        obs, reward, fell, time_out, info = self.walk.step(self.targets(actions.detach().double().numpy()))
        terms = {f"Reward/{name}": float(np.mean(value)) for name, value in info["reward_terms"].items()}
        reward = reward * self.reward_scale
        extras = {"time_outs": torch.from_numpy(time_out.astype(np.float32)), "log": terms}
        dones = torch.from_numpy((fell | time_out).astype(np.float32))
        return _tensordict(obs, self.num_envs), torch.from_numpy(reward.astype(np.float32)), dones, extras

    def state_dict(self) -> dict[str, Any]:
        return self.walk.get_state()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.walk.set_state(state)


def _tensordict(obs: dict[str, np.ndarray], n: int) -> TensorDict:
    return TensorDict({k: torch.from_numpy(v.astype(np.float32)) for k, v in obs.items()}, batch_size=[n])
