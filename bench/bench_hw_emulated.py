"""`bruce-run --backend hw` against `bruce-emulate`: the whole stack with no robot, two processes as on the robot
(the emulated devices are other hardware), on the wall clock.

1. Runs: `bruce-emulate [--realtime] [EMULATOR OPTIONS]`, then `bruce-run --backend hw --duration S` as its own
   process with the printed --set options: a stand (`--controller standing`) and, with `--cmd`, a walk (the policy at
   that command). Reported per run: how it ended, the achieved control rate (ticks per wall second), the late share
   (> 250 µs behind the deadline), the read section p50/p99, the legs' bus thread cycle p50/p99 and rate, the data
   age p99 and max, lost replies, the base height at the end (the emulator's physics).
   Goals (issue #19): no trip; >= 990 bulk cycles/s with no delay configured. Beside each run, a stall witness
   (bench/stall_witness.py: SCHED_FIFO 90 on every CPU) reports the machine's own stalls, and for a run that
   tripped, those in the 60 ms before the emulator saw damping: on a virtual machine the hypervisor stops virtual
   CPUs for 3-40 ms at times, which no scheduling inside it can prevent and the data-age bound must trip on. Beside
   them, what the emulated BEARs logged in those 60 ms: a request that came more than 4 ms after they last answered
   (the host's request late: not sent, or held in the kernel) or a reply that left more than 1 ms after it was due
   (the emulator late); neither means the replies left on time and the host did not get them in time.
2. Faults, `--fault-trials N` each (in this process, through runtime.loop.run.run_session): BEAR IDs 3 and 4 silenced,
   the E-stop input, the IMU stream stopped, the leg bus unplugged; time from the fault (the emulator's reply stamp,
   system monotonic clock) to the hw backend entering damping. Goals: silence, IMU stop, unplug <= 10 ms;
   E-stop <= 2 ms. The E-stop also from the moment the first reply that carries its bit left the emulated BEARs
   (their event log): what the host takes, apart from the bus's own reply delay.

    python bench/bench_hw_emulated.py [--seconds 30] [--cmd 0.4,0,0] [--transfer shadow_twin] [--runs 5] \
        [--fault-trials 3] [--emulator-args "--bear-delay 0.0007 --bear-jitter 0.0015"] [--set KEY=VALUE ...]

3. The series (issue #34's acceptance): `--conditions clean,delay,drop,corrupt` runs the stand and the walk under
   each named link condition (CONDITIONS: a fresh emulator each) and the fault trials under each; `--busy-core`
   with another process keeping one core busy at nice 19 the whole time. It ends with the tally: runs completed of
   all, and for each run that ended, its cause beside the longest machine stall the witness saw in the 60 ms before.

    python bench/bench_hw_emulated.py --seconds 30 --cmd 0.4,0,0 --runs 3 --conditions clean,delay,drop,corrupt \
        --fault-trials 5 [--busy-core]

Each run also reports the host stalls it counted itself (bruce_hw.host_witness), its late ticks split three ways
(with the host stalled; of the loop's own CPU time, which alone ran past the deadline from an on-time start; with
the loop ready and not run: a higher-priority thread on its CPU, the GIL, a pause shorter than the witness sees, or a
late start inherited), and the tick's CPU time as a share of the period (the loop's own cost, which a VM that does
not run the thread does not advance).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from stall_witness import Witness

from bruce_hw.backend import BackendError
from bruce_hw.config import load_config
from bruce_hw.emulation.process import EmulatorProcess, FaultAt, reply_time
from bruce_hw.hw import make_hw_backend
from runtime.loop.run import run_session

BULK_RATE_GOAL_HZ = 990.0
EXCHANGE_LATE = " ms after "  # the BEAR emulator's events for a late request or reply (drivers/emulators/bear.py)
ESTOP_SENT = "first reply with the E-stop bit sent"  # the BEAR emulator's event (drivers/emulators/bear.py)
TRIP_LOOKBACK_S = 0.06  # a machine stall this close before a trip explains it (the data-age bound is 8 ms)
CONDITIONS = {  # the link conditions of the series: bruce-emulate options
    "clean": "",
    "delay": "--bear-delay 0.0007 --bear-jitter 0.0015",   # 0.7 ms + U(0, 1.5 ms) on every BEAR answer
    "drop": "--bear-drop 0.01",                            # 1 % of BEAR replies never sent
    "corrupt": "--bear-corrupt 0.01",                      # 1 % of BEAR replies with a bad checksum
}
FAULTS = (("BEAR IDs 3, 4 silent", "silence bear 3 4", "answer bear 3 4", 0.010),
          ("E-stop", "estop on", "estop off", 0.002),
          ("IMU stream stopped", "imu stop", "imu start", 0.010),
          ("BEAR bus unplugged", "unplug bear", "plug bear", 0.010))


def us(value) -> str:
    return "-" if value is None else f"{value:.0f}"


def steal_s() -> float | None:
    """CPU time the hypervisor took from this machine's virtual CPUs so far (/proc/stat `steal`, all CPUs), None off
    Linux: on a VM a stolen stretch stops every thread at once, the kernel's tty delivery included."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def session(emulator: EmulatorProcess, seconds: float, cmd: str | None, overrides: list[str]) -> dict:
    """One bruce-run process; its stats with the wall-clock figures this benchmark reports."""
    with tempfile.TemporaryDirectory() as tmp:
        stats_path = Path(tmp) / "stats.json"
        argv = emulator.bruce_run_argv(seconds, stats_path, cmd=cmd, overrides=overrides)
        stolen = steal_s()
        with Witness() as witness:
            started = time.monotonic()
            run = subprocess.run(argv, capture_output=True, text=True, timeout=seconds + 120)
            ended = time.monotonic()
        after = steal_s()
        if not stats_path.exists():
            sys.exit(f"bruce-run failed ({run.returncode}):\n{run.stdout}\n{run.stderr}")
        stats = json.loads(stats_path.read_text())
    stats["returncode"] = run.returncode
    stats["steal_s"] = None if stolen is None or after is None else after - stolen
    damped = [t for t, text in emulator.events() if started <= t <= ended and "torque_enable" in text
              and "-> 3" in text]
    stats["witness"] = {"stalls": witness.between(started, ended), "notes": witness.notes,
                        "damped_at": damped[0] - started if damped else None,
                        "before_trip": witness.between(damped[0] - TRIP_LOOKBACK_S, damped[0]) if damped else []}
    for key in ("stalls", "before_trip"):
        stats["witness"][key] = [(t - started, ms) for t, ms in stats["witness"][key]]
    # The emulated BEARs' own view of the exchanges before the trip: requests that came late, replies that left late
    stats["exchanges_before_trip"] = [] if not damped else [
        (t - damped[0], text.split(" ", 1)[1]) for t, text in emulator.events()
        if damped[0] - TRIP_LOOKBACK_S <= t <= damped[0] and EXCHANGE_LATE in text]
    return stats


