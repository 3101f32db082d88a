"""Reply delay and jitter in the emulators (`bruce-emulate --bear-delay/--bear-jitter/--dxl-…/--sense-…`, the `delay`
stdin command), seen from the real drivers over the ptys. Only lower bounds are tight: a delay is an honest wait, so
a round trip is never shorter than it; upper bounds leave room for a busy machine."""

from __future__ import annotations

import statistics
import threading
import time

import numpy as np
import pytest
import serial

from bruce_hw.emulation.process import EmulatorProcess
from drivers.bear import BearBus
from drivers.dynamixel_codec import INST_PING, encode_packet
from drivers.emulators.reply_delay import ReplyDelay, check_delay, wait_until
from drivers.emulators.sense import SenseBoardEmulator
from drivers.sense import SenseBoard
from runtime.emulate_cli import main

IDS = list(range(1, 11))
PING_REPLY_LEN = 14  # FF FF FD 00, ID, LEN (2), 0x55, error, model (2), firmware, CRC (2)


def _port(emulator: EmulatorProcess, bus: str) -> str:
    return next(item.split("=", 1)[1] for item in emulator.overrides if item.startswith(f"buses.{bus}.port="))


def _bulk_round_trips(bus: BearBus, n: int) -> list[float]:
    out = []
    for _ in range(n):
        start = time.monotonic()
        bus.bulk_cycle(IDS, None)
        out.append(time.monotonic() - start)
    return out


def _dxl_ping_round_trip(port: serial.Serial, dxl_id: int = 11) -> float:
    port.reset_input_buffer()
    start = time.monotonic()
    port.write(encode_packet(dxl_id, INST_PING))
    got = b""
    while len(got) < PING_REPLY_LEN and time.monotonic() - start < 1.0:
        got += port.read(PING_REPLY_LEN - len(got))
    assert len(got) == PING_REPLY_LEN, got
    return time.monotonic() - start


@pytest.fixture(scope="module")
def emulator():
    """`bruce-emulate --lockstep` with a 3 ms BEAR reply delay from the start."""
    with EmulatorProcess("--lockstep", "--bear-delay", "0.003", "--loss-seed", "5") as emu:
        yield emu


def test_bad_delay_values_are_refused_in_one_line_naming_the_option(capsys):
    for option in ("--bear-delay", "--bear-jitter", "--dxl-delay", "--dxl-jitter", "--sense-delay", "--sense-jitter"):
        for value in ("-0.001", "nan", "inf", "0.2", "soon"):
            assert main([option, value]) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith(f"bruce-emulate: {option}: "), err
    assert check_delay("0.1", "x") == 0.1 and check_delay(0, "x") == 0.0


def test_a_seed_repeats_the_jitter_draws():
    a, b = ReplyDelay(0.001, 0.002, seed="5/bear"), ReplyDelay(0.001, 0.002, seed="5/bear")
    draws = [a.draw() for _ in range(50)]
    assert draws == [b.draw() for _ in range(50)]
    assert all(0.001 <= d <= 0.003 for d in draws) and len(set(draws)) == 50
    assert ReplyDelay(0.002).draw() == 0.002


def test_wait_until_is_never_early():
    for wait in (0.0005, 0.002, 0.004):
        deadline = time.monotonic() + wait
        wait_until(deadline)
        assert time.monotonic() >= deadline


def test_bear_round_trips_follow_the_delay_and_the_command_changes_it(emulator):
    """Through BearBus (reply timeout 20 ms, so slow replies are timed, not lost): with 3 ms from the command line no
    bulk cycle is faster than 3 ms; `delay bear 0` brings the median 2+ ms below; 2 ms + U(0, 4 ms) spreads them."""
    status = emulator.status()
    assert status["reply_delay"]["bear"] == [0.003, 0.0]
    with BearBus(_port(emulator, "bear"), reply_timeout_s=0.02) as bus:
        slow = _bulk_round_trips(bus, 60)
        assert min(slow) >= 0.003, min(slow)
        assert statistics.median(slow) < 0.003 + 0.02  # generous: a busy machine adds, never subtracts
        reply = emulator.send("delay bear 0")
        assert reply.startswith("ok delay bear 0 t=")
        fast = _bulk_round_trips(bus, 200)
        # Relative to the slow ones: a busy machine adds to both, the 3 ms delay only to those.
        fast_median, slow_median = statistics.median(fast), statistics.median(slow)
        assert fast_median < slow_median - 0.002, (fast_median, slow_median)
        emulator.send("delay bear 0.002 0.004")
        jittered = _bulk_round_trips(bus, 200)
        assert min(jittered) >= 0.002
        assert statistics.median(jittered) >= 0.003  # median draw ~2 ms of jitter: ~4 ms
        assert max(jittered) - min(jittered) >= 0.002  # 200 draws of U(0, 4 ms) span nearly 4 ms
        assert emulator.status()["reply_delay"]["bear"] == [0.002, 0.004]
    emulator.wait_event("bear reply delay 2 ms + U(0, 4 ms)")
    emulator.send("delay bear 0")


