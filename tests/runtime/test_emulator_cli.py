"""`bruce-emulate`'s fault commands (unplug, plug, loss, delay) on an emulated robot in this process, and its event
lines from a child process, through EmulatorProcess."""

from __future__ import annotations

import time

import pytest
import serial

from bruce_hw.config import load_config
from bruce_hw.emulation.process import EmulatorProcess, parse_event, reply_time
from drivers.bear import BearBus, encode_ping
from drivers.dynamixel_codec import INST_PING, encode_packet
from drivers.errors import BusTimeout
from drivers.sense_codec import encode_command
from runtime.emulate_cli import execute, status


@pytest.fixture(scope="module")
def robot():
    from bruce_hw.emulation.robot import EmulatedRobot

    with EmulatedRobot(load_config()) as emulated:
        yield emulated


def _texts(robot) -> list[str]:
    return [text for _, text in robot.drain_events()]


def _sense_packets(robot) -> int:
    return robot.sense.packets_sent + robot.sense.packets_dropped  # dropped: nobody reads the pty here


def test_unplug_and_plug_cut_and_mend_each_bus(robot):
    robot.drain_events()
    with serial.Serial(robot.sense.path, timeout=0.1) as board:
        board.write(encode_command("nominal"))  # streaming, so that its stop shows
        deadline = time.monotonic() + 5.0
        while robot.sense.mode.name != "NOMINAL" and time.monotonic() < deadline:
            time.sleep(0.01)
    dxl_id = robot.config.buses.dynamixel.ids[0]
    dxl_ping = encode_packet(dxl_id, INST_PING)
    assert robot.dynamixel.handle(dxl_ping)  # answers while plugged
    reply = execute(robot, ["unplug", "bear"])
    assert reply.startswith("ok unplug bear t=") and reply_time(reply) <= time.monotonic()
    assert robot.bear.unplugged and robot.bear.handle(encode_ping(1)) == b""
    with BearBus(robot.bear.path, reply_timeout_s=0.01) as bus:
        with pytest.raises(BusTimeout):
            bus.ping(1)
        execute(robot, ["unplug", "dynamixel"])
        assert robot.dynamixel.handle(dxl_ping) == b""
        execute(robot, ["unplug", "sense"])
        time.sleep(0.01)  # a packet may be on its way
        sent = _sense_packets(robot)
        time.sleep(0.05)
        assert _sense_packets(robot) == sent
        assert status(robot)["unplugged"] == ["bear", "dynamixel", "sense"]
        for bus_name in ("bear", "dynamixel", "sense"):
            assert execute(robot, ["plug", bus_name]).startswith(f"ok plug {bus_name} t=")
        assert bus.ping(1).id == 1
    assert robot.dynamixel.handle(dxl_ping)
    time.sleep(0.05)
    assert _sense_packets(robot) > sent
    assert status(robot)["unplugged"] == []
    texts = _texts(robot)
    for text in ("bear unplug", "dynamixel unplug", "sense unplug", "bear plug", "dynamixel plug", "sense plug"):
        assert text in texts
    with pytest.raises(ValueError):
        execute(robot, ["unplug", "can"])
    with pytest.raises(ValueError):
        execute(robot, ["unplug"])


def test_loss_command_sets_the_bear_reply_loss(robot):
    robot.drain_events()
    assert execute(robot, ["loss", "bear", "0.5", "0", "3"]).startswith("ok loss bear 0.5 0 3 t=")
    assert _texts(robot) == ["bear reply loss drop 0.5 corrupt 0"]
    for _ in range(40):
        robot.bear.handle(encode_ping(1))
    dropped = status(robot)["bear"]["reply_losses"]["drop"]
    assert 5 < dropped < 35
    execute(robot, ["loss", "bear", "0", "0"])
    assert all(robot.bear.handle(encode_ping(1)) for _ in range(20))
    for bad in (["loss", "bear", "2", "0"], ["loss", "dynamixel", "0.1", "0"], ["loss", "bear", "0.1"]):
        with pytest.raises(ValueError):
            execute(robot, bad)


