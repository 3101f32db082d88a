"""The gait's timing and the swing foot's path, as pure functions of time.

The gait is locked to the policy's clock input (paper Table I: sin/cos of 2 pi t / C_T): a period C_T holds
two steps of C_T / 2, right foot in stance first, after one start-up period in double support. A student
policy sees only that clock, so the teacher's phase must be a function of t alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class GaitPhase:
    starting: bool       # in the start-up period (both feet down, shifting weight)
    step: int            # index of the current step (0 = first step); -1 while starting
    stance: int          # leg in stance: 0 right, 1 left
    t_in_step: float     # s since the step began
    t_remaining: float   # s until the step ends


def gait_phase(t: float, period: float) -> GaitPhase:
    step_time = 0.5 * period
    if t < period:
        return GaitPhase(True, -1, 0, t - period + step_time, period - t)
    k = int((t - period) // step_time)
    t_in = t - period - k * step_time
    return GaitPhase(False, k, k % 2, t_in, step_time - t_in)


def min_jerk(s: float) -> float:
    """Minimum-jerk blend 0 -> 1 for s in [0, 1] (clamped): zero slope and curvature at both ends. The teacher
    takes its rates and accelerations by differencing the joint targets, so no derivative is given."""
    s = min(1.0, max(0.0, s))
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def swing_height(s: float, apex: float, landing: float) -> float:
    """Height of the swing ankle above its stance-ankle level: a bump of height `apex` with zero slope at
    lift-off and touch-down, ending at `landing` (slightly below the ground, so the foot lands rather than
    hovers)."""
    s = min(1.0, max(0.0, s))
    return apex * 16.0 * s * s * (1.0 - s) * (1.0 - s) + landing * min_jerk(s)


def lipm_omega(com_height: float, gravity: float = 9.81) -> float:
    return math.sqrt(gravity / com_height)
