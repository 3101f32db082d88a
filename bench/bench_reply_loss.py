"""Lost and corrupted BEAR replies: `bruce-run --backend hw` stands against `bruce-emulate --realtime` whose BEAR
bus drops (or corrupts) each reply with a given probability.

A lost reply is not a fault: the actuator keeps its last sample and its age counts; the run goes to damping only
when one actuator loses more than `safety.reply_loss_max` (3 %) of its replies over `safety.reply_loss_window_s`
(1 s), or a sample gets older than `safety.max_sensor_age_s`. Goals (issue "Safe on a real robot"): at 1 % dropped
and at 1 % corrupted a stand completes, the losses counted in the stats; at 5 % the run ends in damping with a
message that names the loss rate. Printed per case: how the run ended, replies lost, late share, the data age
p50/p99 (oldest joint or IMU sample when the tick read it) and the bulk cycle (read section) p50/p99.

    python bench/bench_reply_loss.py [--seconds 30]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from drivers.emulators.cli import EmulatorProcess

CASES = (("no loss", 0.0, 0.0), ("1 % dropped", 0.01, 0.0), ("1 % corrupted", 0.0, 0.01),
         ("5 % dropped", 0.05, 0.0), ("5 % corrupted", 0.0, 0.05))


def stand(emulator: EmulatorProcess, seconds: float) -> tuple[dict, int]:
    with tempfile.TemporaryDirectory() as tmp:
        stats_path = Path(tmp) / "stats.json"
        argv = [sys.executable, "-m", "runtime.cli", *emulator.command_line[1:], "--controller", "standing",
                "--duration", str(seconds), "--rerun", "off", "--stats", str(stats_path)]
        run = subprocess.run(argv, capture_output=True, text=True, timeout=seconds + 120)
        if not stats_path.exists():
            sys.exit(f"bruce-run wrote no stats ({run.returncode}):\n{run.stdout}\n{run.stderr}")
        return json.loads(stats_path.read_text()), run.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=0, help="seed of the emulator's loss draws")
    args = parser.parse_args()
    print(f"stand {args.seconds:g} s per case, bruce-emulate --realtime, standing controller")
    print(f"{'case':15s} {'exit':>4s} {'ticks':>6s} {'lost':>6s} {'lost %':>7s} {'late %':>7s} "
          f"{'age p50/p99 µs':>15s} {'read p50/p99 µs':>16s}  end")
    for name, drop, corrupt in CASES:
        with EmulatorProcess("--realtime", "--bear-drop", str(drop), "--bear-corrupt", str(corrupt),
                             "--loss-seed", str(args.seed)) as emulator:
            stats, code = stand(emulator, args.seconds)
        legs = (stats.get("link") or {}).get("legs", {})
        age, read = stats["data_age_us"], stats["sections_us"].get("read", {"p50": None, "p99": None})
        completed = stats["stop_cause"] == "duration reached"
        end = "completed" if completed else f"damping: {stats['stop_cause']}"
        print(f"{name:15s} {code:4d} {stats['ticks']:6d} {legs.get('replies_lost_total', 0):6d} "
              f"{100 * legs.get('reply_loss_share', 0.0):7.2f} {100 * stats['late_share']:7.2f} "
              f"{age['p50'] or 0:7.0f}/{age['p99'] or 0:<7.0f} {read['p50'] or 0:7.0f}/{read['p99'] or 0:<8.0f} {end}")


if __name__ == "__main__":
    main()
