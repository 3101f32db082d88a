"""A witness of the machine itself: one tiny process per CPU at SCHED_FIFO 90 (above everything the stack runs)
that wakes every millisecond and reports each wake-up later than a threshold. Nothing of ours can delay it; only the
kernel with interrupts off, or a hypervisor that did not run the virtual CPU, can. So a stall the witness saw at the
moment a run tripped was the machine's, not the loop's.

    python bench/stall_witness.py --cpu 1 [--threshold-ms 2]   # prints `stall <time.monotonic()> <ms>` lines

`Witness(cpus)` runs one per CPU around a benchmark (used by bench_hw_emulated.py); without SCHED_FIFO (no
privileges) it still runs, and says so.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

PERIOD_S = 0.001
PRIORITY = 90


def watch(cpu: int, threshold_s: float) -> None:
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY))
        print(f"witness cpu {cpu} SCHED_FIFO {PRIORITY}", flush=True)
    except (AttributeError, OSError) as exc:
        print(f"witness cpu {cpu} without SCHED_FIFO ({exc}): its stalls may be its own", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    due = time.monotonic() + PERIOD_S
    while True:
        time.sleep(max(0.0, due - time.monotonic()))
        now = time.monotonic()
        if now - due > threshold_s:
            print(f"stall {due:.6f} {1e3 * (now - due):.2f}", flush=True)
        due = max(due + PERIOD_S, now)


class Witness:
    """One witness process per CPU while the `with` block runs; `stalls` afterwards: (start, ms) by time."""

    def __init__(self, cpus: list[int] | None = None, threshold_ms: float = 2.0):
        self.cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
        self.threshold_ms = threshold_ms
        self.stalls: list[tuple[float, float]] = []
        self.notes: list[str] = []
        self._procs: list[subprocess.Popen] = []

    def __enter__(self) -> Witness:
        for cpu in self.cpus:
            self._procs.append(subprocess.Popen(
                [sys.executable, __file__, "--cpu", str(cpu), "--threshold-ms", str(self.threshold_ms)],
                stdout=subprocess.PIPE, text=True))
        return self

    def __exit__(self, *exc) -> None:
        for proc in self._procs:
            proc.terminate()
        for proc in self._procs:
            out, _ = proc.communicate(timeout=5)
            for line in out.splitlines():
                words = line.split()
                if words[:1] == ["stall"]:
                    self.stalls.append((float(words[1]), float(words[2])))
                else:
                    self.notes.append(line)
        self.stalls.sort()

    def between(self, start: float, end: float) -> list[tuple[float, float]]:
        return [s for s in self.stalls if start <= s[0] <= end]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cpu", type=int, required=True)
    parser.add_argument("--threshold-ms", type=float, default=2.0)
    args = parser.parse_args()
    watch(args.cpu, args.threshold_ms / 1e3)


if __name__ == "__main__":
    main()
