"""The gait's timing (`GaitClock`) and the swing foot's path (`min_jerk`, `swing_height`).

The gait is locked to the policy's clock input (paper Table I: sin/cos of the gait phase): a period C_T holds two
steps of C_T / 2, right foot in stance first, after one start-up period in double support. A student policy sees
only that clock and the command, so the teacher's phase must be a function of the command history alone, which
`GaitClock` is: the teacher and the policy's observation builder each run one. C_T follows the commanded forward
speed (`policy.gait_period_s`, docs/walking.md); the clock integrates 1 / C_T, so a change of cadence never jumps
the phase. The clock also keeps the command the gait follows, rate-limited to `COMMAND_ACCELERATION` (the pendulum
cannot follow a step change of the footstep offsets within a step), which the policy observes too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bruce_hw.types import GRAVITY

COMMAND_ACCELERATION = np.array([0.5, 0.5, 1.0])  # m/s^2, m/s^2, rad/s^2: (vx, vy, yaw rate) change at most this fast


@dataclass(frozen=True, slots=True)
class GaitPhase:
    starting: bool       # in the start-up period (both feet down, shifting weight)
    step: int            # index of the current step (0 = first step); -1 while starting
    stance: int          # leg in stance: 0 right, 1 left
    t_in_step: float     # s since the step began
    t_remaining: float   # s until the step ends, at the current cadence
    step_time: float     # s, C_T / 2 at the current cadence
    start_share: float   # share of the start-up period done (1 once stepping)


def gait_phase(cycles: float, period: float) -> GaitPhase:
    """The gait at `cycles` gait periods since the start, stepping at period C_T = `period` (s)."""
    step_time = 0.5 * period
    if cycles < 1.0:
        return GaitPhase(True, -1, 0, (cycles - 0.5) * period, (1.0 - cycles) * period, step_time, cycles)
    steps = 2.0 * (cycles - 1.0)
    k = int(steps)
    share = steps - k
    return GaitPhase(False, k, k % 2, share * step_time, (1.0 - share) * step_time, step_time, 1.0)


def interpolate(table: tuple[tuple[float, float], ...], x: float) -> float:
    """y at x from a table of (x, y) points (x increasing): linear between them, constant beyond them."""
    xs, ys = zip(*table, strict=True)
    return float(np.interp(x, xs, ys))


def gait_period(cadence: tuple[tuple[float, float], ...], vx: float) -> float:
    """C_T (s) at forward speed vx, from the cadence table of (vx, C_T) points."""
    return interpolate(cadence, vx)


class GaitClock:
    """The gait phase in periods and the command the gait follows, advanced once per policy tick."""

    def __init__(self, cadence: tuple[tuple[float, float], ...], dt: float):
        self.cadence = cadence
        self.dt = dt
        self.reset()

    def reset(self) -> None:
        self.cycles = 0.0
        self.command = np.zeros(3)  # (vx, vy, yaw rate), rate-limited
        self.period = gait_period(self.cadence, 0.0)

    def tick(self, command: np.ndarray) -> float:
        """This tick's phase (periods since the start), then advance one policy tick: the followed command moves
        toward `command` (vx, vy, yaw rate) at the bounded acceleration, and the cadence with it."""
        cycles = self.cycles
        limit = COMMAND_ACCELERATION * self.dt
        self.command = self.command + np.clip(np.asarray(command, dtype=float) - self.command, -limit, limit)
        self.period = gait_period(self.cadence, float(self.command[0]))
        self.cycles += self.dt / self.period
        return cycles

    def phase(self, cycles: float) -> GaitPhase:
        return gait_phase(cycles, self.period)


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


def lipm_omega(com_height: float, gravity: float = GRAVITY) -> float:
    return math.sqrt(gravity / com_height)
