"""A host stall is not a device fault (issue 34): `bruce-run --backend hw` in a child process against
`bruce-emulate --lockstep`, its whole process stopped with SIGSTOP for a set time and continued (every thread stops
at once, as when a VM is not run), while the emulated devices go on with their own clocks and watchdogs.

Each test asserts how the run ends, what every motor ends in, and the host-stall counters. The rate floor is the
shipped one (500 Hz over 50 ms: a 30-ms freeze trips it unless the freeze is discounted as a host stall); the data
age is 50 ms, as in the other emulator tests, since the emulator's own packets are sometimes tens of milliseconds late
on a shared machine (device lateness, which no host-side rule may excuse); the stall bound is 45 ms (below the BEARs'
50 ms watchdog), so a freeze of 30 ms lies inside it and one of 80 ms well outside. Where the machine cannot pace the
1-kHz loop against the emulators at all (on a slow or loaded VM the bus thread above the loop on its CPU leaves it too
little: the rate floor trips before any freeze, long after one, or over a window in which the loop was too slow even
without the freeze), a test is skipped with that trip's line: it cannot show there what a stall does. A rate-floor
trip within 100 ms of a freeze's end, over a window that the freeze's discount would have kept, is the freeze's and
fails the test.

The host also holds the leg bus's own port at times while the process runs: the kernel's tty work for the port not run
(docs/timing.md, "Scheduling"), so the bus thread's flush before a request waits in the kernel. The last tests hold
that flush in an in-process hw backend (the emulators' WALL_CLOCK_SLACK settings: data age 50 ms, stall bound 90 ms,
the BEARs' watchdog 100 ms): a hold longer than the data age and shorter than the bound is ridden through and counted,
a longer one ends in damping naming it, and a silent BEAR beside a hold is still found.
"""

import json
import os
import signal
import subprocess
import threading
import time

import pytest
from support.emulated_robot import BEAR_IDS, DXL_IDS, WALL_CLOCK_SLACK

from bruce_hw import BackendError
from bruce_hw.config import load_config
from bruce_hw.hw import make_hw_backend
from runtime.loop.exit import ExitCode
from runtime.loop.run import run_session

pytestmark = pytest.mark.usefixtures("no_memory_lock")
STALL_BOUND_S = 0.045
SETTINGS = ["safety.max_sensor_age_s=0.05", "buses.bear.reply_timeout_s=0.004",
            f"safety.host_stall_max_s={STALL_BOUND_S}"]


@pytest.fixture
def devices(emulator):
    for command in ("plug bear", f"answer bear {' '.join(map(str, BEAR_IDS))}",
                    f"answer dynamixel {' '.join(map(str, DXL_IDS))}", "loss bear 0 0", "estop off", "imu start",
                    "place"):
        emulator.send(command)
    return emulator


RATE_FLOOR = "below safety.min_rate_hz"
RATE_WINDOW_S = load_config().safety.rate_window_s  # the shipped one
# The witness wakes each millisecond, so it counts a freeze up to that much short: a window that, less the freeze,
# is within this of the floor's window could have been kept or tripped by the discount either way.
WITNESS_RESOLUTION_S = 0.001
FREEZE_REACH_S = 0.1  # a rate-floor trip that a freeze causes is printed within the floor's 50-ms window after it


