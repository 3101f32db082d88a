"""The control thread's cost of the robot's transfer schemes, in CPU time, next to Eq. 9's, measured in one run
(issue #33, item 5).

Each scheme walks the `default`-gap mock at 0.4 m/s, paced to the wall clock as on the robot, robot-faithful (the
kinematic estimator; the twin resynchronised from it and stepping on its own thread). The figure is the tick's own
CPU time (`LoopStats.cpu`: the control thread's CPU clock over the tick, which a VM that does not run the thread
does not advance), so the machine's stalls do not enter it. The twin thread's CPU time is the process's CPU time
less the control thread's, per tick. Schemes run interleaved, `--rounds` times each, and the percentiles are pooled
over the rounds.

Goal (issue #33): the recommended scheme's control-thread CPU time p99 <= 1.5x Eq. 9's.

    python bench/bench_robot_transfer_cost.py [--seconds 10] [--rounds 2] [--schemes eq9,shadow,shadow_twin]
"""

from __future__ import annotations

import argparse
import time

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import load_gap
from runtime.control.commands import CommandSchedule
from runtime.loop.loopstats import Histogram
from runtime.loop.run import run_session

RATIO_GOAL = 1.5
RECOMMENDED = "shadow_twin"


def merged(histograms: list[Histogram]) -> Histogram:
    out = Histogram()
    for h in histograms:
        out.counts = [a + b for a, b in zip(out.counts, h.counts, strict=True)]
        out.n += h.n
        out.max_ns = max(out.max_ns, h.max_ns)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--schemes", default="eq9,shadow,shadow_twin")
    args = parser.parse_args()
    schemes = args.schemes.split(",")
    config = load_config()
    period_us = 1e6 / config.loop_hz
    cpu: dict[str, list[Histogram]] = {s: [] for s in schemes}
    sections: dict[str, dict[str, list[Histogram]]] = {s: {} for s in schemes}
    twin_us: dict[str, list[float]] = {s: [] for s in schemes}
    late: dict[str, list[float]] = {s: [] for s in schemes}
    for _ in range(args.rounds):
        for scheme in schemes:
            process0 = time.process_time()
            summary = run_session(MujocoBackend(config, gap=load_gap("default")), config, duration=args.seconds,
                                  realtime=True, transfer=scheme, estimator="kinematic",
                                  commands=CommandSchedule.constant(0.4, 0.0, 0.0))
            process_s = time.process_time() - process0
            stats = summary.loop
            cpu[scheme].append(stats.cpu)
            for name, h in stats.sections.items():
                sections[scheme].setdefault(name, []).append(h)
            control_s = sum(us * count for us, count in enumerate(stats.cpu.counts)) / 1e6  # lower edges: a floor
            twin_us[scheme].append(max(0.0, process_s - control_s) / max(1, stats.ticks) * 1e6)
            late[scheme].append(100.0 * stats.late_ticks / max(1, stats.ticks))
            if summary.truth is not None and summary.truth.fell:
                print(f"warning: {scheme} fell")
    rows = {}
    print(f"\ncontrol thread CPU time per tick, {args.rounds} x {args.seconds:g} s per scheme, paced, default gap, "
          f"kinematic estimator (period {period_us:.0f} µs)")
    print("| scheme | p50 µs | p99 µs | p99.9 µs | p99 / period | p99 / Eq. 9's | pinn section p99 µs | "
          "other threads' CPU per tick µs | late % |")
    print("|---|---|---|---|---|---|---|---|---|")
    base = merged(cpu["eq9"]).percentile(99) if "eq9" in cpu else None
    for scheme in schemes:
        h = merged(cpu[scheme])
        p50, p99, p999 = h.percentile(50), h.percentile(99), h.percentile(99.9)
        ratio = p99 / base if base else float("nan")
        rows[scheme] = ratio
        pinn = merged(sections[scheme]["pinn"]).percentile(99)
        print(f"| {scheme} | {p50:.0f} | {p99:.0f} | {p999:.0f} | {p99 / period_us:.2f} | {ratio:.2f} | {pinn:.0f} | "
              f"{sum(twin_us[scheme]) / len(twin_us[scheme]):.0f} | {sum(late[scheme]) / len(late[scheme]):.3f} |")
    if RECOMMENDED in rows and base:
        verdict = "met" if rows[RECOMMENDED] <= RATIO_GOAL else "NOT met"
        print(f"\n{RECOMMENDED} / eq9 control-thread CPU p99: {rows[RECOMMENDED]:.2f} "
              f"(goal <= {RATIO_GOAL}: {verdict})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
