"""Gains of the transfer schemes, derived from a stated delay margin instead of chosen by hand.

Each joint is treated as an inertia I (the smallest it shows: 1 / (M^-1)_jj of the nominal MJCF at the standing
pose with the base free and no contact; contact and a moving body only make it larger, which lowers every
crossover below, so the margins only grow). The loop around a scheme's feedback has a pure delay D (the state is
read late, the torque acts late: `transfer.delay_margin_s`, stated with the robot), and we ask that a phase margin
phi (`transfer.phase_margin_deg`) is left at crossover when the delay is D.

PD towards a reference (shadow scheme), plant 1 / (I s^2), controller Kp + Kd s with its zero at a third of the
crossover (Kp = Kd wc / 3, which gives the controller atan(3) = 71.6 deg of phase lead at wc):

    phase margin = atan(3) - wc D   =>   wc = (atan(3) - phi) / D,   Kd = I wc,   Kp = I wc^2 / 3.

Residual observer (an integrator of the one-step velocity residual r = qd_predicted - qd_measured, u += k r each
tick): the residual responds to the observer's own torque as -dt / I, so the loop is u' = -(u + d) / T with
k = I / T, a crossover at 1 / T and a phase margin of pi/2 - D / T:

    T >= D / (pi/2 - phi)   (the shortest time constant the margin allows),   k = I / T  (N·m per rad/s, per tick).

For BRUCE (I = 0.0046, 0.0120, 0.0113, 0.0041, 0.0018 kg·m² for hip yaw, hip pitch, hip roll, knee, ankle), the
shipped D = 9 ms and phi = 45 deg: wc = 51.5 rad/s, Kd = 0.24, 0.62, 0.58, 0.21, 0.094 N·m·s/rad and Kp = 4.1,
10.6, 10.0, 3.6, 1.6 N·m/rad. The paper's Eq. 9 gains (Kp' = 60, Kd' = 2; ankle 10, 1) sit 3-16x above: their
crossover (~Kd' / I, 430-560 rad/s) leaves no phase beyond ~3 ms of loop delay. The PD above loses its last degree
of margin at D = atan(3) / wc = 24 ms. The observer may not be faster than T = 11.5 ms; the shipped 200 ms stays
stable up to D = (pi/2) T = 314 ms. 9 ms is the sweep's smallest margin (docs/transfer_schemes_notes.md) with which
the shadow still walks, on every seed, through the 6 ms of actuator latency that direct transfer walks through.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from bruce_hw.config import PdGains, RobotConfig

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
    from bruce_hw.mock import MujocoBackend  # places the standing pose and knows the joints' dof addresses

    nominal = MujocoBackend(config)
    nominal.configure()
    model, data = nominal.model, nominal.data
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    inverse = np.linalg.inv(mass)
    dofs = nominal._dofs
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
    """Kp, Kd per joint for a PD towards a reference (module docstring)."""
    wc = pd_crossover(delay_s, phase_margin_deg)
    kd = inertia * wc
    return PdGains(kp=kd * wc / PD_ZERO_RATIO, kd=kd)


def shortest_observer_time_constant(delay_s: float, phase_margin_deg: float) -> float:
    """The fastest residual observer (s) that keeps `phase_margin_deg` at a loop delay of `delay_s`."""
    return delay_s / (math.pi / 2 - math.radians(phase_margin_deg))


def observer_gain(inertia: np.ndarray, time_constant_s: float) -> np.ndarray:
    """k per joint (N·m per rad/s of residual, each tick): the observer's torque settles with `time_constant_s`."""
    return inertia / time_constant_s
