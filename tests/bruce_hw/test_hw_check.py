"""`bruce-hw-check`: `--probe-watchdog` against the BEAR emulator (which takes watchdog_timeout in milliseconds), on a
pseudo-terminal with no plant: the emulator checks its watchdog when a packet arrives, which is what the probe's
ping is; and the default check's round-trip report against `bruce-emulate` (every bus, reply delays from its stdin)."""

from __future__ import annotations

import re
import struct
import time

import pytest

from bruce_hw.hw_check import main
from bruce_hw.watchdog_probe import ProbeError, probe_watchdog
from drivers.bear import BearBus
from drivers.emulators import bear as bear_emulator
from drivers.emulators.bear import BearBusEmulator

IDS = list(range(1, 11))


@pytest.fixture
def emulator():
    with BearBusEmulator(IDS) as emu:
        yield emu


def _argv(emu: BearBusEmulator, *more: str) -> list[str]:
    return ["--set", f"buses.bear.port={emu.path}", "--probe-watchdog", *more]


def test_probe_measures_the_emulators_millisecond_and_restores_the_bear(emulator, capsys, monkeypatch):
    goals = []
    write_status = bear_emulator._Bear.write_status

    def spy(bear, address, raw):  # every goal current a BEAR is told
        if address == 0x03:
            goals.append(struct.unpack("<f", raw)[0])
        write_status(bear, address, raw)

    monkeypatch.setattr(bear_emulator._Bear, "write_status", spy)
    emulator.set_register_value(3, "watchdog_timeout", 77, "config")
    emulator.set_register_value(3, "mode", 2, "config")
    emulator.drain_events()
    start = time.monotonic()
    assert main(_argv(emulator, "--probe-id", "3")) == 0
    took = time.monotonic() - start
    out = capsys.readouterr().out
    last = out.strip().splitlines()[-1]
    unit = float(re.search(r"BEAR watchdog unit (\S+) s per count", last).group(1))
    assert abs(unit - 0.001) < 0.0002, out  # the emulator's unit, within 20 %
    assert f"--set buses.bear.watchdog_unit_s={unit:g}" in last and "linear" in last, last
    assert "watchdog_timeout 100: trips after" in out and "watchdog_timeout 200: trips after" in out
    assert took < 30.0
    # restored: torque off, the old watchdog_timeout and mode; flash untouched; only ever goal_iq 0
    assert emulator.register_value(3, "torque_enable") == 0
    assert emulator.register_value(3, "watchdog_timeout", "config") == 77
    assert emulator.register_value(3, "mode", "config") == 2
    assert emulator.saved_config(3)["watchdog_timeout"] == 0
    assert goals and set(goals) == {0.0}
    texts = [text for _, text in emulator.drain_events()]
    trips = [t for t in texts if "(watchdog: " in t]
    assert trips and all(t.startswith("bear 3 torque_enable 1 -> 3") for t in trips)
    # Nobody else touched: every event is BEAR 3's, but the bus's own timing log (the probe's deliberate pauses are
    # requests long after the last answer).
    per_bear = [t for t in texts if re.match(r"bear \d+ ", t)]
    assert all(t.startswith("bear 3 ") for t in per_bear)
    assert all(t in per_bear or re.fullmatch(r"bear request [\d.]+ ms after the last answer", t) for t in texts)
    assert per_bear[-1] == "bear 3 watchdog_timeout 77"


def test_probe_names_a_silent_bear_in_one_line(emulator, capsys):
    emulator.silence([1])
    start = time.monotonic()
    assert main(_argv(emulator)) == 1
    assert time.monotonic() - start < 5.0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "BEAR ID 1" in out[0] and "does not answer" in out[0], out


def test_probe_refuses_a_bear_in_e_stop_and_restores_it(emulator, capsys):
    emulator.set_estop(True, [1])
    assert main(_argv(emulator)) == 1
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert "E-stop" in last and "restored torque disabled, watchdog_timeout 0, mode 0" in last, last


def test_probe_gives_up_on_a_watchdog_that_never_trips(emulator, monkeypatch):
    monkeypatch.setattr(bear_emulator._Bear, "check_watchdog", lambda bear, now: None)
    with BearBus(emulator.path, reply_timeout_s=0.02) as bus:
        start = time.monotonic()
        with pytest.raises(ProbeError, match="did not trip"):
            probe_watchdog(bus, 1, (100, 200), feed_s=0.01, max_wait_s=0.05, say=lambda text: None)
        assert time.monotonic() - start < 3.0


