"""The PPO training loop on rsl-rl-lib's PPO, actor-critic models and rollout storage.

rsl-rl's `OnPolicyRunner` is this loop plus its own logging and checkpoints; we run the loop ourselves because an
identical `--resume` needs the environment's state and the random generators in the checkpoint (the runner saves
only the networks and the optimizer), and because `bruce-train-policy` shows a progress bar and logs the reward
terms instead of the runner's per-iteration text blocks.

An optional anchor keeps the actor near its warm start (transferred or cloned): every PPO optimizer step also
descends `anchor_weight` x the mean squared distance between the actor's mean and the anchor's (network units) on a
mini-batch of the iteration's observations — kickstarting (Schmitt et al. 2018, "Kickstarting Deep Reinforcement
Learning") with a constant weight. rsl-rl's `PPO.update` takes no extra loss term, so the anchor's gradient joins
PPO's through the optimizer's step pre-hook (after PPO's gradient clipping), in the same Adam step.
"""

from __future__ import annotations

import contextlib
import copy
import io
import statistics
import time
from collections import deque
from dataclasses import dataclass, field

import torch
from rsl_rl.algorithms import PPO

from training.rl.vec_env import RslVecEnv


@dataclass
class IterationStats:
    iteration: int
    steps: int                    # env steps taken in this iteration (all envs)
    seconds: float
    mean_reward: float            # mean return of the episodes finished in the last 100 (nan before the first)
    mean_length_s: float          # their mean length (s)
    losses: dict[str, float]
    learning_rate: float
    action_std: float
    terms: dict[str, float] = field(default_factory=dict)  # per-step mean of each weighted reward term


