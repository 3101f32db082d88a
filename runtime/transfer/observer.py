"""The residual observer (`--transfer observer`): tau* + u, u a slow clipped integrator of the one-step velocity
residual (model under tau* minus measured)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.yaml_reader import Bound
from runtime.transfer.gains import joint_inertia, observer_gain, shortest_observer_time_constant
from runtime.transfer.interface import TransferScheme
from runtime.transfer.reference_models import ReferenceModel
from runtime.transfer.registry import SchemeContext, register_scheme
from runtime.transfer.settings import Relation, bounds_of, setting


@dataclass(frozen=True)
class ObserverSettings:
    """transfer.observer"""

    time_constant_s: float = setting(0.2, Bound(0.005, 10.0, "s", "observer settling; at least the delay margin's"))
    clip: float = setting(0.25, Bound(0.0, 1.0, "", "share of joints.torque_limits", low_open=True))

    @classmethod
    def relations(cls, transfer, config) -> dict[str, Relation]:
        """The integrator keeps the stage's phase margin at its delay margin (runtime/transfer/gains.py)."""
        shortest = shortest_observer_time_constant(transfer.delay_margin_s, transfer.phase_margin_deg)
        bound = bounds_of(cls)["time_constant_s"].narrowed(
            "at least transfer.delay_margin_s / (pi/2 - transfer.phase_margin_deg)", low=shortest)
        return {"time_constant_s": Relation(bound, "transfer.delay_margin_s", transfer.delay_margin_s, "a margin")}


class ObserverScheme(TransferScheme):
    """Gain I / T (T = `transfer.observer.time_constant_s`), clipped to `transfer.observer.clip` x the torque limit.
    It settles where the robot under tau* + u moves as the model does under tau*: a disturbance observer whose
    nominal plant is the reference model. Held at zero during the safety stage's torque ramp (the robot then gets
    less than tau*); the model's own mean residual on the simulator (`pinn.residual_bias`) is taken off, since
    integrated, a model's bias becomes a posture offset on any robot."""

    name = "observer"

    def __init__(self, reference: ReferenceModel, gain: np.ndarray, clip: np.ndarray, hold_ticks: int = 0,
                 bias: np.ndarray | None = None):
        super().__init__(reference)
        self.gain, self.clip, self.hold_ticks = gain, clip, hold_ticks
        # The model's own mean residual on the simulator (predicted minus simulated qd): not a gap, so not integrated.
        self.bias = np.zeros_like(gain) if bias is None else bias
        self.u = np.zeros_like(gain)
        self._ticks = 0

    def reset(self) -> None:
        super().reset()
        self.u = np.zeros_like(self.gain)
        self._ticks = 0

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        if self.one_step is not None and self._ticks >= self.hold_ticks:
            residual = self.one_step[1] - qd - self.bias  # > 0: the robot is slower than the model: push more
            self.u = np.clip(self.u + self.gain * residual, -self.clip, self.clip)
        self._ticks += 1
        self.one_step = self.reference.step(q, qd, tau_star)
        self.q_hat, self.qd_hat = self.one_step

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return tau_star + self.u


def build_observer(context: SchemeContext) -> ObserverScheme:
    config, settings = context.config, context.settings
    reference = context.reference()
    bias = config.models.pinn_residual_bias if context.transfer.reference_model == "pinn" else None
    return ObserverScheme(reference, observer_gain(joint_inertia(config), settings.time_constant_s),
                          settings.clip * config.tau_limit,
                          hold_ticks=round(config.safety.torque_ramp_s * config.loop_hz), bias=bias)


register_scheme("observer", ObserverSettings, build_observer, uses_reference=True,
                help="a slow integrator of the reference model's one-step residual")
