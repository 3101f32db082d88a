"""`bruce-emulate` driven from Python (tests, benchmarks, the bring-up suite): `EmulatorProcess` runs it as a child
process and speaks its stdin fault commands and event log; `FaultAt` injects one fault from inside a run's loop at
a known moment."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

PROG = "bruce-emulate"

class EmulatorProcess:
    """`bruce-emulate` as a child process: the bruce-run command line it printed (`command_line`, `overrides`),
    its stdin fault commands (`send` waits for the reply line, `post` does not), and its event log (`events()`,
    `wait_event()`)."""

    def __init__(self, *args: str, start_timeout_s: float = 60.0, cwd: str | None = None):
        """`cwd`: run the emulator of the checkout there (benchmarks compare versions); default this one."""
        import queue
        import subprocess

        env = None
        if cwd is not None:
            env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [cwd, os.environ.get("PYTHONPATH")])))
        self.proc = subprocess.Popen([sys.executable, "-m", "runtime.emulate_cli", *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                                     cwd=cwd, env=env)
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        self._events: list[tuple[float, str]] = []
        self._events_changed = threading.Condition()
        threading.Thread(target=self._pump, name="emulate-output", daemon=True).start()
        try:
            line = self._expect(lambda text: text.strip().startswith("bruce-run "), start_timeout_s)
        except BaseException:
            self.close()
            raise
        self.command_line = line.split()
        words = self.command_line
        self.overrides = [words[i + 1] for i, w in enumerate(words) if w == "--set"]

    def bruce_run_argv(self, seconds: float, stats_path: Path, cmd: str | None = None,
                       overrides: list[str] | tuple[str, ...] = ()) -> list[str]:
        """A headless `bruce-run` against these devices, as a Python command line: the command `cmd` (VX,VY,WZ) or
        the standing controller, for `seconds`, its stats to `stats_path`, with `--set` overrides."""
        controller = [f"--cmd={cmd}"] if cmd else ["--controller", "standing"]
        return [sys.executable, "-m", "runtime.cli", *self.command_line[1:], *controller, "--duration", str(seconds),
                "--rerun", "off", "--stats", str(stats_path), *(w for item in overrides for w in ("--set", item))]

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.output.append(line)
            event = parse_event(line)
            if event is None:
                self.lines.put(line)  # event lines never answer a command: kept out of `_expect`'s way
                continue
            with self._events_changed:
                self._events.append(event)
                self._events_changed.notify_all()

    def events(self) -> list[tuple[float, str]]:
        """Every event printed so far: (monotonic stamp, text), in the order printed."""
        with self._events_changed:
            return list(self._events)

    def wait_event(self, match, timeout_s: float = 10.0, since: float = 0.0) -> tuple[float, str]:
        """The first event stamped at or after `since` whose text contains `match` (a string) or satisfies it (a
        callable), waiting up to `timeout_s` for it to be printed; RuntimeError naming the events seen if none."""
        test = match if callable(match) else (lambda text: match in text)
        deadline = time.monotonic() + timeout_s
        with self._events_changed:
            while True:
                for stamp, text in self._events:
                    if stamp >= since and test(text):
                        return stamp, text
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = "\n".join(f"  {stamp:.6f} {text}" for stamp, text in self._events[-20:])
                    raise RuntimeError(f"{PROG}: no event matching {match!r} in {timeout_s:g} s; the last "
                                       f"events:\n{seen}")
                self._events_changed.wait(left)

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


def parse_event(line: str) -> tuple[float, str] | None:
    """(stamp, text) of an `event t=<monotonic> <text>` line; None for any other line."""
    if not line.startswith("event t="):
        return None
    stamp, _, text = line[len("event t="):].rstrip("\n").partition(" ")
    try:
        return float(stamp), text
    except ValueError:
        return None


def reply_time(reply: str) -> float:
    """The monotonic time (the system's, shared by every process) at which a command took effect ("ok ... t=...")."""
    return float(reply.rsplit("t=", 1)[1])


class FaultAt:
    """A command source for runtime.loop.run.run_session (stand still) that posts one fault command to an
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
