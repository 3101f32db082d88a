"""Reference models for the transfer stage: what the simulator would do next from a given joint state and torque.

A reference model maps (q, qd, tau) at tick t to the simulator's (q, qd) at tick t + 1 (`step`). Two kinds:

- `PinnReference`: the committed ONNX PINN (`runtime.control.inference.OnnxPinn`), its LSTM state carried from call to
  call, as the paper runs it;
- `NominalReference`: the nominal MuJoCo model itself, its state set to the given joint state and a base state
  (from the robot's estimate in a robot-faithful run, `place_from_estimate`; from the simulator's truth in a
  truth-fed one), stepped once under the torque; a shadow that feeds it its own last output rolls the whole model
  on, base included. It is the *perfect-model control*: any scheme run on it shows what that scheme gives when its
  model is the simulator exactly, so a gain that the PINN version has and this one lacks comes from the PINN's
  errors, not from modelling the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.quaternion import euler_of, roll_pitch_quaternion, rotation_entries
from bruce_hw.robot_model import BruceModel
from bruce_hw.types import GroundTruth
from runtime.control.inference import ModelError, OnnxPinn
from runtime.estimation import BaseEstimate
from runtime.estimation.kinematic import FEET

REFERENCE_MODELS = ("pinn", "nominal")  # transfer.reference_model: the kinds `build_reference` makes


class ReferenceModel(Protocol):
    name: str
    pinn: OnnxPinn | None  # the ONNX PINN it steps, checked on the measured pose before the motors are enabled
    self_contained: bool   # its step reads nothing but its arguments: it may step on another thread

    def reset(self) -> None: ...

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def nominal_model(config: RobotConfig) -> tuple[BruceModel, mujoco.MjData]:
    """The simulator's model without a reality gap (`BruceModel`: it checks the MJCF and finds the joints, motors and
    sensors) and a state of it standing on the floor, as the mock starts: what a reference or the twin sets to the
    robot's state and steps."""
    robot = BruceModel(config)
    data = robot.new_data()
    robot.place_standing(data)
    return robot, data


def nominal_model_on_truth(config: RobotConfig, base_state: Callable[[], GroundTruth | None],
                           refusal: str) -> tuple[BruceModel, mujoco.MjData]:
    """`nominal_model`, for a user of the simulator's state: ModelError with `refusal` where there is none to start
    from (any backend but the mock, or a robot-faithful run)."""
    if base_state() is None:
        raise ModelError(refusal)
    return nominal_model(config)


def foot_spheres(model: mujoco.MjModel) -> list[tuple[int, float]]:
    """(geom id, radius) of every toe and heel sphere: what the robot stands on."""
    return [(model.geom(name).id, float(model.geom(name).size[0])) for foot in FEET for name in foot]


def lowest_point(data: mujoco.MjData, spheres: list[tuple[int, float]]) -> float:
    """Height of the lowest point of any of `spheres` (negative: in the floor); needs the model's kinematics."""
    xpos = data.geom_xpos
    return min(float(xpos[geom][2]) - radius for geom, radius in spheres)


def place_from_estimate(robot: BruceModel, data: mujoco.MjData, estimate: BaseEstimate, q: np.ndarray,
                        qd: np.ndarray, spheres: list[tuple[int, float]], own: BaseEstimate | None = None) -> None:
    """Put the nominal model at what a robot knows of itself: the joints as measured; roll, pitch and the base's
    angular and linear velocity (body frame) from the robot's estimate; yaw and planar position stay the model's own
    (nothing on the robot observes them), and the height is set so that the lowest toe or heel (`spheres`, from
    `foot_spheres`) keeps the model's own contact depth: the new posture neither sinks a foot into the floor nor
    lifts the stance off it. Ends with mj_forward.

    `own`: the model's own estimator's estimate at this tick, from the model's own sensors (the twin runs one). Then
    the base is the model's own state moved by the difference of the two estimates (robot's minus own): what the
    two estimators share, above all their lag behind a walking gait's velocity swings, cancels, and where the
    robot is the model the base is left as it is."""
    depth = lowest_point(data, spheres)
    roll, pitch, _ = (float(v) for v in estimate.euler)
    angvel = np.asarray(estimate.angvel, dtype=float)
    linvel = np.asarray(estimate.linvel, dtype=float)
    true_roll, true_pitch, yaw = (float(v) for v in euler_of(data.qpos[3:7]))
    if own is not None:
        rotation = np.array(rotation_entries(data.qpos[3:7])).reshape(3, 3)
        roll += true_roll - float(own.euler[0])
        pitch += true_pitch - float(own.euler[1])
        angvel = angvel + data.qvel[3:6] - np.asarray(own.angvel, dtype=float)
        linvel = linvel + rotation.T @ data.qvel[0:3] - np.asarray(own.linvel, dtype=float)
    w, x, y, z = roll_pitch_quaternion(roll, pitch)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    quat = (cy * w - sy * z, cy * x - sy * y, cy * y + sy * x, cy * z + sy * w)  # q_z(yaw) q_y(pitch) q_x(roll)
    data.qpos[3:7] = quat
    data.qpos[robot.qpos], data.qvel[robot.dofs] = q, qd
    data.qvel[3:6] = angvel  # a free joint's angular velocity is in the body frame, as the estimate's
    data.qvel[0:3] = np.array(rotation_entries(quat)).reshape(3, 3) @ linvel
    mujoco.mj_kinematics(robot.model, data)
    data.qpos[2] += depth - lowest_point(data, spheres)
    mujoco.mj_forward(robot.model, data)


