"""The live gap monitor: how far the robot's next tick lands from where the reference model said it would.

Per joint and tick, the one-step residual is the measured qd minus the qd the model predicted one tick earlier from
the measured state under tau* (the same for q); on the simulator itself it is the model's own error, on the robot
that plus the reality gap. The monitor keeps a short-window RMS of the velocity residual (what a lab watches while the
robot walks), the whole run's RMS of both (the stats JSON's `gap_residual_rms` and `gap_residual_rms_q`, per joint)
and the mean velocity residual (`gap_residual_mean`: on the simulator itself, the model's bias, `pinn.residual_bias`),
and logs one warning line when a joint's window RMS crosses `transfer.gap_monitor.warn_rms` (again only after it
has fallen below half of it): a gap that large is worth a look, never a fault.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from bruce_hw.yaml_reader import Bound
from runtime.transfer.settings import Relation, bounds_of, setting

log = logging.getLogger("runtime.transfer.gap_monitor")


@dataclass(frozen=True)
class GapMonitorSettings:
    """transfer.gap_monitor"""

    window_s: float = setting(0.1, Bound(0.005, 10.0, "s", "RMS window of the one-step residual"))
    warn_rms: float = setting(2.0, Bound(0.0, 100.0, "rad/s", "window RMS that logs a warning", low_open=True))

    @classmethod
    def relations(cls, transfer, config) -> dict[str, Relation]:
        bound = bounds_of(cls)["window_s"].narrowed("at least 5 ticks of rates.loop_hz", low=5.0 / config.loop_hz)
        return {"window_s": Relation(bound, "rates.loop_hz", config.loop_hz)}


@dataclass
class GapResidual:
    """One tick's residual, measured minus predicted, per joint."""

    q: np.ndarray
    qd: np.ndarray


@dataclass
class GapMonitor:
    joints: tuple[str, ...]
    window_ticks: int
    warn_rms: float                     # rad/s, on the window RMS of the velocity residual
    samples: int = 0
    last: GapResidual | None = None
    warnings: int = 0
    _ring: np.ndarray = field(init=False, repr=False)
    _ring_sum: np.ndarray = field(init=False, repr=False)
    _sum_qd: np.ndarray = field(init=False, repr=False)
    _sum_q: np.ndarray = field(init=False, repr=False)
    _sum_signed_qd: np.ndarray = field(init=False, repr=False)
    _warned: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n = len(self.joints)
        self._ring = np.zeros((self.window_ticks, n))   # squared velocity residuals of the last window
        self._ring_sum = np.zeros(n)
        self._sum_qd, self._sum_q, self._sum_signed_qd = np.zeros(n), np.zeros(n), np.zeros(n)
        self._warned = np.zeros(n, dtype=bool)

    def update(self, predicted: tuple[np.ndarray, np.ndarray] | None, q: np.ndarray,
               qd: np.ndarray) -> GapResidual | None:
        """Score the prediction made a tick ago (None: none was made) against this tick's measured state."""
        if predicted is None:
            return None
        residual = GapResidual(q=q - predicted[0], qd=qd - predicted[1])
        squared = residual.qd * residual.qd
        slot = self.samples % self.window_ticks
        self._ring_sum += squared - self._ring[slot]
        self._ring[slot] = squared
        self._sum_qd += squared
        self._sum_q += residual.q * residual.q
        self._sum_signed_qd += residual.qd
        self.samples += 1
        self.last = residual
        if self.samples >= self.window_ticks:
            self._warn(self.window_rms)
        return residual

    @property
    def window_rms(self) -> np.ndarray:
        """RMS of the velocity residual over the last window (fewer ticks before it has filled)."""
        filled = min(self.samples, self.window_ticks)
        return np.sqrt(np.maximum(self._ring_sum, 0.0) / max(filled, 1))

    def _warn(self, rms: np.ndarray) -> None:
        crossed = (rms > self.warn_rms) & ~self._warned
        self._warned |= crossed
        self._warned &= ~(rms < 0.5 * self.warn_rms)
        for i in np.flatnonzero(crossed):
            self.warnings += 1
            log.warning("gap: %s one-step velocity residual %.3g rad/s RMS over the last %d ticks (warning above "
                        "%.3g: the robot is not doing what the model predicts)", self.joints[i], rms[i],
                        self.window_ticks, self.warn_rms)

    def to_json(self) -> dict:
        if not self.samples:
            return {"gap_residual_rms": None, "gap_residual_rms_q": None, "gap_residual_mean": None, "gap_samples": 0}
        rms_qd = np.sqrt(self._sum_qd / self.samples)
        rms_q = np.sqrt(self._sum_q / self.samples)
        return {"gap_residual_rms": dict(zip(self.joints, rms_qd.tolist(), strict=True)),
                "gap_residual_rms_q": dict(zip(self.joints, rms_q.tolist(), strict=True)),
                "gap_residual_mean": dict(zip(self.joints, (self._sum_signed_qd / self.samples).tolist(), strict=True)),
                "gap_samples": self.samples, "gap_warnings": self.warnings}