class Run:
    """bruce-run standing against the emulators, started and waited for until its loop is active; its output read
    as it comes, each line stamped, so that a trip is placed against the freezes."""

    def __init__(self, emulator, tmp_path, seconds: float = 3.0):
        self.stats = tmp_path / "stats.json"
        argv = emulator.bruce_run_argv(seconds, self.stats, overrides=SETTINGS)
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[tuple[float, str]] = []
        self.freezes: list[tuple[float, float]] = []
        self.active = threading.Event()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()
        started = time.monotonic()
        while not self.active.wait(0.1):  # until the loop is active, or the run has ended without it
            if self.proc.poll() is not None or time.monotonic() - started > 60:
                self.proc.kill()
                self.reader.join()
                raise AssertionError(self.text())

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append((time.monotonic(), line))
            if "backend active" in line:
                self.active.set()

    def text(self) -> str:
        return "".join(line for _, line in self.lines)

    def freeze(self, seconds: float, halfway=None) -> float:
        """SIGSTOP, `seconds` (`halfway()` called half-way through), SIGCONT; the monotonic time of the stop."""
        self.skip_if_unpaced()
        stopped = time.monotonic()
        os.kill(self.proc.pid, signal.SIGSTOP)
        time.sleep(seconds / 2)
        if halfway is not None:
            halfway()
        time.sleep(seconds / 2)
        os.kill(self.proc.pid, signal.SIGCONT)
        self.freezes.append((stopped, time.monotonic()))
        return stopped

    def skip_if_unpaced(self) -> None:
        """Skip where the machine could not run the 1-kHz loop at all: the rate floor tripped before any freeze,
        later than a freeze could have made it trip, or over a window that the loop had been too slow in apart from
        the freeze (its span less the freeze still longer than the window: no discount of the freeze could have
        kept it). A trip the freezes cause (the rule under test broken) fails the test."""
        for stamp, line in self.lines:
            if RATE_FLOOR not in line:
                continue  # the first such line is the trip's; the summary repeats it when the run has ended
            frozen = sum(resumed - stopped for stopped, resumed in self.freezes
                         if resumed <= stamp <= resumed + FREEZE_REACH_S)
            span_s = float(line.split(" ticks in ")[1].split(" ms")[0]) / 1e3
            if not frozen or span_s - frozen > RATE_WINDOW_S - WITNESS_RESOLUTION_S:
                since = [f"{1e3 * (stamp - resumed):.0f} ms after a freeze" for _, resumed in self.freezes
                         if stamp > resumed] or ["before any freeze"]
                self.proc.kill()
                pytest.skip(f"this machine could not pace the loop against the emulators ({since[-1]}, "
                            f"{1e3 * frozen:.0f} ms of it frozen): {line.strip()}")
            return

    def finish(self) -> tuple[dict, str]:
        self.proc.wait(timeout=60)
        self.reader.join(timeout=10)
        self.skip_if_unpaced()
        return json.loads(self.stats.read_text()), self.text()


def test_a_stall_below_the_bound_is_ridden_through_and_counted(devices, tmp_path):
    run = Run(devices, tmp_path)
    time.sleep(1.0)
    run.freeze(0.030)
    time.sleep(0.3)
    run.freeze(0.030)
    stats, text = run.finish()
    assert stats["exit_code"] == ExitCode.OK and stats["stop_cause"] == "duration reached", text
    stalls = stats["link"]["host_stalls"]
    assert stalls["count"] >= 2 and stalls["worst_ms"] >= 28.0 and stalls["total_ms"] >= 56.0, stalls
    assert "  host: " in text and " stalls (this process not run" in text
    bear = devices.status()["bear"]
    assert bear["torque_enable"] == [3] * 10  # the run's own end: damping (deactivate), as every run ends


def test_a_stall_beyond_the_bound_ends_in_damping_naming_the_stall(devices, tmp_path):
    run = Run(devices, tmp_path)
    time.sleep(1.0)
    run.freeze(0.080)
    stats, text = run.finish()
    assert stats["exit_code"] == ExitCode.SAFETY_TRIP, text
    cause = stats["stop_cause"]
    assert "host stall: this process was not run for" in cause and "safety.host_stall_max_s 45 ms" in cause, cause
    assert float(cause.split("not run for ")[1].split(" ms")[0]) >= 78.0
    assert devices.status()["bear"]["torque_enable"] == [3] * 10  # the BEARs' watchdog (50 ms) and the host agree


def test_device_silence_during_a_run_still_trips_beside_a_stall(devices, tmp_path):
    """BEAR 4 goes silent, and the host is stopped 30 ms soon after: the silence is still found, on the time the
    host ran, and named as silence, not as a stall."""
    run = Run(devices, tmp_path)
    time.sleep(1.0)
    devices.send("silence bear 4")
    run.freeze(0.030)
    stats, text = run.finish()
    assert stats["exit_code"] == ExitCode.BUS_FAULT, text
    assert "no reply from ID(s) 4" in stats["stop_cause"], stats["stop_cause"]
    assert "host stall" not in stats["stop_cause"]


