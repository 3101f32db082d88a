"""`bruce-emulate`: BRUCE's devices emulated on this machine (BEAR bus, Dynamixel bus and sense board on
pseudo-terminals, or CAN motors on python-can's virtual bus), driven by the MuJoCo physics at 1 kHz in real time,
so that `bruce-run --backend hw` runs end to end with no robot.

It prints the device paths and the `bruce-run` command line that uses them, then runs until Ctrl-C (or
--duration). Faults can be injected while it runs, one command per line on its standard input (each answered by
one line on its standard output, "ok ..." with the monotonic time it took effect, "error ..." or "status {json}"):

  silence bear|dynamixel|can ID...   these devices stop answering, as if unplugged
  answer bear|dynamixel|can ID...    they answer again
  estop on|off                       the E-stop input of every BEAR (error bit 3, damping)
  imu stop|start                     the sense board stops (resumes) streaming
  place                              put the robot back on its feet, held until a leg actuator is enabled
  status                             one JSON line: actuator modes and enables, arms, sense board, physics

--realtime runs the emulators at SCHED_FIFO 40 on every CPU but the last (bruce-run's loop takes that one), as
devices with their own clocks; on a loaded machine it keeps their replies within the BEAR's 2 ms timeout.

CAN configs: python-can's `virtual` interface reaches only this process, so run the stack inside it:
`bruce-emulate --config configs/robots/bruce_can.yaml --run [bruce-run options]` (--run works for every config).
In one process the host, the four motor threads and the physics share one GIL and an emulated CAN round trip takes
about a millisecond: that needs --set buses.can.timeout_s=0.005 and does not keep 1 kHz. Across processes,
--can-interface socketcan on vcan channels (not tried here: this machine has no vcan).
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

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, load_config

PROG = "bruce-emulate"
# The emulators' threads (pty servers, sense-board firmware, plant) answer within a fraction of a millisecond only
# if none of them can hold the GIL for CPython's default 5 ms.
SWITCH_INTERVAL_S = 0.0005
EMULATOR_PRIORITY = 40  # SCHED_FIFO priority with --realtime: below bruce-run's control loop (50)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
    p.add_argument("--run", nargs=argparse.REMAINDER, default=None, metavar="BRUCE_RUN_ARGS",
                   help="run `bruce-run --backend hw` against the emulators inside this process with these "
                        "options (the rest of the command line), then stop; needed for CAN configs")
    return p


def bruce_run_args(args: argparse.Namespace, robot) -> list[str]:
    """bruce-run's options that point the hw backend at these emulators (config, the user's overrides, ports)."""
    out = ["--backend", "hw"]
    if args.config != DEFAULT_CONFIG:
        out += ["--config", args.config]
    for item in [*args.overrides, *robot.port_overrides()]:
        out += ["--set", item]
    return out


def main(argv: list[str] | None = None) -> int:
    from drivers.emulators.plant import EmulatedRobot

    args = build_parser().parse_args(argv)
    try:
        config = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    restore = None
    if args.realtime:
        restore, text = _realtime()  # for this thread while it starts the emulators': they inherit it
        print(f"{PROG}: {text}")
    robot = EmulatedRobot(config, sense_command_poll_s=args.sense_poll_s, can_interface=args.can_interface)
    try:
        robot.start()
    except Exception as exc:
        print(f"{PROG}: cannot start the emulators: {exc}", file=sys.stderr)
        return 1
    finally:
        if restore is not None:
            restore()  # the main thread (and bruce-run with --run) back to normal scheduling on every CPU
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
            return bruce_run(run_args + args.run)
        if robot.can and robot.can_interface == "virtual":
            print(f"{PROG}: the CAN motors are on python-can's `virtual` bus, which only this process reaches: run "
                  f"the stack here with\n  {PROG} --config {shlex.quote(args.config)} --run [bruce-run options]\n"
                  "  (in one process the emulated CAN round trip takes about a millisecond: add "
                  "--set buses.can.timeout_s=0.005; 1 kHz needs --can-interface socketcan on vcan channels)")
        print("run the robot stack against it with:")
        print(f"  bruce-run {shlex.join(run_args)}")
        print("Ctrl-C stops the emulators; fault commands on stdin (silence, answer, estop, imu, place, status).",
              flush=True)
        _serve(robot, args.duration)
        return 0
    finally:
        robot.close()
        print(f"{PROG}: stopped; {_counters(robot)}", flush=True)


def _realtime():
    """SCHED_FIFO for the calling thread (threads it starts inherit it), kept off the last CPU, which bruce-run's
    real-time loop takes (runtime/realtime.py): sharing it, the two would exceed the kernel's real-time budget for
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

    def restore() -> None:
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
            print(execute(robot, words), flush=True)
        except (ValueError, KeyError, IndexError) as exc:
            print(f"error {' '.join(words)}: {exc}", flush=True)


