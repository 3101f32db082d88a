"""`BruceWalkEnv`'s interface over shards: `env.shards` batches of `num_envs / shards` simulations each.

A shard is a `BruceWalkEnv` of its own, seeded `train.seed + i` (shard i), so a run is reproducible from its config
whatever executes the shards: `LocalShards` steps them one after the other in this process, `RayShards`
(training/rl/ray_shards.py) on Ray actors across a cluster, all at once. The two give the same numbers step for
step; one shard is the plain `BruceWalkEnv` (seeded `train.seed`). The learner (rsl-rl's PPO through `RslVecEnv`)
sees one batch of `num_envs` and does not know how it was stepped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from bruce_hw.config import RobotConfig
from training.rl.env import BruceWalkEnv, WalkEnvConfig
from training.rl.sim_model import build_sim_model

# What a shard's step returns to the learner: the observations, reward, fell, time_out, and the info the learner
# reads (the weighted reward terms and the episode lengths; not the rewards' input, which stays with the shard).
StepResult = tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict]


def shard_config(config: WalkEnvConfig, shards: int) -> WalkEnvConfig:
    """One shard's settings: `num_envs / shards` simulations (the split must be even)."""
    if shards < 1 or config.num_envs % shards:
        raise ValueError(f"{config.source}: env.shards: {shards} must divide env.num_envs ({config.num_envs})")
    return dataclasses.replace(config, num_envs=config.num_envs // shards)


def shard_seeds(seed: int, shards: int) -> list[int]:
    return [seed + i for i in range(shards)]


def lean_step(env: BruceWalkEnv, actions: np.ndarray) -> StepResult:
    """`env.step` with the info the learner reads."""
    obs, reward, fell, time_out, info = env.step(actions)
    return obs, reward, fell, time_out, {"reward_terms": info["reward_terms"], "episode_length": info["episode_length"]}


class LocalShards:
    """The shards as `BruceWalkEnv`s of this process, stepped in turn."""

    def __init__(self, robot: RobotConfig, config: WalkEnvConfig, seeds: list[int],
                 reward_weights: Mapping[str, float] | None = None):
        self.envs = [BruceWalkEnv(robot, config, seed=seed, reward_weights=reward_weights) for seed in seeds]

    def step(self, actions: list[np.ndarray]) -> list[StepResult]:
        return [lean_step(env, a) for env, a in zip(self.envs, actions, strict=True)]

    def observations(self) -> list[dict[str, np.ndarray]]:
        return [env.get_observations() for env in self.envs]

    def get_state(self) -> list[dict[str, Any]]:
        return [env.get_state() for env in self.envs]

    def set_state(self, states: list[Mapping[str, Any]]) -> None:
        for env, state in zip(self.envs, states, strict=True):
            env.set_state(state)

    def close(self) -> None:
        for env in self.envs:
            env.close()


class ShardedWalkEnv:
    """N simulations in `shards` (a `LocalShards` or `RayShards`), as one `BruceWalkEnv` to `RslVecEnv`."""

    def __init__(self, robot: RobotConfig, config: WalkEnvConfig, shards):
        self.robot = robot
        self.config = config
        self.sim = build_sim_model(robot)  # the standing pose and model the warm start reads
        self.shards = shards
        self.num_envs = config.num_envs
        self.num_actions = robot.n_joints
        self.dt = 1.0 / robot.policy_hz
        self.max_episode_length = round(config.episode_s * robot.policy_hz)
        self.episode_length = np.zeros(self.num_envs, dtype=int)  # a mirror: the shards hold their own
        parts = shards.observations()
        self.obs = _joined(parts)
        self._split = np.cumsum([len(o["policy"]) for o in parts])[:-1]

    def get_observations(self) -> dict[str, np.ndarray]:
        return self.obs

    def step(self, actions: np.ndarray) -> StepResult:
        results = self.shards.step(np.split(np.asarray(actions, dtype=float), self._split))
        obs = _joined([r[0] for r in results])
        reward, fell, time_out = (np.concatenate([r[k] for r in results]) for k in (1, 2, 3))
        terms = {name: np.concatenate([r[4]["reward_terms"][name] for r in results])
                 for name in results[0][4]["reward_terms"]}
        lengths = np.concatenate([r[4]["episode_length"] for r in results])
        self.episode_length = np.where(fell | time_out, 0, lengths)
        self.obs = obs
        return obs, reward, fell, time_out, {"reward_terms": terms, "episode_length": lengths}

    def get_state(self) -> dict[str, Any]:
        states = self.shards.get_state()
        return states[0] if len(states) == 1 else {"shards": states}  # one shard: the plain env's checkpoint

    def set_state(self, saved: Mapping[str, Any]) -> None:
        self.shards.set_state([saved] if "shards" not in saved else saved["shards"])
        self.obs = _joined(self.shards.observations())

    def close(self) -> None:
        self.shards.close()


def _joined(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
