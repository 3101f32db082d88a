"""What "fell" means, for every evaluation of a run (the run summary, bruce-collect, bruce-eval transfer, DAgger).

A robot has fallen when the simulator's truth puts its base below FALL_HEIGHT_FRACTION of its nominal standing
height (the mock's `nominal_base_height`: the legs in the standing pose, soles on the floor) or tilts it more
than FALL_TILT_RAD from upright. Mock only: a robot has no ground truth.
"""

from __future__ import annotations

import math

from bruce_hw.quaternion import tilt_of
from bruce_hw.types import GroundTruth

FALL_HEIGHT_FRACTION = 0.6   # fallen when the base is below this share of its nominal standing height
FALL_TILT_RAD = math.pi / 4  # ... or the base is tilted more than this


def has_fallen(truth: GroundTruth, nominal_base_height: float) -> bool:
    return bool(fallen(float(truth.base_pos[2]), tilt_of(truth.base_quat), nominal_base_height))


def fallen(base_height, tilt, nominal_base_height: float):
    """The rule on numbers or arrays (a batch of simulations: training/rl): base height (m), tilt (rad)."""
    return (base_height < FALL_HEIGHT_FRACTION * nominal_base_height) | (tilt > FALL_TILT_RAD)


def fall_rule() -> dict:
    """The definition as data, for the metadata of files made under it."""
    return {"base_height_below": f"{FALL_HEIGHT_FRACTION} x nominal standing height", "tilt_above_rad": FALL_TILT_RAD}