def report(name: str, stats: dict, emulator: EmulatorProcess, no_delay: bool) -> bool:
    legs = (stats.get("link") or {}).get("legs", {})
    cycle = legs.get("bus_cycle_us") or {}
    rate = stats["rate_hz"] or float("nan")
    bulk_rate = cycle.get("rate_hz") or float("nan")
    plant = emulator.status()["plant"]
    tripped = stats["fault_class"] is not None
    print(f"   {name}: {stats['final_state']} ({stats['stop_cause']}); exit {stats['returncode']}"
          f"{' -- TRIPPED' if tripped else ''}")
    print(f"     control rate {rate:.0f} Hz ({stats['ticks']} ticks in {stats['loop_s']:.2f} s); late "
          f"{stats['late_ticks']} = {100 * stats['late_share']:.2f} %, skipped {stats['skipped_ticks']}, breaths "
          f"{stats['breaths']}; work p50/p99 "
          f"{us(stats['work_us']['p50'])}/{us(stats['work_us']['p99'])} µs")
    read = stats["sections_us"].get("read", {})
    goal = ""
    if no_delay:
        met = "met" if bulk_rate >= BULK_RATE_GOAL_HZ else "MISSED"
        goal = f" (goal >= {BULK_RATE_GOAL_HZ:.0f}/s with no delay: {met})"
    print(f"     read p50/p99 {us(read.get('p50'))}/{us(read.get('p99'))} µs; bus thread: {cycle.get('cycles', 0)} "
          f"bulk cycles = {bulk_rate:.0f}/s{goal}, cycle p50/p99/max {us(cycle.get('p50'))}/{us(cycle.get('p99'))}/"
          f"{us(cycle.get('max'))} µs; replies lost {legs.get('replies_lost_total', '?')}, taken late "
          f"{legs.get('replies_late', '?')}")
    steal = "-" if stats["steal_s"] is None else f"{1e3 * stats['steal_s']:.0f} ms"
    held = legs.get("port_held") or {}
    print(f"     host: {legs.get('host_stalls', '?')} bus sends or reads it held (not counted against the BEARs; "
          f"the port held {held.get('count', '?')} times, worst {held.get('worst_ms', float('nan')):.1f} ms); "
          f"hypervisor steal during the run {steal}")
    stalls = (stats.get("link") or {}).get("host_stalls") or {}
    print(f"     host stalls the run counted (its own witness, > 2 ms): {stalls.get('count', '?')}, worst "
          f"{stalls.get('worst_ms', float('nan')):.1f} ms, {stalls.get('total_ms', float('nan')):.0f} ms in all; late "
          f"ticks: {stats.get('late_ticks_machine', '?')} with the host stalled, {stats.get('late_ticks_loop', '?')} "
          f"of the loop's own CPU time ({100 * stats.get('late_share_loop', float('nan')):.2f} %), "
          f"{stats.get('late_ticks_not_run', '?')} with the loop ready and not run")
    shares = stats.get("cpu_share_of_period") or {}
    if shares:
        tick = shares["tick"]
        worst = max((k for k in shares if k != "tick"), key=lambda k: shares[k]["p99"])
        print(f"     tick CPU time, share of the period: p50 {100 * tick['p50']:.0f} / p99 {100 * tick['p99']:.0f} / "
              f"p99.9 {100 * tick['p99.9']:.0f} %; the largest section at p99: {worst} "
              f"{100 * shares[worst]['p99']:.0f} %")
    costliest = stats.get("costliest_tick")
    if costliest:
        parts = sorted(costliest["sections_cpu_us"].items(), key=lambda kv: -kv[1])[:3]
        print(f"     the costliest tick: #{costliest['tick']}, CPU {costliest['cpu_us']:.0f} µs in "
              f"{costliest['wall_us']:.0f} µs of wall time (" + ", ".join(f"{k} {v:.0f}" for k, v in parts) + " µs)")
    runner = stats.get("controller") or {}
    if runner.get("lag_ticks"):
        cpu = runner.get("cpu_us") or {}
        print(f"     controller on {runner['runs_on']}, its targets {runner['lag_ticks']} tick(s) after its reading: "
              f"CPU p50/p99 {cpu.get('p50') or 0:.0f}/{cpu.get('p99') or 0:.0f} µs a call; {runner['late_ticks']} "
              f"ticks waited for targets due, worst {runner['worst_late_ticks']} ticks late")
    shadow = stats.get("shadow") or {}
    if shadow:
        print(f"     shadow's model stepped on {shadow['steps_on']}: {shadow['late']} answers not back in time, "
              f"{shadow['skipped']} ticks not asked")
    seen = stats["witness"]
    longest = max((ms for _, ms in seen["stalls"]), default=0.0)
    print(f"     machine stalls seen by the witness (SCHED_FIFO 90 on every CPU, > 2 ms): {len(seen['stalls'])}, "
          f"longest {longest:.1f} ms" + "".join(f"; {note}" for note in seen["notes"] if "without" in note))
    if tripped and seen["damped_at"] is not None:
        near = ", ".join(f"{ms:.1f} ms at {1e3 * (t - seen['damped_at']):+.0f} ms" for t, ms in seen["before_trip"])
        print(f"     in the {1e3 * TRIP_LOOKBACK_S:.0f} ms before the emulator saw damping: {near or 'none'}")
        late = "; ".join(f"{text} at {1e3 * t:+.1f} ms" for t, text in stats["exchanges_before_trip"])
        print(f"     the emulated BEARs in those {1e3 * TRIP_LOOKBACK_S:.0f} ms: "
              f"{late or 'every request and reply on time'}")
    print(f"     data age p50/p99/max {us(stats['data_age_us']['p50'])}/{us(stats['data_age_us']['p99'])}/"
          f"{us(stats['data_age_us']['max'])} µs; base height at the end {plant['base_height']:.3f} m (nominal "
          f"{plant['nominal_base_height']:.3f} m)")
    return not tripped


