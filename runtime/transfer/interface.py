"""The interface of every transfer scheme: the stage of the tick after Eq. 8 (tau*), before safety
(docs/transfer.md, "The schemes").

A scheme gets the policy's targets a_t, the measured joint state and tau*, asks its reference model (a
`reference_models.ReferenceModel`: the PINN, or the nominal MuJoCo model as the perfect-model control) what the
simulator would do (`predict`: the model work, timed as the loop's `pinn` section) and returns the torque to send
(`torque`: the mixing). `one_step` is the model's prediction of the next tick's (q, qd) from this tick's measured
state (None when the scheme made none this tick): the gap monitor's input (`runtime.transfer.gap_monitor`). The
defaults are direct transfer: tau* unchanged (runtime/transfer/direct.py registers it).
"""

from __future__ import annotations

import numpy as np

from runtime.transfer.reference_models import ReferenceModel


class TransferScheme:
    """Direct transfer (tau* unchanged), and the interface of every scheme."""

    name = "direct"

    def __init__(self, reference: ReferenceModel | None = None):
        self.reference = reference
        self.q_hat: np.ndarray | None = None   # the reference state shown beside the measured one (telemetry)
        self.qd_hat: np.ndarray | None = None
        self._prediction: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def one_step(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The model's prediction of this tick's (q, qd), made at the last tick from its measured state (None: none);
        read by the loop before `predict` (a scheme whose step runs beside the loop takes it then)."""
        return self._prediction

    @one_step.setter
    def one_step(self, value: tuple[np.ndarray, np.ndarray] | None) -> None:
        self._prediction = value

    def reset(self) -> None:
        self.q_hat = self.qd_hat = None
        self._prediction = None
        if self.reference is not None:
            self.reference.reset()

    def predict(self, a: np.ndarray, q: np.ndarray, qd: np.ndarray, tau_star: np.ndarray,
                command: np.ndarray | None = None) -> None:
        """The model work of this tick (none for direct transfer); `command` is the (vx, vy, yaw rate) in force."""

    def torque(self, tau_star: np.ndarray, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        return tau_star

    def steer(self, command: np.ndarray) -> np.ndarray:
        """The velocity command the robot's controller gets on this policy tick, from the one in force (only the
        twin's command correction changes it)."""
        return command

    def close(self) -> None:
        """Release what the scheme started (the twin's thread); called on every exit path of a run."""

    def report(self) -> dict:
        """The scheme's own figures for the run's summary (the twin's: resyncs, how far behind it ran)."""
        return {}
