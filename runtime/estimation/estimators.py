"""The base-state estimators by name (`--estimator`): the one place that knows every `runtime.estimation.Estimator`
(kept apart from the contract, which each estimator imports)."""

from __future__ import annotations

from bruce_hw.backend import Backend
from runtime.estimation import Estimator, GroundTruthEstimator
from runtime.estimation.kinematic import KinematicEstimator

ESTIMATORS = ("truth", "kinematic")


def make_estimator(kind: str, backend: Backend, config) -> Estimator:
    """`truth`: the simulator's ground truth (mock only); `kinematic`: IMU + leg kinematics + contacts."""
    if kind == "truth":
        return GroundTruthEstimator(backend)
    if kind == "kinematic":
        return KinematicEstimator(config)
    raise ValueError(f"unknown estimator {kind!r} (expected one of {', '.join(ESTIMATORS)})")
