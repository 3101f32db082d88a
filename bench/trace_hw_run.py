"""An ftrace of `bruce-run --backend hw` against `bruce-emulate --realtime` until a run ends on a BEAR silence: what
the two CPUs ran while the host waited for its replies (Linux, root: the kernel's tracefs).

Both processes write trace markers into the kernel's trace (`H req` / `H got N/10` around each host BEAR exchange,
`H late N` for the replies a bulk cycle took after their deadline, `H SILENCE` when the hw backend judges a silence,
`E recv` / `E send` at each emulated device's pty, `P s` / `P e` around each physics step); the kernel records
beside them every context switch and wake-up (`sched_switch`, `sched_wakeup`) and the tty layer's work items
(`workqueue_*`: `flush_to_ldisc` moves a pty's bytes from one side to the other, in a `kworker` thread at normal
priority). The markers come from a `sitecustomize` this script writes into
a temporary folder on the children's PYTHONPATH: nothing in the stack changes.

    sudo python bench/trace_hw_run.py [--emulator-args "--bear-delay 0.0007 --bear-jitter 0.0015"] [--runs 10] \
        [--seconds 30] [--out trace_out]

Each run is a standing `bruce-run` of --seconds; the first that ends on `no reply from ID(s)` keeps its trace
(`trace.txt`, all of it, ~100 MB for 30 s) and prints the window before the silence: the markers, and for each CPU
which threads held it for longer than 0.5 ms at a stretch (docs/results/timing.md reads such windows).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from stall_witness import Witness

from bruce_hw.emulation.process import EmulatorProcess

TRACEFS = Path("/sys/kernel/tracing")
EVENTS = ("sched:sched_switch", "sched:sched_wakeup", "sched:sched_migrate_task", "workqueue:workqueue_queue_work",
          "workqueue:workqueue_execute_start", "workqueue:workqueue_execute_end")
WINDOW_S = 0.012  # printed before the silence marker: longer than the data-age bound (8 ms)

MARKERS = '''
import os, sys, importlib.abc, importlib.util
_fd = os.open("/sys/kernel/tracing/trace_marker", os.O_WRONLY)
def mark(text):
    try:
        os.write(_fd, text.encode())
    except OSError:
        pass

def _patch(module):
    name = module.__name__
    if name == "drivers.bear":
        exchange = module.BearBus._exchange
        def _exchange(self, request, ids, length, *args, **kwargs):
            mark(f"H req {len(ids)}")
            got = exchange(self, request, ids, length, *args, **kwargs)
            mark(f"H got {len(got)}/{len(ids)}")
            return got
        module.BearBus._exchange = _exchange
        harvest = module.BearBus._harvest
        def _harvest(self):
            late = harvest(self)
            mark(f"H late {0 if late is None else len(late.ids)}")
            return late
        module.BearBus._harvest = _harvest
    elif name == "runtime.loop.safety":
        trip = module.SafetyStage.trip
        def _trip(self, cause):
            mark("H SILENCE " + str(cause))  # the stop, whatever its cause: the window ends here
            return trip(self, cause)
        module.SafetyStage.trip = _trip
    elif name == "bruce_hw.bear_legs":
        silence = module.silence
        def _silence(*args, **kwargs):
            found = silence(*args, **kwargs)
            if found is not None:
                mark("H SILENCE " + found)
            return found
        module.silence = _silence
    elif name == "drivers.emulators.pty_device":
        send, init = module.PtyDevice.send, module.PtyDevice.__init__
        def _send(self, data):
            mark(f"E send {self.name} {len(data)}")
            send(self, data)
        def _init(self, name, on_bytes):
            def received(data):
                mark(f"E recv {name} {len(data)}")
                on_bytes(data)
            init(self, name, received)
        module.PtyDevice.send, module.PtyDevice.__init__ = _send, _init
    elif name == "bruce_hw.emulation.plant":
        step = module.Plant.step
        def _step(self):
            mark("P s")
            step(self)
            mark("P e")
        module.Plant.step = _step

class _AfterImport(importlib.abc.MetaPathFinder):
    names = {"drivers.bear", "bruce_hw.bear_legs", "drivers.emulators.pty_device", "bruce_hw.emulation.plant",
             "runtime.loop.safety"}
    def find_spec(self, name, path, target=None):
        if name not in self.names:
            return None
        sys.meta_path.remove(self)
        try:
            spec = importlib.util.find_spec(name)
        finally:
            sys.meta_path.insert(0, self)
        execute = spec.loader.exec_module
        def exec_module(module):
            execute(module)
            _patch(module)
        spec.loader.exec_module = exec_module
        return spec

sys.meta_path.insert(0, _AfterImport())
'''


def write(name: str, value: str) -> None:
    (TRACEFS / name).write_text(value)


def setup(buffer_kb: int) -> dict[str, str]:
    """Trace the EVENTS into a `buffer_kb` buffer per CPU on the monotonic clock; returns the settings it changed, as
    they were, for `restore`."""
    if not (TRACEFS / "trace_marker").exists():
        subprocess.run(["mount", "-t", "tracefs", "nodev", str(TRACEFS)], check=True)
    clock = re.search(r"\[(\w+)\]", (TRACEFS / "trace_clock").read_text())
    before = {"buffer_size_kb": (TRACEFS / "buffer_size_kb").read_text().split()[0],
              "trace_clock": clock.group(1) if clock else "local"}
    write("tracing_on", "0")
    write("trace", "")
    write("buffer_size_kb", str(buffer_kb))
    write("trace_clock", "mono")  # time.monotonic(): the stack's stamps and the trace on one clock
    write("set_event", "")
    with open(TRACEFS / "set_event", "w") as f:  # one open: the file takes one event per line
        f.write("\n".join(EVENTS) + "\n")
    return before


def restore(before: dict[str, str]) -> None:
    """Tracing off, no events, the buffer (its memory back) and clock as they were."""
    write("tracing_on", "0")
    write("set_event", "")
    write("trace", "")
    for name, value in before.items():
        write(name, value)


def window(trace: Path, before_s: float) -> list[str]:
    """The trace lines from `before_s` before the first silence marker to it."""
    lines = trace.read_text(errors="replace").splitlines()
    at = next((i for i, line in enumerate(lines) if "H SILENCE" in line), None)
    if at is None:
        return []
    end = stamp(lines[at])
    return [line for line in lines[:at + 1] if (t := stamp(line)) is not None and end - before_s <= t <= end]


def stamp(line: str) -> float | None:
    match = re.search(r"\s(\d+\.\d{6}):", line)
    return float(match.group(1)) if match else None


def long_stretches(lines: list[str], least_s: float = 0.0005) -> list[str]:
    """Per CPU, each thread that held it for `least_s` or longer without a switch (one still holding it at the
    window's end included)."""
    out, since = [], {}
    end = stamp(lines[-1]) if lines else None
    for line in lines:
        if "sched_switch:" not in line:
            continue
        cpu = re.search(r"\[(\d+)\]", line).group(1)
        t = stamp(line)
        prev = re.search(r"prev_comm=(\S+) prev_pid=(\d+) prev_prio=(\d+)", line)
        if cpu in since and prev is not None:
            start, who = since[cpu]
            if t - start >= least_s:
                out.append(f"CPU {cpu}: {who} ran {1e3 * (t - start):.1f} ms from {start:.6f}")
        nxt = re.search(r"next_comm=(\S+) next_pid=(\d+) next_prio=(\d+)", line)
        since[cpu] = (t, f"{nxt.group(1)} (pid {nxt.group(2)}, prio {nxt.group(3)})")
    for cpu, (start, who) in since.items():
        if end is not None and end - start >= least_s:
            out.append(f"CPU {cpu}: {who} ran {1e3 * (end - start):.1f} ms from {start:.6f}, still at the end")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--emulator-args", default="", metavar="ARGS", help="more bruce-emulate options")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--out", type=Path, default=Path("trace_out"))
    parser.add_argument("--buffer-kb", type=int, default=60000, help="per CPU: a 30-s run needs about 50 MB")
    parser.add_argument("--until", default="no reply", metavar="TEXT",
                        help="keep the first run whose stop cause holds TEXT (default: a BEAR silence)")
    parser.add_argument("--witness-ms", type=float, default=0.5,
                        help="the machine witness's threshold (bench/stall_witness.py) during each run")
    args = parser.parse_args()
    if os.geteuid() != 0:
        sys.exit("trace_hw_run: needs root (the kernel's tracefs)")
    args.out.mkdir(parents=True, exist_ok=True)
    before = setup(args.buffer_kb)
    with tempfile.TemporaryDirectory() as hooks:
        Path(hooks, "sitecustomize.py").write_text(MARKERS)
        os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [hooks, os.environ.get("PYTHONPATH")]))
        try:
            with EmulatorProcess("--realtime", *args.emulator_args.split()) as emulator:
                for k in range(args.runs):
                    emulator.send("place")
                    stats_path = args.out / "stats.json"
                    stats_path.unlink(missing_ok=True)
                    argv = emulator.bruce_run_argv(args.seconds, stats_path)
                    write("trace", "")
                    write("tracing_on", "1")
                    with Witness(threshold_ms=args.witness_ms) as witness:
                        run = subprocess.run(argv, capture_output=True, text=True)
                    write("tracing_on", "0")
                    cause = json.loads(stats_path.read_text()).get("stop_cause") if stats_path.exists() else None
                    print(f"run {k + 1}: exit {run.returncode}: {cause}", flush=True)
                    if cause and args.until in cause:
                        trace = args.out / "trace.txt"
                        trace.write_bytes((TRACEFS / "trace").read_bytes())
                        lines = window(trace, WINDOW_S)
                        marks = [line.strip() for line in lines if "tracing_mark_write" in line
                                 and "sense" not in line and "dynamixel" not in line]
                        print("\n".join(marks[-40:]))
                        print("\n".join(long_stretches(lines)))
                        if lines:
                            end = stamp(lines[-1])
                            seen = witness.between(end - WINDOW_S - 0.05, end)
                            print(f"machine witness (> {args.witness_ms:g} ms) in the window: "
                                  + (", ".join(f"{ms:.2f} ms at {1e3 * (t - end):+.1f} ms" for t, ms in seen)
                                     or "none"))
                        print(f"trace: {trace}")
                        return
                    time.sleep(0.5)
            print(f"no run ended on a stop holding {args.until!r}")
        finally:
            restore(before)


if __name__ == "__main__":
    main()
