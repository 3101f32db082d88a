"""The heading a velocity command asks for, shared by the walking teacher (which steers to it) and the policy's
observation (which carries the error to it), so a distilled policy sees the state its teacher acts on.

The commanded yaw rate is integrated from the first measured yaw; the reference never leads or trails the measured
yaw by more than `HEADING_LEAD_MAX`, so a slip does not wind it up. Called once per policy tick.
"""

from __future__ import annotations

import math

HEADING_LEAD_MAX = 0.3  # rad


class HeadingReference:
    def __init__(self, dt: float, lead_max: float = HEADING_LEAD_MAX):
        self.dt = dt
        self.lead_max = lead_max
        self.heading: float | None = None

    def reset(self) -> None:
        self.heading = None

    def update(self, yaw: float, yaw_rate_command: float) -> float:
        """Advance one policy tick at the commanded yaw rate; the new reference heading (rad)."""
        if self.heading is None:
            self.heading = yaw
        self.heading += yaw_rate_command * self.dt
        lead = math.remainder(self.heading - yaw, math.tau)
        if abs(lead) > self.lead_max:
            self.heading = yaw + math.copysign(self.lead_max, lead)
        return self.heading

    def error(self, yaw: float) -> float:
        """Measured yaw minus the reference, wrapped to (-pi, pi]; 0 before the first update."""
        return 0.0 if self.heading is None else math.remainder(yaw - self.heading, math.tau)
