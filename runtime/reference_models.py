"""Reference models for the transfer stage: what the simulator would do next from a given joint state and torque.

A reference model maps (q, qd, tau) at tick t to the simulator's (q, qd) at tick t + 1 (`step`). Two kinds:

- `PinnReference`: the committed ONNX PINN (`runtime.inference.OnnxPinn`), its LSTM state carried from call to
  call, as the paper runs it;
- `NominalReference`: the nominal MuJoCo model itself, its state set to the given joint state (and the base state
  from `base_state`, the simulator's truth in the rehearsal), stepped once under the torque; a shadow that feeds it
  its own last output rolls the whole model on, base included. It is the
  *perfect-model control*: any scheme run on it shows what that scheme gives when its model is the simulator
  exactly, so a gain that the PINN version has and this one lacks comes from the PINN's errors, not from
  modelling the simulator. It needs a base state, which only the mock has (`bruce_hw.mock` ground truth).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import mujoco
import numpy as np

from bruce_hw.config import REFERENCE_MODELS, RobotConfig
from bruce_hw.types import GroundTruth
from runtime.inference import ModelError, OnnxPinn


class ReferenceModel(Protocol):
    name: str

    def reset(self) -> None: ...

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def nominal_backend(config: RobotConfig, base_state: Callable[[], GroundTruth | None], refusal: str):
    """A configured nominal mock whose model a reference sets to the simulator's state and steps; ModelError with
    `refusal` where there is no simulator state to start from (any backend but the mock)."""
    from bruce_hw.mock import MujocoBackend  # its configure() finds the joints, motors and checks the MJCF

    if base_state() is None:
        raise ModelError(refusal)
    nominal = MujocoBackend(config)
    nominal.configure()
    return nominal


def set_state(data: mujoco.MjData, qpos: slice, dofs: slice, base: GroundTruth, q: np.ndarray,
              qd: np.ndarray) -> None:
    """Put the nominal model at the simulator's base state and the given joint state (`qpos`, `dofs`: the joints'
    slices in qpos and qvel)."""
    data.qpos[0:3], data.qpos[3:7] = base.base_pos, base.base_quat
    data.qvel[0:3], data.qvel[3:6] = base.base_linvel, base.base_angvel
    data.qpos[qpos], data.qvel[dofs] = q, qd


class PinnReference:
    """The ONNX PINN as a reference model (one call per `step`, the LSTM state carried)."""

    name = "pinn"

    def __init__(self, pinn: OnnxPinn):
        self.pinn = pinn

    def reset(self) -> None:
        self.pinn.reset()

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.pinn.step(q, qd, tau)


class NominalReference:
    """The nominal MuJoCo model stepped once from (base state, q, qd) under tau, saturated as the mock's motors do."""

    name = "nominal"

    def __init__(self, config: RobotConfig, base_state: Callable[[], GroundTruth | None]):
        nominal = nominal_backend(config, base_state, "transfer.reference_model nominal: the nominal MuJoCo model "
                                  "needs the simulator's base state, which only the mock backend has (it is the "
                                  "rehearsal's perfect-model control)")
        self.model, self.data = nominal.model, nominal.data
        # The backend's own index slices of the config's joints in qpos, qvel and ctrl (checked contiguous there).
        self._qpos, self._dofs, self._acts = nominal._qpos, nominal._dofs, nominal._acts
        self._coupling = config.coupling
        self._torque_limit = config.actuator_torque_limit
        self._base_state = base_state
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # what step returned last, to recognise a rollout

    def reset(self) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self._last = None

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One tick from (q, qd). Given back the very arrays it returned last, unchanged (a shadow rolling on), the
        whole model rolls on, base included, as the simulator would; any other state starts from the base state read
        now."""
        data = self.data
        rolling = self._last is not None and q is self._last[0] and qd is self._last[1]
        if not rolling:
            base = self._base_state()
            if base is None:
                raise ModelError("nominal reference model: needs the simulator's base state (mock backend only)")
            set_state(data, self._qpos, self._dofs, base, q, qd)
        data.ctrl[self._acts] = self._coupling.saturate(tau, self._torque_limit)
        mujoco.mj_step(self.model, data)
        self._last = (data.qpos[self._qpos].copy(), data.qvel[self._dofs].copy())
        return self._last


def build_reference(config: RobotConfig, kind: str, pinn_path: Path | None,
                    base_state: Callable[[], GroundTruth | None], lookahead: int = 0,
                    scheme: str = "pinn") -> ReferenceModel:
    """The reference model `kind` (REFERENCE_MODELS): the PINN at `pinn_path` (default: pinn.model of the config;
    `lookahead` ticks rolled further, for Eq. 9's look-ahead variant), or the nominal MuJoCo model on `base_state`
    (the backend's ground truth). `scheme` names the transfer scheme that asked, in errors."""
    if kind == "nominal":
        return NominalReference(config, base_state)
    if kind != "pinn":
        raise ValueError(f"transfer.reference_model: expected one of {', '.join(REFERENCE_MODELS)}, got {kind!r}")
    path = pinn_path or config.models.pinn
    if path is None:
        raise ModelError(f"--transfer {scheme} needs a PINN model: pass --pinn PATH or set pinn.model in "
                         f"{config.path} (or transfer.reference_model: nominal on the mock)")
    pinn = OnnxPinn(path, config.n_joints, lookahead=lookahead)
    pinn.warmup()
    return PinnReference(pinn)
