"""The walking reward of the paper's Table II (docs/rl.md): `WalkStep` (one policy step of N envs), one function per
term, `REWARD_TERMS` (name -> function, paper weight), `ADDED_TERMS` (ours, beyond Table II, weight 0 unless a
training config sets one) and `compute(step, weights, params) -> (total, terms)`. Every term function returns its
unweighted value per env, shape (N,).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

RIGHT, LEFT = 0, 1
DOUBLE_SUPPORT = -1  # stance_desired during the gait's start-up period: both feet down
WRONG_CONTACT = -0.5  # Table II's foot contact pattern: 1 where it matches, this where it does not


@dataclass(frozen=True)
class WalkStep:
    """One policy step of N envs, after the physics. World frame on flat ground (z = height above the floor) unless
    said; joint arrays in the config's joint order; legs (right, left). At an episode's first step the "_prev" values
    are the current ones, so the smoothness terms start at their best."""

    dt: float                     # s, policy period
    alive: np.ndarray             # (N,) bool: not terminated this step
    base_pos: np.ndarray          # (N, 3) base body origin
    base_euler: np.ndarray        # (N, 3) roll, pitch, yaw (ZYX)
    base_linvel: np.ndarray       # (N, 3) base frame
    base_angvel: np.ndarray       # (N, 3) base frame
    base_linvel_prev: np.ndarray  # (N, 3) the previous policy step's base_linvel
    base_angvel_prev: np.ndarray  # (N, 3) the previous policy step's base_angvel
    command: np.ndarray           # (N, 3) followed (rate-limited) command: vx, vy (heading frame), yaw rate
    heading_linvel: np.ndarray    # (N, 3) base linear velocity in the heading (yaw-only) frame
    foot_pos: np.ndarray          # (N, 2, 3) sole sites (r_sole, l_sole)
    foot_vel: np.ndarray          # (N, 2, 3) linear velocity of the sole sites
    foot_contact: np.ndarray      # (N, 2) bool: the foot touches the ground
    knee_pos: np.ndarray          # (N, 2, 3) knee joint centres (shank body origins)
    stance_desired: np.ndarray    # (N,) int: RIGHT, LEFT or DOUBLE_SUPPORT, from the env's GaitClock
    swing_height_desired: np.ndarray  # (N,) m, swing sole above the floor (runtime.walking.gait.swing_height)
    q: np.ndarray                 # (N, 10)
    qd: np.ndarray                # (N, 10)
    qd_prev: np.ndarray           # (N, 10) the previous policy step's qd
    tau: np.ndarray               # (N, 10) joint torques applied
    action: np.ndarray            # (N, 10) a_t
    action_prev: np.ndarray       # (N, 10) a_{t-1}
    action_prev2: np.ndarray      # (N, 10) a_{t-2}
    joint_names: tuple[str, ...]  # the config's joint names, to find the hip yaw and roll joints
    heading_error: np.ndarray | None = None       # (N,) rad: yaw minus the command's heading reference
    mean_velocity: np.ndarray | None = None       # (N, 3) vx, vy (heading frame), yaw rate, averaged over ~a step cycle


@dataclass(frozen=True)
class RewardParams:
    """The constants Table II leaves open, for BRUCE. Computed once with MuJoCo from configs/robots/bruce.yaml's
    standing pose (the mock's `place`: base level, soles on the floor; tests/training/rl/test_rl_rewards.py recomputes
    them)."""

    feet_distance: float = 0.1394   # m, D_f^des: |r_sole - l_sole| standing
    knee_distance: float = 0.1461   # m, D_k^des: |r_shank - l_shank| (knee joint centres) standing
    base_height: float = 0.4240     # m, base origin above the floor standing: the mock's nominal_base_height
    hip_yaw_default: tuple[float, float] = (-0.010, 0.010)  # rad, (right, left): joints.standing_pose
    hip_roll_default: tuple[float, float] = (0.019, -0.019)  # rad, (right, left): joints.standing_pose


def phi(w: float, e: np.ndarray) -> np.ndarray:
    """The paper's Phi(w, e) = exp(-w |e|^2), the norm over the last axis: (N, k) -> (N,)."""
    return np.exp(-w * np.sum(np.square(e), axis=-1))


