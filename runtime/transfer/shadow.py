"""The shadow (`--transfer shadow`): a PD towards the reference model's shadow of the simulator at the same tick,
its gains from the delay margin (`runtime.transfer.gains.pd_gains`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.config import PdGains
from bruce_hw.yaml_reader import Bound
from runtime.control.mixing import eq8_torque, eq9_torque
from runtime.transfer.gains import joint_inertia, pd_gains
from runtime.transfer.interface import TransferScheme
from runtime.transfer.reference_models import ReferenceModel
from runtime.transfer.registry import SchemeContext, register_scheme
from runtime.transfer.settings import setting


@dataclass(frozen=True)
class ShadowSettings:
    """transfer.shadow"""

    resync_ticks: int = setting(10, Bound(1, 1000, "ticks", "shadow horizon: up to 1 s at 1 kHz", integer=True))


class ShadowScheme(TransferScheme):
    """The model rolls the shadow on from its own previous state under the simulator's own Eq. 8 torque on the same
    a_t, resynchronised to the measured state every `transfer.shadow.resync_ticks`."""

    name = "shadow"

    def __init__(self, reference: ReferenceModel, gains: PdGains, eq8: PdGains, resync_ticks: int):
        super().__init__(reference)
        self.gains, self.eq8, self.resync_ticks = gains, eq8, resync_ticks
        self._tick = 0
        self._next: tuple[np.ndarray, np.ndarray] | None = None  # the shadow's state at the coming tick

    def reset(self) -> None:
        super().reset()
        self._tick = 0
        self._next = None

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        resync = self._next is None or self._tick % self.resync_ticks == 0
        self._tick += 1
        if resync:
            self.q_hat, self.qd_hat = q.copy(), qd.copy()
            tau_shadow = tau_star
        else:
            self.q_hat, self.qd_hat = self._next
            tau_shadow = eq8_torque(a, self.q_hat, self.qd_hat, self.eq8)  # the simulator's own Eq. 8 torque
        self._next = self.reference.step(self.q_hat, self.qd_hat, tau_shadow)
        self.one_step = self._next if resync else None

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return eq9_torque(tau_star, self.q_hat, self.qd_hat, q, qd, self.gains)  # same PD form, margin-derived gains


def build_shadow(context: SchemeContext) -> ShadowScheme:
    transfer, reference = context.transfer, context.reference()
    gains = pd_gains(joint_inertia(context.config), transfer.delay_margin_s, transfer.phase_margin_deg)
    return ShadowScheme(reference, gains, context.config.eq8, context.settings.resync_ticks)


register_scheme("shadow", ShadowSettings, build_shadow, uses_reference=True,
                help="a PD towards the reference model's shadow of the simulator")
