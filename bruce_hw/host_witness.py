"""When this process was not run: an in-process witness of host stalls (`HostWitness`), on a log of stall
intervals (`StallLog`) that a serial bus keeps for its own port calls too.

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


class StallLog:
    """Intervals in which something of this process was held by the host, merged as they come (`record`), and how
    much of an interval they cover (`stalled_between`). The host witness keeps one (the whole process not run); a
    serial leg bus keeps one too (its own port calls held in the kernel: `bruce_hw.bear_legs`). `open_since(now)`,
    if given, says when a stall still in progress began (None: none is), so a stall counts before it has ended."""

    def __init__(self, open_since: Callable[[float], float | None] | None = None):
        self._stalls: deque[Stall] = deque(maxlen=STALL_LOG)
        self._lock = threading.Lock()
        self._open_since = open_since or (lambda now: None)
        self.count = 0           # stalls seen since the start (or that began after `reset_counts`)
        self.total_s = 0.0       # their total length
        self.worst_s = 0.0       # the longest
        self._counted_from = -float("inf")

    def reset_counts(self, since: float) -> None:
        """Count the stalls that begin at `since` or later (the backend's activation: stalls during start-up,
        loading models, are not the run's); the log `stalled_between` reads is kept. A stall that began before it is
        start-up's, however late it is recorded: the witness records a stall when it wakes, and what kept it from
        waking just before the loop (the full garbage collection that holds the interpreter lock 20-25 ms here, at
        normal priority on a CPU the devices' threads may hold) may end only after the activation."""
        with self._lock:
            self.count, self.total_s, self.worst_s = 0, 0.0, 0.0
            self._counted_from = since

    def record(self, start: float, end: float) -> None:
        """A stall from `start` to `end`. What overlaps the stall recorded last extends it rather than counting
        twice."""
        with self._lock:
            last = self._stalls[-1] if self._stalls else None
            if last is not None and start <= last.end:  # the same stall, seen again: extend it
                if end <= last.end:
                    return
                stall = self._stalls[-1] = Stall(last.start, end)
                grown = end - last.end
            else:
                stall = Stall(start, end)
                self._stalls.append(stall)
                grown = stall.length
                if stall.start >= self._counted_from:
                    self.count += 1
            if stall.start >= self._counted_from:
                self.total_s += grown
                self.worst_s = max(self.worst_s, stall.length)

    def intervals(self, t0: float, t1: float) -> list[tuple[float, float]]:
        """The parts of [t0, t1] the stalls cover, oldest first: those recorded, and one in progress at `t1`."""
        found: list[tuple[float, float]] = []
        if t1 <= t0:
            return found
        with self._lock:
            recorded_to = self._stalls[-1].end if self._stalls else -float("inf")
            for stall in reversed(self._stalls):
                if stall.end <= t0:
                    break  # recorded in time order: the older ones end earlier still
                if stall.start < t1:
                    found.append((max(stall.start, t0), min(stall.end, t1)))
        found.reverse()
        since = self._open_since(t1)
        if since is not None:
            start = max(since, recorded_to, t0)
            if start < t1:
                found.append((start, t1))
        return found

    def holding(self, now: float) -> bool:
        """A stall is in progress at `now`."""
        return self._open_since(now) is not None

    def stalled_between(self, t0: float, t1: float) -> float:
        """Seconds of [t0, t1] in which the stalls held it."""
        # Asked several times a tick and nearly always 0: an interval that begins after the newest recorded stall ends
        # can only hold one in progress, answered without the lock (the log changes only at its end, in time order).
        stalls = self._stalls
        if (not stalls or t0 >= stalls[-1].end) and self._open_since(t1) is None:
            return 0.0
        return sum(end - start for start, end in self.intervals(t0, t1))

    def stalls_since(self, t0: float) -> list[Stall]:
        """The recorded stalls that ended after `t0`, oldest first."""
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


def stalled_union(*logs: StallLog) -> Callable[[float, float], float]:
    """`stalled_between` over several logs at once: the seconds of [t0, t1] that any of them covers (a VM stall that
    also held a port call counts once)."""
    def stalled_between(t0: float, t1: float) -> float:
        spans = sorted(span for log in logs for span in log.intervals(t0, t1))
        total, reach = 0.0, -float("inf")
        for start, end in spans:
            start = max(start, reach)
            if end > start:
                total += end - start
                reach = end
        return total
    return stalled_between


class HostWitness(StallLog):
    def __init__(self, period_s: float = 0.001, tolerance_s: float = STALL_TOLERANCE_S,
                 clock: Callable[[], float] = time.monotonic):
        super().__init__(open_since=self._unrecorded_since)
        self.period_s, self.tolerance_s, self.clock = period_s, tolerance_s, clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
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

    def record(self, start: float, end: float) -> None:
        """A stall from `start` to `end`: the thread's own finding, or a test's."""
        super().record(start, end)
        self.last_wake = max(self.last_wake, end)

    def silent_since(self, now: float) -> float | None:
        """When the witness last woke, if that is longer ago than its tolerance (it has not been run since: the
        process, or its Python threads, were not run), else None."""
        last = self.last_wake
        return last if self.running and now - last > self.tolerance_s else None

    def _unrecorded_since(self, now: float) -> float | None:
        """A stall still unrecorded that reaches `now` (the witness silent for longer than its tolerance: a thread
        that asks right after the process resumed runs before the witness has woken to record the stall): from a
        period after its last wake-up."""
        silent = self.silent_since(now)
        return None if silent is None else silent + self.period_s
