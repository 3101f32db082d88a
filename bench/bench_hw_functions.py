"""Where the hw path's CPU goes, function by function: `bruce-run --backend hw` against `bruce-emulate --realtime`
(two processes, paced, as bench_hw_emulated.py runs them), with the functions below wrapped to add up the CPU time
of each call (`time.thread_time_ns` of the calling thread) on the thread that runs them every tick or cycle: the
control thread and the legs' bus thread. Per function: calls, p50 and p99 µs of CPU a call, the first second left
out (start-up). The wrapper itself costs about 1 µs a call, counted in the callers' figures.

    python bench/bench_hw_functions.py [--seconds 10] [--cmd 0.4,0,0] [--set KEY=VALUE ...]

The stats' sections (`sections_cpu_us`) say which part of the tick costs; this says which function inside it.

`--again`: the policy's network, a pure function of its observation, is called a second time at once on the same
observation, its result dropped, and that call's CPU counted apart ("again at once"): in the same run and on the
same tick, what the call costs on warm caches against what it cost as the tick ran it (bench_cold_calls.py: what
cools them).
"""

from __future__ import annotations

import argparse
import atexit
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

SKIP_S = 1.0  # start-up's calls (cold caches, the first cycles) left out

# (module, class, method, thread): the functions wrapped, on the thread whose calls count
WRAPPED = (
    ("bruce_hw.hw", "HwBackend", "_read", "MainThread"),
    ("bruce_hw.hw", "HwBackend", "_ride_through", "MainThread"),
    ("bruce_hw.hw", "HwBackend", "_write", "MainThread"),
    ("bruce_hw.bear_legs", "BearLegs", "silence", "MainThread"),
    ("bruce_hw.attitude", "MahonyAttitude", "update", "MainThread"),
    ("bruce_hw.host_witness", "StallLog", "stalled_between", "MainThread"),
    ("runtime.estimation.kinematic", "KinematicEstimator", "update", "MainThread"),
    ("runtime.loop.safety", "SafetyStage", "check", "MainThread"),
    ("runtime.loop.safety", "SafetyStage", "filter", "MainThread"),
    ("runtime.control.policy", "PolicyController", "__call__", "MainThread"),
    ("runtime.observation.builder", "ObservationBuilder", "build", "MainThread"),
    ("runtime.control.inference", "OnnxPolicy", "__call__", "MainThread"),
    ("bruce_hw.bear_legs", "BearLegs", "cycle", "hw-legs"),
    ("drivers.bear", "BearBus", "bulk_cycle", "hw-legs"),
    ("drivers.bear", "BearBus", "_exchange", "hw-legs"),
    ("drivers.bear", "BearBus", "_send", "hw-legs"),
    ("drivers.bear", "BulkReply", "in_order", "hw-legs"),
    ("bruce_hw.bear_legs", "BearLegs", "_keep", "hw-legs"),
    ("bruce_hw.bear_legs", "BearLegs", "_loss_problem", "hw-legs"),
)
PURE = {"OnnxPolicy.__call__"}  # called again at once with --again: the same input gives the same output, no state
AGAIN = "BENCH_HW_FUNCTIONS_AGAIN"  # the child's environment: --again


def child(argv: list[str]) -> int:
    """bruce-run itself, with WRAPPED wrapped; the table on stderr at exit."""
    import importlib

    calls: dict[str, list[tuple[int, int]]] = defaultdict(list)  # label -> (start ns, CPU ns)

    def wrap(owner, name: str, thread: str, label: str, again: bool) -> None:
        function, cpu, clock, current = getattr(owner, name), time.thread_time_ns, time.monotonic_ns, \
            threading.current_thread

        def wrapped(*args, **kwargs):
            if current().name != thread:
                return function(*args, **kwargs)
            start, c0 = clock(), cpu()
            result = function(*args, **kwargs)
            c1 = cpu()
            calls[label].append((start, c1 - c0))
            if again:
                function(*args, **kwargs)
                calls[label + " again at once"].append((start, cpu() - c1))
            return result
        setattr(owner, name, wrapped)

    for module, cls, name, thread in WRAPPED:
        wrap(getattr(importlib.import_module(module), cls), name, thread, f"{thread}: {cls}.{name}",
             bool(os.environ.get(AGAIN)) and f"{cls}.{name}" in PURE)
    begin = time.monotonic_ns()

    def table() -> None:
        print(f"{'function (thread)':58s} {'calls':>7s} {'p50 µs':>8s} {'p99 µs':>8s}", file=sys.stderr)
        rows = []
        for label, samples in calls.items():
            cpu = np.array([ns for start, ns in samples if start - begin > SKIP_S * 1e9]) / 1e3
            if cpu.size:
                rows.append((label, cpu.size, np.percentile(cpu, 50), np.percentile(cpu, 99)))
        for label, n, p50, p99 in sorted(rows, key=lambda row: (row[0].split(":")[0], -row[2])):
            print(f"{label:58s} {n:7d} {p50:8.1f} {p99:8.1f}", file=sys.stderr)
    atexit.register(table)
    from runtime.cli import main
    return main(argv)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        sys.exit(child(sys.argv[2:]))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--cmd", default=None, metavar="VX,VY,WZ", help="walk at this command (default: stand)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="bruce-run config overrides")
    parser.add_argument("--again", action="store_true",
                        help="call the policy's network again at once on the same observation, counted apart")
    args = parser.parse_args()
    from bruce_hw.emulation.process import EmulatorProcess

    with EmulatorProcess("--realtime") as emulator, tempfile.TemporaryDirectory() as tmp:
        emulator.send("place")
        argv = emulator.bruce_run_argv(args.seconds, Path(tmp) / "stats.json", cmd=args.cmd,
                                       overrides=args.overrides)
        module = argv.index("-m")  # python -m runtime.cli ... -> python this-file --child ...
        argv[module:module + 2] = [str(Path(__file__).resolve()), "--child"]
        env = dict(os.environ, **({AGAIN: "1"} if args.again else {}))
        run = subprocess.run(argv, capture_output=True, text=True, timeout=args.seconds + 120, env=env)
    ending = next((line for line in (run.stdout + run.stderr).splitlines()
                   if line.lstrip().startswith("final state")), "")
    print(f"bruce-run --backend hw {'--cmd ' + args.cmd if args.cmd else '--controller standing'}, "
          f"{args.seconds:g} s: {ending.strip() or f'exit {run.returncode}'}")
    table = run.stderr[run.stderr.find("function (thread)"):] if "function (thread)" in run.stderr else run.stderr
    print(table.rstrip())


if __name__ == "__main__":
    main()
