"""Real-time pacing by absolute deadlines on the monotonic clock.

Sleep until shortly before the deadline, then spin: plain sleeps overshoot by tens of microseconds, and
relative sleeps (sleep(dt - elapsed)) drift. The spin yields the GIL on every turn (sleep(0)): the hw backend's bus
thread runs its cycle in this part of the tick, and a spin that held the GIL would keep it waiting up to the
interpreter's switch interval. A SCHED_FIFO thread does not spin at all: the kernel gives real-time threads no timer
slack, so a sleep wakes within tens of microseconds, and a spin would count against the CPU's real-time budget
(sched_rt_runtime_us, 95 % of each second): with the bus and I/O threads on the same CPU, 20 % of spin pushed it
into real-time throttling, which stops every real-time thread on the CPU for the rest of the second (50 ms
stalls). A tick that starts more than `late_after_s` past its deadline is
late; if whole periods were missed, their ticks are skipped and counted, never run in a burst to catch up.

A SCHED_FIFO loop that is behind never sleeps, and nothing at normal priority runs on its CPU meanwhile: not the
kernel's tty worker that moves the bus adapter's bytes (a USB adapter's replies, a pseudo-terminal's requests),
which the scheduler often wakes on the loop's CPU. Traced on the hw path (docs/results/timing.md): the loop ran
7.2 ms of late ticks back to back while the worker holding the host's request waited on its CPU, and every BEAR
looked silent. So a real-time loop that has not slept for a whole period sleeps `breath_s` before its next tick
(counted as `breaths`): the worker's few microseconds run then, at a cost of tens of microseconds to a tick that
was late anyway. One long tick does the same from inside: traced again, a tick of 1.6 ms (the I/O threads
preempting it) kept a worker woken on the loop's CPU, and the host's request it held, waiting 2.7 ms; so the loop
calls `breathe` after its costliest section, which breathes once the loop has gone `mid_tick_s` without a sleep.
"""

from __future__ import annotations

import os
import time


class Pacer:
    def __init__(self, period_s: float, spin_s: float = 200e-6, late_after_s: float = 250e-6,
                 breath_s: float = 50e-6, mid_tick_s: float = 500e-6):
        self.period_ns = round(period_s * 1e9)
        self.mid_tick_ns = round(mid_tick_s * 1e9)
        self.spin_ns = round(spin_s * 1e9)
        self.late_ns = round(late_after_s * 1e9)
        self.breath_ns = round(breath_s * 1e9)
        self.deadline_ns = 0
        self.slept_ns = 0  # when the thread last came back from a sleep
        self.late_ticks = 0
        self.skipped_ticks = 0
        self.breaths = 0

    def start(self) -> None:
        """From now; call it on the thread that will wait (its scheduling decides whether to spin and to breathe)."""
        if _fifo():
            self.spin_ns = 0
        else:
            self.breath_ns = 0  # at normal priority the scheduler shares the CPU by itself
        self.slept_ns = time.monotonic_ns()
        self.deadline_ns = self.slept_ns + self.period_ns

    def breathe(self) -> None:
        """Inside a tick: a real-time loop that has gone `mid_tick_s` without a sleep sleeps `breath_s` now."""
        if self.breath_ns and time.monotonic_ns() - self.slept_ns > self.mid_tick_ns:
            self._breath()

    def _breath(self) -> int:
        """Sleep `breath_s` (others on the CPU run) and count it; returns the time after it."""
        time.sleep(self.breath_ns / 1e9)
        self.slept_ns = time.monotonic_ns()
        self.breaths += 1
        return self.slept_ns

    def wait(self) -> int:
        """Block until this tick's deadline; returns how far past it the tick starts (ns, >= 0)."""
        now = time.monotonic_ns()
        if now - self.deadline_ns <= self.late_ns:
            remaining = self.deadline_ns - now - self.spin_ns
            if remaining > 0:
                time.sleep(remaining / 1e9)
                self.slept_ns = time.monotonic_ns()
            while (now := time.monotonic_ns()) < self.deadline_ns:
                time.sleep(0)
        if self.breath_ns and now - self.slept_ns > self.period_ns:  # a period without a sleep: let others run
            now = self._breath()
        behind = now - self.deadline_ns
        if behind > self.late_ns:  # late on arrival, or woken late (the machine did not run us on time)
            self.late_ticks += 1
            missed = behind // self.period_ns
            if missed:
                self.skipped_ticks += missed
                self.deadline_ns += missed * self.period_ns
        self.deadline_ns += self.period_ns
        return behind


def _fifo() -> bool:
    try:
        return os.sched_getscheduler(0) == os.SCHED_FIFO
    except (AttributeError, OSError):
        return False
