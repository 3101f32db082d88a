"""`bruce-emulate` (`main`): BRUCE's devices emulated on this machine (`bruce_hw.emulation.robot.EmulatedRobot`),
driven by the MuJoCo physics, so that `bruce-run --backend hw` runs end to end with no robot. It prints the device
paths and the `bruce-run` line that uses them, takes fault commands on stdin and prints every emulator event as an
`event t=<monotonic> <text>` line. `EmulatorProcess` runs it in a subprocess for tests and benchmarks. What it does
and every option, as --help prints it: `DESCRIPTION`.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import shlex
import signal
import sys
import threading
import time

from bruce_hw.config import DEFAULT_CONFIG, load_config_or_say
from bruce_hw.leg_kinds import LEG_KINDS, leg_kind_of
from drivers.emulators.reply_delay import MAX_DELAY_S, check_delay

PROG = "bruce-emulate"
DESCRIPTION = """\
`bruce-emulate`: BRUCE's devices emulated on this machine (BEAR bus, Dynamixel bus and sense board on
pseudo-terminals, or CAN motors on python-can's virtual bus), driven by the MuJoCo physics at 1 kHz in real time,
so that `bruce-run --backend hw` runs end to end with no robot.

It prints the device paths and the `bruce-run` command line that uses them, then runs until Ctrl-C (or
--duration). Faults can be injected while it runs, one command per line on its standard input (each answered by
one line on its standard output, "ok ..." with the monotonic time it took effect, "error ..." or "status {json}"):

  silence bear|dynamixel|can ID...   these devices stop answering, as if unplugged
  answer bear|dynamixel|can ID...    they answer again
  unplug bear|dynamixel|sense        cut the bus's wire both ways. BEAR: bytes from the host are discarded and
                                     nothing answers, so every BEAR watchdog runs out; Dynamixel: every servo
                                     silenced; sense board: stops streaming (as `imu stop`)
  plug bear|dynamixel|sense          mend it (Dynamixel: every servo answers again, as `answer` with all IDs)
  loss bear DROP CORRUPT [SEED]      from now on each BEAR reply is dropped with probability DROP or corrupted
                                     (bad checksum, truncated, garbage, drawn evenly) with probability CORRUPT
  delay bear|dynamixel|sense FIXED [JITTER]
                                     from now on the bus answers FIXED + U(0, JITTER) seconds late (each at most
                                     0.1 s; JITTER defaults to 0), as --bear-delay and --bear-jitter do
  estop on|off                       the E-stop input of every BEAR (error bit 3, damping)
  imu stop|start                     the sense board stops (resumes) streaming
  place                              put the robot back on its feet, held until a leg actuator is enabled
  stand on|off                       a bring-up stand: the base held 5 cm up and level, the feet in the air (on);
                                     back on its feet (off)
  status                             one JSON line: actuator modes and enables, arms, sense board, physics, loss,
                                     reply delays

Events: every emulator event (the BEAR emulator's: each change of a BEAR's torque_enable with its cause, watchdog
expiries, watchdog_timeout values taking effect, unplug / plug, loss and delay settings; see
drivers/emulators/bear.py; those of the other emulators that keep a log; the robot's own: unplug / plug and reply
delays of the Dynamixel bus and the sense board) is printed as it happens as one line `event t=<monotonic> <text>`,
stamped with the emulator's time.monotonic() when it happened (the system's clock, shared by every process), not
when printed. `EmulatorProcess.events()` parses them.

Reply delays (--bear-delay/--bear-jitter, --dxl-delay/--dxl-jitter, --sense-delay/--sense-jitter, or `delay`), to
try a host's timing policy on purpose: a BEAR or Dynamixel answer starts FIXED + U(0, JITTER) s after the request
arrived (a BEAR bulk cycle's replies as a whole: the first starts late, the others follow it at once, as they do
without a delay); each sense-board packet leaves that much later than it would have, at the same rate. The waits are
honest wall-clock waits (sleep, then spin) on each bus's own thread, so one slow bus slows no other, nor the physics;
with --lockstep the physics still steps once per bulk cycle, after the replies are out. The jitter draws are seeded
by --loss-seed when given.

