"""PPO training throughput on this machine: policy steps per second, environment alone and whole iterations.

Builds the training of training/rl/bruce_walk.yaml (its env count, randomisation, networks and PPO settings), runs
one untimed iteration, then times `--iterations` PPO iterations (rollout + update) and, separately, the
environment stepping the same number of steps with the policy's actions, and the physics alone (the same rollout
of 10 Eq. 8 PD steps per policy step, with no observation, reward or policy): the ceiling of this machine at the
runtime's 1 kHz physics. Goal (issue #22): >= 10,000 policy steps/s on 2 cores.

    python bench/bench_policy_training.py [--envs 256] [--iterations 5] [--threads 1] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from bruce_hw.config import load_config
from training.rl.env import BruceWalkEnv
from training.rl.ppo_loop import PolicyTrainer
from training.rl.train_config import load_training_config
from training.rl.vec_env import RslVecEnv

GOAL_STEPS_PER_S = 10_000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=None, help="num_envs (default: the config's)")
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (default: bruce-train-policy's 1; the physics threads take the cores)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    overrides = args.set + ([f"env.num_envs={args.envs}"] if args.envs else [])
    config = load_training_config(overrides=overrides)
    env = BruceWalkEnv(load_config(), config.env, seed=0, reward_weights=config.reward_weights)
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    trainer = PolicyTrainer(vec, config.ppo, seed=0)
    trainer.step_iteration()
    steps_per_iteration = config.ppo["num_steps_per_env"] * env.num_envs

    n_steps = args.iterations * config.ppo["num_steps_per_env"]

    def iterations() -> None:
        for _ in range(args.iterations):
            trainer.step_iteration()

    def environment() -> None:
        obs = vec.get_observations()
        with torch.inference_mode():
            for _ in range(n_steps):
                obs, *_ = vec.step(policy(obs))

    def physics() -> None:
        hold = env.last_action.copy()
        for _ in range(n_steps):
            env._physics(hold)  # the rollout alone: what any learner on this env pays per policy step

    policy = trainer.alg.get_policy()
    total_s, total_cpu = timed(iterations)
    env_s, env_cpu = timed(environment)
    physics_s, physics_cpu = timed(physics)
    env.close()

    steps = args.iterations * steps_per_iteration
    whole = steps / total_s
    us = 1e6 / steps
    print(f"bench_policy_training: {env.num_envs} envs x {config.ppo['num_steps_per_env']} steps x "
          f"{args.iterations} iterations, torch threads {args.threads}, rollout threads {config.env.nthread}, "
          f"{os.cpu_count()} cores")
    print("  (CPU time is the process's, all threads: what a policy step costs whatever the overlap)")
    print(f"  physics alone (1 kHz Eq. 8 PD, mujoco.rollout): {steps / physics_s:,.0f} policy steps/s, "
          f"{physics_cpu * us:.0f} CPU-us per policy step")
    print(f"  environment + policy inference: {steps / env_s:,.0f} policy steps/s "
          f"({steps * env.decimation / env_s:,.0f} physics steps/s), {env_cpu * us:.0f} CPU-us per policy step")
    print(f"  whole PPO iterations (rollout + update): {whole:,.0f} policy steps/s, "
          f"{total_s / args.iterations:.2f} s per iteration, of which the update about "
          f"{max(0.0, total_s - env_s) / args.iterations:.2f} s; {total_cpu * us:.0f} CPU-us per policy step")
    ceiling = steps * (os.cpu_count() or 1) / total_cpu
    print(f"  all cores busy all the time with this work would give {ceiling:,.0f} policy steps/s "
          f"(cores / CPU time per step)")
    print(f"  goal >= {GOAL_STEPS_PER_S:,} policy steps/s: ratio {whole / GOAL_STEPS_PER_S:.2f} "
          f"({'met' if whole >= GOAL_STEPS_PER_S else 'not met'}); goal / that bound {GOAL_STEPS_PER_S / ceiling:.2f}")


def timed(work) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the whole process) that `work()` takes."""
    wall, cpu = time.perf_counter(), time.process_time()
    work()
    return time.perf_counter() - wall, time.process_time() - cpu


if __name__ == "__main__":
    main()
