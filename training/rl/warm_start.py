"""Warm start: the actor made from an ONNX policy (the distilled one), then the critic fitted with the actor held.

Transfer (`transfer_policy`) copies the weights when the ONNX is an ELU MLP between an input normalisation and an
output scaling (`training.distill.StudentPolicy`, as exported) and the actor has the same hidden layers: the actor
then computes the ONNX policy exactly, with its normaliser set to the ONNX's and frozen (rsl-rl's `until`). Else
cloning (`clone_policy`) fits it. Cloning is DAgger over the training environment (randomisation and pushes
included): round 0 lets the ONNX policy act, later rounds the clone, and the ONNX policy labels every visited
observation; the actor's mean is fitted by mean squared error in network units. Its observation normaliser is set
from the visited observations first, so it starts where PPO's running statistics will be.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from runtime.control.inference import OnnxPolicy
from training.rl.ppo_loop import IterationStats, PolicyTrainer
from training.rl.vec_env import RslVecEnv

ROUNDS = 4


class TransferMismatch(ValueError):
    """The ONNX policy is not an MLP the actor can take exactly (the message says what differs)."""


def transfer_policy(trainer: PolicyTrainer, vec: RslVecEnv, policy_path: Path) -> dict[str, float]:
    """Set the actor's weights so that its deployed action (q_stand + action_scale x mean) is `policy_path`'s;
    the largest difference from onnxruntime on the environment's present observations (rad)."""
    layers, norm = _student_weights(policy_path)
    actor = trainer.actor
    linear = [m for m in actor.mlp if isinstance(m, torch.nn.Linear)]
    shapes = [tuple(w.shape) for w, _ in layers]
    if [tuple(m.weight.shape) for m in linear] != shapes or \
            any(not isinstance(m, torch.nn.ELU) for m in actor.mlp if not isinstance(m, torch.nn.Linear)):
        raise TransferMismatch(f"{policy_path}: an ELU MLP with layers {shapes}; the actor's are "
                               f"{[tuple(m.weight.shape) for m in linear]} ({type(actor.mlp[1]).__name__})")
    standing = vec.walk.sim.standing_pose
    with torch.no_grad():
        for m, (w, b) in zip(linear[:-1], layers[:-1], strict=True):
            m.weight.copy_(torch.from_numpy(w))
            m.bias.copy_(torch.from_numpy(b))
        # a = act_mean + act_scale (W h + b) = q_stand + action_scale u  =>  u = W' h + b'
        w, b = layers[-1]
        k = norm["act_scale"][:, None] / vec.action_scale
        linear[-1].weight.copy_(torch.from_numpy(k * w))
        linear[-1].bias.copy_(torch.from_numpy((norm["act_mean"] + norm["act_scale"] * b - standing)
                                               / vec.action_scale))
        normaliser = actor.obs_normalizer
        if isinstance(normaliser, torch.nn.Identity):
            raise TransferMismatch(f"{policy_path}: transfer needs the actor's observation normaliser "
                                   "(ppo.actor.obs_normalization: true) to hold the ONNX's input scaling")
        std = torch.from_numpy(1.0 / norm["obs_scale"] - normaliser.eps).float()[None]
        normaliser._mean.copy_(torch.from_numpy(norm["obs_mean"]).float()[None])
        normaliser._std.copy_(std)
        normaliser._var.copy_(std ** 2)
    freeze_normaliser(trainer)
    obs = vec.walk.get_observations()["policy"]
    teacher = OnnxPolicy(policy_path, obs.shape[1], vec.num_actions)
    with torch.no_grad():
        out = actor(TensorDict({"policy": torch.from_numpy(obs).float()}, batch_size=[len(obs)])).double().numpy()
    return {"transfer_max_error_rad": float(np.max(np.abs(vec.targets(out) - np.stack([teacher(o) for o in obs]))))}


def freeze_normaliser(trainer: PolicyTrainer) -> None:
    """Stop PPO's updates of the actor's input statistics (rsl-rl's `until`): a transferred actor keeps the ONNX's."""
    trainer.actor.obs_normalizer.until = 0


def _student_weights(path: Path) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    """The (weight, bias) of each Gemm and the normalisation of an exported `StudentPolicy`; TransferMismatch if
    the graph is not Sub, Mul, (Gemm, Elu)..., Gemm, Mul, Add."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    values = {t.name: t for t in model.graph.initializer}
    ops = [n.op_type for n in model.graph.node]
    body = ops[2:-2]
    if ops[:2] != ["Sub", "Mul"] or ops[-2:] != ["Mul", "Add"] or body[-1:] != ["Gemm"] or \
            body[:-1] != ["Gemm", "Elu"] * ((len(body) - 1) // 2) or \
            not {"obs_mean", "obs_scale", "act_mean", "act_scale"} <= set(values):
        raise TransferMismatch(f"{path}: not a normalised ELU MLP policy (graph {ops})")
    arrays = {name: numpy_helper.to_array(t).astype(np.float64) for name, t in values.items()}
    layers = []
    for node in model.graph.node:
        if node.op_type == "Gemm":
            attrs = {a.name: a for a in node.attribute}
            if "transB" not in attrs or attrs["transB"].i != 1:
                raise TransferMismatch(f"{path}: Gemm {node.name} without transB")
            layers.append((arrays[node.input[1]], arrays[node.input[2]]))
    return layers, {k: arrays[k] for k in ("obs_mean", "obs_scale", "act_mean", "act_scale")}


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