--realtime runs the emulators at SCHED_FIFO 40 on every CPU but the last (bruce-run's loop takes that one), as
devices with their own clocks; on a loaded machine it keeps their replies within the BEAR's 2 ms timeout. The
physics steps in a child process at normal priority (without --lockstep), so a device answers while the world is
being stepped, as real devices do, and the kernel's tty workers preempt the physics, never wait for it.

CAN configs: python-can's `virtual` interface reaches only this process, so run the stack inside it:
`bruce-emulate --config configs/robots/bruce_can.yaml --run [bruce-run options]` (--run works for every config).
In one process the host, the four motor threads and the physics share one GIL and an emulated CAN round trip takes
about a millisecond: that needs --set buses.can.timeout_s=0.005 and does not keep 1 kHz. Across processes,
--can-interface socketcan on vcan channels (a Linux vcan interface: `ip link add dev vcan0 type vcan`).
"""  # the --help text
# The emulators' threads (pty servers, sense-board firmware, plant) answer within a fraction of a millisecond only
# if none of them can hold the GIL for long (CPython's default: 5 ms). A pty thread woken by a request waits for the
# GIL up to this long while another thread computes: at 0.5 ms the BEAR bulk cycle's p99 was 1-6 ms on a 2-core VM,
# at 0.1 ms 0.5-0.6 ms (bench/bench_bear_rtt.py).
SWITCH_INTERVAL_S = 0.0001
EMULATOR_PRIORITY = 40  # SCHED_FIFO priority with --realtime: below bruce-run's control loop (50)
# The physics is no device: on the wall clock it steps in a process of its own at normal priority
# (bruce_hw/emulation/physics_process.py), so the devices' threads share neither a CPU turn nor an interpreter lock
# with it. In this process, at the devices' real-time priority, it kept the kernel's tty worker (the `kworker` that
# moves every pty byte, at normal priority) off the CPU for 5-10 ms, and the host's requests sat in the pty; at normal
# priority, preempted by any other process, it held the lock the devices needed (ftrace, docs/results/timing.md).
OPERATOR_PRIORITY = EMULATOR_PRIORITY - 1  # the main thread, the event printer, the stdin reader
EVENT_POLL_S = 0.002  # how often the emulators' event logs are drained and printed
_print_lock = threading.Lock()  # event lines and command replies come from two threads: whole lines only
# (bus as the `delay` command names it, option prefix, what is delayed)
DELAY_OPTIONS = (("bear", "bear", "BEAR answer"), ("dynamixel", "dxl", "Dynamixel answer"),
                 ("sense", "sense", "sense-board packet"))


def _say(text: str) -> None:
    """One or more whole lines to stdout, flushed, never interleaved with another thread's."""
    with _print_lock:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text} is not a probability in [0, 1]")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key path (repeatable); passed on to bruce-run too")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: Ctrl-C)")
    p.add_argument("--sense-poll-s", type=float, default=0.05, metavar="S",
                   help="how often the emulated sense board reads commands while streaming (the real firmware: "
                        "1 s; default %(default)s s so that repeated start-ups do not wait a second each)")
    p.add_argument("--can-interface", default="virtual", metavar="NAME",
                   help="python-can interface of the emulated CAN motors (default %(default)s: this process only; "
                        "socketcan with vcan channels reaches other processes)")
    p.add_argument("--realtime", action="store_true",
                   help=f"run the emulators at SCHED_FIFO {EMULATOR_PRIORITY} (below bruce-run's loop), as devices "
                        "with their own clocks would; on a loaded machine this keeps their replies in time")
    p.add_argument("--lockstep", action="store_true",
                   help="step the physics once per BEAR bulk cycle of the host instead of on the wall clock (the "
                        "IMU streams one packet per step; the motors' watchdogs keep the wall clock): runs and "
                        "tests come out the same however loaded the machine is; BEAR legs only")
    p.add_argument("--bear-drop", type=_probability, default=0.0, metavar="P",
                   help="drop each BEAR reply with probability P (default %(default)s)")
    p.add_argument("--bear-corrupt", type=_probability, default=0.0, metavar="P",
                   help="corrupt each BEAR reply with probability P: bad checksum, truncated or garbage before it, "
                        "drawn evenly (default %(default)s)")
    p.add_argument("--loss-seed", type=int, default=None, metavar="N",
                   help="seed of the reply-loss and reply-jitter draws, for a repeatable run (default: random)")
    for _, option, what in DELAY_OPTIONS:
        p.add_argument(f"--{option}-delay", default="0", metavar="S",
                       help=f"every {what} starts S seconds late (at most {MAX_DELAY_S:g}; default 0)")
        p.add_argument(f"--{option}-jitter", default="0", metavar="S",
                       help=f"and a further uniform random 0..S seconds (at most {MAX_DELAY_S:g}; default 0)")
    p.add_argument("--run", nargs=argparse.REMAINDER, default=None, metavar="BRUCE_RUN_ARGS",
                   help="run `bruce-run --backend hw` against the emulators inside this process with these "
                        "options (the rest of the command line), then stop; needed for CAN configs")
    return p


