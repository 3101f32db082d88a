"""The BEAR bulk cycle's round trip against `bruce-emulate`: the host's `BearBus.bulk_cycle` for the config's 10 IDs,
timed cycle by cycle and unpaced (each request as soon as the last reply is in), so the figures are the emulator's
and the link's, not a control loop's.

Per emulator mode (plain, --lockstep, --realtime, --realtime --lockstep) two cases:
- read-only: `bulk_cycle(ids, None)` with torque off (the robot is held: the physics has nothing to do);
- force: every BEAR enabled in force mode, goals = the pose measured at the start, read and written every cycle
  (the physics runs: in lockstep one step per cycle, right after the replies go out).
Printed per case: p50 / p90 / p99 / max of the round trip, lost replies, cycles per second (the acceptance of
issue #19: at least 990 cycles/s without a reply delay), and the host's own CPU time a cycle (the calling thread's
clock: what the legs' bus thread costs its CPU on the robot computer, with the kernel's share of the port calls).

Mode `floor`: instead of the emulator, a child process that answers every request at once with the same 10 canned
replies (no device logic, no physics): what the host driver, the pty and two process wake-ups cost by themselves,
the least any emulator of this kind can do on this machine (read-only case only).

`--emulator-root DIR` runs the emulator from another checkout (e.g. `git archive` of an older commit), so that the
emulator's speed before and after a change is measured with the same host. `--bear-delay S` adds a reply delay.

    python bench/bench_bear_rtt.py [--cycles 3000] [--modes floor,plain,lockstep] [--emulator-root DIR] [--bear-delay S]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

from bruce_hw.emulation.process import EmulatorProcess
from drivers.bear import BearBus
from drivers.bear_registers import Mode

MODES = {"floor": (), "plain": (), "lockstep": ("--lockstep",), "realtime": ("--realtime",),
         "realtime+lockstep": ("--realtime", "--lockstep")}
WARM_UP = 200


def _cycles(bus: BearBus, ids: list[int], n: int, mode: Mode | None = None, goals=None
            ) -> tuple[np.ndarray, np.ndarray, int, float]:
    """(round trips in s, the host's CPU time in s, replies lost, wall time) of n cycles: read-only (`mode` None),
    goal currents (TORQUE: the legs' cycle on the robot) or goal positions (FORCE)."""
    rtt, cpu = np.empty(n), np.empty(n)
    lost = 0
    start = time.perf_counter()
    for k in range(n):
        t0, c0 = time.perf_counter(), time.thread_time()
        if mode is None:
            reply = bus.bulk_cycle(ids, None, partial=True)
        elif mode is Mode.TORQUE:
            reply = bus.bulk_cycle(ids, Mode.TORQUE, goal_iq=goals, partial=True)
        else:
            reply = bus.bulk_cycle(ids, Mode.FORCE, goals, np.zeros(len(ids)), np.zeros(len(ids)), partial=True)
        rtt[k], cpu[k] = time.perf_counter() - t0, time.thread_time() - c0
        if reply.answered is not None:
            lost += int(np.count_nonzero(~reply.answered))
    return rtt, cpu, lost, time.perf_counter() - start


def _line(case: str, rtt: np.ndarray, cpu: np.ndarray, lost: int, wall: float) -> str:
    p50, p90, p99 = (1e3 * float(np.percentile(rtt, q)) for q in (50, 90, 99))
    cpu50, cpu99 = (1e6 * float(np.percentile(cpu, q)) for q in (50, 99))
    return (f"  {case:10s} p50 {p50:.3f}  p90 {p90:.3f}  p99 {p99:.3f}  max {1e3 * rtt.max():.3f} ms  "
            f"{lost} replies lost  {len(rtt) / wall:.0f} cycles/s; the host's CPU a cycle p50 {cpu50:.0f} / p99 "
            f"{cpu99:.0f} µs")


def serve_floor() -> None:
    """The `floor` device: canned replies to whatever comes, from the pty thread, until stdin closes."""
    from drivers.bear_codec import encode_status
    from drivers.bear_registers import ERROR_OK
    from drivers.emulators.pty_device import PtyDevice
    from runtime.emulate_cli import SWITCH_INTERVAL_S

    sys.setswitchinterval(SWITCH_INTERVAL_S)
    replies = b"".join(encode_status(i, ERROR_OK, bytes(12)) for i in range(1, 11))
    device = None

    def answer(_data: bytes) -> None:
        device.send(replies)

    device = PtyDevice("floor", answer).start()
    print(device.path, flush=True)
    sys.stdin.read()


def run_floor(cycles: int) -> None:
    child = subprocess.Popen([sys.executable, "-m", "bench.bench_bear_rtt", "--serve-floor"], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        port = child.stdout.readline().strip()
        print("floor (canned replies, no emulator):", flush=True)
        ids = list(range(1, 11))
        with BearBus(port, reply_timeout_s=0.02) as bus:
            _cycles(bus, ids, WARM_UP)
            print(_line("read-only", *_cycles(bus, ids, cycles)), flush=True)
            currents = np.linspace(-1.0, 1.0, len(ids))
            _cycles(bus, ids, WARM_UP, Mode.TORQUE, currents)
            print(_line("torque", *_cycles(bus, ids, cycles, Mode.TORQUE, currents)), flush=True)
    finally:
        child.stdin.close()
        child.wait(timeout=10)


def run_mode(name: str, cycles: int, root: str | None, delay: float) -> None:
    if name == "floor":
        run_floor(cycles)
        return
    extra = ("--bear-delay", str(delay)) if delay else ()
    with EmulatorProcess(*MODES[name], *extra, cwd=root) as emulator:
        port = next(item.split("=", 1)[1] for item in emulator.overrides if item.startswith("buses.bear.port="))
        ids = list(range(1, 11))
        print(f"{name} ({' '.join(MODES[name] + extra) or 'no options'}):", flush=True)
        with BearBus(port, reply_timeout_s=0.02) as bus:
            _cycles(bus, ids, WARM_UP)
            print(_line("read-only", *_cycles(bus, ids, cycles)), flush=True)
            pose = bus.bulk_cycle(ids, None).position
            for device_id in ids:
                bus.write_config(device_id, {"mode": int(Mode.FORCE)})
            bus.set_torque_enable(ids, 1)
            try:
                _cycles(bus, ids, WARM_UP, Mode.FORCE, pose)
                print(_line("force", *_cycles(bus, ids, cycles, Mode.FORCE, pose)), flush=True)
            finally:
                bus.set_torque_enable(ids, 0)
                for device_id in ids:
                    bus.write_config(device_id, {"mode": int(Mode.TORQUE)}, verify=False)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cycles", type=int, default=3000)
    p.add_argument("--modes", default=",".join(MODES), help="comma-separated, of: " + ", ".join(MODES))
    p.add_argument("--emulator-root", default=None, metavar="DIR", help="run bruce-emulate from this checkout")
    p.add_argument("--bear-delay", type=float, default=0.0, metavar="S")
    p.add_argument("--serve-floor", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.serve_floor:
        serve_floor()
        return
    root = os.path.abspath(args.emulator_root) if args.emulator_root else None
    print(f"BEAR bulk cycle, 10 IDs, {args.cycles} cycles per case, unpaced; emulator from {root or 'this checkout'}; "
          f"load average {os.getloadavg()[0]:.2f}")
    for name in args.modes.split(","):
        if name not in MODES:
            sys.exit(f"unknown mode {name!r} (one of {', '.join(MODES)})")
        run_mode(name, args.cycles, root, args.bear_delay)


if __name__ == "__main__":
    main()