class PinnReference:
    """The ONNX PINN as a reference model (one call per `step`, the LSTM state carried)."""

    name = "pinn"
    self_contained = True

    def __init__(self, pinn: OnnxPinn):
        self.pinn = pinn

    def reset(self) -> None:
        self.pinn.reset()

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.pinn.step(q, qd, tau)


class NominalReference:
    """The nominal MuJoCo model stepped once from (base, q, qd) under tau, saturated as the mock's motors do. The
    base comes from `base_state`: the robot's estimate in a robot-faithful run (`place_from_estimate`), the
    simulator's truth in a truth-fed one."""

    name = "nominal"
    pinn = None
    self_contained = False  # a step from a state it did not give reads the robot's base state

    def __init__(self, config: RobotConfig, base_state: Callable[[], BaseEstimate | GroundTruth | None]):
        robot, self.data = nominal_model(config)
        self.robot, self.model = robot, robot.model
        # The model's own index slices of the config's joints in qpos, qvel and ctrl (checked contiguous there).
        self._qpos, self._dofs, self._acts = robot.qpos, robot.dofs, robot.acts
        self._spheres = foot_spheres(self.model)
        self._coupling = config.coupling
        self._torque_limit = config.actuator_torque_limit
        self._base_state = base_state
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # what step returned last, to recognise a rollout

    def reset(self) -> None:
        self.robot.place_standing(self.data)  # on the floor, as the robot starts: its contact depth is kept
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
                raise ModelError("nominal reference model: no base state (the simulator's truth is gone)")
            if isinstance(base, GroundTruth):
                self.robot.set_truth(data, base, q, qd)
            else:
                place_from_estimate(self.robot, data, base, q, qd, self._spheres)
        data.ctrl[self._acts] = self._coupling.saturate(tau, self._torque_limit)
        mujoco.mj_step(self.model, data)
        self._last = (data.qpos[self._qpos].copy(), data.qvel[self._dofs].copy())
        return self._last


def build_reference(config: RobotConfig, kind: str, pinn_path: Path | None,
                    base_state: Callable[[], BaseEstimate | GroundTruth | None], lookahead: int = 0,
                    scheme: str = "pinn") -> ReferenceModel:
    """The reference model `kind` (REFERENCE_MODELS): the PINN at `pinn_path` (default: pinn.model of the config;
    `lookahead` ticks rolled further, for Eq. 9's look-ahead variant), or the nominal MuJoCo model on `base_state`
    (the robot's base estimate, or in a truth-fed run the backend's ground truth). `scheme` names the transfer
    scheme that asked, in errors."""
    if kind == "nominal":
        return NominalReference(config, base_state)
    if kind != "pinn":
        raise ValueError(f"transfer.reference_model: expected one of {', '.join(REFERENCE_MODELS)}, got {kind!r}")
    path = pinn_path or config.models.pinn
    if path is None:
        raise ModelError(f"--transfer {scheme} needs a PINN model: pass --pinn PATH or set pinn.model in "
                         f"{config.path} (or transfer.reference_model: nominal)")
    pinn = OnnxPinn(path, config.n_joints, lookahead=lookahead)
    pinn.warmup()
    return PinnReference(pinn)
