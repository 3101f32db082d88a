"""The shadow (`--transfer shadow`): a PD towards the reference model's shadow of the simulator at the same tick,
its gains from the delay margin (`runtime.transfer.gains.pd_gains`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.config import PdGains
from bruce_hw.yaml_reader import Bound
from runtime.control.inference import ModelError
from runtime.control.mixing import eq8_torque, eq9_torque
from runtime.transfer.gains import joint_inertia, pd_gains
from runtime.transfer.interface import TransferScheme
from runtime.transfer.reference_models import ReferenceModel
from runtime.transfer.registry import SchemeContext, register_scheme
from runtime.transfer.settings import setting
from runtime.transfer.shadow_stepper import InlineShadowStepper, make_shadow_stepper


@dataclass(frozen=True)
class ShadowSettings:
    """transfer.shadow"""

    resync_ticks: int = setting(10, Bound(1, 1000, "ticks", "shadow horizon: up to 1 s at 1 kHz", integer=True))


class ShadowScheme(TransferScheme):
    """The model rolls the shadow on from its own previous state under the simulator's own Eq. 8 torque on the same
    a_t, resynchronised to the measured state every `transfer.shadow.resync_ticks`. Its step at a tick gives the
    shadow at the next one: `stepper` runs it on the tick, or beside the loop (`shadow_stepper`); a step not back in
    time is a resync."""

    name = "shadow"

    def __init__(self, reference: ReferenceModel, gains: PdGains, eq8: PdGains, resync_ticks: int,
                 stepper: InlineShadowStepper | None = None):
        super().__init__(reference)
        self.gains, self.eq8, self.resync_ticks = gains, eq8, resync_ticks
        self.stepper = stepper if stepper is not None else InlineShadowStepper(reference)
        self._tick = 0
        self._resynced = False  # the last tick started from the measured state: its step is a one-step prediction

    @property
    def one_step(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The step made from the measured state at the last tick, if it resynced (read at the next tick). An error
        in it is raised by `predict`, where the loop ends the run on it."""
        if not self._resynced:
            return None
        try:
            return self.stepper.answer(self._tick - 1)
        except ModelError:
            return None

    def reset(self) -> None:
        self.stepper.reset()  # idle before the model is reset
        super().reset()
        self._tick = 0
        self._resynced = False
        self.stepper.start()  # before the loop: a thread's first start costs the tick that makes it

    def close(self) -> None:
        self.stepper.close()

    def report(self) -> dict:
        return {"shadow": self.stepper.report()}

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        tick = self._tick
        self._tick += 1
        shadow = self.stepper.answer(tick - 1) if tick else None  # the shadow at this tick, stepped at the last
        resync = shadow is None or tick % self.resync_ticks == 0
        if resync:
            self.q_hat, self.qd_hat = q.copy(), qd.copy()
            tau_shadow = tau_star
        else:
            self.q_hat, self.qd_hat = shadow
            tau_shadow = eq8_torque(a, self.q_hat, self.qd_hat, self.eq8)  # the simulator's own Eq. 8 torque
        self._resynced = resync
        self.stepper.ask(tick, self.q_hat, self.qd_hat, tau_shadow)

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return eq9_torque(tau_star, self.q_hat, self.qd_hat, q, qd, self.gains)  # same PD form, margin-derived gains


def build_shadow(context: SchemeContext) -> ShadowScheme:
    transfer, reference = context.transfer, context.reference()
    gains = pd_gains(joint_inertia(context.config), transfer.delay_margin_s, transfer.phase_margin_deg)
    return ShadowScheme(reference, gains, context.config.eq8, context.settings.resync_ticks,
                        make_shadow_stepper(reference, context.paced))


register_scheme("shadow", ShadowSettings, build_shadow, uses_reference=True,
                help="a PD towards the reference model's shadow of the simulator")
