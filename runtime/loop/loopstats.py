"""Loop statistics: per-section and whole-tick timing histograms, lateness, the worst overruns.

Histograms have 1 µs bins up to 20 ms plus an overflow bin and keep the exact maximum, so recording is an
integer division and a list increment on the control thread (no allocation, no sorting), and percentiles
come out at 1 µs resolution at the end of the run, however long it was.
"""

from __future__ import annotations

import heapq
from collections import deque

SECTIONS = ("read", "policy", "pinn", "mixing", "safety", "write", "telemetry")
HISTOGRAM_BINS_US = 20_000
WORST_OVERRUNS_KEPT = 10
LATE_TICKS_KEPT = 1 << 17  # late ticks whose moment is kept for attributing them to the machine or the loop


def section_spans(marks: tuple[int, ...]) -> tuple[int, ...]:
    """A tick's SECTIONS, in their order, from its nine marks on one clock (`LoopStats.add_sections`)."""
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = marks
    return m1 - m0, m2 - m1, m4 - m3, m3 - m2 + m5 - m4, m6 - m5, m7 - m6, m8 - m7


class Histogram:
    __slots__ = ("counts", "n", "max_ns")

    def __init__(self):
        self.counts = [0] * (HISTOGRAM_BINS_US + 1)
        self.n = 0
        self.max_ns = 0

    def add(self, ns: int) -> None:
        us = ns // 1000
        self.counts[us if us < HISTOGRAM_BINS_US else HISTOGRAM_BINS_US] += 1
        self.n += 1
        if ns > self.max_ns:
            self.max_ns = ns

    def percentile(self, p: float) -> float | None:
        """Upper edge (µs) of the bin holding the p-th percentile, or the exact max if that is lower (always for
        the overflow bin)."""
        if self.n == 0:
            return None
        rank = p / 100.0 * self.n
        seen = 0
        for us, count in enumerate(self.counts):
            seen += count
            if seen >= rank and count:
                return min(float(us + 1), self.max_ns / 1000.0)  # never above the exact max
        return self.max_ns / 1000.0


