"""How late an emulated device answers: a fixed delay plus a uniform random extra in [0, jitter], per bus, so that a
host's timing policy (reply timeouts, late ticks, data-age checks) can be tried on purpose against a slow device.

The waits are honest wall-clock waits on time.monotonic(): sleep until shortly before the moment, then spin
(plain sleeps overshoot by tens of microseconds to a millisecond on a loaded machine; runtime/loop/pacing.py does the
same), so a real-time host measures the delay it was given. Each bus's emulator waits on its own thread (the pty
thread that received the request, or the sense board's sender), never holding a lock another bus or the physics
needs, so a slow bus slows nobody else.

Draws come from a `random.Random` seeded per bus (`seed`, e.g. `--loss-seed`), so a run can be repeated.
"""

from __future__ import annotations

import math
import random
import threading
import time

MAX_DELAY_S = 0.1  # longer than any timeout a host uses: beyond it nothing more is learned, only waited
SPIN_S = 0.0002    # the last stretch of a wait is spun, not slept


def check_delay(value: float, what: str) -> float:
    """`value` as seconds in [0, MAX_DELAY_S]; ValueError naming `what` (an option or a field) otherwise."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: {value!r} is not a number of seconds") from None
    if not math.isfinite(value) or not 0.0 <= value <= MAX_DELAY_S:
        raise ValueError(f"{what}: {value:g} s is not a delay in [0, {MAX_DELAY_S:g}] s")
    return value


def wait_until(deadline: float) -> None:
    """Return at `deadline` (time.monotonic()), not before: sleep, then spin the last SPIN_S."""
    while True:
        left = deadline - time.monotonic()
        if left <= 0.0:
            return
        if left > SPIN_S:
            time.sleep(left - SPIN_S)


class ReplyDelay:
    """fixed + U(0, jitter) seconds, thread-safe to change while a bus uses it. Zero (the default) costs nothing."""

    def __init__(self, fixed: float = 0.0, jitter: float = 0.0, seed: int | str | None = None):
        self._lock = threading.Lock()
        self._rng = random.Random(seed)
        self.fixed, self.jitter = 0.0, 0.0
        self.set(fixed, jitter)

    def set(self, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """New values (checked: ValueError naming the field); `seed` restarts the draws when given."""
        fixed, jitter = check_delay(fixed, "delay"), check_delay(jitter, "jitter")
        with self._lock:
            self.fixed, self.jitter = fixed, jitter
            if seed is not None:
                self._rng = random.Random(seed)

    @property
    def active(self) -> bool:
        return self.fixed > 0.0 or self.jitter > 0.0

    def draw(self) -> float:
        """One delay in seconds."""
        with self._lock:
            if self.jitter > 0.0:
                return self.fixed + self.jitter * self._rng.random()
            return self.fixed

    def wait(self, since: float) -> float:
        """Wait until one drawn delay after `since` (time.monotonic(), e.g. when the request arrived); returns that
        moment (`since` without a delay)."""
        if self.fixed > 0.0 or self.jitter > 0.0:
            due = since + self.draw()
            wait_until(due)
            return due
        return since

    def describe(self) -> list[float]:
        """[fixed, jitter] in seconds, for a status line."""
        return [self.fixed, self.jitter]

    def text(self) -> str:
        return f"{1e3 * self.fixed:g} ms" + (f" + U(0, {1e3 * self.jitter:g} ms)" if self.jitter else "")
