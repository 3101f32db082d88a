"""Gains of the transfer schemes, derived from a stated delay margin instead of chosen by hand (docs/transfer.md,
"Gains from a stated delay margin"; the sweep behind the margin: docs/results/transfer_schemes.md).

Each joint is an inertia I (`joint_inertia`); the loop around a scheme's feedback has a pure delay D
(`transfer.delay_margin_s`) and must keep a phase margin phi (`transfer.phase_margin_deg`) at crossover.
`pd_gains`: the shadow's PD on 1 / (I s^2) with its zero at a third of the crossover, wc = (atan(3) - phi) / D,
Kd = I wc, Kp = I wc^2 / 3. `shortest_observer_time_constant` / `observer_gain`: the residual observer's loop
u' = -(u + d) / T with gain k = I / T, margin pi/2 - D / T, so T >= D / (pi/2 - phi).
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from bruce_hw.config import PdGains, RobotConfig
from bruce_hw.robot_model import BruceModel

PD_ZERO_RATIO = 3.0  # Kp = Kd wc / PD_ZERO_RATIO: the PD's zero this many times below the crossover


def joint_inertia(config: RobotConfig) -> np.ndarray:
    """Per joint, the smallest inertia it shows (kg·m²): 1 / (M^-1)_jj of the nominal model at the standing pose,
    base free, no contact."""
    key = (Path(config.mjcf), config.joints)
    if key not in _INERTIA:
        _INERTIA[key] = _smallest_inertia(config)
    return _INERTIA[key]


_INERTIA: dict[tuple[Path, tuple[str, ...]], np.ndarray] = {}  # per model file: loading it costs ~50 ms


def _smallest_inertia(config: RobotConfig) -> np.ndarray:
    robot = BruceModel(config)  # knows the joints' dof addresses and places the standing pose
    model, data = robot.model, robot.new_data()
    robot.place_standing(data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    inverse = np.linalg.inv(mass)
    dofs = robot.dofs
    inertia = 1.0 / np.diag(inverse)[dofs]
    inertia.setflags(write=False)
    return inertia


def pd_crossover(delay_s: float, phase_margin_deg: float) -> float:
    """The PD crossover (rad/s) that leaves `phase_margin_deg` at a loop delay of `delay_s`."""
    wc = (math.atan(PD_ZERO_RATIO) - math.radians(phase_margin_deg)) / delay_s
    if not wc > 0:
        raise ValueError(f"transfer.phase_margin_deg: {phase_margin_deg:g} deg is more than a PD's "
                         f"{math.degrees(math.atan(PD_ZERO_RATIO)):.1f} deg of phase lead")
    return wc


def pd_gains(inertia: np.ndarray, delay_s: float, phase_margin_deg: float) -> PdGains:
    """Kp, Kd per joint for a PD towards a reference: Kd = I wc, Kp = Kd wc / PD_ZERO_RATIO."""
    wc = pd_crossover(delay_s, phase_margin_deg)
    kd = inertia * wc
    return PdGains(kp=kd * wc / PD_ZERO_RATIO, kd=kd)


def shortest_observer_time_constant(delay_s: float, phase_margin_deg: float) -> float:
    """The fastest residual observer (s) that keeps `phase_margin_deg` at a loop delay of `delay_s`."""
    return delay_s / (math.pi / 2 - math.radians(phase_margin_deg))


def observer_gain(inertia: np.ndarray, time_constant_s: float) -> np.ndarray:
    """k per joint (N·m per rad/s of residual, each tick): the observer's torque settles with `time_constant_s`."""
    return inertia / time_constant_s