def yaw_rate(step: WalkStep) -> np.ndarray:
    """(N,) world-z rate of the base, what the yaw-rate command means (runtime.loop.observers.heading_velocity): the
    base angular velocity dotted with the world's z axis in the base frame."""
    return world_yaw_rate(step.base_euler, step.base_angvel)


def world_yaw_rate(euler: np.ndarray, angvel: np.ndarray) -> np.ndarray:
    """(N,) world-z rate from the base's (roll, pitch, yaw) and its base-frame angular velocity."""
    roll, pitch = euler[:, 0], euler[:, 1]
    up = np.stack([-np.sin(pitch), np.cos(pitch) * np.sin(roll), np.cos(pitch) * np.cos(roll)], axis=1)
    return np.sum(up * angvel, axis=1)


def desired_contact(stance_desired: np.ndarray) -> np.ndarray:
    """(N, 2) bool: the feet that should be down, (right, left): the stance foot, or both in double support."""
    return np.stack([stance_desired != LEFT, stance_desired != RIGHT], axis=1)


# -- the terms of Table II, unweighted ---------------------------------------------------------------------------
def alive(step: WalkStep, params: RewardParams) -> np.ndarray:
    return step.alive.astype(float)


def swing_foot_height(step: WalkStep, params: RewardParams) -> np.ndarray:
    """Phi(1000, swing sole height - desired); in double support both soles should be on the floor (desired 0)."""
    z = step.foot_pos[:, :, 2]
    single = step.stance_desired != DOUBLE_SUPPORT
    swing = np.where(single, 1 - step.stance_desired, 0)
    swing_error = np.take_along_axis(z, swing[:, None], axis=1)[:, 0] - step.swing_height_desired
    return np.where(single, phi(1000.0, swing_error[:, None]), phi(1000.0, z))


def foot_contact_pattern(step: WalkStep, params: RewardParams) -> np.ndarray:
    """Per foot 1 where its contact is the desired one, else -0.5, averaged over the two feet: the paper's 1 / -0.5
    when one foot is down (the right one / the wrong one); 0.25 for half a match (both or neither down in single
    stance, one down in double support)."""
    match = step.foot_contact == desired_contact(step.stance_desired)
    return np.where(match, 1.0, WRONG_CONTACT).mean(axis=1)


def foot_slip(step: WalkStep, params: RewardParams) -> np.ndarray:
    """|v_st|^2: the squared horizontal speed of every foot in contact, summed."""
    speed_sq = np.sum(np.square(step.foot_vel[:, :, :2]), axis=2)
    return np.sum(speed_sq * step.foot_contact, axis=1)


def feet_distance(step: WalkStep, params: RewardParams) -> np.ndarray:
    distance = np.linalg.norm(step.foot_pos[:, LEFT] - step.foot_pos[:, RIGHT], axis=1)
    return phi(10.0, (distance - params.feet_distance)[:, None])


def knee_distance(step: WalkStep, params: RewardParams) -> np.ndarray:
    distance = np.linalg.norm(step.knee_pos[:, LEFT] - step.knee_pos[:, RIGHT], axis=1)
    return phi(10.0, (distance - params.knee_distance)[:, None])


def default_yaw_roll(step: WalkStep, params: RewardParams) -> np.ndarray:
    """Mean of Phi(4, hip yaw offset) and Phi(5, hip roll offset) over both legs, offsets from the standing pose."""
    total = np.zeros(len(step.q))
    for leg, side in enumerate(("r", "l")):
        for joint, w, default in (("hip_yaw", 4.0, params.hip_yaw_default), ("hip_roll", 5.0, params.hip_roll_default)):
            offset = step.q[:, step.joint_names.index(f"{side}_{joint}")] - default[leg]
            total += phi(w, offset[:, None])
    return total / 4.0


