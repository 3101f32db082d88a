"""PPO training throughput on this machine: policy steps per second, environment alone and whole iterations.

Builds the training of training/rl/bruce_walk.yaml (its env count, randomisation, networks and PPO settings), runs
one untimed iteration, then times `--iterations` PPO iterations (rollout + update) and, separately, the
environment stepping the same number of steps with the policy's actions. Goal (issue #22): >= 10,000 policy
steps/s on 2 cores.

    python bench/bench_policy_training.py [--envs 256] [--iterations 5] [--threads 2] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
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
    parser.add_argument("--threads", type=int, default=2, help="torch threads (the physics threads are idle "
                                                                "while torch runs)")
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

    start = time.perf_counter()
    for _ in range(args.iterations):
        trainer.step_iteration()
    total_s = time.perf_counter() - start
    policy = trainer.alg.get_policy()
    obs = vec.get_observations()
    start = time.perf_counter()
    with torch.inference_mode():
        for _ in range(args.iterations * config.ppo["num_steps_per_env"]):
            obs, *_ = vec.step(policy(obs))
    env_s = time.perf_counter() - start
    env.close()

    steps = args.iterations * steps_per_iteration
    whole = steps / total_s
    print(f"bench_policy_training: {env.num_envs} envs x {config.ppo['num_steps_per_env']} steps x "
          f"{args.iterations} iterations, torch threads {args.threads}, rollout threads {config.env.nthread}")
    print(f"  environment + policy inference: {steps / env_s:,.0f} policy steps/s "
          f"({steps * env.decimation / env_s:,.0f} physics steps/s)")
    print(f"  whole PPO iterations (rollout + update): {whole:,.0f} policy steps/s, "
          f"{total_s / args.iterations:.2f} s per iteration, of which the update about "
          f"{max(0.0, total_s - env_s) / args.iterations:.2f} s")
    print(f"  goal >= {GOAL_STEPS_PER_S:,} policy steps/s: ratio {whole / GOAL_STEPS_PER_S:.2f} "
          f"({'met' if whole >= GOAL_STEPS_PER_S else 'not met'})")


if __name__ == "__main__":
    main()
