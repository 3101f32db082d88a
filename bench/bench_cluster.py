"""Throughput on a Ray cluster against the local executor, in one run (docs/cluster.md).

1. Sweep: the same `bruce-eval transfer` runs (`--runs` distinct direct-transfer runs of `--seconds`, nothing
   cached) through the local executor (`--jobs` processes), then through Ray on a cluster of 1 and of 2 nodes
   started here (`ray.cluster_utils.Cluster`, `--cpus-per-node` each): runs per minute.
2. PPO: `bruce-train-policy`'s iteration (rollout of `num_steps_per_env` steps of `--envs` simulations, then the
   update) with the environment local (one batch, `env.nthread` threads) and on 1, 2 and 4 Ray actors (the batch in
   as many shards, one rollout thread each): policy steps per second, and the time Ray adds per batch step (the
   1-actor run's step less the local one's: sending the actions and getting the observations back).

On one machine the nodes share its cores: the figures show Ray's overhead and that results scale with the cores
it is given, not a cluster's speed-up. Run it on a cluster's head with `--address auto` to measure that cluster
as well (its row is added).

    python bench/bench_cluster.py [--runs 8] [--seconds 5] [--envs 256] [--iterations 3] [--address auto]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bruce_hw.config import DEFAULT_CONFIG, load_config, resolve_config_path
from bruce_hw.reality_gap import load_gap
from training.evaluation.transfer_eval import execute
from training.evaluation.transfer_runs import EXPERIMENTS, RunSpec
from training.executor import LocalExecutor, RayExecutor
from training.rl.train_cli import make_env
from training.rl.train_config import load_training_config


def sweep_specs(runs: int, seconds: float) -> list[RunSpec]:
    tracking = EXPERIMENTS[0]
    gap = load_gap("default")
    return [RunSpec(tracking.name, tracking.command, seconds, "direct", dataclasses.replace(gap, seed=seed))
            for seed in range(runs)]


def time_sweep(specs: list[RunSpec], executor) -> float:
    """Runs per minute of the sweep's gapped runs (its one nominal reference is run first, not counted)."""
    out = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    try:
        execute(specs[:1], out, executor, progress=False)  # the nominal reference, and the workers warmed up
        start = time.perf_counter()
        execute(specs, out, executor, progress=False)
        return (len(specs) - 1) * 60.0 / (time.perf_counter() - start)
    finally:
        shutil.rmtree(out, ignore_errors=True)


def time_ppo(executor, shards: int, envs: int, iterations: int, nthread: int) -> tuple[float, float]:
    """(policy steps/s over whole iterations, seconds per batch step of the rollout alone)."""
    from training.rl.ppo_loop import PolicyTrainer
    from training.rl.vec_env import RslVecEnv

    config = load_training_config(overrides=[f"env.num_envs={envs}", f"env.shards={shards}",
                                             f"env.nthread={nthread}"])
    env = make_env(load_config(), config, executor)
    try:
        vec = RslVecEnv(env, config.action_scale, config.reward_scale)
        trainer = PolicyTrainer(vec, config.ppo, seed=0)
        trainer.step_iteration()  # untimed: the actors started, the first episodes begun
        start = time.perf_counter()
        steps = sum(trainer.step_iteration().steps for _ in range(iterations))
        whole = steps / (time.perf_counter() - start)
        actions = torch.zeros(envs, vec.num_actions)
        start = time.perf_counter()
        for _ in range(20):
            vec.step(actions)
        return whole, (time.perf_counter() - start) / 20
    finally:
        env.close()