def linvel_tracking(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(5.0, step.heading_linvel[:, :2] - step.command[:, :2])


def angvel_tracking(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(7.0, (yaw_rate(step) - step.command[:, 2])[:, None])


def velocity_mismatch(step: WalkStep, params: RewardParams) -> np.ndarray:
    """(Phi(25, vertical velocity) + Phi(2, roll and pitch rates in the base frame)) / 2."""
    return 0.5 * (phi(25.0, step.heading_linvel[:, 2:3]) + phi(2.0, step.base_angvel[:, :2]))


def orientation(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(5.0, step.base_euler[:, :2])


def base_height(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(5.0, (step.base_pos[:, 2] - params.base_height)[:, None])


def base_acceleration_smoothness(step: WalkStep, params: RewardParams) -> np.ndarray:
    """Phi(1, change of the base's linear and angular velocity over one policy step)."""
    change = np.concatenate([step.base_linvel - step.base_linvel_prev, step.base_angvel - step.base_angvel_prev],
                            axis=1)
    return phi(1.0, change)


def action_smoothness(step: WalkStep, params: RewardParams) -> np.ndarray:
    return np.sum(np.square(step.action - 2.0 * step.action_prev + step.action_prev2), axis=1)


def torque_velocity(step: WalkStep, params: RewardParams) -> np.ndarray:
    return np.sum(np.square(step.tau), axis=1) + 10.0 * np.sum(np.square(step.qd), axis=1)


def joint_acceleration(step: WalkStep, params: RewardParams) -> np.ndarray:
    return np.sum(np.square((step.qd - step.qd_prev) / step.dt), axis=1)


RewardTerm = Callable[[WalkStep, RewardParams], np.ndarray]

# Table II: name -> (term, the paper's weight mu_i), in the paper's order.
REWARD_TERMS: dict[str, tuple[RewardTerm, float]] = {
    "alive": (alive, 0.15),
    "swing_foot_height": (swing_foot_height, 1.0),
    "foot_contact_pattern": (foot_contact_pattern, 1.0),
    "foot_slip": (foot_slip, -0.05),
    "feet_distance": (feet_distance, 1.0),
    "knee_distance": (knee_distance, 1.0),
    "default_yaw_roll": (default_yaw_roll, 0.5),
    "linvel_tracking": (linvel_tracking, 2.0),
    "angvel_tracking": (angvel_tracking, 1.0),
    "velocity_mismatch": (velocity_mismatch, 0.5),
    "orientation": (orientation, 1.0),
    "base_height": (base_height, 0.5),
    "base_acceleration_smoothness": (base_acceleration_smoothness, 0.05),
    "action_smoothness": (action_smoothness, -0.002),
    "torque_velocity": (torque_velocity, -5e-6),
    "joint_acceleration": (joint_acceleration, -5e-7),
}
PAPER_WEIGHTS: dict[str, float] = {name: weight for name, (_, weight) in REWARD_TERMS.items()}


# Ours, beyond Table II (docs/rl.md). The paper's tracking terms score the instantaneous velocity, which sways with
# every step; what a command asks (and what the acceptance measures) is the mean over steps, and the heading the
# yaw-rate command integrates to (the observation's third Euler entry).
def mean_velocity_tracking(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(20.0, step.mean_velocity - step.command)


def heading_tracking(step: WalkStep, params: RewardParams) -> np.ndarray:
    return phi(10.0, step.heading_error[:, None])


ADDED_TERMS: dict[str, tuple[RewardTerm, float]] = {
    "mean_velocity_tracking": (mean_velocity_tracking, 0.0),
    "heading_tracking": (heading_tracking, 0.0),
}
TERMS: dict[str, tuple[RewardTerm, float]] = {**REWARD_TERMS, **ADDED_TERMS}


def compute(step: WalkStep, weights: Mapping[str, float] | None = None,
            params: RewardParams | None = None) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The reward of each env, (N,), and each term weighted, name -> (N,); they sum to the reward. `weights` names
    the terms to use (None: all, at the paper's weights); a term it leaves out is not computed."""
    weights = PAPER_WEIGHTS if weights is None else weights
    unknown = sorted(set(weights) - set(TERMS))
    if unknown:
        raise ValueError(f"unknown reward terms {unknown}; the terms are {list(TERMS)}")
    params = params or RewardParams()
    terms = {name: weight * TERMS[name][0](step, params) for name, weight in weights.items()}
    return sum(terms.values(), np.zeros(len(step.alive))), terms
