"""The heading a velocity command asks for, shared by the walking teacher (which steers to it) and the policy's
observation (which carries the error to it), so a distilled policy sees the state its teacher acts on.

The commanded yaw rate is integrated from the first measured yaw; the reference never leads or trails the measured
yaw by more than `HEADING_LEAD_MAX`, so a slip does not wind it up. Called once per policy tick, on one robot (numbers)
or on a batch of simulated ones (arrays with a leading robot axis, `num_envs`), with the same arithmetic.
"""

from __future__ import annotations

import math

import numpy as np

HEADING_LEAD_MAX = 0.3  # rad


def wrap_angle(x):
    """math.remainder(x, 2 pi) elementwise, exactly (IEEE remainder: in [-pi, pi], ties to the even quotient).
    fmod is exact, and so is the one subtraction of 2 pi that follows (Sterbenz)."""
    if np.ndim(x) == 0:
        return math.remainder(x, math.tau)
    r = np.fmod(x, math.tau)
    r = np.where(np.abs(r) > math.pi, r - np.copysign(math.tau, r), r)
    # |r| == pi: x is an odd multiple of pi; the quotient toward zero is odd when x mod 4 pi is 3 pi, not pi.
    odd = (np.abs(r) == math.pi) & (np.abs(np.fmod(x, 2.0 * math.tau)) > math.tau)
    return np.where(odd, -r, r)


class HeadingReference:
    def __init__(self, dt: float, lead_max: float = HEADING_LEAD_MAX, num_envs: int | None = None):
        self.dt = dt
        self.lead_max = lead_max
        shape = () if num_envs is None else (num_envs,)
        self.heading = np.zeros(shape)
        self.started = np.zeros(shape, dtype=bool)  # a reference exists (the first update has run)

    def reset(self, envs=...) -> None:
        """Forget the reference (of the robots `envs` selects: a mask or indices into the batch)."""
        self.started[envs] = False

    def update(self, yaw, yaw_rate_command):
        """Advance one policy tick at the commanded yaw rate; the new reference heading (rad)."""
        heading = np.where(self.started, self.heading, yaw) + yaw_rate_command * self.dt
        lead = wrap_angle(heading - yaw)
        self.heading = np.where(np.abs(lead) > self.lead_max, yaw + np.copysign(self.lead_max, lead), heading)
        self.started[...] = True
        return self.heading[()]

    def error(self, yaw):
        """Measured yaw minus the reference, wrapped to [-pi, pi]; 0 before the first update."""
        return np.where(self.started, wrap_angle(yaw - self.heading), 0.0)[()]
