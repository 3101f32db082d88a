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
    """One robot's gait phase (numbers), or a batch's (arrays, one entry per robot)."""

    starting: bool       # in the start-up period (both feet down, shifting weight)
    step: int            # index of the current step (0 = first step); -1 while starting
    stance: int          # leg in stance: 0 right, 1 left
    t_in_step: float     # s since the step began
    t_remaining: float   # s until the step ends, at the current cadence
    step_time: float     # s, C_T / 2 at the current cadence
    start_share: float   # share of the start-up period done (1 once stepping)


def gait_phase(cycles, period) -> GaitPhase:
    """The gait at `cycles` gait periods since the start, stepping at period C_T = `period` (s). Numbers give a phase
    of numbers; arrays (a batch of robots) give one of arrays."""
    step_time = 0.5 * period
    starting = cycles < 1.0
    steps = np.maximum(2.0 * (cycles - 1.0), 0.0)
    k = np.floor(steps)
    share = steps - k
    k = k.astype(int)
    fields = (starting, np.where(starting, -1, k), np.where(starting, 0, k % 2),
              np.where(starting, (cycles - 0.5) * period, share * step_time),
              np.where(starting, (1.0 - cycles) * period, (1.0 - share) * step_time),
              step_time, np.where(starting, cycles, 1.0))
    if np.ndim(cycles) == 0:  # one robot's phase: plain numbers
        return GaitPhase(*(np.asarray(f).item() for f in fields))
    return GaitPhase(*fields)


def interpolate(table: tuple[tuple[float, float], ...], x: float) -> float:
    """y at x from a table of (x, y) points (x increasing): linear between them, constant beyond them."""
    xs, ys = zip(*table, strict=True)
    return float(np.interp(x, xs, ys))


def gait_period(cadence: tuple[tuple[float, float], ...], vx: float) -> float:
    """C_T (s) at forward speed vx, from the cadence table of (vx, C_T) points."""
    return interpolate(cadence, vx)


class GaitClock:
    """The gait phase in periods and the command the gait follows, advanced once per policy tick; of one robot
    (numbers, a (3,) command) or of a batch of `num_envs` simulated ones (arrays, (num_envs, 3) commands)."""

    def __init__(self, cadence: tuple[tuple[float, float], ...], dt: float, num_envs: int | None = None):
        self.cadence = cadence
        self.dt = dt
        self._points = tuple(np.array(axis, dtype=float) for axis in zip(*cadence, strict=True))
        shape = () if num_envs is None else (num_envs,)
        self.cycles = np.zeros(shape)
        self.command = np.zeros((*shape, 3))  # (vx, vy, yaw rate), rate-limited
        self.reset()

    def reset(self, envs=...) -> None:
        """Start over (the robots `envs` selects: a mask or indices into the batch)."""
        self.cycles = np.array(self.cycles)  # one robot's is a number after a tick
        self.cycles[envs] = 0.0
        self.command[envs] = 0.0
        self.period = np.interp(self.command[..., 0], *self._points)

    def tick(self, command):
        """This tick's phase (periods since the start), then advance one policy tick: the followed command moves
        toward `command` (vx, vy, yaw rate) at the bounded acceleration, and the cadence with it."""
        cycles = self.cycles
        limit = COMMAND_ACCELERATION * self.dt
        # clip(x, -l, l) as max then min: the same values, without np.clip's Python layer (the policy's tick)
        step = np.minimum(np.maximum(np.asarray(command, dtype=float) - self.command, -limit), limit)
        self.command = self.command + step
        self.period = np.interp(self.command[..., 0], *self._points)
        self.cycles = cycles + self.dt / self.period
        return cycles[()]

    def phase(self, cycles) -> GaitPhase:
        return gait_phase(cycles, self.period)


def _unit(s):
    """s clamped to [0, 1] (a number or an array)."""
    return min(1.0, max(0.0, s)) if np.ndim(s) == 0 else np.clip(s, 0.0, 1.0)


def min_jerk(s):
    """Minimum-jerk blend 0 -> 1 for s in [0, 1] (clamped): zero slope and curvature at both ends. The teacher
    takes its rates and accelerations by differencing the joint targets, so no derivative is given."""
    s = _unit(s)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def swing_height(s, apex: float, landing: float):
    """Height of the swing ankle above its stance-ankle level: a bump of height `apex` with zero slope at
    lift-off and touch-down, ending at `landing` (slightly below the ground, so the foot lands rather than
    hovers)."""
    s = _unit(s)
    return apex * 16.0 * s * s * (1.0 - s) * (1.0 - s) + landing * min_jerk(s)


def lipm_omega(com_height: float, gravity: float = GRAVITY) -> float:
    return math.sqrt(gravity / com_height)