class PolicyTrainer:
    """PPO on `env` with rsl-rl's `PPO.construct_algorithm(obs, env, cfg)`; `cfg` is rsl-rl's train config."""

    def __init__(self, env: RslVecEnv, cfg: dict, seed: int):
        torch.manual_seed(seed)
        self.env = env
        self.cfg = copy.deepcopy(cfg)
        self.cfg.setdefault("multi_gpu", None)
        with contextlib.redirect_stdout(io.StringIO()):  # rsl-rl prints both networks
            self.alg: PPO = PPO.construct_algorithm(env.get_observations(), env, self.cfg, "cpu")
        self.iteration = 0
        self._returns: deque[float] = deque(maxlen=100)
        self._lengths: deque[float] = deque(maxlen=100)
        self._episode_return = torch.zeros(env.num_envs)
        self._episode_steps = torch.zeros(env.num_envs)
        self.anchor: torch.nn.Module | None = None
        self.anchor_weight = 0.0
        self._anchor_hook = None
        self._anchor_batches: list[tuple[torch.Tensor, torch.Tensor]] = []
        self._anchor_losses: list[float] = []

    def set_anchor(self, weight: float) -> None:
        """Hold the actor near its present policy from now on (weight 0: no anchor)."""
        if self._anchor_hook is not None:
            self._anchor_hook.remove()
        self.anchor_weight = float(weight)
        self.anchor = self._anchor_hook = None
        if self.anchor_weight > 0.0:
            self.anchor = self.actor.as_jit().eval()  # a frozen copy: normaliser -> MLP -> mean
            for p in self.anchor.parameters():
                p.requires_grad_(False)
            self._anchor_hook = self.alg.optimizer.register_step_pre_hook(self._add_anchor_gradient)

    @property
    def actor(self) -> torch.nn.Module:
        return self.alg.get_policy()

    @property
    def mean_return(self) -> float:
        """Mean return of the last 100 finished episodes (nan before the first)."""
        return statistics.fmean(self._returns) if self._returns else float("nan")

    def step_iteration(self) -> IterationStats:
        """One PPO iteration: `num_steps_per_env` steps of every env, then the update."""
        start = time.perf_counter()
        self.alg.train_mode()
        obs = self.env.get_observations()
        terms: dict[str, float] = {}
        steps = int(self.cfg["num_steps_per_env"])
        visited: list[torch.Tensor] = []
        with torch.inference_mode():
            for _ in range(steps):
                if self.anchor is not None:
                    visited.append(obs["policy"].clone())
                actions = self.alg.act(obs)
                obs, rewards, dones, extras = self.env.step(actions)
                self.alg.process_env_step(obs, rewards, dones, extras)
                for name, value in extras["log"].items():
                    terms[name] = terms.get(name, 0.0) + float(value) / steps
                self._book_episodes(rewards, dones)
            self.alg.compute_returns(obs)
        if self.anchor is not None:
            self._anchor_batches = self._batches_for_the_anchor(torch.cat(visited))
        losses = self.alg.update()
        if self.anchor is not None:
            losses["anchor"] = statistics.fmean(self._anchor_losses)
            self._anchor_batches, self._anchor_losses = [], []
        self.iteration += 1
        return IterationStats(
            iteration=self.iteration, steps=steps * self.env.num_envs, seconds=time.perf_counter() - start,
            mean_reward=self.mean_return,
            mean_length_s=statistics.fmean(self._lengths) * self.env.dt if self._lengths else float("nan"),
            losses={k: float(v) for k, v in losses.items()}, learning_rate=float(self.alg.learning_rate),
            action_std=float(self.actor.output_std.detach().mean()), terms=terms)

    def _batches_for_the_anchor(self, obs: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """One observation mini-batch with the anchor's means for each of PPO's optimizer steps this update."""
        algorithm = self.cfg["algorithm"]
        epochs = int(algorithm.get("num_learning_epochs", 1))
        with torch.no_grad():
            target = self.anchor(obs)
        order = torch.cat([torch.randperm(len(obs)) for _ in range(epochs)])
        batches = order.chunk(epochs * int(algorithm.get("num_mini_batches", 1)))
        return [(obs[idx], target[idx]) for idx in batches][::-1]

    def _add_anchor_gradient(self, optimizer, args, kwargs) -> None:
        """Before each of PPO's optimizer steps: add the anchor loss's gradient to the actor's."""
        if not self._anchor_batches:
            return
        obs, target = self._anchor_batches.pop()
        mlp = self.actor.mlp
        with torch.enable_grad():
            loss = torch.mean((mlp(self.actor.obs_normalizer(obs)) - target) ** 2)
            grads = torch.autograd.grad(self.anchor_weight * loss, list(mlp.parameters()))
        for p, g in zip(mlp.parameters(), grads, strict=True):
            p.grad = g if p.grad is None else p.grad + g
        self._anchor_losses.append(float(loss.detach()))

    def _book_episodes(self, rewards: torch.Tensor, dones: torch.Tensor) -> None:
        self._episode_return += rewards
        self._episode_steps += 1
        done = dones.bool()
        if done.any():
            self._returns.extend(self._episode_return[done].tolist())
            self._lengths.extend(self._episode_steps[done].tolist())
            self._episode_return[done] = 0.0
            self._episode_steps[done] = 0.0

    # -- checkpoints: everything an identical continuation needs -----------------------------------------------
    def state_dict(self) -> dict:
        return {"alg": self.alg.save(), "iteration": self.iteration, "env": self.env.state_dict(),
                "torch_rng": torch.get_rng_state(), "returns": list(self._returns), "lengths": list(self._lengths),
                "episode_return": self._episode_return.clone(), "episode_steps": self._episode_steps.clone(),
                "anchor": None if self.anchor is None else {"weight": self.anchor_weight,
                                                            "model": self.anchor.state_dict()}}

    def load_state_dict(self, state: dict) -> None:
        self.alg.load(state["alg"], None, strict=True)
        self.iteration = int(state["iteration"])
        self.env.load_state_dict(state["env"])
        torch.set_rng_state(state["torch_rng"])
        self._returns = deque(state["returns"], maxlen=100)
        self._lengths = deque(state["lengths"], maxlen=100)
        self._episode_return = state["episode_return"].clone()
        self._episode_steps = state["episode_steps"].clone()
        anchor = state.get("anchor")
        self.set_anchor(anchor["weight"] if anchor else 0.0)
        if anchor:
            self.anchor.load_state_dict(anchor["model"])

