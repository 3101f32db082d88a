"""The paper's Eq. 9 (`--transfer eq9`, and `pinn`, its older name): tau* + Kp' (q^' - q) + Kd' (qd^' - qd) on the
reference model's one-step (or look-ahead) prediction under tau*, gains `gains.eq9`. No settings of its own:
`pinn.lookahead_ticks` rolls the reference further ahead."""

from __future__ import annotations

import numpy as np

from bruce_hw.config import PdGains
from runtime.control.mixing import eq9_torque
from runtime.transfer.interface import TransferScheme
from runtime.transfer.reference_models import ReferenceModel
from runtime.transfer.registry import SchemeContext, register_scheme


class Eq9Scheme(TransferScheme):
    """Eq. 9's feedback is nearly nothing: q^' - q ~ qd dt whatever the gap, so it mostly adds Kp' qd dt +
    Kd' (qd^' - qd)."""

    name = "eq9"

    def __init__(self, reference: ReferenceModel, gains: PdGains, one_step: bool = True):
        super().__init__(reference)
        self.gains = gains
        self._one_step = one_step  # False: the model rolls ahead (pinn.lookahead_ticks), not a one-step prediction

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.q_hat, self.qd_hat = self.reference.step(q, qd, tau_star)
        self.one_step = (self.q_hat, self.qd_hat) if self._one_step else None

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return eq9_torque(tau_star, self.q_hat, self.qd_hat, q, qd, self.gains)


def build_eq9(context: SchemeContext) -> Eq9Scheme:
    lookahead = context.config.models.pinn_lookahead_ticks
    return Eq9Scheme(context.reference(lookahead), context.config.eq9, one_step=lookahead == 0)


# `--transfer pinn` has always meant the paper's Eq. 9
register_scheme("eq9", None, build_eq9, aliases=("pinn",), uses_reference=True,
                help="the paper's Eq. 9, tracking the reference model's prediction")
