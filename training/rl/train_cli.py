"""`bruce-train-policy`: PPO for BRUCE's walking policy in MuJoCo (paper §IV-A), exported for `bruce-run --policy`.

    bruce-train-policy --out runs/rl [--config training/rl/bruce_walk.yaml] [--set KEY=VALUE ...]
                       [--warm-start configs/robots/policies/bruce_walk.onnx | none] [--resume] [--stop-after N]

DIR gets `checkpoint.pt` (every `train.checkpoint_every` iterations and at the end: networks, optimizer, the
environments' state and the random generators, so `--resume` continues exactly), TensorBoard files in `tb/`
(losses, learning rate, episode reward and length, each reward term), `policy.onnx` with its sidecar, and with
`train.snapshot_every` N, `snapshots/policy_<iteration>.onnx` every N iterations (to pick one by `bruce-eval
walking`). The policy observes and acts as the spec `env.policy_spec` says (default table1, the paper's Table I;
`--set env.policy_spec=FILE` trains on another), and its sidecar records the spec, so `bruce-run --policy` runs it so.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import logging
import os
import shlex
import sys
import time
from importlib import metadata
from pathlib import Path

import torch
import yaml

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, load_config
from bruce_hw.yaml_reader import read_yaml
from runtime.control.policy_spec import spec_file
from runtime.loop.recorder import file_sha256, portable_path
from training.executor import Executor, ExecutorError, add_executor_arguments, make_executor
from training.rl.train_config import DEFAULT_TRAINING_CONFIG, TrainingConfig, TrainingConfigError, load_training_config

CHECKPOINT = "checkpoint.pt"
log = logging.getLogger("bruce-train-policy")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bruce-train-policy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="run directory (checkpoint, TensorBoard, policy.onnx)")
    p.add_argument("--config", type=Path, default=DEFAULT_TRAINING_CONFIG, help="training config (YAML)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a training config key, e.g. train.iterations=200 (repeatable)")
    p.add_argument("--robot-config", default=DEFAULT_CONFIG, help="robot config (default %(default)s)")
    p.add_argument("--warm-start", default=None, metavar="ONNX|none",
                   help="clone this ONNX policy before PPO (overrides train.warm_start.policy); none: from scratch")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--stop-after", type=int, default=None, metavar="N",
                   help="stop (with a checkpoint) after N PPO iterations of this call; --resume continues")
    p.add_argument("--export", type=Path, default=None, help="ONNX file to write at the end (default OUT/policy.onnx)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (one log line per checkpoint)")
    add_executor_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.command_line = "bruce-train-policy " + shlex.join(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        robot, config, resumed = _prepare(args)
    except (ConfigError, TrainingConfigError, FileNotFoundError) as exc:
        print(f"bruce-train-policy: {exc}", file=sys.stderr)
        return 2
    try:
        return train(args, config, robot, resumed)
    except (TrainingConfigError, ExecutorError) as exc:
        print(f"bruce-train-policy: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"bruce-train-policy: interrupted; the last checkpoint is in {args.out} (continue with --resume)",
              file=sys.stderr)
        return 130


def _prepare(args: argparse.Namespace) -> tuple:
    from training.rl.env import training_spec  # torch and MuJoCo load after the arguments are checked

    robot = load_config(args.robot_config)
    config = load_training_config(args.config, args.set)
    training_spec(robot, config.env)  # a spec that cannot be trained on fails here, in one line
    if args.warm_start is not None:
        policy = None if args.warm_start == "none" else Path(args.warm_start)
        if policy is not None and not policy.is_file():
            raise FileNotFoundError(f"{policy}: --warm-start policy file not found")
        config = dataclasses.replace(config, warm_start=dataclasses.replace(config.warm_start, policy=policy))
    if config.warm_start.policy is not None and not config.warm_start.policy.is_file():
        raise FileNotFoundError(f"{config.path}: train.warm_start.policy: {config.warm_start.policy} not found")
    if args.stop_after is not None and args.stop_after < 1:
        raise TrainingConfigError(f"--stop-after: expected an integer >= 1, got {args.stop_after}")
    checkpoint = args.out / CHECKPOINT
    if args.resume and not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint}: --resume: no checkpoint to continue from")
    if not args.resume and checkpoint.exists():
        raise TrainingConfigError(f"{args.out}: holds a run already (continue it with --resume, or choose "
                                  "another --out)")
    resumed = torch.load(checkpoint, weights_only=False) if args.resume else None
    if resumed is not None and _extensible(resumed["run"]) != _extensible(_run_identity(config, robot.path)):
        raise TrainingConfigError(f"{checkpoint}: --resume: the run was started with other settings "
                                  f"(config, robot config or warm start); start a new --out")
    return robot, config, resumed


def _run_identity(config: TrainingConfig, robot_path: Path) -> dict:
    """What a run is started with; a resumed run must share it but for `train.iterations` (`_extensible`)."""
    return {"config": config.raw, "robot_config_sha256": file_sha256(robot_path),
            "warm_start": str(config.warm_start.policy) if config.warm_start.policy else None}


def _extensible(identity: dict) -> dict:
    """`identity` less `train.iterations`: a finished run may be extended."""
    identity = copy.deepcopy(identity)
    identity["config"].get("train", {}).pop("iterations", None)
    return identity


def train(args: argparse.Namespace, config: TrainingConfig, robot, resumed: dict | None) -> int:
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    from training.rl.env import training_spec
    from training.rl.export import export_policy
    from training.rl.ppo_loop import PolicyTrainer
    from training.rl.vec_env import RslVecEnv
    from training.rl.warm_start import fit_critic, freeze_normaliser

    torch.set_num_threads(1)  # the physics threads take the cores; the small networks gain nothing from more
    args.out.mkdir(parents=True, exist_ok=True)
    spec_path = spec_file(config.env.policy_spec)
    executor = make_executor(args, jobs=1, ship=[robot.path.parent, spec_path])
    try:
        env = make_env(robot, config, executor)
    except BaseException:
        executor.close()
        raise
    vec = RslVecEnv(env, config.action_scale, config.reward_scale)
    spec, spec_tree = training_spec(robot, config.env), read_yaml(spec_path, ConfigError, "policy spec")
    ppo = config.warm_start.ppo(config.ppo) if config.warm_start.policy else config.ppo
    trainer = PolicyTrainer(vec, ppo, seed=config.seed)
    writer = SummaryWriter(log_dir=str(args.out / "tb"))
    identity = _run_identity(config, robot.path)
    history = resumed["history"] if resumed else {"wall_s": 0.0, "warm_start": None, "env_steps": 0}
    since = time.perf_counter()

    def save() -> None:
        nonlocal since
        now = time.perf_counter()
        history["wall_s"] += now - since
        since = now
        state = {"run": identity, "trainer": trainer.state_dict(), "history": history}
        tmp = args.out / (CHECKPOINT + ".tmp")
        torch.save(state, tmp)
        os.replace(tmp, args.out / CHECKPOINT)

    try:
        warm_iterations = config.warm_start.critic_iterations if config.warm_start.policy else 0
        if resumed:
            trainer.load_state_dict(resumed["trainer"])
            if (history["warm_start"] or {}).get("method") == "transfer":
                freeze_normaliser(trainer)
            log.info("resumed %s at iteration %d", args.out / CHECKPOINT, trainer.iteration)
        elif config.warm_start.policy:
            started = _start_from_policy(trainer, vec, config, log.info)
            fit_critic(trainer, warm_iterations, report=lambda s: _log(writer, s))
            trainer.set_anchor(config.warm_start.anchor_weight)
            history["warm_start"] = {"policy": str(config.warm_start.policy),
                                     "policy_sha256": file_sha256(config.warm_start.policy), **started,
                                     "critic_iterations": warm_iterations}
            save()
        total = warm_iterations + config.iterations
        stop_at = total if args.stop_after is None else min(total, trainer.iteration + args.stop_after)
        bar = tqdm(total=total, initial=trainer.iteration, desc="bruce-train-policy", unit="it",
                   disable=args.no_progress, dynamic_ncols=True)
        def export(path: Path) -> None:
            export_policy(trainer.actor, path, env.get_observations()["policy"].shape[1], robot.standing_pose,
                          config.action_scale, _record(args, config, robot, trainer, history),
                          {"vx": config.env.command_vx, "vy": config.env.command_vy, "wz": config.env.command_wz},
                          spec, spec_tree)

        while trainer.iteration < stop_at:
            stats = trainer.step_iteration()
            history["env_steps"] += stats.steps
            _log(writer, stats)
            bar.update(1)
            bar.set_postfix(reward=f"{stats.mean_reward:.2f}", length_s=f"{stats.mean_length_s:.1f}",
                            steps_s=f"{stats.steps / stats.seconds:.0f}")
            if config.snapshot_every and trainer.iteration % config.snapshot_every == 0:
                export(args.out / "snapshots" / f"policy_{trainer.iteration}.onnx")
            if trainer.iteration % config.checkpoint_every == 0 or trainer.iteration == stop_at:
                save()
                if args.no_progress:
                    log.info("iteration %d/%d: mean episode reward %.2f, length %.1f s, %.0f steps/s",
                             trainer.iteration, total, stats.mean_reward, stats.mean_length_s,
                             stats.steps / stats.seconds)
        bar.close()
        if trainer.iteration < total:
            print(f"bruce-train-policy: stopped at iteration {trainer.iteration}/{total}; "
                  f"continue with --resume. Checkpoint: {args.out / CHECKPOINT}")
            return 0
        out = args.export or args.out / "policy.onnx"
        export(out)
        print(f"bruce-train-policy: wrote {out} and {out}.json; checkpoint {args.out / CHECKPOINT}; "
              f"TensorBoard: {args.out / 'tb'}")
        return 0
    finally:
        writer.close()
        env.close()
        executor.close()


def make_env(robot, config: TrainingConfig, executor: Executor):
    """The training environment: `env.num_envs` simulations in `env.shards` shards, on Ray actors with the Ray
    executor (training/rl/env_shards.py)."""
    from training.rl.env import BruceWalkEnv
    from training.rl.env_shards import LocalShards, ShardedWalkEnv, shard_config, shard_seeds

    shards = config.env.shards
    if shards == 1 and executor.name == "local":
        return BruceWalkEnv(robot, config.env, seed=config.seed, reward_weights=config.reward_weights)
    try:
        per_shard = shard_config(config.env, shards)
    except ValueError as exc:
        raise TrainingConfigError(str(exc)) from None
    seeds = shard_seeds(config.seed, shards)
    # the spec as the workers read it (shipped with the job, as the robot config)
    per_shard = dataclasses.replace(per_shard, policy_spec=executor.where(spec_file(config.env.policy_spec)))
    if executor.name == "ray":
        from training.rl.ray_shards import RayShards

        parts = RayShards(executor, robot.path, per_shard, seeds, config.reward_weights)
    else:
        parts = LocalShards(robot, per_shard, seeds, config.reward_weights)
    return ShardedWalkEnv(robot, config.env, parts)


def _start_from_policy(trainer, vec, config: TrainingConfig, progress) -> dict:
    """The actor made from `train.warm_start.policy` by its method; what was done and how close it came."""
    from training.rl.warm_start import TransferMismatch, clone_policy, transfer_policy

    warm = config.warm_start
    if warm.method in ("auto", "transfer"):
        try:
            result = transfer_policy(trainer, vec, warm.policy)
            progress(f"warm start: weights transferred from {warm.policy} (largest action difference "
                     f"{result['transfer_max_error_rad']:.2g} rad)")
            return {"method": "transfer", **result}
        except TransferMismatch as exc:
            if warm.method == "transfer":
                raise TrainingConfigError(f"{config.path}: train.warm_start.method transfer: {exc}") from None
            progress(f"warm start: {exc}; cloning instead")
    return {"method": "clone", **clone_policy(trainer, vec, warm.policy, warm.samples, warm.epochs, config.seed,
                                               progress=progress)}


def _record(args: argparse.Namespace, config: TrainingConfig, robot, trainer, history: dict) -> dict:
    """The exported policy's sidecar record: how to train it again, and what the training reached."""
    return {"command": args.command_line, "seed": config.seed, "config": portable_path(config.path),
            "config_sha256": file_sha256(config.path), "overrides": list(args.set),
            "robot_config": portable_path(robot.path), "robot_config_sha256": file_sha256(robot.path),
            "resolved_config": yaml.safe_dump(config.raw, sort_keys=False),
            "policy_spec": portable_path(spec_file(config.env.policy_spec)),
            "warm_start": history["warm_start"], "iterations": trainer.iteration,
            "env_steps": history["env_steps"], "train_wall_s": round(history["wall_s"], 1),
            "versions": {name: _version(name) for name in ("rsl-rl-lib", "mujoco", "torch", "numpy")},
            "final": {"mean_episode_reward": trainer.mean_return, "machine": os.uname().machine}}


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def _log(writer, stats) -> None:
    it = stats.iteration
    writer.add_scalar("Train/mean_episode_reward", stats.mean_reward, it)
    writer.add_scalar("Train/mean_episode_length_s", stats.mean_length_s, it)
    writer.add_scalar("Perf/steps_per_s", stats.steps / stats.seconds, it)
    writer.add_scalar("Loss/learning_rate", stats.learning_rate, it)
    writer.add_scalar("Policy/mean_std", stats.action_std, it)
    for name, value in stats.losses.items():
        writer.add_scalar(f"Loss/{name}", value, it)
    for name, value in stats.terms.items():
        writer.add_scalar(name, value, it)


if __name__ == "__main__":
    sys.exit(main())
