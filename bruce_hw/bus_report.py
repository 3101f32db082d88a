"""What `bruce-hw-check` reports of one bus (`BusReport`: its devices, what is missing or faulty, warnings) and the
round trips it times (`RoundTrips`, `verdict_1khz`, `add_timing`): shared by every bus's check. The criteria and the
command line: bruce_hw/hw_check.py."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bruce_hw.bus_startup import ids_text

TICK_S = 0.001
COMPUTE_S = 0.0002            # a tick's own work besides the bus
HOLDS_P99_S = TICK_S - COMPUTE_S
RTT_REPLY_TIMEOUT_S = 0.05    # a slow reply is timed, not lost
PRESENCE_TIMEOUT_S = 0.02     # pings and reads: a device this late is as good as missing
PRESENCE_TRIES = 3            # requests in a row a device must leave unanswered to be missing: one lost reply is not


@dataclass
class BusReport:
    name: str
    lines: list[str] = field(default_factory=list)   # one per device, for people
    missing: list[int] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)  # "ID n: flags"
    warnings: list[str] = field(default_factory=list)
    error: str | None = None                         # the bus itself could not be used

    @property
    def ok(self) -> bool:
        return self.error is None and not self.missing and not self.faults

    def problem(self) -> str:
        """One phrase naming the bus and what is wrong with it (empty when ok)."""
        what = ([f"cannot use the bus ({self.error})"] if self.error else []) + (
            [f"missing {ids_text(self.missing)}"] if self.missing else []) + (
            [f"{len(self.faults)} device(s) with faults"] if self.faults else [])
        return f"{self.name.split(' (')[0]}: {', '.join(what)}" if what else ""

    def text(self) -> str:
        head = f"{self.name}: " + ("OK" if self.ok else "PROBLEM")
        body = [f"  {line}" for line in self.lines]
        if self.error:
            body.append(f"  cannot use the bus: {self.error}")
        if self.missing:
            body.append(f"  missing ID(s): {', '.join(str(i) for i in self.missing)}")
        body += [f"  fault: {f}" for f in self.faults] + [f"  warning: {w}" for w in self.warnings]
        return "\n".join([head, *body])



@dataclass
class RoundTrips:
    """Timed exchanges of one bus: seconds each (those that completed), and how many lost a reply."""

    what: str
    seconds: list[float] = field(default_factory=list)
    lost: int = 0

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.seconds, q)) if self.seconds else math.nan

    @property
    def p50(self) -> float:
        return self.percentile(50)

    @property
    def p99(self) -> float:
        return self.percentile(99)

    def line(self) -> str:
        """"round trip over 300 read-only bulk cycles of 10 IDs: p50 0.412 ms, p99 0.803 ms, max 1.210 ms"."""
        head = f"round trip over {len(self.seconds) + self.lost} {self.what}: "
        if not self.seconds:
            return head + "no exchange completed"
        text = head + (f"p50 {1e3 * self.p50:.3f} ms, p99 {1e3 * self.p99:.3f} ms, max {1e3 * max(self.seconds):.3f} "
                       "ms")
        return text + (f", {self.lost} lost a reply (not timed)" if self.lost else "")


def verdict_1khz(trips: RoundTrips) -> tuple[str, bool]:
    """(a phrase for people, whether the bus holds 1 kHz without help), by DESCRIPTION's criterion."""
    if not trips.seconds:
        return "cannot hold 1 kHz: no exchange completed", False
    if trips.p99 <= HOLDS_P99_S:
        return f"holds 1 kHz (p99 <= {1e3 * HOLDS_P99_S:.1f} ms)", True
    if trips.p50 <= TICK_S:
        return (f"holds 1 kHz only with late ticks or a bus thread (p99 > {1e3 * HOLDS_P99_S:.1f} ms, p50 <= "
                f"{1e3 * TICK_S:.1f} ms)"), False
    rate = 10 * math.floor(1.0 / (trips.p50 + COMPUTE_S) / 10)
    return (f"cannot hold 1 kHz: expect {rate} Hz (p50 {1e3 * trips.p50:.2f} ms + {1e3 * COMPUTE_S:.1f} ms of work "
            "per tick)"), False



def add_timing(report: BusReport, timing, verdict: tuple[str, bool]) -> None:
    """The figures and the verdict as one line of the report; a bus that cannot keep up is a warning too."""
    text, holds = verdict
    report.lines.append(f"{timing.line()}: {text}")
    if not holds and "cannot hold" in text:
        report.warnings.append(f"round trip: {text}")