def _delays(args: argparse.Namespace) -> dict[str, tuple[float, float]]:
    """{bus: (fixed, jitter)} of the buses given a reply delay; ValueError (one line naming the option) for a value
    that is not a number of seconds in [0, MAX_DELAY_S]."""
    out = {}
    for bus, option, _ in DELAY_OPTIONS:
        fixed = check_delay(getattr(args, f"{option}_delay"), f"--{option}-delay")
        jitter = check_delay(getattr(args, f"{option}_jitter"), f"--{option}-jitter")
        if fixed or jitter:
            out[bus] = (fixed, jitter)
    return out


def bruce_run_args(args: argparse.Namespace, robot) -> list[str]:
    """bruce-run's options that point the hw backend at these emulators (config, the user's overrides, ports)."""
    out = ["--backend", "hw"]
    if args.config != DEFAULT_CONFIG:
        out += ["--config", args.config]
    for item in [*args.overrides, *robot.port_overrides()]:
        out += ["--set", item]
    return out


def main(argv: list[str] | None = None) -> int:
    from bruce_hw.emulation.robot import EmulatedRobot

    args = build_parser().parse_args(argv)
    try:
        delays = _delays(args)
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    config = load_config_or_say(PROG, args.config, args.overrides)
    if config is None:
        return 2
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    restore = None
    if args.realtime:
        restore, text = _realtime()  # for this thread while it starts the emulators': they inherit it
        print(f"{PROG}: {text}")
    legs = leg_kind_of(config)
    if args.lockstep and not legs.lockstep:
        print(f"{PROG}: --lockstep steps the physics on the legs' bus cycles (BEAR bulk cycles); this config's legs "
              f"({legs.name}) cannot clock it", file=sys.stderr)
        return 2
    robot = EmulatedRobot(config, sense_command_poll_s=args.sense_poll_s, can_interface=args.can_interface,
                          lockstep=args.lockstep, physics_process=args.run is None)
    try:
        robot.start()
    except Exception as exc:
        print(f"{PROG}: cannot start the emulators: {exc}", file=sys.stderr)
        return 1
    finally:
        if restore is not None:
            # The main thread and those it starts next (the event printer, the stdin reader) one real-time step below
            # the devices, off bruce-run's CPU: a thread of ours left at normal priority, preempted by any busy
            # process while it held our GIL, stalled every emulated device for tens of milliseconds. With --run,
            # bruce-run is this process: normal scheduling on every CPU.
            restore(below=args.run is None)
    if args.bear_drop or args.bear_corrupt:
        if robot.legs.bus != "bear":
            robot.close()
            print(f"{PROG}: --bear-drop / --bear-corrupt need a BEAR bus; this config's legs are {robot.legs.bus}",
                  file=sys.stderr)
            return 2
        robot.legs.set_reply_loss(args.bear_drop, args.bear_corrupt, args.loss_seed)
    for bus, (fixed, jitter) in delays.items():
        if bus not in robot.reply_delays():
            robot.close()
            print(f"{PROG}: --{bus}-delay / --{bus}-jitter need a {bus} bus; this config's legs are "
                  f"{robot.legs.bus}", file=sys.stderr)
            return 2
        seed = None if args.loss_seed is None else f"{args.loss_seed}/{bus}"
        robot.set_reply_delay(bus, fixed, jitter, seed)
    # Started after `restore()`: printing is no device's work, it runs below the devices.
    printer = _EventPrinter(robot)
    # Everything allocated so far (MuJoCo, numpy, the emulators) out of the collector's reach: a full collection
    # over it holds the GIL for milliseconds, long enough for a BEAR reply to miss the host's 2 ms timeout.
    gc.collect()
    gc.freeze()
    try:
        run_args = bruce_run_args(args, robot)
        print(f"{PROG}: {config.name} emulated from {config.path}, MuJoCo physics at {config.loop_hz} Hz in real time")
        for what, where in robot.devices():
            print(f"  {what:36s} {where}")
        if args.run is not None:
            from runtime.cli import main as bruce_run

            print(f"{PROG}: running bruce-run {shlex.join(run_args + args.run)}", flush=True)
            printer.start()
            return bruce_run(run_args + args.run)
        hint = robot.legs.hint(f"{PROG} --config {shlex.quote(args.config)} --run [bruce-run options]")
        if hint:
            print(f"{PROG}: {hint}")
        print("run the robot stack against it with:")
        print(f"  bruce-run {shlex.join(run_args)}")
        print("Ctrl-C stops the emulators; fault commands on stdin (silence, answer, unplug, plug, loss, delay, estop, "
              "imu, place, stand, status).")
        print(f"Both run on this machine: where it stops them for longer than safety.host_stall_max_s "
              f"({1e3 * config.safety.host_stall_max_s:g} ms; a VM does at times), the run ends on a line naming the "
              "host stall (docs/safety.md).", flush=True)
        printer.start()
        _serve(robot, args.duration)
        return 0
    finally:
        printer.stop()
        robot.close()
        printer.flush()  # what happened up to the end (closing included)
        _say(f"{PROG}: stopped; {_counters(robot)}")


