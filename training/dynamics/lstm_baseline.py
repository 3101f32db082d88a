"""The pure-LSTM baseline (issue #5): the PINN's LSTM without the physics, predicting the state increments.

    (dq, dqd) = head(LSTM([q, qd, tau]))     normalised inputs, 3 layers x 72 units like the PINN's LSTM
    q' = q + dq,   qd' = qd + dqd           no M^-1, no Euler step: the increments are learnt outright

Same interface, size and training as `training.dynamics.pinn.PinnStep` (one tick for [B, n] inputs, a
teacher-forced window for [W, B, n]; LSTM state explicit; exported with the PINN's tensor names, so
`runtime.control.inference.OnnxPinn` runs it too). The head's outputs are scaled to the increments' training spread: dqd
by the spread of qd' - qd, and dq by qd_std * dt (q' - q is mostly qd dt at 1 kHz). Parameters: 115,508 at the
paper's sizes vs the PINN's 123,055.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from training.dynamics.normalisation import set_statistic_buffers

if TYPE_CHECKING:
    from training.dataset import DatasetStats


@dataclass(frozen=True)
class LstmConfig:
    n_joints: int = 10
    dt: float = 1e-3
    lstm_hidden: int = 72
    lstm_layers: int = 3

    def __post_init__(self) -> None:
        for name in ("n_joints", "lstm_hidden", "lstm_layers"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"LstmConfig.{name}: expected an integer > 0, got {value!r}")
        if not self.dt > 0:
            raise ValueError(f"LstmConfig.dt: expected a time step > 0 s, got {self.dt!r}")


class LstmStep(nn.Module):
    """One tick: (q, qd, tau [B, n], h, c [layers, B, hidden]) -> (q', qd', h', c')."""

    def __init__(self, config: LstmConfig | None = None):
        super().__init__()
        self.config = config = config or LstmConfig()
        n = config.n_joints
        self.n_joints = n
        self.dt = config.dt
        self.register_buffer("input_mean", torch.zeros(3 * n))
        self.register_buffer("input_std", torch.ones(3 * n))
        self.register_buffer("increment_scale", torch.ones(2 * n))  # [dq, dqd]
        self.lstm = nn.LSTM(input_size=3 * n, hidden_size=config.lstm_hidden, num_layers=config.lstm_layers)
        self.head = nn.Linear(config.lstm_hidden, 2 * n)
        nn.init.zeros_(self.head.weight)  # an untrained model predicts "no change", like the PINN's zero head
        nn.init.zeros_(self.head.bias)
        self.is_folded = False

    def fit_normalisation(self, stats: DatasetStats) -> None:
        set_statistic_buffers(self, {"input_mean": np.concatenate([stats.q_mean, stats.qd_mean, stats.tau_mean]),
                                     "input_std": np.concatenate([stats.q_std, stats.qd_std, stats.tau_std]),
                                     "increment_scale": np.concatenate([stats.qd_std * self.dt, stats.qd_inc_std])},
                              "LstmStep.fit_normalisation")

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        shape = (self.config.lstm_layers, batch, self.config.lstm_hidden)
        return self.input_mean.new_zeros(shape), self.input_mean.new_zeros(shape)

    def forward(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor, h: torch.Tensor, c: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        window = q.dim() == 3
        features = torch.cat([q, qd, tau], dim=-1)
        if not self.is_folded:
            features = (features - self.input_mean) / self.input_std
        lstm_out, (h_next, c_next) = self.lstm(features if window else features.unsqueeze(0), (h, c))
        head = self.head(lstm_out if window else h_next[-1])
        if not self.is_folded:
            head = head * self.increment_scale
        dq, dqd = head.split(self.n_joints, dim=-1)
        return q + dq, qd + dqd, h_next, c_next

    @torch.no_grad()
    def folded(self) -> LstmStep:
        """The export copy: input normalisation folded into the LSTM's input weights, the increment scales into
        the head (the same function, fewer graph nodes; see PinnStep.folded)."""
        out = copy.deepcopy(self).eval()
        if self.is_folded:
            return out
        weight_ih = out.lstm.weight_ih_l0.clone()
        out.lstm.weight_ih_l0.copy_(weight_ih / self.input_std)
        out.lstm.bias_ih_l0.sub_(weight_ih @ (self.input_mean / self.input_std))
        out.head.weight.mul_(self.increment_scale[:, None])
        out.head.bias.mul_(self.increment_scale)
        out.input_mean.zero_()
        out.input_std.fill_(1.0)
        out.increment_scale.fill_(1.0)
        out.is_folded = True
        return out