# -- round trips (bruce-hw-check's default report) against `bruce-emulate` -------------------------------------------
RTT_LINE = re.compile(r"round trip over (\d+) (.+?): p50 ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms: (.+)")
STREAM_LINE = re.compile(r"stream over (\d+) ticks of 1 ms: (\d+) packets/s .*age of the newest packet at a tick p50 "
                         r"([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms: (.+)")


@pytest.fixture(scope="module")
def emulated_robot():
    from bruce_hw.emulation.process import EmulatorProcess

    with EmulatorProcess() as emu:
        yield emu


def _check(emulated_robot, capsys, *more: str) -> tuple[int, str]:
    argv = [a for item in emulated_robot.overrides for a in ("--set", item)]
    code = main([*argv, *more])
    return code, capsys.readouterr().out


def _round_trips(out: str) -> dict[str, tuple]:
    """{"bulk cycles" / "sync reads": (count, p50 ms, p99 ms, max ms, verdict)} from the report."""
    found = {}
    for match in RTT_LINE.finditer(out):
        key = "bulk cycles" if "bulk cycles" in match.group(2) else "sync reads"
        found[key] = (int(match.group(1)), *(float(match.group(k)) for k in (3, 4, 5)), match.group(6))
    return found


def test_the_check_reports_each_bus_round_trip_and_verdict(emulated_robot, capsys):
    code, out = _check(emulated_robot, capsys, "--rtt-cycles", "200")
    assert code == 0, out
    trips = _round_trips(out)
    assert set(trips) == {"bulk cycles", "sync reads"}, out
    count, p50, p99, top, verdict = trips["bulk cycles"]
    assert count == 200 and 0 < p50 <= p99 <= top, out
    assert "read-only bulk cycles of 10 IDs" in out
    assert verdict.startswith(("holds 1 kHz", "cannot hold 1 kHz: expect")), verdict  # which depends on the machine
    assert "arm thread's 50 Hz" in trips["sync reads"][4]
    stream = STREAM_LINE.search(out)
    assert stream and int(stream.group(1)) == 200 and int(stream.group(2)) > 500, out
    assert "OK, every device answers" in out


def test_a_bear_reply_delay_changes_the_verdict(emulated_robot, capsys):
    """2 ms late replies: every bulk cycle takes at least 2 ms, so 1 kHz is out of reach and the check says what to
    expect; the devices are still all there (a late answer is not a missing device)."""
    emulated_robot.send("delay bear 0.002")
    try:
        code, out = _check(emulated_robot, capsys, "--rtt-cycles", "100")
    finally:
        emulated_robot.send("delay bear 0")
    assert code == 0, out
    count, p50, p99, top, verdict = _round_trips(out)["bulk cycles"]
    assert count == 100 and p50 >= 2.0 and p99 >= 2.0, out
    rate = int(re.match(r"cannot hold 1 kHz: expect (\d+) Hz", verdict).group(1))
    assert rate <= 1000 / (p50 + 0.2) and rate < 500, verdict
    assert f"warning: round trip: cannot hold 1 kHz: expect {rate} Hz" in out


def test_round_trips_are_skipped_while_a_bear_is_enabled_and_with_zero_cycles(emulated_robot, capsys):
    port = next(item.split("=", 1)[1] for item in emulated_robot.overrides if item.startswith("buses.bear.port="))
    with BearBus(port, reply_timeout_s=0.02) as bus:
        bus.set_torque_enable([3], 1)
        try:
            code, out = _check(emulated_robot, capsys, "--rtt-cycles", "20")
        finally:
            bus.set_torque_enable([3], 0)
    assert "round trip not measured: ID(s) 3 read torque_enable 1" in out, out
    assert "bulk cycles" not in _round_trips(out) and "sync reads" in _round_trips(out)
    code, out = _check(emulated_robot, capsys, "--rtt-cycles", "0")
    assert code == 0 and "round trip" not in out and "stream over" not in out, out


def test_a_bad_cycle_count_is_one_line(capsys):
    for value in ("-1", "many", "1000000"):
        assert main(["--rtt-cycles", value]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("bruce-hw-check: --rtt-cycles: "), err


def test_the_problem_line_names_every_bus_it_counts():
    from bruce_hw.hw_check import BusReport

    reports = [BusReport("BEAR legs (/dev/ttyUSB0)", missing=[3, 4]), BusReport("Dynamixel arms", error="no port"),
               BusReport("sense board", faults=["ID 1: IMU"])]
    phrases = [r.problem() for r in reports]
    assert phrases == ["BEAR legs: missing 3, 4", "Dynamixel arms: cannot use the bus (no port)",
                       "sense board: 1 device(s) with faults"]
    assert BusReport("ok bus").problem() == ""