def faults(emulator: EmulatorProcess, trials: int, overrides: list[str]) -> None:
    print(f"2. fault -> damping, {trials} trial(s) each (paced, standing)")
    for name, inject, undo, goal_s in FAULTS:
        latencies, causes = [], set()
        from_reply = []  # the E-stop: from the reply that carried the bit leaving the emulated BEARs
        for _ in range(trials):
            config = load_config(overrides=emulator.overrides + overrides)
            backend = make_hw_backend(config, check_imu=False)
            quiet = io.StringIO()  # the session's summary and log lines
            fault = FaultAt(emulator, inject)
            with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet), \
                    contextlib.suppress(BackendError):
                run_session(backend, config, duration=2.0, realtime=True, controller_kind="standing",
                            commands=fault)
            if not fault.sent:  # the run ended before the fault was injected
                causes.add(f"ended before the fault: {backend.fault_cause}")
                emulator.send("place")
                continue
            at = reply_time(emulator.reply())
            emulator.send(undo)
            emulator.send("place")
            if backend.fault_stamp is not None:
                latencies.append(backend.fault_stamp - at)
                carried = [t for t, text in emulator.events() if t >= at and ESTOP_SENT in text]
                if inject == "estop on" and carried:
                    from_reply.append(backend.fault_stamp - carried[0])
            causes.add(backend.fault_cause)
        ms = [1e3 * v for v in latencies] or [float("nan")]
        met = "met" if max(ms) <= 1e3 * goal_s else "MISSED"
        carried = "" if not from_reply else (
            f"; from the reply that carried the bit leaving the BEARs: {1e3 * min(from_reply):.1f}.."
            f"{1e3 * max(from_reply):.1f} ms")
        print(f"   {name}: damping after {statistics.median(ms):.1f} ms median, {min(ms):.1f}..{max(ms):.1f} ms "
              f"(goal <= {1e3 * goal_s:.0f} ms: {met}){carried}; cause: {' | '.join(sorted(str(c) for c in causes))}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--cmd", default=None, metavar="VX,VY,WZ", help="also walk at this command")
    parser.add_argument("--runs", type=int, default=1, help="runs of each kind (stand, walk)")
    parser.add_argument("--transfer", default=None, help="bruce-run --transfer for the walk (default: the config's)")
    parser.add_argument("--fault-trials", type=int, default=3)
    parser.add_argument("--emulator-args", default="", metavar="ARGS",
                        help='more bruce-emulate options, e.g. "--bear-delay 0.0007 --bear-jitter 0.0015"')
    parser.add_argument("--emulator-priority", choices=("realtime", "normal"), default="realtime",
                        help="bruce-emulate --realtime (SCHED_FIFO 40) or at normal priority")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="bruce-run config overrides")
    parser.add_argument("--conditions", default=None, metavar="NAME,...",
                        help=f"run the stand and walk under each of these link conditions ({', '.join(CONDITIONS)})"
                             "; --emulator-args adds to each")
    parser.add_argument("--busy-core", action="store_true",
                        help="keep one core busy at nice 19 meanwhile (another job on the robot computer)")
    args = parser.parse_args()
    names = args.conditions.split(",") if args.conditions else [None]
    unknown = [n for n in names if n is not None and n not in CONDITIONS]
    if unknown:
        sys.exit(f"--conditions: unknown {', '.join(unknown)} (expected some of {', '.join(CONDITIONS)})")
    busy = (subprocess.Popen(["nice", "-n", "19", sys.executable, "-c", "while True: pass"])
            if args.busy_core else None)
    tally: list[tuple[str, dict | None]] = []
    try:
        for name in names:
            condition = CONDITIONS.get(name, "")
            if name is not None:
                print(f"== condition {name}: {condition or 'no delay, no loss'}"
                      f"{'; one core kept busy' if busy else ''}")
            series(args, f"{condition} {args.emulator_args}", name or "runs", tally, args.fault_trials)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    ended = [(label, stats) for label, stats in tally if stats is not None]
    print(f"series: {len(tally) - len(ended)} of {len(tally)} runs completed without a trip"
          f"{' (one core kept busy)' if busy else ''}")
    for label, stats in ended:
        before = stats["witness"]["before_trip"]
        longest = max((ms for _, ms in before), default=0.0)
        print(f"   {label} ended at {stats['loop_s']:.1f} s: {stats['stop_cause']}; the witness's longest machine "
              f"stall in the 60 ms before: {longest:.1f} ms")