def round_trip(executor, shards: int) -> float:
    """Seconds per batch step with one simulation per shard: what stepping costs beyond the physics."""
    config = load_training_config(overrides=[f"env.num_envs={shards}", f"env.shards={shards}", "env.nthread=0"])
    env = make_env(load_config(), config, executor)
    try:
        actions = np.tile(env.robot.standing_pose, (shards, 1))
        for _ in range(5):
            env.step(actions)
        start = time.perf_counter()
        for _ in range(100):
            env.step(actions)
        return (time.perf_counter() - start) / 100
    finally:
        env.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=8, help="gapped runs in the sweep (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per run (default: %(default)s)")
    cores = os.cpu_count() or 1
    p.add_argument("--jobs", type=int, default=cores, help="local processes (default: CPU count)")
    p.add_argument("--envs", type=int, default=256, help="simulations in the PPO batch (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=3, help="timed PPO iterations (default: %(default)s)")
    p.add_argument("--address", default=None, help="also measure this running cluster (auto or HOST:PORT)")
    args = p.parse_args()
    torch.set_num_threads(1)  # as bruce-train-policy
    from ray.cluster_utils import Cluster

    def cluster(nodes: int, cpus: int) -> Cluster:
        made = Cluster(initialize_head=True, head_node_args={"num_cpus": cpus})
        for _ in range(nodes - 1):
            made.add_node(num_cpus=cpus)
        made.wait_for_nodes()
        return made

    config_folder = resolve_config_path(DEFAULT_CONFIG).parent
    specs = sweep_specs(args.runs + 1, args.seconds)[1:]  # distinct seeds
    print(f"machine: {cores} CPUs; sweep: {len(specs)} runs of {args.seconds:g} s; "
          f"PPO: {args.envs} envs, {args.iterations} timed iterations", flush=True)
    with contextlib.redirect_stdout(io.StringIO()):  # each run's summary
        sweep = [(f"local ({args.jobs} processes)", time_sweep(specs, LocalExecutor(args.jobs)))]
    # The sweep's clusters offer this machine's cores, on one node or split over two: Ray's cost, not more cores.
    for nodes, cpus in ((1, cores), (2, max(1, cores // 2))):
        made = cluster(nodes, cpus)
        try:
            with RayExecutor(made.address, ship=[config_folder]) as executor:
                sweep.append((f"Ray, {nodes} node(s) x {cpus} CPU(s)", time_sweep(specs, executor)))
        finally:
            made.shutdown()
    ppo = [(f"local (1 batch, {cores} threads)", *time_ppo(LocalExecutor(1), 1, args.envs, args.iterations, cores))]
    local = time_ppo(LocalExecutor(1), 1, args.envs, args.iterations, nthread=1)
    ppo.append(("local (1 batch, 1 thread)", *local))
    trips = [("local, 1 shard", round_trip(LocalExecutor(1), 1))]
    # 4 actors of 1 CPU each need 4 logical CPUs: two nodes of 2 (on a 2-core machine they share its cores).
    made = cluster(2, 2)
    try:
        with RayExecutor(made.address, ship=[config_folder]) as executor:
            for actors in (1, 2, 4):
                ppo.append((f"Ray, {actors} actor(s), 2 nodes", *time_ppo(executor, actors, args.envs,
                                                                         args.iterations, nthread=1)))
            trips += [(f"Ray, {actors} actor(s)", round_trip(executor, actors)) for actors in (1, 2, 4)]
    finally:
        made.shutdown()
    if args.address:
        with RayExecutor(args.address, ship=[config_folder]) as executor:
            cpus = int(executor.resources().get("CPU", 0))
            sweep.append((f"Ray at {args.address} ({cpus} CPUs)", time_sweep(specs, executor)))
            for actors in (1, 2, 4):
                ppo.append((f"Ray at {args.address}, {actors} actor(s)",
                            *time_ppo(executor, actors, args.envs, args.iterations, nthread=1)))
            trips += [(f"Ray at {args.address}, {actors} actor(s)", round_trip(executor, actors))
                      for actors in (1, 2, 4)]
    print("\n| sweep executor | runs/min |\n|---|---|")
    for label, rate in sweep:
        print(f"| {label} | {rate:.1f} |")
    print("\n| PPO environment | policy steps/s (whole iterations) | batch step of the rollout (ms) |")
    print("|---|---|---|")
    for label, rate, step in ppo:
        print(f"| {label} | {rate:,.0f} | {step * 1e3:.1f} |")
    print("\n| one simulation per shard (the cost beyond physics) | batch step (ms) |\n|---|---|")
    for label, step in trips:
        print(f"| {label} | {step * 1e3:.2f} |")
    one_actor = dict(trips)["Ray, 1 actor(s)"]
    print(f"\nRay adds {(one_actor - trips[0][1]) * 1e3:.2f} ms per batch step (1 actor, 1 simulation, against the "
          f"same shard stepped here); per policy step of a {args.envs}-simulation batch: "
          f"{(one_actor - trips[0][1]) * 1e6 / args.envs:.1f} us")


if __name__ == "__main__":
    main()
