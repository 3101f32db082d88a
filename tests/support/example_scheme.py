"""A transfer scheme added the way docs/extending.md ("Adding a transfer scheme") says: this one file (its settings,
the scheme, its builder) and nothing else but the registration call at the end. `offset` sends tau* plus a constant
share of each joint's torque limit (`transfer.offset.share`), and counts its ticks, so a test sees a run used it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.yaml_reader import Bound
from runtime.transfer.interface import TransferScheme
from runtime.transfer.registry import SchemeContext, register_scheme
from runtime.transfer.settings import setting


@dataclass(frozen=True)
class OffsetSettings:
    """transfer.offset"""

    share: float = setting(0.0, Bound(-0.05, 0.05, "", "share of joints.torque_limits added to tau*"))


class OffsetScheme(TransferScheme):
    name = "offset"

    def __init__(self, offset: np.ndarray):
        super().__init__()  # no reference model: nothing to predict
        self.offset = offset
        self.ticks = 0

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.ticks += 1

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return tau_star + self.offset

    def report(self) -> dict:  # lands in the run's summary and its stats JSON
        return {"offset": {"ticks": self.ticks, "torque": self.offset.tolist()}}


def build_offset(context: SchemeContext) -> OffsetScheme:
    return OffsetScheme(context.settings.share * context.config.tau_limit)


register_scheme("offset", OffsetSettings, build_offset, help="tau* plus a constant share of the torque limits")
