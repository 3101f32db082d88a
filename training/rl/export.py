"""The trained actor as the runtime's policy file: obs [1, obs_dim] -> action [1, n_joints] (PD targets, rad).

rsl-rl's deterministic actor (its observation normaliser, the MLP, the Gaussian's mean) is followed by the
environment's action map a = q_stand + action_scale * output, so `bruce-run --policy FILE` loads it like the
distilled policy. The sidecar records how to make the file again.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import nn

from training.onnx_export import export_mlp_policy_onnx, sidecar_path


class DeployedPolicy(nn.Module):
    """obs -> PD targets: the actor's mean action mapped about the standing pose."""

    def __init__(self, actor: nn.Module, standing: np.ndarray, action_scale: float):
        super().__init__()
        self.actor = actor.as_jit()  # a copy: normaliser -> MLP -> mean, taking one tensor
        self.register_buffer("standing", torch.as_tensor(standing, dtype=torch.float32).reshape(1, -1))
        self.action_scale = float(action_scale)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.standing + self.action_scale * self.actor(obs)


def export_policy(actor: nn.Module, path: str | Path, obs_dim: int, standing: np.ndarray, action_scale: float,
                  record: Mapping[str, object], commands: Mapping[str, tuple[float, float]]) -> Path:
    """Write the ONNX policy and add `record` (command, seed, config, data hashes, training figures) to its
    sidecar under "rl", and the command ranges it was trained on (vx, vy, wz: low, high) under "commands", which
    bruce-run checks a command against (`runtime.policy.trained_commands`)."""
    model = DeployedPolicy(actor, standing, action_scale).eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    export_mlp_policy_onnx(model, path, obs_dim, len(standing))
    sidecar = sidecar_path(path)
    data = json.loads(sidecar.read_text())
    data["commands"] = {axis: list(span) for axis, span in commands.items()}
    data["rl"] = dict(record)
    sidecar.write_text(json.dumps(data, indent=2) + "\n")
    return path
