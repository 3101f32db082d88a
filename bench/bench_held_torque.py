"""How long a walking BRUCE tolerates a held torque: the measurement behind `safety.host_stall_bound_s`.

When the host is not run (a VM stall, a page fault, a higher-priority task), the motors keep the last current
they were sent, as they do between any two ticks, until the host comes back or their own watchdog fires. This
bench holds the torque for k ms at a random gait phase and lets the run go on for `--after` s: does the robot
still stand? The mock's `HoldingMock` steps the physics k extra 1-ms steps inside one read(), the command (bus
delay line, motor lag) and the sensor path advancing per physics step as in time, so the loop's next tick sees
the state k ms later, as after a real stall (the loop then goes on at once: it skips the missed deadlines).

Cases: standing (the policy at a zero command), walking at 0.4 m/s and at -0.5 m/s; the nominal mock and the
`default` reality gap; the robot's own estimator (`kinematic`) and direct transfer (Eq. 8). The hold starts at a
seeded random time in [--start, --start + 1) s, after the walk has settled. A run falls when the base drops
(the mock's fall rule, `runtime.loop.falls`). Per case and k: the runs that fell of the phases tried.

The result: the shortest k at which any case fell, and the bound set below it with a margin
(docs/results/safety_held_torque.md).
Each finished run is appended to OUT/held_torque.jsonl; a second call with the same OUT skips those (resume).

    python bench/bench_held_torque.py --out /tmp/held [--phases 6] [--jobs 2]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bruce_hw.backend import LifecycleState
from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.reality_gap import load_gap
from runtime.control.commands import CommandSchedule

CASES = {"stand": (0.0, 0.0, 0.0), "walk 0.4 m/s": (0.4, 0.0, 0.0), "walk -0.5 m/s": (-0.5, 0.0, 0.0)}
GAPS = ("none", "default")
HOLDS_MS = (0, 10, 20, 30, 40, 50, 60, 75, 100)


class HoldingMock(MujocoBackend):
    """The mock whose active read number `at` first steps the physics `k` extra 1-ms steps with the torque held."""

    def __init__(self, config, gap, at: int, k: int):
        super().__init__(config, gap=gap)
        self.at, self.k = at, k
        self.active_reads = 0

    def _read(self):
        if self._state is LifecycleState.ACTIVE:
            self.active_reads += 1
            if self.active_reads == self.at:
                for _ in range(self.k):
                    super()._read()  # motor torque of the held command, mj_step, the sensor path
        return super()._read()


def run_one(job: dict) -> dict:
    from runtime.loop.run import run_session

    # The loop's rate floor would end the run at the stall itself: set aside, since this measures the robot.
    config = load_config(overrides=["safety.min_rate_hz=50", "safety.rate_window_s=1.0"])
    gap = None if job["gap"] == "none" else load_gap(job["gap"])
    rng = np.random.default_rng([job["phase"], 4242])
    start_s = job["start_s"] + float(rng.random())
    backend = HoldingMock(config, gap, at=round(start_s * config.loop_hz), k=job["k_ms"])
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        summary = run_session(backend, config, duration=start_s + job["after_s"], realtime=False,
                              estimator="kinematic", commands=CommandSchedule.constant(*CASES[job["case"]]))
    truth = summary.truth
    return {**job, "hold_at_s": start_s, "fell": bool(truth is not None and truth.fell),
            "ticks": summary.ticks, "stop_cause": summary.stop_cause}


def key(job: dict) -> tuple:
    return job["case"], job["gap"], job["k_ms"], job["phase"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="folder for held_torque.jsonl (resumable)")
    parser.add_argument("--phases", type=int, default=6, help="hold start times per case and k (seeded)")
    parser.add_argument("--holds-ms", default=",".join(map(str, HOLDS_MS)))
    parser.add_argument("--start", type=float, default=2.0, help="earliest hold start, s after activation")
    parser.add_argument("--after", type=float, default=3.0, help="s run on after the hold")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "held_torque.jsonl"
    done = {key(r): r for r in map(json.loads, path.read_text().splitlines())} if path.exists() else {}
    jobs = [{"case": case, "gap": gap, "k_ms": k, "phase": phase, "start_s": args.start, "after_s": args.after}
            for case in CASES for gap in GAPS for k in map(int, args.holds_ms.split(","))
            for phase in range(args.phases)]
    todo = [j for j in jobs if key(j) not in done]
    print(f"{len(jobs)} runs, {len(jobs) - len(todo)} already in {path}")
    with ProcessPoolExecutor(args.jobs) as pool, path.open("a") as log:
        for i, result in enumerate(pool.map(run_one, todo), 1):
            done[key(result)] = result
            log.write(json.dumps(result) + "\n")
            log.flush()
            if i % 20 == 0:
                print(f"  {i}/{len(todo)}")
    holds = sorted({j["k_ms"] for j in jobs})
    print("\nruns that fell / runs, per case, gap and held torque (ms):\n")
    print("| case | gap | " + " | ".join(f"{k} ms" for k in holds) + " |")
    print("|---|---|" + "---|" * len(holds))
    first_fall = None
    for case in CASES:
        for gap in GAPS:
            cells = []
            for k in holds:
                runs = [done[key(j)] for j in jobs if (j["case"], j["gap"], j["k_ms"]) == (case, gap, k)]
                fell = sum(r["fell"] for r in runs)
                cells.append(f"{fell}/{len(runs)}")
                if fell and (first_fall is None or k < first_fall):
                    first_fall = k
            print(f"| {case} | {gap} | " + " | ".join(cells) + " |")
    print(f"\nshortest held torque that felled any case: {first_fall} ms" if first_fall is not None
          else "\nno case fell at any held torque tried")


if __name__ == "__main__":
    main()
