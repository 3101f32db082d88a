"""The trained actor as the runtime's policy file: obs [1, obs_dim] -> action [1, n_joints].

rsl-rl's deterministic actor (its observation normaliser, the MLP, the Gaussian's mean) is followed by the
environment's action map a = q_stand + action_scale * output, then by the inverse of the policy spec's action map
(none for Table I, whose action is the targets), so `bruce-run --policy FILE` gets the trained targets back through
the spec. The sidecar records the spec (`policy_spec`, inline: bruce-run runs the policy with it) and how to make
the file again.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import nn

from runtime.control.policy_spec import PolicySpec
from training.onnx_export import export_mlp_policy_onnx, sidecar_path


class DeployedPolicy(nn.Module):
    """obs -> PD targets: the actor's mean action mapped about the standing pose; with a `spec` whose action is not
    the targets in the config's joint order, the output its action map turns into those targets."""

    def __init__(self, actor: nn.Module, standing: np.ndarray, action_scale: float, spec: PolicySpec | None = None):
        super().__init__()
        self.actor = actor.as_jit()  # a copy: normaliser -> MLP -> mean, taking one tensor
        self.register_buffer("standing", torch.as_tensor(standing, dtype=torch.float32).reshape(1, -1))
        self.action_scale = float(action_scale)
        self.spec_map = spec is not None and not _targets_in_config_order(spec)
        if self.spec_map:
            action = spec.action
            self.register_buffer("spec_order", torch.as_tensor(spec.order, dtype=torch.long))
            self.register_buffer("spec_offset", torch.as_tensor(action.offset, dtype=torch.float32).reshape(1, -1))
            inverse = np.divide(1.0, action.scale, out=np.zeros(len(action.scale)), where=action.scale != 0.0)
            self.register_buffer("spec_inverse_scale", torch.as_tensor(inverse, dtype=torch.float32).reshape(1, -1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        targets = self.standing + self.action_scale * self.actor(obs)
        if not self.spec_map:
            return targets
        return (targets[:, self.spec_order] - self.spec_offset) * self.spec_inverse_scale


def _targets_in_config_order(spec: PolicySpec) -> bool:
    """Whether the spec's action is the joint targets in the config's order (Table I's)."""
    action = spec.action
    return (np.array_equal(spec.order, np.arange(len(spec.order))) and not np.any(action.offset)
            and bool(np.all(action.scale == 1.0)))


def export_policy(actor: nn.Module, path: str | Path, obs_dim: int, standing: np.ndarray, action_scale: float,
                  record: Mapping[str, object], commands: Mapping[str, tuple[float, float]],
                  spec: PolicySpec | None = None, spec_tree: Mapping | None = None) -> Path:
    """Write the ONNX policy and add `record` (command, seed, config, data hashes, training figures) to its
    sidecar under "rl", the command ranges it was trained on (vx, vy, wz: low, high) under "commands", which
    bruce-run checks a command against (`runtime.control.policy_spec.trained_commands`), and `spec_tree` (the spec
    file's YAML tree, of `spec`, the spec it was trained on) under "policy_spec"."""
    model = DeployedPolicy(actor, standing, action_scale, spec).eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = {} if spec is None else {"input_name": spec.input_name, "output_name": spec.output_name}
    export_mlp_policy_onnx(model, path, obs_dim, len(standing), **names)
    sidecar = sidecar_path(path)
    data = json.loads(sidecar.read_text())
    data["commands"] = {axis: list(span) for axis, span in commands.items()}
    if spec_tree is not None:
        data["policy_spec"] = dict(spec_tree)
    data["rl"] = dict(record)
    sidecar.write_text(json.dumps(data, indent=2) + "\n")
    return path
