"""Lost and corrupted BEAR replies: `bruce-run --backend hw` stands against `bruce-emulate --realtime` whose BEAR
bus drops (or corrupts) each reply with a given probability.

A lost reply is not a fault: the actuator keeps its last sample and its age counts; the run goes to damping only
when one actuator loses more than `safety.reply_loss_max` (3 %) of its replies over `safety.reply_loss_window_s`
(1 s), or a sample gets older than `safety.max_sensor_age_s`. Goals (issue "Safe on a real robot"): at 1 % dropped
and at 1 % corrupted a stand completes, the losses counted in the stats; at 5 % the run ends in damping with a
message that names the loss rate. Printed per case: how the run ended, replies lost, late share, the data age
p50/p99 (oldest joint or IMU sample when the tick read it) and the legs' bus-thread cycle p50/p99.

Two modes:
- `lockstep` (default): `bruce-emulate --lockstep` (the physics steps once per bulk cycle) and the session in this
  process, paced, with the robot config as shipped.
- `realtime`: `bruce-emulate --realtime` and `bruce-run --backend hw` paced at 1 kHz in a process of its own: the
  late share and data age a robot would see.

    python bench/bench_reply_loss.py [--seconds 30] [--mode lockstep|realtime]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from bruce_hw.emulation.process import EmulatorProcess

CASES = (("no loss", 0.0, 0.0), ("1 % dropped", 0.01, 0.0), ("1 % corrupted", 0.0, 0.01),
         ("5 % dropped", 0.05, 0.0), ("5 % corrupted", 0.0, 0.05))


def stand_lockstep(emulator: EmulatorProcess, seconds: float, overrides: list[str]) -> tuple[dict, int]:
    import contextlib
    import io

    from bruce_hw.backend import BackendError
    from bruce_hw.config import load_config
    from bruce_hw.hw import make_hw_backend
    from runtime.loop.run import exit_code_of, run_session

    config = load_config(overrides=emulator.overrides + overrides)
    with tempfile.TemporaryDirectory() as tmp:
        stats_path = Path(tmp) / "stats.json"
        code = 0
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                code = run_session(make_hw_backend(config, check_imu=False), config, duration=seconds,
                                   realtime=True, controller_kind="standing", stats_path=stats_path).exit_code
            except BackendError as exc:
                code = exit_code_of(exc)
        return json.loads(stats_path.read_text()), int(code)


def stand(emulator: EmulatorProcess, seconds: float, overrides: list[str]) -> tuple[dict, int]:
    with tempfile.TemporaryDirectory() as tmp:
        stats_path = Path(tmp) / "stats.json"
        run = subprocess.run(emulator.bruce_run_argv(seconds, stats_path, overrides=overrides), capture_output=True,
                             text=True, timeout=seconds + 120)
        if not stats_path.exists():
            sys.exit(f"bruce-run wrote no stats ({run.returncode}):\n{run.stdout}\n{run.stderr}")
        return json.loads(stats_path.read_text()), run.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--seed", type=int, default=0, help="seed of the emulator's loss draws")
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="robot config override for the runs, e.g. safety.max_sensor_age_s=0.02 (printed)")
    args = parser.parse_args()
    if args.overrides:
        print("config overrides: " + " ".join(args.overrides))
    print(f"stand {args.seconds:g} s per case, standing controller, mode {args.mode}: " + (
        "bruce-emulate --lockstep, session paced in this process" if args.mode == "lockstep"
        else "bruce-emulate --realtime, bruce-run --backend hw paced in its own process"))
    print(f"{'case':15s} {'exit':>4s} {'ticks':>6s} {'lost':>6s} {'lost %':>7s} {'late %':>7s} "
          f"{'age p50/p99 µs':>15s} {'bus p50/p99 µs':>16s}  end")
    for name, drop, corrupt in CASES:
        with EmulatorProcess("--realtime", *(["--lockstep"] if args.mode == "lockstep" else []), "--bear-drop",
                             str(drop), "--bear-corrupt", str(corrupt), "--loss-seed", str(args.seed)) as emulator:
            stats, code = (stand_lockstep if args.mode == "lockstep" else stand)(emulator, args.seconds,
                                                                                args.overrides)
        legs = (stats.get("link") or {}).get("legs", {})
        age, read = stats["data_age_us"], legs.get("bus_cycle_us") or {"p50": None, "p99": None}
        completed = stats["stop_cause"] == "duration reached"
        end = "completed" if completed else f"damping: {stats['stop_cause']}"
        print(f"{name:15s} {code:4d} {stats['ticks']:6d} {legs.get('replies_lost_total', 0):6d} "
              f"{100 * legs.get('reply_loss_share', 0.0):7.2f} {100 * stats['late_share']:7.2f} "
              f"{age['p50'] or 0:7.0f}/{age['p99'] or 0:<7.0f} {read['p50'] or 0:7.0f}/{read['p99'] or 0:<8.0f} {end}")


if __name__ == "__main__":
    main()