class _EventPrinter:
    """Drains every emulator's event log every EVENT_POLL_S and prints one `event t=... text` line per event."""

    def __init__(self, robot, period_s: float = EVENT_POLL_S):
        self.robot, self.period_s = robot, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="emulate-events", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.flush()

    def flush(self) -> None:
        events = self.robot.drain_events()
        if events:
            _say("\n".join(f"event t={stamp:.6f} {text}" for stamp, text in events))

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)


def _realtime():
    """SCHED_FIFO for the calling thread (threads it starts inherit it), kept off the last CPU, which bruce-run's
    real-time loop takes (runtime/loop/realtime.py): sharing it, the two would exceed the kernel's real-time budget for
    one CPU (sched_rt_runtime_us, 95 %) and be throttled for tens of milliseconds at a time. Returns (a function
    that restores the thread's scheduling, or None, and a line for people)."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(EMULATOR_PRIORITY))
    except (AttributeError, OSError) as exc:
        return None, f"SCHED_FIFO refused ({getattr(exc, 'strerror', None) or exc}); running at normal priority"
    text = f"realtime: SCHED_FIFO {EMULATOR_PRIORITY}"
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) > 1:
        try:
            os.sched_setaffinity(0, allowed[:-1])
            text += f", CPU(s) {', '.join(map(str, allowed[:-1]))} (CPU {allowed[-1]} is left to bruce-run's loop)"
        except OSError as exc:
            text += f" (affinity refused: {exc.strerror})"

    def restore(below: bool = False) -> None:
        if below:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(OPERATOR_PRIORITY))
            return
        os.sched_setscheduler(0, policy, param)
        os.sched_setaffinity(0, allowed)

    return restore, text


def _serve(robot, duration: float | None) -> None:
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threading.Thread(target=_commands, args=(robot, stop), name="emulate-stdin", daemon=True).start()
    try:
        stop.wait(duration)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)


def _commands(robot, stop: threading.Event) -> None:
    """Fault commands from stdin until EOF (a closed stdin leaves the emulators running)."""
    for line in sys.stdin:
        if stop.is_set():
            return
        words = line.split()
        if not words:
            continue
        try:
            _say(execute(robot, words))
        except (ValueError, KeyError, IndexError) as exc:
            _say(f"error {' '.join(words)}: {exc}")


def execute(robot, words: list[str]) -> str:
    """One fault command (listed in DESCRIPTION); returns the reply line."""
    verb, rest = words[0], words[1:]
    if verb in ("silence", "answer"):
        bus, ids = rest[0], [int(w) for w in rest[1:]]
        if not ids:
            raise ValueError("name at least one ID")
        silent = verb == "silence"
        if bus == robot.legs.bus:
            robot.legs.silence(ids, silent)
        elif bus == "dynamixel":
            robot.dynamixel.silence(ids, silent)
        else:
            raise ValueError(f"no emulated bus {bus!r} ({', '.join(LEG_KINDS)} or dynamixel, as the config has)")
    elif verb in ("unplug", "plug"):
        if len(rest) != 1:
            raise ValueError(f"{verb} one bus: bear, dynamixel or sense")
        robot.unplug(rest[0], verb == "unplug")
    elif verb == "loss":
        if len(rest) not in (3, 4) or rest[0] != "bear":
            raise ValueError("loss bear DROP CORRUPT [SEED]")
        if not hasattr(robot.legs, "set_reply_loss") or robot.legs.bus != rest[0]:
            raise ValueError(f"no emulated {rest[0]} bus with reply loss (this config's legs are {robot.legs.bus})")
        robot.legs.set_reply_loss(float(rest[1]), float(rest[2]), int(rest[3]) if len(rest) == 4 else None)
    elif verb == "delay":
        if len(rest) not in (2, 3) or rest[0] not in ("bear", "dynamixel", "sense"):
            raise ValueError("delay bear|dynamixel|sense FIXED [JITTER] (seconds)")
        robot.set_reply_delay(rest[0], check_delay(rest[1], "FIXED"),
                              check_delay(rest[2], "JITTER") if len(rest) == 3 else 0.0)
    elif verb == "estop" and rest[0] in ("on", "off") and hasattr(robot.legs, "set_estop"):
        robot.legs.set_estop(rest[0] == "on")
    elif verb == "imu" and rest[0] in ("stop", "start"):
        robot.sense.set_silent(rest[0] == "stop")
    elif verb == "place":
        robot.plant.place()
    elif verb == "stand" and rest[:1] in (["on"], ["off"]):
        robot.plant.stand(rest[0] == "on")
    elif verb == "status":
        return "status " + json.dumps(status(robot))
    else:
        raise ValueError("unknown command (silence, answer, unplug, plug, loss, delay, estop on|off, imu stop|start, "
                         "place, stand on|off, status)")
    return f"ok {' '.join(words)} t={time.monotonic():.6f}"


def status(robot) -> dict:
    cfg = robot.config
    plant = robot.plant.status()  # one moment (with the physics in its own process, one answer)
    out = {"plant": {"steps": plant["steps"], "late_steps": plant["late_steps"],
                     "skipped_steps": plant["skipped_steps"], "held": plant["held"],
                     "base_height": float("nan") if plant["truth"] is None else float(plant["truth"].base_pos[2]),
                     "nominal_base_height": plant["nominal_base_height"], "arm_q": plant["arm_q"].tolist()},
           "dynamixel": {"ids": list(cfg.buses.dynamixel.ids),
                         "torque_enabled": [bool(x) for x in robot.dynamixel.torque_enabled_all()]},
           "sense": {"mode": robot.sense.mode.name.lower(), "packets_sent": robot.sense.packets_sent,
                     "packets_dropped": robot.sense.packets_dropped}}
    out[robot.legs.bus] = robot.legs.status()
    out["unplugged"] = sorted(getattr(robot, "unplugged", ()))
    out["reply_delay"] = robot.reply_delays()  # {bus: [fixed, jitter]} in seconds
    return out


def _counters(robot) -> str:
    plant = None if robot.plant is None else robot.plant.status()
    text = "" if plant is None else (f"{plant['steps']} physics steps ({plant['late_steps']} late, "
                                     f"{plant['skipped_steps']} skipped)")
    legs = robot.legs.counters() if robot.legs is not None else ""
    return f"{text}; {legs}" if legs else text


if __name__ == "__main__":
    sys.exit(main())
