"""`bruce-hw-check --probe-watchdog` against the BEAR emulator (which takes watchdog_timeout in milliseconds), on a
pseudo-terminal with no plant: the emulator checks its watchdog when a packet arrives, which is what the probe's
ping is."""

from __future__ import annotations

import re
import struct
import time

import pytest

from drivers.bear import BearBus
from drivers.emulators import bear as bear_emulator
from drivers.emulators.bear import BearBusEmulator
from drivers.hw_check import ProbeError, main, probe_watchdog

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
    assert not any(t.startswith("bear ") and not t.startswith("bear 3 ") for t in texts)  # nobody else touched
    assert texts[-1] == "bear 3 watchdog_timeout 77"


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
