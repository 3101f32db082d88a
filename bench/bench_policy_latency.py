"""How much loop latency a walking policy walks through under the robot's own estimator: the mock as the robot
(`--estimator kinematic`: IMU, leg kinematics and contacts, no simulator truth), with a reality-gap profile that has
nothing but latency, the actuator's (the command reaches the joints `a` ms late) and the sensors' (the reading is
`s` ms old when the tick uses it), for each policy, command and (a, s) on a grid.

    python bench/bench_policy_latency.py [--policies configs/robots/policies/bruce_walk.onnx,...] \
        [--cmds 0.4,0,0 -0.5,0,0] [--ms 0,1,2,3] [--seconds 30]

Why: on the hw path against `bruce-emulate` a reading is the reply delay plus up to a tick old when the tick uses
it, and a command waits for the bus cycle in flight (docs/results/timing.md): 1-2 ms of each on a clean bus, 2-4 ms
with the 0.7 + U(0, 1.5) ms reply delay of issue #34's series. A policy that falls at that latency in the mock falls
on the hw path whatever the scheduling. Each cell: `bruce-run --backend mock` in a process of its own; `ok` or the
simulated second it fell at (the safety stage's tilt bound, or a target beyond what the joint can be asked).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_POLICIES = ("configs/robots/policies/bruce_walk.onnx", "configs/robots/policies/bruce_walk_rl.onnx")


def walk(policy: str, cmd: str, actuator_ms: float, sensor_ms: float, seconds: float, tmp: Path) -> tuple[bool, float]:
    """(completed, simulated seconds walked) of one mock run with that latency."""
    gap = tmp / "latency.yaml"
    gap.write_text(f"actuator:\n  latency_s: {actuator_ms / 1e3:g}\nsensor:\n  latency_s: {sensor_ms / 1e3:g}\n")
    stats = tmp / "stats.json"
    stats.unlink(missing_ok=True)
    argv = [sys.executable, "-m", "runtime.cli", "--backend", "mock", "--policy", policy, f"--cmd={cmd}",
            "--duration", str(seconds), "--gap", str(gap), "--estimator", "kinematic", "--rerun", "off",
            "--stats", str(stats)]
    run = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    if not stats.exists():
        sys.exit(f"bruce-run failed ({run.returncode}):\n{run.stdout}\n{run.stderr}")
    s = json.loads(stats.read_text())
    return s["fault_class"] is None, s["ticks"] * 1e-3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policies", default=",".join(DEFAULT_POLICIES), help="comma-separated ONNX policies")
    parser.add_argument("--cmds", nargs="+", default=["0.4,0,0", "-0.5,0,0"], metavar="VX,VY,WZ")
    parser.add_argument("--ms", default="0,1,2,3", help="latencies in ms, the same list for actuator and sensor")
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    grid = [float(x) for x in args.ms.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        for policy in args.policies.split(","):
            for cmd in args.cmds:
                print(f"\n{Path(policy).name}, --cmd {cmd}, {args.seconds:g} s, estimator kinematic: "
                      "rows actuator latency, columns sensor latency (ms); ok or the second it fell at", flush=True)
                print("| actuator \\ sensor | " + " | ".join(f"{s:g}" for s in grid) + " |")
                print("|---" * (len(grid) + 1) + "|")
                for a in grid:
                    cells = []
                    for s in grid:
                        done, walked = walk(policy, cmd, a, s, args.seconds, Path(tmp))
                        cells.append("ok" if done else f"fell {walked:.1f} s")
                    print(f"| {a:g} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