class LoopStats:
    def __init__(self, sections: tuple[str, ...] = SECTIONS):
        self.work = Histogram()
        # The tick's own CPU time (the control thread's CPU clock over the same span as `work`): a VM that does not
        # run the thread does not advance it, so it is the loop's cost apart from the machine's stalls.
        self.cpu = Histogram()
        self.period = Histogram()
        self.data_age = Histogram()  # age of the oldest joint or IMU sample when the tick read it
        self.sections = {name: Histogram() for name in sections}
        self.cpu_sections = {name: Histogram() for name in sections}  # each section's CPU time, as `cpu` the tick's
        self._wall_list = [self.sections[name] for name in SECTIONS]  # add_sections' order
        self._cpu_list = [self.cpu_sections[name] for name in SECTIONS]
        self.period_s: float | None = None  # the loop's period, for CPU time as a share of it
        self.ticks = 0
        self.loop_s = 0.0  # from the first tick's start to the last one's (the achieved rate is ticks / loop_s)
        self.late_ticks = 0
        # (monotonic s of the tick's start, s it was behind, s the control thread's own CPU time alone would have
        # made it late: None where not known)
        self._late = deque(maxlen=LATE_TICKS_KEPT)
        self.late_after_s = 0.0  # a tick this far past its deadline is late (the pacer's bound)
        self.late_machine: int | None = None  # late ticks with a host stall in them (None: not attributed)
        self.late_own: int | None = None      # late ticks the loop's own CPU time made late
        self.late_not_run = 0                 # the rest: the control thread ready and not run
        self.skipped_ticks = 0
        self.breaths = 0  # short sleeps the pacer took after a period without one (runtime/loop/pacing.py)
        self._worst: list[int] = []  # min-heap of the largest lateness values (ns)
        # The tick whose sections took the most CPU time: (its index, its nine marks on each clock), so a run says
        # where its one long tick went, not only that the p99.9 has one.
        self._costliest: tuple[int, tuple[int, ...], tuple[int, ...]] | None = None
        self._costliest_ns = -1

    def add_sections(self, wall: tuple[int, ...], cpu: tuple[int, ...]) -> None:
        """One tick's sections from its nine marks (ns) on each clock: before read, after read, policy, Eq. 8,
        PINN, mixing, safety, write and telemetry. Mixing is Eq. 8 and the scheme's torque together."""
        if cpu[8] - cpu[0] > self._costliest_ns:
            self._costliest_ns = cpu[8] - cpu[0]
            self._costliest = (self.ticks, wall, cpu)
        for marks, hists in ((wall, self._wall_list), (cpu, self._cpu_list)):
            read, policy, pinn, mixing, safety, write, telemetry = hists  # unrolled: this runs twice every tick
            t_read, t_policy, t_pinn, t_mixing, t_safety, t_write, t_telemetry = section_spans(marks)
            read.add(t_read)
            policy.add(t_policy)
            pinn.add(t_pinn)
            mixing.add(t_mixing)
            safety.add(t_safety)
            write.add(t_write)
            telemetry.add(t_telemetry)

    def overrun(self, behind_ns: int, at_s: float | None = None, own_ns: int | None = None) -> None:
        """A late tick, `behind_ns` past its deadline, started at monotonic `at_s`; `own_ns`: how far past it the
        control thread's own CPU time since the previous tick's start would have taken it, had that tick started on
        time and run without a pause (that CPU time less one period)."""
        if at_s is not None:
            self._late.append((at_s, behind_ns / 1e9, None if own_ns is None else own_ns / 1e9))
        if len(self._worst) < WORST_OVERRUNS_KEPT:
            heapq.heappush(self._worst, behind_ns)
        elif behind_ns > self._worst[0]:
            heapq.heapreplace(self._worst, behind_ns)

    def attribute(self, stalled_between=None) -> None:
        """Split the late ticks three ways: the machine's (the process was not run in the period before the tick
        started: `stalled_between(t0, t1)`, the host witness; None: no witness), the loop's own (its CPU time since
        the previous tick's start alone, from an on-time start, ran past the deadline by more than `late_after_s`),
        and the rest: the control thread was ready and not run (a higher-priority thread on its CPU, the GIL held by
        another thread, a wake-up or a pause of the virtual CPU shorter than the witness sees), or inherited the
        lateness of a tick that started late."""
        period = self.period_s or 0.0
        machine = own = 0
        for at, behind, own_s in self._late:
            if stalled_between is not None and stalled_between(at - behind - period, at) > 0.0:
                machine += 1
            elif own_s is None or own_s > self.late_after_s:
                own += 1
        self.late_machine, self.late_own = machine, own
        self.late_not_run = self.late_ticks - machine - own

    def to_json(self) -> dict:
        attributed = {} if self.late_own is None else {
            "late_ticks_machine": self.late_machine, "late_ticks_loop": self.late_own,
            "late_ticks_not_run": self.late_not_run,
            "late_share_loop": self.late_own / self.ticks if self.ticks else 0.0}
        return {**attributed,
            "ticks": self.ticks,
            "late_ticks": self.late_ticks,
            "late_share": self.late_ticks / self.ticks if self.ticks else 0.0,
            "loop_s": self.loop_s,
            "rate_hz": (self.ticks - 1) / self.loop_s if self.loop_s > 0 else None,
            "skipped_ticks": self.skipped_ticks,
            "breaths": self.breaths,
            "work_us": {"p50": self.work.percentile(50), "p99": self.work.percentile(99),
                        "max": self.work.max_ns / 1000.0 if self.work.n else None},
            "cpu_us": {"p50": self.cpu.percentile(50), "p99": self.cpu.percentile(99),
                       "p99.9": self.cpu.percentile(99.9), "max": self.cpu.max_ns / 1000.0 if self.cpu.n else None},
            "period_us": {"p50": self.period.percentile(50), "p99": self.period.percentile(99),
                          "max": self.period.max_ns / 1000.0 if self.period.n else None},
            "data_age_us": {"p50": self.data_age.percentile(50), "p99": self.data_age.percentile(99),
                            "max": self.data_age.max_ns / 1000.0 if self.data_age.n else None},
            "sections_us": {name: {"p50": h.percentile(50), "p99": h.percentile(99)}
                            for name, h in self.sections.items() if h.n},
            "sections_cpu_us": {name: {"p50": h.percentile(50), "p99": h.percentile(99), "p99.9": h.percentile(99.9)}
                                for name, h in self.cpu_sections.items() if h.n},
            "cpu_share_of_period": self._cpu_shares(),
            "worst_overruns_us": [ns / 1000.0 for ns in sorted(self._worst, reverse=True)],
            "costliest_tick": self._costliest_json(),
        }

    def _costliest_json(self) -> dict | None:
        """The tick whose sections took the most CPU time: its index, its CPU and wall time, each section's CPU."""
        if self._costliest is None:
            return None
        tick, wall, cpu = self._costliest
        return {"tick": tick, "cpu_us": (cpu[8] - cpu[0]) / 1e3, "wall_us": (wall[8] - wall[0]) / 1e3,
                "sections_cpu_us": {name: ns / 1e3 for name, ns in zip(SECTIONS, section_spans(cpu), strict=True)}}

    def _cpu_shares(self) -> dict | None:
        """The tick's CPU time and each section's, p50/p99/p99.9, as shares of the loop's period."""
        if not self.period_s or not self.cpu.n:
            return None
        us = 1e6 * self.period_s

        def share(h: Histogram) -> dict:
            return {p: h.percentile(float(p[1:])) / us for p in ("p50", "p99", "p99.9")}
        return {"tick": share(self.cpu), **{name: share(h) for name, h in self.cpu_sections.items() if h.n}}

    def text(self) -> str:
        j = self.to_json()
        if not self.ticks:
            return "  loop: no ticks"

        def us(value: float | None) -> str:  # a one-tick run has no period
            return "-" if value is None else f"{value:.0f}"

        work, period = j["work_us"], j["period_us"]
        rate = "" if j["rate_hz"] is None else f"{j['rate_hz']:.0f} Hz, "
        lines = [f"  loop: {rate}work p50 {us(work['p50'])} / p99 {us(work['p99'])} / max {us(work['max'])} µs, period "
                 f"p50 {us(period['p50'])} / p99 {us(period['p99'])} / max {us(period['max'])} µs, late "
                 f"{self.late_ticks} ({100 * j['late_share']:.3f} %"
                 + ("" if self.late_own is None else
                    f": {self.late_machine} with the host stalled, {self.late_own} of the loop's own CPU time, "
                    f"{self.late_not_run} with the loop ready and not run")
                 + f"), skipped {self.skipped_ticks}, breaths {self.breaths}",
                 f"  tick CPU time p50 {us(j['cpu_us']['p50'])} / p99 {us(j['cpu_us']['p99'])} / p99.9 "
                 f"{us(j['cpu_us']['p99.9'])} µs",
                 f"  data age p50 {us(j['data_age_us']['p50'])} / p99 {us(j['data_age_us']['p99'])} / max "
                 f"{us(j['data_age_us']['max'])} µs"]
        parts = [f"{name} {v['p50']:.0f}/{v['p99']:.0f}" for name, v in j["sections_us"].items()]
        lines.append("  sections p50/p99 µs: " + ", ".join(parts))
        shares = j["cpu_share_of_period"]
        if shares:
            tick = shares["tick"]
            parts = [f"{name} {100 * v['p99']:.0f}" for name, v in shares.items() if name != "tick"]
            lines.append(f"  CPU time, % of the period: tick p50 {100 * tick['p50']:.0f} / p99 {100 * tick['p99']:.0f}"
                         f" / p99.9 {100 * tick['p99.9']:.0f}; sections p99: " + ", ".join(parts))
        costliest = j["costliest_tick"]
        if costliest:
            top = sorted(costliest["sections_cpu_us"].items(), key=lambda kv: -kv[1])[:3]
            lines.append(f"  the costliest tick: #{costliest['tick']}, CPU {costliest['cpu_us']:.0f} µs ("
                         + ", ".join(f"{name} {value:.0f}" for name, value in top) + ")")
        return "\n".join(lines)