def settled_status(emulator, timeout_s: float = 5.0) -> dict:
    """The emulator's status once the physics has stopped stepping (two readings 50 ms apart agree): the step of the
    last bulk cycle comes after its replies, later still on a busy machine."""
    deadline = time.monotonic() + timeout_s
    status = emulator.status()
    while time.monotonic() < deadline:
        time.sleep(0.05)
        newer = emulator.status()
        if newer["plant"]["steps"] == status["plant"]["steps"]:
            return newer
        status = newer
    return status


def test_lockstep_steps_once_per_bulk_cycle_with_a_delay(emulator):
    emulator.send("delay bear 0.002 0.001")
    with BearBus(_port(emulator, "bear"), reply_timeout_s=0.02) as bus:
        bus.bulk_cycle(IDS, None)
        before = settled_status(emulator)  # a cycle's step runs after its replies are out: this one's before the count
        _bulk_round_trips(bus, 50)
        after = settled_status(emulator)
        # one step per BULK_COMM the emulator got (a reply later than the timeout on a loaded machine is asked again)
        cycles = after["bear"]["bulk_comm"] - before["bear"]["bulk_comm"]
        assert cycles >= 50 and after["plant"]["steps"] - before["plant"]["steps"] == cycles
    emulator.send("delay bear 0")


def test_a_slow_bus_does_not_slow_the_others(emulator):
    """BEAR answers 50 ms late, asked back to back from a thread: the Dynamixel bus still answers at once, and the
    command line too; then a 3 ms Dynamixel delay shows in its own round trips."""
    emulator.send("delay bear 0.05")
    stop = threading.Event()
    cycles = []

    def hammer():
        with BearBus(_port(emulator, "bear"), reply_timeout_s=0.1) as bus:
            while not stop.is_set():
                cycles.append(_bulk_round_trips(bus, 1)[0])

    thread = threading.Thread(target=hammer, daemon=True)
    thread.start()
    try:
        with serial.Serial(_port(emulator, "dynamixel"), 2_000_000, timeout=0.05) as port:
            time.sleep(0.06)
            quick = [_dxl_ping_round_trip(port) for _ in range(40)]
            assert statistics.median(quick) < 0.01, statistics.median(quick)
            emulator.send("delay dynamixel 0.003")
            delayed = [_dxl_ping_round_trip(port) for _ in range(20)]
            assert min(delayed) >= 0.003, min(delayed)
            assert emulator.status()["reply_delay"]["dynamixel"] == [0.003, 0.0]
    finally:
        stop.set()
        thread.join(timeout=2.0)
        emulator.send("delay dynamixel 0")
        emulator.send("delay bear 0")
    assert cycles and min(cycles) >= 0.05
    emulator.wait_event("dynamixel reply delay 3 ms")


def test_sense_packets_leave_late_at_the_same_rate():
    """A step in the measured acceleration reaches the host no sooner than the delay after it was sampled; the
    stream keeps its 1 kHz."""
    with SenseBoardEmulator(command_poll_s=0.05, idle_poll_s=0.005) as emulator, SenseBoard(emulator.path) as board:
        board.start(check_imu=False)
        for delay in (0.0, 0.004):
            emulator.set_reply_delay(delay, 0.0, seed=1)
            time.sleep(0.02)
            count, start = board.sample_count, time.monotonic()
            time.sleep(0.3)
            rate = (board.sample_count - count) / (time.monotonic() - start)
            assert rate > 700, rate  # 1 kHz, with room for a busy machine
            marker = 2.0 if delay else 1.0
            changed = time.monotonic()
            emulator.set_measurement(accel=(marker, 0.0, 9.8))
            while abs(float(board.latest()[0].accel[0]) - marker) > 0.01:
                assert time.monotonic() - changed < 1.0
                time.sleep(0.0002)
            latency = time.monotonic() - changed
            if delay:
                assert latency >= delay, latency
        assert np.isclose(emulator.reply_delay.fixed, 0.004)