def series(args, emulator_options: str, label: str, tally: list, fault_trials: int) -> None:
    """The runs (stand, and walk with --cmd) under one emulator, then the fault trials; each run's stats (None: it
    completed) go to `tally`."""
    extra = shlex.split(emulator_options)
    no_delay = not any(a.endswith(("-delay", "-jitter")) for a in extra)
    emulator_args = (["--realtime"] if args.emulator_priority == "realtime" else []) + extra
    print(f"bruce-emulate {' '.join(emulator_args)}; bruce-run --set {' '.join(args.overrides) or '(defaults)'}")
    with EmulatorProcess(*emulator_args) as emulator:
        print(f"1. runs of {args.seconds:g} s")
        completed, runs = 0, 0
        walk = [f"transfer.scheme={args.transfer}"] if args.transfer else []
        for k in range(args.runs):
            for name, cmd, extra_set in (("stand", None, []), (f"walk --cmd {args.cmd}", args.cmd, walk)):
                if name != "stand" and not cmd:
                    continue
                emulator.send("place")
                stats = session(emulator, args.seconds, cmd, args.overrides + extra_set)
                ok = report(f"{name} #{k + 1}", stats, emulator, no_delay)
                completed += ok
                tally.append((f"{label}: {name} #{k + 1}", None if ok else stats))
                runs += 1
        print(f"   runs completed without a trip: {completed} of {runs}")
        if fault_trials > 0:
            emulator.send("place")
            faults(emulator, fault_trials, args.overrides)


if __name__ == "__main__":
    main()
