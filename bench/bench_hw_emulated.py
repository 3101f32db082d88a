"""`bruce-run --backend hw` against `bruce-emulate`: the whole stack with no robot, two processes as on the robot
(the emulated devices are other hardware).

1. Stand: `bruce-emulate --realtime` (emulators at SCHED_FIFO 40), then `bruce-run --backend hw --controller
   standing --duration S` as its own process with the printed --set options. Reported: the BEAR bulk-cycle rate
   (the hw backend's link summary), late ticks (> 250 µs behind the deadline) and their share, tick work and
   period, the base height at the end (from the emulator's physics), the BEARs' state after shutdown.
   Goals (issue #6): 1 kHz sustained, <= 1 % late ticks.
2. Faults, `--fault-trials N` each (in this process, through runtime.run.run_session): BEAR IDs 3 and 4 silenced,
   the E-stop input, the IMU stream stopped; time from the fault (the emulator's reply stamp, system monotonic
   clock) to the hw backend entering damping. Goal: bus silence -> damping within 10 ms.

    python bench/bench_hw_emulated.py [--seconds 10] [--fault-trials 3]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bruce_hw.backend import BackendError
from bruce_hw.config import load_config
from bruce_hw.hw import make_hw_backend
from drivers.emulators.cli import EmulatorProcess, FaultAt, reply_time
from runtime.run import run_session

LATE_SHARE_GOAL = 0.01
RATE_GOAL_HZ = 1000.0
SILENCE_GOAL_S = 0.010
FAULTS = (("BEAR IDs 3, 4 silent", "silence bear 3 4", "answer bear 3 4"),
          ("E-stop", "estop on", "estop off"),
          ("IMU stream stopped", "imu stop", "imu start"))


def stand(emulator: EmulatorProcess, seconds: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        stats_path = Path(tmp) / "stats.json"
        argv = [sys.executable, "-m", "runtime.cli", *emulator.command_line[1:], "--controller", "standing",
                "--duration", str(seconds), "--rerun", "off", "--stats", str(stats_path)]
        run = subprocess.run(argv, capture_output=True, text=True, timeout=seconds + 120)
        if not stats_path.exists():
            sys.exit(f"bruce-run failed ({run.returncode}):\n{run.stdout}\n{run.stderr}")
        stats = json.loads(stats_path.read_text())
    output = run.stdout + run.stderr
    link = re.search(r"(\d+) bulk cycles in ([\d.]+) s \((\d+) Hz\), (\d+) replies lost, (\d+) retries", output)
    grant = re.search(r"bruce-run: (realtime: .*)", output)
    status = emulator.status()
    plant, bear = status["plant"], status["bear"]
    print(f"1. stand {seconds:g} s: bruce-run {' '.join(emulator.command_line[1:])} --controller standing "
          f"(exit {run.returncode}; {grant.group(1) if grant else 'no realtime grant'})")
    print(f"   final state: {stats['final_state']} ({stats['stop_cause']}); error: {stats['error']}")
    late = stats["late_share"]
    rate = float(link.group(3)) if link else float("nan")
    print(f"   bulk cycles: {link.group(1) if link else '?'} in {link.group(2) if link else '?'} s = {rate:.0f} Hz "
          f"(goal {RATE_GOAL_HZ:.0f} Hz sustained: {'met' if rate >= 0.98 * RATE_GOAL_HZ else 'MISSED'}); "
          f"replies lost {link.group(4) if link else '?'}, retries {link.group(5) if link else '?'}")
    print(f"   late ticks: {stats['late_ticks']} of {stats['ticks']} = {100 * late:.3f} % (goal <= "
          f"{100 * LATE_SHARE_GOAL:.0f} %: {'met' if late <= LATE_SHARE_GOAL else 'MISSED'}); skipped "
          f"{stats.get('skipped_ticks', '?')}; worst overruns µs {[round(v) for v in stats['worst_overruns_us'][:5]]}")
    print(f"   tick work p50/p99/max {stats['work_us']['p50']:.0f}/{stats['work_us']['p99']:.0f}/"
          f"{stats['work_us']['max']:.0f} µs; read (one bulk cycle) p50/p99 {stats['sections_us']['read']['p50']:.0f}/"
          f"{stats['sections_us']['read']['p99']:.0f} µs; period p99 {stats['period_us']['p99']:.0f} µs")
    print(f"   base height at the end {plant['base_height']:.3f} m (nominal {plant['nominal_base_height']:.3f} m); "
          f"physics steps {plant['steps']} ({plant['late_steps']} late); BEAR torque_enable after shutdown "
          f"{bear['torque_enable']} (3 = damping)")


def faults(emulator: EmulatorProcess, trials: int) -> None:
    print(f"2. fault -> damping, {trials} trial(s) each (hw backend defaults: BEAR reply timeout 2 ms, no retry in "
          "a tick; safety.max_sensor_age_s)")
    for name, inject, undo in FAULTS:
        latencies, causes = [], set()
        for _ in range(trials):
            config = load_config(overrides=emulator.overrides)
            backend = make_hw_backend(config, check_imu=False)
            quiet = io.StringIO()  # the session's summary and log lines
            with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet), \
                    contextlib.suppress(BackendError):
                run_session(backend, config, duration=2.0, realtime=True, controller_kind="standing",
                            commands=FaultAt(emulator, inject))
            at = reply_time(emulator.reply())
            emulator.send(undo)
            if backend.fault_stamp is not None:
                latencies.append(backend.fault_stamp - at)
            causes.add(backend.fault_cause)
        ms = [1e3 * v for v in latencies]
        goal = ""
        if inject.startswith("silence"):
            goal = f" (goal <= {1e3 * SILENCE_GOAL_S:.0f} ms: {'met' if max(ms) <= 1e3 * SILENCE_GOAL_S else 'MISSED'})"
        print(f"   {name}: damping after {statistics.median(ms):.1f} ms median, {min(ms):.1f}..{max(ms):.1f} ms"
              f"{goal}; cause: {' | '.join(sorted(str(c) for c in causes))}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--fault-trials", type=int, default=3)
    parser.add_argument("--emulator-priority", choices=("realtime", "normal"), default="realtime",
                        help="bruce-emulate --realtime (SCHED_FIFO 40) or at normal priority")
    args = parser.parse_args()
    with EmulatorProcess(*(["--realtime"] if args.emulator_priority == "realtime" else [])) as emulator:
        stand(emulator, args.seconds)
        if args.fault_trials > 0:
            faults(emulator, args.fault_trials)


if __name__ == "__main__":
    main()
