"""Setting a model's normalisation buffers from statistics: checked, copied, all or nothing."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import nn

OptionalArray = np.ndarray | torch.Tensor | Sequence[float] | float | None


def register_input_statistics(module: nn.Module, n_joints: int) -> None:
    """Buffers q_mean, q_std, qd_mean, qd_std, tau_mean, tau_std ([n_joints], identity until fitted)."""
    for name in ("q", "qd", "tau"):
        module.register_buffer(f"{name}_mean", torch.zeros(n_joints))
        module.register_buffer(f"{name}_std", torch.ones(n_joints))


def set_statistic_buffers(module: nn.Module, given: Mapping[str, OptionalArray], where: str) -> None:
    """Copy each non-None value of `given` into `module`'s buffer of the same name.

    Each must match the buffer's shape and be finite; names ending in `_mean` may take any sign, all others (stds,
    scales) must be > 0. Values are copied (datasets hand out read-only arrays) into buffers, so they travel with
    state_dict and the ONNX export. All or nothing: a bad value leaves every buffer as it was. `where` names the
    caller in messages, e.g. "PinnStep.set_normalisation"."""
    checked = {}
    for name, value in given.items():
        if value is None:
            continue
        tensor = (value.detach().to(torch.float64) if isinstance(value, torch.Tensor)
                  else torch.tensor(np.array(value, dtype=np.float64)))
        buffer = getattr(module, name)
        if tensor.shape != buffer.shape:
            raise ValueError(f"{where}: {name} must have shape {tuple(buffer.shape)}, got {tuple(tensor.shape)}")
        if not torch.isfinite(tensor).all():
            raise ValueError(f"{where}: {name} has non-finite entries")
        if not name.endswith("_mean") and not (tensor > 0).all():
            raise ValueError(f"{where}: {name} must be > 0 everywhere, got {tensor.tolist()}")
        checked[name] = tensor
    with torch.no_grad():
        for name, tensor in checked.items():
            getattr(module, name).copy_(tensor.to(getattr(module, name).dtype))
