"""Paced runs that should complete, on a machine that may not run the loop at its rate.

A run paced to the wall clock against the emulators shares two cores with the emulators' physics and device threads;
on a slow or loaded VM the loop can be left most of its ticks late (the loop at 600-850 Hz, ticks skipped, the data
aging) and the run can end on the rate floor, a stale sample or a joint limit: that says nothing about what the test
is for. Such a run is repeated once, then reported as a skip naming the share of late ticks. A run that ends while
its loop kept pace is the test's to judge.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import pytest

OVERLOADED_LATE_SHARE = 0.25  # a paced run with a quarter of its ticks late did not run at the loop rate
Result = TypeVar("Result")


def completed_or_skipped(attempt: Callable[[], tuple[bool, float, Result]],
                         before_again: Callable[[], None] | None = None) -> Result:
    """`attempt()` -> (completed, late share, result): its result where it completed or kept pace; otherwise
    `before_again()` (the robot back on its feet) and a second attempt; where that too was overloaded, a skip."""
    for again in (False, True):
        if again and before_again is not None:
            before_again()
        completed, late_share, result = attempt()
        if completed or late_share < OVERLOADED_LATE_SHARE:
            return result
    pytest.skip(f"the machine could not pace the loop: {100 * late_share:.0f} % of the ticks late twice")
