"""A bus's cycles on a thread of its own (`BusThread`), so that the 1 kHz tick never waits for serial I/O.

BRUCE-OP runs its BEAR bulk cycle in a process of its own and shares the latest state through shared memory; this
is the same idea inside the hw backend. The control thread's write() hands over the newest command (`post`) and
wakes the thread, which starts a cycle at once (or right after the one in flight); read() takes the newest complete
reading (`latest`) and never waits, so a bus cycle overlaps the tick's pacing sleep instead of its work
(docs/timing.md). The hw backend puts this thread one real-time priority step above the loop
(`bruce_hw.io_priority`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

CYCLE_RING = 1 << 16  # cycle durations (microseconds) kept for the run's percentiles: no allocation per cycle


class BusThread:
    """Without a wake-up the thread cycles on its own every `period_s`, resending the newest command (goal writes are
    idempotent; before the first one, read-only cycles), so a tick that runs late still finds a fresh reading; but
    only while that command (or the start) is at most `hold_s` old: a control thread that hangs, or a frozen
    process, stops the cycles and the motors' own watchdogs take over, as for a killed process. The command's age is
    the time the process ran since it was posted (`stalled`: seconds of an interval in which the process was not
    run, `bruce_hw.host_witness`): after a host stall the thread cycles on at once, so the control thread finds a
    fresh reading when it resumes. An exception in a
    cycle ends the thread; `error` keeps it for the control thread to raise. `halt(reading)`, run after every cycle,
    may act on a reading that cannot wait for the next tick (the hw backend damps every BEAR on an E-stop or a device
    fault) and return its cause: the thread then ends with `halted` and `halted_at` set, the reading still `latest`
    for the control thread to act on."""

    def __init__(self, name: str, cycle: Callable[[Any], Any], *, period_s: float, hold_s: float,
                 halt: Callable[[Any], str | None] | None = None,
                 stalled: Callable[[float, float], float] | None = None):
        self.name = name
        self._cycle = cycle
        self._halt = halt
        self.halted: str | None = None
        self.halted_at: float | None = None  # time.monotonic() when `halt` acted
        self.period_s = period_s
        self.hold_s = hold_s
        self._stalled = stalled or (lambda t0, t1: 0.0)
        self._latest: Any = None
        self._go = threading.Event()
        self._command: Any = None
        self._command_stamp = time.monotonic()
        self._wake = threading.Event()
        self._stopping = False
        self.error: BaseException | None = None
        self.cycles = 0
        self.first_start = self.last_end = 0.0  # time.monotonic() of the first cycle's start, the last one's end
        self.last_start: float | None = None     # ... of the last cycle's start (the one in flight, if any)
        self.idle_waits = 0        # times the thread stopped cycling on a command older than hold_s
        self._durations = np.zeros(CYCLE_RING, dtype=np.int32)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def latest(self) -> Any:
        """The newest complete reading (a reference swap: never torn, never waited for)."""
        return self._latest

    @property
    def cycling(self) -> bool:
        """Between begin() and stop()."""
        return self._go.is_set() and not self._stopping

    @property
    def thread(self) -> threading.Thread:
        return self._thread

    def start(self) -> None:
        """Create the OS thread, waiting for `begin`. Early, before the loop asks for mlockall: a thread created
        after it has its whole stack (8 MB) faulted in and locked at creation, tens of milliseconds."""
        self._thread.start()

    def begin(self, first_reading: Any) -> None:
        """Start cycling; `latest` is `first_reading` until the first cycle is done."""
        self._latest = first_reading
        self._command_stamp = time.monotonic()
        self._go.set()

    def post(self, command: Any) -> None:
        """The command for the next cycle; starts it now (or right after the cycle in flight)."""
        self._command = command
        self._command_stamp = time.monotonic()
        self._wake.set()

    def stop(self, timeout_s: float = 0.1) -> bool:
        """End the thread after the cycle in flight; True when it has ended within `timeout_s`."""
        self._stopping = True
        self._wake.set()
        self._go.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def cycle_us(self) -> dict[str, float | None]:
        """Cycles, their rate, and p50/p99/max of their durations (the newest CYCLE_RING of them)."""
        n = min(self.cycles, CYCLE_RING)
        span = self.last_end - self.first_start
        out = {"cycles": self.cycles, "rate_hz": self.cycles / span if self.cycles > 1 and span > 0 else None}
        if not n:
            return {**out, "p50": None, "p99": None, "max": None}
        values = self._durations[:n]
        return {**out, "p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)),
                "max": float(values.max())}

    def _run(self) -> None:
        perf = time.perf_counter_ns
        self._go.wait()
        while True:
            woken = self._wake.wait(self.period_s) if self.cycles else True  # the first cycle at once
            self._wake.clear()
            if self._stopping:
                return
            if not woken and self._command_age() > self.hold_s:
                self.idle_waits += 1  # the control thread is gone: no cycles, the motors' watchdogs take over
                self._wake.wait()
                continue
            t0 = perf()
            self.last_start = time.monotonic()
            if not self.cycles:
                self.first_start = self.last_start
            try:
                reading = self._cycle(self._command)
                # Acted on before it is published: the control thread never sees a reading that halt has yet to
                # act on.
                at = time.monotonic()
                cause = self._halt(reading) if self._halt is not None else None
            except BaseException as exc:  # ends the thread; the control thread raises it on its next read
                self.error = exc
                return
            if cause is not None:
                self.halted, self.halted_at = cause, at
            self._latest = reading
            self._durations[self.cycles % CYCLE_RING] = min((perf() - t0) // 1000, 2**31 - 1)
            self.cycles += 1
            self.last_end = time.monotonic()
            if cause is not None:
                return

    def _command_age(self) -> float:
        now = time.monotonic()
        return now - self._command_stamp - self._stalled(self._command_stamp, now)