def test_an_estop_during_a_stall_is_acted_on_at_the_first_tick_after_it(devices, tmp_path):
    run = Run(devices, tmp_path)
    time.sleep(1.0)
    run.freeze(0.020, halfway=lambda: devices.send("estop on"))
    stats, text = run.finish()
    assert stats["exit_code"] == ExitCode.SAFETY_TRIP or stats["exit_code"] == ExitCode.BUS_FAULT, text
    assert "E-stop" in stats["stop_cause"] or "e-stop" in stats["stop_cause"], stats["stop_cause"]
    assert devices.status()["bear"]["torque_enable"] == [3] * 10
    assert "host stall" not in stats["stop_cause"]  # 20 ms: ridden through, then the E-stop acted on


# -- the leg port held by the host's kernel ---------------------------------------------------------------------
def hold_next_flush(backend, seconds: float) -> None:
    """The legs' next flush before a request waits `seconds` in the kernel (as behind a tty worker kept from its
    CPU); the flushes after it are the port's own."""
    serial_port = backend.legs.bus._serial
    real_flush = type(serial_port).reset_input_buffer.__get__(serial_port)

    def held_flush():
        serial_port.reset_input_buffer = real_flush
        time.sleep(seconds)
        real_flush()

    serial_port.reset_input_buffer = held_flush


def stand_with_a_held_port(devices, tmp_path, hold_s: float, before=None):
    """A 2.5-s stand, in process, whose leg port is held `hold_s` once, 1 s in (after `before()`); the stats."""
    config = load_config(overrides=devices.overrides + WALL_CLOCK_SLACK)
    assert config.safety.max_sensor_age_s < 0.07 < config.safety.host_stall_max_s < 0.12
    backend = make_hw_backend(config, check_imu=False)
    stats = tmp_path / "stats.json"

    def hold():
        if before is not None:
            before()
        hold_next_flush(backend, hold_s)

    timer = threading.Timer(1.0, hold)
    timer.start()
    try:
        run_session(backend, config, duration=2.5, realtime=True, controller_kind="standing", stats_path=stats)
    finally:
        timer.cancel()
    return json.loads(stats.read_text())


@pytest.mark.usefixtures("no_memory_lock")
def test_a_leg_port_the_host_holds_below_the_bound_is_ridden_through_and_counted(devices, tmp_path):
    """70 ms held: the BEARs' data is older than the 50-ms age bound, but nobody asked them anything meanwhile."""
    stats = stand_with_a_held_port(devices, tmp_path, 0.070)
    assert stats["exit_code"] == ExitCode.OK and stats["stop_cause"] == "duration reached", stats["stop_cause"]
    held = stats["link"]["legs"]["port_held"]
    assert held["count"] >= 1 and held["worst_ms"] >= 69.0, held
    assert devices.status()["bear"]["torque_enable"] == [3] * 10  # the run's own end: damping


@pytest.mark.usefixtures("no_memory_lock")
def test_a_leg_port_the_host_holds_beyond_the_bound_ends_in_damping_naming_it(devices, tmp_path):
    with pytest.raises(BackendError) as info:
        stand_with_a_held_port(devices, tmp_path, 0.120)
    message = str(info.value)
    assert "the host held its port" in message and "safety.host_stall_max_s 90 ms" in message, message
    assert float(message.split("held its port ")[1].split(" ms")[0]) >= 90.0
    assert devices.status()["bear"]["torque_enable"] == [3] * 10


@pytest.mark.usefixtures("no_memory_lock")
def test_a_silent_bear_beside_a_held_port_is_still_found(devices, tmp_path):
    """BEAR 4 goes silent and the port is held 40 ms right after: the hold is left out of its age, the rest of the
    silence is not."""
    with pytest.raises(BackendError) as info:
        stand_with_a_held_port(devices, tmp_path, 0.040, before=lambda: devices.send("silence bear 4"))
    message = str(info.value)
    assert "no reply from ID(s) 4" in message and "held its port" not in message, message
