"""When this process was not run: an in-process witness of host stalls (`HostWitness`).

On a VM (and, more rarely, on any machine) the host is sometimes not run for 1-50 ms: every thread of the process
stops at once, the loop and the bus and IMU reader threads alike, while the devices go on with their own clocks and
the motors hold their last current. A reading that aged during such a stall is not a silent device: nobody asked it
anything (docs/timing.md traces these stalls to the VM; bench/stall_witness.py is the same witness outside the
process). So the hw backend judges device silence on the time the process actually ran: a data age less the stalls
the witness saw in that interval (`stalled_between`).

The witness is a thread that sleeps `period_s` at a time and records each wake-up that came more than
`tolerance_s` late as a stall (its start: when the sleep was due to end; its end: the late wake-up). It runs at the
bus thread's real-time priority once the backend has one (`bruce_hw.io_priority`), so on a machine that runs the
process it wakes within a fraction of a millisecond; a thread kept off the GIL is kept off like the readers, which
is also time the process could not ask its devices anything. The clock is injectable (tests record stalls on a
virtual clock with `record`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

STALL_TOLERANCE_S = 0.002  # a wake-up later than this is a stall: above the GIL switch interval and timer slack
STALL_LOG = 4096            # stalls kept for `stalled_between` (at the VM's ~80 per minute: most of an hour)


@dataclass(frozen=True)
class Stall:
    start: float  # host monotonic time
    end: float

    @property
    def length(self) -> float:
        return self.end - self.start


class HostWitness:
    def __init__(self, period_s: float = 0.001, tolerance_s: float = STALL_TOLERANCE_S,
                 clock: Callable[[], float] = time.monotonic):
        self.period_s, self.tolerance_s, self.clock = period_s, tolerance_s, clock
        self._stalls: deque[Stall] = deque(maxlen=STALL_LOG)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.count = 0           # stalls seen since the start
        self.total_s = 0.0       # their total length
        self.worst_s = 0.0       # the longest
        self.last_wake = clock()  # the witness's last wake-up: a stall in progress is the time since
        self.running = False      # its thread is watching (a witness that is not cannot say it was silent)

    @property
    def thread(self) -> threading.Thread | None:
        return self._thread

    def start(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="host-witness", daemon=True)
            self.last_wake = self.clock()
            self.running = True
            self._thread.start()

    def stop(self) -> None:
        if self._thread is not None:
            self.running = False
            self._stop.set()
            self._thread.join(timeout=0.1)
            self._thread = None

    def _run(self) -> None:
        clock, period = self.clock, self.period_s
        due = clock() + period
        while not self._stop.wait(max(0.0, due - clock())):
            now = clock()
            if now - due > self.tolerance_s:
                self.record(due, now)
            self.last_wake = now
            due = now + period

    def reset_counts(self) -> None:
        """Count from now on (the backend's activation: stalls during start-up, loading models, are not the run's);
        the log `stalled_between` reads is kept."""
        with self._lock:
            self.count, self.total_s, self.worst_s = 0, 0.0, 0.0

    def record(self, start: float, end: float) -> None:
        """A stall from `start` to `end`: the thread's own finding, or a test's. What overlaps a stall already recorded
        extends it rather than counting twice."""
        with self._lock:
            last = self._stalls[-1] if self._stalls else None
            if last is not None and start <= last.end:  # the same stall, seen again: extend it
                if end <= last.end:
                    return
                stall = self._stalls[-1] = Stall(last.start, end)
                self.total_s += end - last.end
            else:
                stall = Stall(start, end)
                self._stalls.append(stall)
                self.count += 1
                self.total_s += stall.length
            self.worst_s = max(self.worst_s, stall.length)
        self.last_wake = max(self.last_wake, end)

    def silent_since(self, now: float) -> float | None:
        """When the witness last woke, if that is longer ago than its tolerance (it has not been run since: the
        process, or its Python threads, were not run), else None."""
        last = self.last_wake
        return last if self.running and now - last > self.tolerance_s else None

    def stalled_between(self, t0: float, t1: float) -> float:
        """Seconds of [t0, t1] in which the process was not run: the stalls recorded so far, and one still unrecorded
        that reaches `t1` (the witness silent for longer than its tolerance at `t1`: a thread that asks right after
        the process resumed runs before the witness has woken to record the stall)."""
        if t1 <= t0:
            return 0.0
        total = 0.0
        with self._lock:
            recorded_to = self._stalls[-1].end if self._stalls else -float("inf")
            for stall in reversed(self._stalls):
                if stall.end <= t0:
                    break  # recorded in time order: the older ones end earlier still
                total += max(0.0, min(stall.end, t1) - max(stall.start, t0))
        silent = self.silent_since(t1)
        if silent is not None:
            start = max(silent + self.period_s, recorded_to, t0)
            total += max(0.0, t1 - start)
        return total

    def stalls_since(self, t0: float) -> list[Stall]:
        """The stalls that ended after `t0`, oldest first."""
        with self._lock:
            found = []
            for stall in reversed(self._stalls):
                if stall.end <= t0:
                    break
                found.append(stall)
        return found[::-1]

    def report(self) -> dict:
        """Count, worst and total (ms), for the run's summary and stats."""
        return {"count": self.count, "worst_ms": 1e3 * self.worst_s, "total_ms": 1e3 * self.total_s}