def test_delay_command_sets_each_bus_reply_delay(robot):
    robot.drain_events()
    assert execute(robot, ["delay", "dynamixel", "0.002", "0.001"]).startswith("ok delay dynamixel 0.002 0.001 t=")
    assert execute(robot, ["delay", "sense", "0.001"]).startswith("ok delay sense 0.001 t=")
    assert status(robot)["reply_delay"] == {"bear": [0.0, 0.0], "dynamixel": [0.002, 0.001], "sense": [0.001, 0.0]}
    assert _texts(robot) == ["dynamixel reply delay 2 ms + U(0, 1 ms)", "sense reply delay 1 ms"]
    for bad in (["delay", "bear", "-0.001"], ["delay", "bear", "0.5"], ["delay", "bear", "0.001", "nan"],
                ["delay", "can", "0.001"], ["delay", "bear"], ["delay", "bear", "soon"]):
        with pytest.raises(ValueError):
            execute(robot, bad)
    for bus_name in ("dynamixel", "sense"):
        execute(robot, ["delay", bus_name, "0"])
    assert status(robot)["reply_delay"]["sense"] == [0.0, 0.0]


def test_robot_events_come_in_time_order(robot):
    robot.drain_events()
    robot.unplug("sense")
    robot.bear.unplug()
    robot.unplug("sense", False)
    robot.bear.unplug(False)
    events = robot.drain_events()
    assert [text for _, text in events] == ["sense unplug", "bear unplug", "sense plug", "bear plug"]
    assert [stamp for stamp, _ in events] == sorted(stamp for stamp, _ in events)


def test_parse_event():
    assert parse_event("event t=12.500000 bear 3 torque_enable 1 -> 3 (host write)\n") == \
        (12.5, "bear 3 torque_enable 1 -> 3 (host write)")
    assert parse_event("ok place t=1.0") is None and parse_event("event t=x y") is None


def test_bruce_emulate_prints_events_with_the_emulators_stamps():
    """One child process: loss options at start-up, then a BEAR enabled with a 20 ms watchdog and left alone (the
    plant's 1 kHz poll must catch the expiry), and an unplug; the status and ok replies still come through."""
    with EmulatorProcess("--bear-drop", "0.05", "--bear-corrupt", "0.01", "--loss-seed", "4") as emulator:
        emulator.wait_event("bear reply loss drop 0.05 corrupt 0.01")
        assert emulator.send("loss bear 0 0").startswith("ok loss bear 0 0 t=")
        port = next(item.split("=", 1)[1] for item in emulator.overrides if item.startswith("buses.bear.port="))
        with BearBus(port, reply_timeout_s=0.05) as bus:
            bus.write_config(1, {"watchdog_timeout": 20})
            bus.set_torque_enable([1], 1)
            before = time.monotonic()
            bus.ping(1)  # the last packet: the BEAR heard it between `before` and the reply
            after = time.monotonic()
            enabled, _ = emulator.wait_event("bear 1 torque_enable 0 -> 1 (host write)")
            assert enabled <= after  # written before the ping, heard before its reply
            stamp, text = emulator.wait_event("bear 1 torque_enable 1 -> 3 (watchdog: ")
            assert stamp - before > 0.020
            assert stamp - after < 0.020 + 0.030, text  # ~1 ms late on a quiet machine; slack for a loaded one
            bus.set_torque_enable([1], 0)
            emulator.wait_event("bear 1 torque_enable 3 -> 0 (host write)")  # heard before the wire is cut below
        unplugged_at = reply_time(emulator.send("unplug bear"))
        stamp, _ = emulator.wait_event("bear unplug")
        assert abs(stamp - unplugged_at) < 0.01
        assert emulator.status()["unplugged"] == ["bear"]
        texts = [text for _, text in emulator.events()]
        assert "bear 1 watchdog_timeout 20" in texts and "bear 1 torque_enable 3 -> 0 (host write)" in texts
        assert all(a <= b for (a, _), (b, _) in zip(emulator.events(), emulator.events()[1:], strict=False))
    assert any("bruce-emulate: stopped" in line for line in emulator.output)
