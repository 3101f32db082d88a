"""Cost of rerun telemetry on the 1 kHz control thread: `Telemetry.append` with its consumer thread running.

Measures, in one run, a loop paced to 1 kHz by `runtime.pacing.Pacer` whose body makes fresh copies of five
10-joint arrays (as the loop passes them) and, with telemetry on, calls `Telemetry.append` every tick and
`append_pose` every 20 ticks (sink save= to a temporary .rrd, the MuJoCo mock's model, so the 3-D geometry and
poses are sent too). Telemetry off is the same body without the calls. Reported per tick: the telemetry calls
alone, the whole body (which also pays for the arrays staying alive until the consumer sends them), and how late
the ticks start (the consumer holds the GIL while it batches; the loop can only start once it gets it back).
Like `bruce-run --realtime`, the loop runs on the last allowed CPU and the telemetry threads on the others.
Goal: <= 5 µs per tick in telemetry on the control thread.

    python bench/bench_telemetry.py [--ticks 30000] [--switch-interval 0.005]
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bruce_hw import load_config, make_backend
from runtime.pacing import Pacer
from runtime.telemetry import Telemetry, parse_sink

GOAL_US = 5.0
POSE_EVERY = 20


def paced_loop(config, mock, telemetry: Telemetry | None, ticks: int) -> dict[str, np.ndarray]:
    """Per-tick µs: the telemetry calls, the whole body, and how late the tick started."""
    joints = np.linspace(-0.5, 0.5, config.n_joints)
    calls, bodies, late = (np.empty(ticks) for _ in range(3))
    clock = time.perf_counter_ns
    pacer = Pacer(config.dt)
    gc.collect()
    gc.disable()  # as in the loop: its allocations are acyclic
    try:
        pacer.start()
        for tick in range(ticks):
            behind = pacer.wait()
            t0 = clock()
            q, qd, a, tau_star, tau = (joints.copy() for _ in range(5))
            poses = mock.body_poses() if tick % POSE_EVERY == 0 else None
            t1 = clock()
            if telemetry is not None:
                telemetry.append(tick, tick * config.dt, q, qd, None, None, a, tau_star, tau, 1000.0, 60.0, 0)
                if poses is not None:
                    telemetry.append_pose(tick, tick * config.dt, *poses)
            t2 = clock()
            calls[tick], bodies[tick], late[tick] = (t2 - t1) / 1e3, (t2 - t0) / 1e3, behind / 1e3
    finally:
        gc.enable()
    return {"calls": calls, "bodies": bodies, "late": late}


def pin(cpus: set[int]) -> None:
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, cpus)  # the calling thread; threads started afterwards inherit it


def row(label: str, values: np.ndarray) -> str:
    return (f"  {label:34s} median {np.median(values):6.2f}  mean {values.mean():6.2f}  "
            f"p99 {np.percentile(values, 99):7.2f}  max {values.max():8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=30_000, help="ticks per measurement (1 kHz: 1 s per 1000)")
    parser.add_argument("--switch-interval", type=float, default=None,
                        help="sys.setswitchinterval (s) for the run; default: leave CPython's 0.005")
    args = parser.parse_args()
    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    loop_cpu, others = (allowed[-1], set(allowed[:-1])) if len(allowed) > 1 else (None, set(allowed))
    config = load_config()
    mock = make_backend("mock", config)
    mock.configure()

    if loop_cpu is not None:
        pin({loop_cpu})
    off = paced_loop(config, mock, None, args.ticks)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.rrd"
        telemetry = Telemetry(config, parse_sink(f"save={path}"), model=mock.model)
        if loop_cpu is not None:
            pin(others)  # the consumer and rerun's own threads start here and inherit these CPUs
        started = time.perf_counter()
        telemetry.start()
        start_s = time.perf_counter() - started
        if loop_cpu is not None:
            pin({loop_cpu})
        cpu0, main0 = time.process_time(), time.thread_time()
        on = paced_loop(config, mock, telemetry, args.ticks)
        others_cpu = (time.process_time() - cpu0) - (time.thread_time() - main0)
        closing = time.perf_counter()
        telemetry.close()
        close_s = time.perf_counter() - closing
        size_mb = path.stat().st_size / 1e6

    extra = on["calls"] - off["calls"]
    print(f"telemetry on the control thread, {args.ticks} ticks paced to 1 kHz per measurement, "
          f"loop on CPU {loop_cpu}, telemetry threads on {sorted(others) or 'the same CPU'}, "
          f"switch interval {sys.getswitchinterval() * 1e6:.0f} µs:")
    print("per tick, µs")
    print(row("off: timer pair only", off["calls"]))
    print(row("on: append (+ append_pose /20)", on["calls"]))
    print(row("off: loop body (5 array copies)", off["bodies"]))
    print(row("on: loop body + telemetry", on["bodies"]))
    print(row("off: tick start, late by", off["late"]))
    print(row("on: tick start, late by", on["late"]))
    print(f"  on - off, telemetry calls: median {np.median(on['calls']) - np.median(off['calls']):.2f} µs, "
          f"mean {extra.mean():.2f} µs; loop body: median "
          f"{np.median(on['bodies']) - np.median(off['bodies']):.2f} µs, mean "
          f"{on['bodies'].mean() - off['bodies'].mean():.2f} µs")
    print(f"  ticks starting > 250 µs late: off {int(np.sum(off['late'] > 250))}, on {int(np.sum(on['late'] > 250))}")
    print(f"rows sent {telemetry.sent_rows}, dropped {telemetry.dropped}; poses sent {telemetry.sent_poses}, "
          f"dropped {telemetry.dropped_poses}; error {telemetry.error!r}")
    print(f"start() {start_s * 1e3:.0f} ms, close() {close_s * 1e3:.0f} ms, .rrd {size_mb:.1f} MB, "
          f"telemetry threads' CPU {100 * others_cpu / (args.ticks * config.dt):.1f} % of one core")
    mean_cost = on["calls"].mean()
    print(f"goal <= {GOAL_US:.0f} µs per tick in telemetry on the control thread (mean of the calls): "
          f"{'met' if mean_cost <= GOAL_US else 'NOT met'} ({mean_cost:.2f} µs)")


if __name__ == "__main__":
    main()