def execute(robot, words: list[str]) -> str:
    """One fault command (see the module docstring); returns the reply line."""
    verb, rest = words[0], words[1:]
    if verb in ("silence", "answer"):
        bus, ids = rest[0], [int(w) for w in rest[1:]]
        if not ids:
            raise ValueError("name at least one ID")
        silent = verb == "silence"
        if bus == "bear" and robot.bear is not None:
            robot.bear.silence(ids, silent)
        elif bus == "dynamixel":
            robot.dynamixel.silence(ids, silent)
        elif bus == "can" and robot.can:
            for emulator in robot.can.values():
                mine = [i for i in ids if i in emulator.motor_ids]
                if mine:
                    (emulator.silence if silent else emulator.resume)(mine)
        else:
            raise ValueError(f"no emulated bus {bus!r} (bear, dynamixel or can, as the config has)")
    elif verb == "estop" and rest[0] in ("on", "off") and robot.bear is not None:
        robot.bear.set_estop(rest[0] == "on")
    elif verb == "imu" and rest[0] in ("stop", "start"):
        robot.sense.set_silent(rest[0] == "stop")
    elif verb == "place":
        robot.plant.place()
    elif verb == "status":
        return "status " + json.dumps(status(robot))
    else:
        raise ValueError("unknown command (silence, answer, estop on|off, imu stop|start, place, status)")
    return f"ok {' '.join(words)} t={time.monotonic():.6f}"


def status(robot) -> dict:
    cfg = robot.config
    truth = robot.plant.ground_truth()
    out = {"plant": {"steps": robot.plant.steps, "late_steps": robot.plant.late_steps,
                     "skipped_steps": robot.plant.skipped_steps, "held": robot.plant.held,
                     "base_height": float(truth.base_pos[2]), "nominal_base_height": robot.plant.nominal_base_height,
                     "arm_q": robot.plant.arm_q.tolist()},
           "dynamixel": {"ids": list(cfg.buses.dynamixel.ids),
                         "torque_enabled": [bool(x) for x in robot.dynamixel.torque_enabled_all()]},
           "sense": {"mode": robot.sense.mode.name.lower(), "packets_sent": robot.sense.packets_sent}}
    if robot.bear is not None:
        c = robot.bear.commands(list(cfg.buses.bear.ids))
        out["bear"] = {"ids": list(cfg.buses.bear.ids), "mode": c["mode"].tolist(),
                       "torque_enable": c["torque_enable"].tolist(), "error": c["error"].tolist(),
                       "bulk_comm": robot.bear.requests["BULK_COMM"]}
    for channel, emulator in robot.can.items():
        out.setdefault("can", {})[channel] = {
            "ids": list(emulator.motor_ids), "motor_mode": [emulator.in_motor_mode(i) for i in emulator.motor_ids],
            "kd": [emulator.command(i).kd for i in emulator.motor_ids]}
    return out


def _counters(robot) -> str:
    plant = robot.plant
    text = "" if plant is None else (f"{plant.steps} physics steps ({plant.late_steps} late, {plant.skipped_steps} "
                                     "skipped)")
    if robot.bear is not None:
        text += f"; BEAR bus: {robot.bear.requests['BULK_COMM']} BULK_COMM"
    return text


# -- driving bruce-emulate from Python (tests, benchmarks) -------------------------------------------------------
class EmulatorProcess:
    """`bruce-emulate` as a child process: the bruce-run command line it printed (`command_line`, `overrides`),
    and its stdin fault commands (`send` waits for the reply line, `post` does not)."""

    def __init__(self, *args: str, start_timeout_s: float = 60.0):
        import queue
        import subprocess

        self.proc = subprocess.Popen([sys.executable, "-m", "drivers.emulators.cli", *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._pump, name="emulate-output", daemon=True).start()
        try:
            line = self._expect(lambda text: text.strip().startswith("bruce-run "), start_timeout_s)
        except BaseException:
            self.close()
            raise
        self.command_line = line.split()
        words = self.command_line
        self.overrides = [words[i + 1] for i, w in enumerate(words) if w == "--set"]

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.output.append(line)
            self.lines.put(line)

    def _expect(self, match, timeout_s: float) -> str:
        import queue

        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"{PROG} did not answer in {timeout_s:g} s; it said:\n" + "".join(self.output)) \
                    from None
            if match(line):
                return line.strip()

    def post(self, command: str) -> None:
        """Send a command without waiting (safe from a control loop); `reply()` collects the answer later."""
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def reply(self, timeout_s: float = 10.0) -> str:
        line = self._expect(lambda text: text.startswith(("ok ", "error ", "status ")), timeout_s)
        if line.startswith("error "):
            raise RuntimeError(f"{PROG}: {line}")
        return line

    def send(self, command: str) -> str:
        self.post(command)
        return self.reply()

    def status(self) -> dict:
        return json.loads(self.send("status").removeprefix("status "))

    def close(self) -> None:
        import subprocess

        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def reply_time(reply: str) -> float:
    """The monotonic time (the system's, shared by every process) at which a command took effect ("ok ... t=...")."""
    return float(reply.rsplit("t=", 1)[1])


class FaultAt:
    """A command source for runtime.run.run_session (stand still) that posts one fault command to an
    EmulatorProcess `t` seconds after activation, from inside the control loop, so that its moment is known."""

    name = "fault injection"

    def __init__(self, emulator: EmulatorProcess, command: str, t: float = 0.4):
        self.emulator, self.command, self.t, self.sent = emulator, command, t, False

    def at(self, t: float):
        import numpy as np

        if t >= self.t and not self.sent:
            self.sent = True
            self.emulator.post(self.command)
        return np.zeros(3)


if __name__ == "__main__":
    sys.exit(main())
