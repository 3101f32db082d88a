"""The walking environment's shards on Ray actors (`bruce-train-policy --executor ray`), as RLlib's EnvRunners.

Each actor holds one `BruceWalkEnv` shard (training/rl/env_shards.py), built on its node from the robot config the
job shipped (`RayExecutor.where`), and steps it with `mujoco.rollout` on its own threads; a step sends every actor
its slice of the actions at once and waits for them all. The learner stays where the command runs.

An actor that dies (its process killed, its node gone) is replaced by a fresh one that starts new episodes: the
step it missed reports those simulations as timed out (a time-out is bootstrapped, not a fall), one warning line
says so, and training goes on with the current policy. Its random draws then differ from an uninterrupted run's.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np

from training.rl.env import WalkEnvConfig
from training.rl.env_shards import StepResult, lean_step

log = logging.getLogger("bruce-train-policy")


class WalkShard:
    """One shard, inside a Ray actor."""

    def __init__(self, robot_config: str, config: WalkEnvConfig, seed: int,
                 reward_weights: Mapping[str, float] | None):
        from bruce_hw.config import load_config
        from training.rl.env import BruceWalkEnv

        self.env = BruceWalkEnv(load_config(robot_config), config, seed=seed, reward_weights=reward_weights)

    def step(self, actions: np.ndarray) -> StepResult:
        return lean_step(self.env, actions)

    def observations(self) -> dict[str, np.ndarray]:
        return self.env.get_observations()

    def get_state(self) -> dict[str, Any]:
        return self.env.get_state()

    def set_state(self, state: Mapping[str, Any]) -> dict[str, np.ndarray]:
        self.env.set_state(state)
        return self.env.get_observations()

    def pid(self) -> int:
        import os

        return os.getpid()


class RayShards:
    """`LocalShards`' interface over one Ray actor per shard."""

    def __init__(self, executor, robot_path, config: WalkEnvConfig, seeds: list[int],
                 reward_weights: Mapping[str, float] | None = None, cpus_per_actor: float = 1.0):
        import ray

        self._ray = ray
        self._actor_class = ray.remote(num_cpus=cpus_per_actor, max_restarts=0)(WalkShard)
        self._args = (executor.where(robot_path), config, reward_weights)
        self.seeds = list(seeds)
        self.restarts = 0
        self.actors = [self._start(seed) for seed in self.seeds]
        self._obs = ray.get([a.observations.remote() for a in self.actors])
        self._terms: list[str] = []  # the reward terms' names, for a dead shard's step

    def _start(self, seed: int):
        robot_config, config, reward_weights = self._args
        return self._actor_class.remote(robot_config, config, seed, reward_weights)

    def step(self, actions: list[np.ndarray]) -> list[StepResult]:
        refs = [actor.step.remote(a) for actor, a in zip(self.actors, actions, strict=True)]
        results: list[StepResult | None] = []
        for i, ref in enumerate(refs):
            try:
                results.append(self._ray.get(ref))
                self._terms = list(results[-1][4]["reward_terms"])
            except (self._ray.exceptions.RayActorError, self._ray.exceptions.ActorUnavailableError) as exc:
                self._replace(i, exc)
                results.append(None)
        for i, result in enumerate(results):
            if result is None:  # the dead shard's step: time-outs into the fresh actor's new episodes
                n = len(self._obs[i]["policy"])
                results[i] = (self._obs[i], np.zeros(n), np.zeros(n, dtype=bool), np.ones(n, dtype=bool),
                              {"reward_terms": {name: np.zeros(n) for name in self._terms},
                               "episode_length": np.zeros(n, dtype=int)})
            self._obs[i] = results[i][0]
        return results

    def _replace(self, i: int, exc: Exception) -> None:
        """A fresh actor in place of shard i's dead one."""
        self.restarts += 1
        seed = self.seeds[i] + 1_000_003 * self.restarts  # new draws: replaying the lost episodes' would bias them
        log.warning("env shard %d: its actor died (%s); restarted with new episodes (restart %d)", i,
                    type(exc).__name__, self.restarts)
        self.actors[i] = self._start(seed)
        self._obs[i] = self._ray.get(self.actors[i].observations.remote())

    def observations(self) -> list[dict[str, np.ndarray]]:
        return list(self._obs)

    def get_state(self) -> list[dict[str, Any]]:
        return self._ray.get([a.get_state.remote() for a in self.actors])

    def set_state(self, states: list[Mapping[str, Any]]) -> None:
        self._obs = self._ray.get([a.set_state.remote(s) for a, s in zip(self.actors, states, strict=True)])

    def pids(self) -> list[int]:
        """Each actor's process id (tests kill one)."""
        return self._ray.get([a.pid.remote() for a in self.actors])

    def close(self) -> None:
        for actor in self.actors:
            self._ray.kill(actor)
