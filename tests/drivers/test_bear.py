"""BEAR RS-485: packets against hand-built bytes from the spec, the driver against the byte-exact emulator over a real
pseudo-terminal, an independent raw-pyserial host against the emulator, and property tests of both parsers."""

from __future__ import annotations

import struct
import threading
import time
import types

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.bear import BearBus
from drivers.bear_codec import (
    StatusPacket,
    StatusParser,
    encode_bulk,
    encode_frame,
    encode_ping,
    encode_read,
    encode_save_config,
    encode_status,
    encode_write,
)
from drivers.bear_registers import (
    CONFIG_REGISTERS,
    CYCLE_READS,
    GOALS_BY_MODE,
    MAX_FRAME,
    STATUS_REGISTERS,
    BearError,
    Mode,
    config_register,
    error_flags,
    status_register,
)
from drivers.emulators import bear as bear_emulator
from drivers.emulators.bear import BearBusEmulator, EventLog
from drivers.errors import BusTimeout, DeviceFault, DriverError

IDS = list(range(1, 11))
PROPERTY = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


def frame(device_id: int, code: int, params: bytes = b"") -> bytes:
    """A packet built straight from the spec's table, independently of drivers.bear: CHK = 255 - (sum mod 256)."""
    body = bytes([device_id, len(params) + 2, code]) + params
    return b"\xff\xff" + body + bytes([255 - sum(body) % 256])


def f32(value: float) -> bytes:
    return struct.pack("<f", value)


def u32(value: int) -> bytes:
    return struct.pack("<I", value)


@pytest.fixture
def emulator():
    with BearBusEmulator(IDS) as emu:
        yield emu


@pytest.fixture
def bus(emulator):
    # Generous reply timeout: the emulator is a Python thread on a shared, noisy machine.
    with BearBus(emulator.path, reply_timeout_s=0.2) as driver:
        yield driver


# -- packets against the spec ---------------------------------------------------------------------------------------
def test_instruction_packets_are_the_spec_bytes():
    assert encode_ping(1) == bytes.fromhex("ff ff 01 02 01 fb")
    assert encode_ping(10) == frame(10, 0x01)
    assert encode_read(1, [status_register("present_position")]) == bytes.fromhex("ff ff 01 03 02 09 f0")
    assert encode_read(4, [config_register("mode"), config_register("limit_iq_max")]) == frame(4, 0x04, b"\x01\x14")
    assert encode_save_config(1) == bytes.fromhex("ff ff 01 02 06 f6")
    # torque_enable is u32: 1 goes out as 01 00 00 00, never as float32 1.0 (00 00 80 3f).
    assert encode_write(1, [(status_register("torque_enable"), 1)]) == bytes.fromhex("ff ff 01 07 03 00 01 00 00 00 f3")
    assert encode_write(2, [(status_register("goal_iq"), 1.0), (status_register("goal_position"), -0.5)]) == \
        frame(2, 0x03, b"\x03" + f32(1.0) + b"\x05" + f32(-0.5))
    assert encode_write(3, [(config_register("watchdog_timeout"), 20), (config_register("p_gain_force"), 10.0)]) == \
        frame(3, 0x05, b"\x1a" + u32(20) + b"\x10" + f32(10.0))


def test_bulk_packet_layout_and_length():
    ids = [1, 2]
    reads = [status_register("present_position")]
    writes = [status_register("goal_iq"), status_register("torque_enable")]
    packet = encode_bulk(ids, reads, writes, [[1.0, 1], [-1.0, 0]])
    params = bytes([2, 0x12, 0x09, 0x03, 0x00]) + b"\x01" + f32(1.0) + u32(1) + b"\x02" + f32(-1.0) + u32(0)
    assert packet == frame(0xFE, 0x12, params)
    n_motors, n_read, n_write = 2, 1, 2
    assert packet[3] == n_motors + n_read + n_write + 4 * n_write * n_motors + 4  # LEN formula of BULK_COMM
    # BRUCE's tick: 10 motors, 3 reads, 3 force-mode writes: 144 bytes on the wire.
    force = [status_register(n) for n in ("goal_position", "goal_velocity", "goal_iq")]
    tick = encode_bulk(IDS, [status_register(n) for n in CYCLE_READS], force, np.zeros((10, 3)))
    assert len(tick) == 144 and tick[2] == 0xFE and tick[4] == 0x12
    # read-only bulk: the IDs follow the addresses
    assert encode_bulk([5, 6], reads) == frame(0xFE, 0x12, bytes([2, 0x10, 0x09, 5, 6]))


@settings(max_examples=300, deadline=None)
@given(mode=st.sampled_from([Mode.TORQUE, Mode.FORCE]),
       goals=st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                                st.floats(-31.0, 31.0), st.integers(-40, 40), st.sampled_from([30.0, -30.0, 3.5e38])),
                      min_size=30, max_size=30),
       as_array=st.booleans())
def test_a_cycles_goals_are_packed_and_refused_as_each_register_packs_and_refuses_them(mode, goals, as_array):
    """The bulk request packs a cycle's goals all at once (`BulkLayout`, built once per shape): its bytes are those of
    each value packed by its register (`Register.encode`, which refuses NaN, inf, beyond float32 and beyond the rated
    current), and it refuses exactly where one of them does, naming the register."""
    writes = [status_register(n) for n in GOALS_BY_MODE[mode]]
    reads = [status_register(n) for n in CYCLE_READS]
    table = np.array(goals[:10 * len(writes)], dtype=np.float64).reshape(10, len(writes))
    if not as_array:
        table = [[goals[k * len(writes) + j] for j in range(len(writes))] for k in range(10)]  # Python ints, floats
    try:
        per_motor = b"".join(bytes([i]) + b"".join(r.encode(v) for r, v in zip(writes, row, strict=True))
                             for i, row in zip(IDS, np.asarray(table).tolist() if as_array else table, strict=True))
    except ValueError as refused:
        with pytest.raises(ValueError, match=str(refused).split(" ")[0]):
            encode_bulk(IDS, reads, writes, table)
        return
    head = bytes([10, len(reads) << 4 | len(writes)]) + bytes(r.address for r in reads + writes)
    assert encode_bulk(IDS, reads, writes, table) == frame(0xFE, 0x12, head + per_motor)


def test_values_are_typed_by_register():
    torque, goal = status_register("torque_enable"), status_register("goal_iq")
    assert torque.encode(np.int64(3)) == u32(3) and torque.encode(1.0) == u32(1) and torque.encode(True) == u32(1)
    for bad in (1.5, -1, 2**32, float("nan"), "1"):
        with pytest.raises(ValueError):
            torque.encode(bad)
    for bad in (float("nan"), float("inf"), 1e39, None):
        with pytest.raises(ValueError):
            goal.encode(bad)
    assert goal.encode(np.float32(0.25)) == f32(0.25)
    assert {r.kind for r in CONFIG_REGISTERS.values() if r.name in ("id", "mode", "baudrate", "watchdog_timeout")} \
        == {"u32"}
    assert STATUS_REGISTERS["homing_complete"].kind == "u32" and STATUS_REGISTERS["present_position"].kind == "f32"
    with pytest.raises(ValueError, match="status registers only"):
        encode_bulk([1], [config_register("mode")])
    with pytest.raises(ValueError, match="read-only"):
        encode_bulk([1], [], [status_register("present_position")], [[0.0]])
    with pytest.raises(ValueError, match="at most 15"):
        encode_bulk([1], [status_register(0x09)] * 16)
    with pytest.raises(ValueError, match="distinct"):
        encode_bulk([1, 1], [status_register(0x09)])


def test_error_byte_flags():
    assert error_flags(0x80) == ()
    assert error_flags(0x88) == ("watchdog_estop",)
    assert error_flags(0x80 | 0x01 | 0x20) == ("communication", "hardware")
    assert error_flags(0xFF) == ("communication", "overheat", "absolute_position", "watchdog_estop", "joint_limit",
                                 "hardware", "initialization")


def test_status_parser_reads_a_spec_reply():
    reply = frame(3, 0x80, f32(1.0) + u32(7))
    assert encode_status(3, 0x80, f32(1.0) + u32(7)) == reply
    parser = StatusParser()
    parser.expect(10, [3])
    assert parser.feed(reply[:5]) == [] and parser.pending == 5
    assert parser.feed(reply[5:]) == [StatusPacket(3, 0x80, f32(1.0) + u32(7))]
    assert parser.stats.packets == 1 and parser.stats.rejected_total == 0


# -- the emulator against hand-built bytes (no pty) -----------------------------------------------------------------
def test_emulator_answers_the_spec_bytes():
    emu = BearBusEmulator([1, 2])
    assert emu.handle(bytes.fromhex("ff ff 01 02 01 fb")) == frame(1, 0x80, b"\x01\x01")
    assert emu.handle(frame(5, 0x01)) == b""  # nobody has ID 5
    assert emu.handle(frame(0xFE, 0x01)) == b""  # broadcast reads get no reply
    emu.set_measured(2, 0.5, -2.0, 1.25)
    assert emu.handle(frame(2, 0x02, b"\x09\x08\x07\x00")) == \
        frame(2, 0x80, f32(0.5) + f32(-2.0) + f32(1.25) + u32(0))
    assert emu.handle(frame(1, 0x04, b"\x00\x01\x10")) == frame(1, 0x80, u32(1) + u32(0) + f32(10.0))
    # writes get no reply; a u32 register takes the u32 encoding
    assert emu.handle(frame(1, 0x03, b"\x00" + u32(1) + b"\x05" + f32(0.75))) == b""
    assert emu.command(1).torque_enable == 1 and emu.command(1).goal_position == 0.75
    # float32 1.0 written to torque_enable is 1065353216, not 1: refused, and reported with the communication bit
    assert emu.handle(frame(2, 0x03, b"\x00" + f32(1.0))) == b""
    assert emu.command(2).torque_enable == 0
    assert emu.handle(frame(2, 0x01)) == frame(2, 0x81, b"\x01\x01")
    assert emu.handle(frame(2, 0x01)) == frame(2, 0x80, b"\x01\x01")  # the warning resets once reported
    # broadcast writes reach everybody, silently
    assert emu.handle(frame(0xFE, 0x03, b"\x03" + f32(-1.5))) == b""
    assert emu.commands([1, 2])["goal_iq"].tolist() == [-1.5, -1.5]


def test_emulator_bulk_replies_in_request_order():
    emu = BearBusEmulator([1, 2, 3])
    emu.set_measured(1, 0.25, 0.0, 0.0)
    emu.set_measured(2, -0.5, 0.0, 0.0)
    # read present_position and torque_enable of ID 2 then ID 1 (3 is not asked), write goal_iq to both
    params = bytes([2, 0x21, 0x09, 0x00, 0x03]) + b"\x02" + f32(2.0) + b"\x01" + f32(-2.0)
    reply = emu.handle(frame(0xFE, 0x12, params))
    assert reply == frame(2, 0x80, f32(-0.5) + u32(0)) + frame(1, 0x80, f32(0.25) + u32(0))
    assert emu.commands([1, 2, 3])["goal_iq"].tolist() == [-2.0, 2.0, 0.0]
    # write-only bulk: no reply; a silent motor is skipped, the others still answer in order
    assert emu.handle(frame(0xFE, 0x12, bytes([1, 0x01, 0x05, 3]) + f32(0.1))) == b""
    emu.silence([2])
    assert emu.handle(frame(0xFE, 0x12, bytes([3, 0x10, 0x09, 3, 2, 1]))) == \
        frame(3, 0x80, f32(0.0)) + frame(1, 0x80, f32(0.25))
    # a bulk whose length disagrees with its counts is dropped
    assert emu.handle(frame(0xFE, 0x12, bytes([2, 0x10, 0x09, 1]))) == b""
    assert emu.stats.rejected["bulk_length"] == 1


def test_a_bulk_reply_in_another_id_order_keeps_each_ids_row():
    from drivers.bear import BulkReply

    late = BulkReply("/dev/x", (3,), ("present_position",), np.array([[9.0]]), np.array([0], np.uint8))
    reply = BulkReply("/dev/x", (3, 1, 2), ("present_position", "present_velocity"),
                      np.array([[3.0, 30.0], [1.0, 10.0], [np.nan, np.nan]]), np.array([8, 0, 0], np.uint8),
                      np.array([True, True, False]), 12.5, late)
    ordered = reply.in_order((1, 2, 3))
    assert ordered.ids == (1, 2, 3) and ordered.registers == reply.registers
    assert ordered.position[[0, 2]].tolist() == [1.0, 3.0] and np.isnan(ordered.position[1])
    assert ordered.velocity[[0, 2]].tolist() == [10.0, 30.0]
    assert ordered.answered.tolist() == [True, False, True] and ordered.lost_ids == (2,)
    assert ordered.estop_ids() == (3,) and ordered.sent_at == 12.5 and ordered.late is late
    assert reply.in_order((3, 1, 2)) is reply
    given = reply.in_order((1, 2, 3), np.array([1, 2, 0]))  # the caller's rows: the same answers, no lookup
    assert given.ids == ordered.ids and given.answered.tolist() == ordered.answered.tolist()
    np.testing.assert_array_equal(given.values, ordered.values)
    np.testing.assert_array_equal(given.error, ordered.error)
    assert BulkReply("/dev/x", (2, 1), ("present_position",), np.array([[2.0], [1.0]]),
                     np.zeros(2, np.uint8)).in_order((1, 2)).answered is None


def test_emulator_torque_enable_and_error_semantics():
    emu = BearBusEmulator([1])
    write_torque = lambda v: emu.handle(frame(1, 0x03, b"\x00" + u32(v)))  # noqa: E731
    ping_error = lambda: emu.handle(frame(1, 0x01))[4]  # noqa: E731
    write_torque(3)  # damping sets bit 3 and reads 3
    assert emu.command(1).torque_enable == 3 and ping_error() == 0x88
    write_torque(0)
    assert emu.command(1).torque_enable == 0 and ping_error() == 0x80
    emu.set_error(1, BearError.ABSOLUTE_POSITION)
    write_torque(1)  # enabled with a fault reads 2
    assert emu.command(1).torque_enable == 2 and ping_error() == 0x84
    write_torque(0)  # writing 0 clears a latched fault
    assert ping_error() == 0x80
    emu.set_estop(True)
    write_torque(0)  # the E-stop input holds until released
    assert ping_error() == 0x88 and emu.command(1).torque_enable == 3
    emu.set_estop(False)
    assert ping_error() == 0x80
    emu.set_register_value(1, "input_voltage", 5.0)  # state-derived bits follow the state
    emu.set_register_value(1, "winding_temperature", 80.0)
    assert ping_error() == 0x80 | 0x20 | 0x02
    emu.set_register_value(1, "input_voltage", 24.0)
    emu.set_register_value(1, "winding_temperature", 30.0)
    emu.set_measured(1, 3.5, 0.0, 0.0)
    assert ping_error() == 0x90
    assert emu.register_value(1, "error_status") == 0x10


def test_emulator_config_rules_and_flash():
    emu = BearBusEmulator([1, 2])
    emu.handle(frame(1, 0x03, b"\x00" + u32(1)))
    emu.handle(frame(1, 0x05, b"\x01" + u32(3)))  # torque enabled: refused
    emu.handle(frame(1, 0x06))
    assert emu.register_value(1, "mode", "config") == 0 and emu.saved_config(1)["mode"] == 0
    emu.handle(frame(1, 0x03, b"\x00" + u32(0)))
    emu.handle(frame(1, 0x05, b"\x01" + u32(3) + b"\x10" + f32(12.5)))
    assert emu.register_value(1, "mode", "config") == 3 and emu.command(1).mode == 3
    emu.handle(frame(1, 0x06))
    emu.handle(frame(1, 0x05, b"\x01" + u32(0)))  # changed after the save: lost at power-up
    emu.power_cycle([1])
    assert emu.register_value(1, "mode", "config") == 3 and emu.register_value(1, "p_gain_force", "config") == 12.5
    emu.handle(frame(1, 0x05, b"\x01" + u32(9)))  # no mode 9
    assert emu.register_value(1, "mode", "config") == 3
    emu.handle(frame(1, 0x05, b"\x00" + u32(2)))  # ID 2 is taken
    emu.handle(frame(1, 0x05, b"\x00" + u32(7)))  # a new ID
    assert emu.ids == (2, 7) and emu.handle(frame(7, 0x01))[:3] == b"\xff\xff\x07"


def test_emulator_watchdog_damps_a_forgotten_torque_mode_motor():
    emu = BearBusEmulator([1])
    emu.handle(frame(1, 0x05, b"\x1a" + u32(20)))  # 20 ms
    emu.handle(frame(1, 0x03, b"\x00" + u32(1)))
    assert emu.command(1).torque_enable == 1
    time.sleep(0.1)
    assert emu.command(1).torque_enable == 3 and emu.command(1).error & 0x08


# -- the emulator's event log, reply loss and cut wire (no pty) -----------------------------------------------------
def _texts(emu: BearBusEmulator) -> list[str]:
    return [text for _, text in emu.drain_events()]


def test_emulator_logs_torque_enable_changes_with_their_causes():
    emu = BearBusEmulator([1, 2])
    write_torque = lambda device_id, v: emu.handle(frame(device_id, 0x03, b"\x00" + u32(v)))  # noqa: E731
    before = time.monotonic()
    emu.handle(frame(1, 0x05, b"\x1a" + u32(20)))  # watchdog_timeout 20 (ms)
    write_torque(1, 1)
    write_torque(1, 1)  # no change, no event
    after = time.monotonic()
    events = emu.drain_events()
    assert [text for _, text in events] == ["bear 1 watchdog_timeout 20", "bear 1 torque_enable 0 -> 1 (host write)"]
    assert all(before <= stamp <= after for stamp, _ in events)
    enabled_at = events[1][0]
    emu.handle(frame(1, 0x05, b"\x1a" + u32(30)))  # refused while enabled: logged as such, no watchdog event
    assert _texts(emu) == ["bear 1 config write ignored (torque_enable 1)"]
    time.sleep(0.05)
    emu.command(1)  # the plant's poll: the watchdog is detected here, and stamped when detected
    (stamp, text), = emu.drain_events()
    assert text.startswith("bear 1 torque_enable 1 -> 3 (watchdog: ") and text.endswith(" ms without a packet)")
    silent_ms = float(text.split("watchdog: ")[1].split(" ms")[0])
    assert 20.0 < silent_ms and abs(silent_ms - 1e3 * (stamp - enabled_at)) < 1.0
    write_torque(1, 0)
    emu.set_estop(True, [2])
    emu.set_estop(False, [2])
    write_torque(2, 1)
    emu.set_register_value(2, "input_voltage", 5.0)
    emu.set_register_value(2, "input_voltage", 24.0)
    emu.set_measured(2, 3.5, 0.0, 0.0)  # past limit_position_max while enabled
    emu.set_measured(2, 0.0, 0.0, 0.0)
    write_torque(2, 3)
    emu.power_cycle([2])
    assert _texts(emu) == [
        "bear 1 torque_enable 3 -> 0 (host write)",
        "bear 2 torque_enable 0 -> 3 (e-stop input)",
        "bear 2 torque_enable 3 -> 0 (e-stop input)",
        "bear 2 torque_enable 0 -> 1 (host write)",
        "bear 2 torque_enable 1 -> 2 (input_voltage set)",
        "bear 2 torque_enable 2 -> 1 (input_voltage set)",
        "bear 2 torque_enable 1 -> 2 (fault: joint_limit)",
        "bear 2 torque_enable 2 -> 1 (fault cleared)",
        "bear 2 torque_enable 1 -> 3 (host write)",
        "bear 2 torque_enable 3 -> 0 (power cycle)",
    ]
    # BULK_COMM writes count as host writes; a watchdog in another mode than torque never fires
    emu.handle(frame(2, 0x05, b"\x01" + u32(2) + b"\x1a" + u32(5)))
    emu.handle(frame(0xFE, 0x12, bytes([1, 0x01, 0x00, 2]) + u32(1)))
    time.sleep(0.02)
    emu.commands()
    assert _texts(emu) == ["bear 2 watchdog_timeout 5", "bear 2 torque_enable 0 -> 1 (host write)"]
    assert emu.drain_events() == []


def test_event_log_is_bounded_and_thread_safe():
    log = EventLog(maxlen=100)

    def add(k: int) -> None:
        for j in range(1000):
            log.add(f"{k} {j}")

    threads = [threading.Thread(target=add, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    kept = log.drain()
    assert len(kept) == 100 and log.dropped == 3900 and log.drain() == []
    assert [stamp for stamp, _ in kept] == sorted(stamp for stamp, _ in kept)
    emu = BearBusEmulator([1])
    for k in range(10_002):  # one event each: the two oldest go
        emu.set_estop(k % 2 == 0)
    events = emu.drain_events()
    assert len(events) == 10_000 and emu.events_dropped == 2
    assert events[0][1] == "bear 1 torque_enable 0 -> 3 (e-stop input)"


def test_reply_loss_matches_its_probabilities():
    emu = BearBusEmulator(IDS)
    emu.set_reply_loss(drop=0.05, corrupt=0.01, seed=1)
    assert _texts(emu) == ["bear reply loss drop 0.05 corrupt 0.01"]
    request = encode_bulk(IDS, [status_register(n) for n in CYCLE_READS])
    parser = StatusParser()
    cycles = 3000
    for _ in range(cycles):
        parser.clear()
        parser.expect(4 * len(CYCLE_READS) + 2, IDS)
        parser.feed(emu.handle(request))
    n = cycles * len(IDS)
    losses = emu.reply_losses
    assert emu.replies == n
    # binomial counts within 5 standard deviations of their means
    for kinds, p in ((("drop",), 0.05), (("checksum", "truncate", "garbage"), 0.01), (("checksum",), 0.01 / 3)):
        count = sum(losses[k] for k in kinds)
        assert abs(count - n * p) < 5 * (n * p * (1 - p)) ** 0.5, (kinds, count)
    assert set(losses) == {"drop", "checksum", "truncate", "garbage"}
    # dropped, bad-checksum and truncated replies are lost; garbage only precedes an intact reply
    lost = losses["drop"] + losses["checksum"] + losses["truncate"]
    assert abs(parser.stats.packets - (n - lost)) <= 3
    assert parser.stats.rejected["garbage"] >= losses["garbage"]
    # the same seed, the same losses; (0, 0) turns it off
    again = BearBusEmulator(IDS)
    again.set_reply_loss(0.05, 0.01, seed=1)
    for _ in range(cycles):
        again.handle(request)
    assert again.reply_losses == losses
    again.set_reply_loss()
    again.handle(request)
    assert again.reply_losses == losses
    with pytest.raises(ValueError):
        emu.set_reply_loss(0.7, 0.4)


def test_unplugged_bus_answers_nothing_and_the_watchdogs_run_out():
    emu = BearBusEmulator([1, 2, 3])
    emu.silence([3])
    for device_id in (1, 2):
        emu.handle(frame(device_id, 0x05, b"\x1a" + u32(20)))
        emu.handle(frame(device_id, 0x03, b"\x00" + u32(1)))
    emu.drain_events()
    packets = emu.stats.packets
    emu.handle(frame(1, 0x01)[:3])  # half a packet on the wire when it is cut
    emu.unplug()
    assert emu.unplugged
    ping, bulk = frame(1, 0x01), encode_bulk([1, 2], [status_register("present_position")])
    for _ in range(3):
        assert emu.handle(ping) == b"" and emu.handle(bulk) == b""
        time.sleep(0.015)  # the host keeps trying: none of it reaches a BEAR
    assert emu.stats.packets == packets and emu.unplugged_bytes == 3 * (len(ping) + len(bulk))
    assert emu.requests["PING"] == 0 and emu.requests["BULK_COMM"] == 0
    texts = _texts(emu)
    assert texts[0] == "bear unplug" and len(texts) == 3
    assert sorted(t.split(" (")[0] for t in texts[1:]) == ["bear 1 torque_enable 1 -> 3", "bear 2 torque_enable 1 -> 3"]
    assert all("(watchdog: " in t for t in texts[1:])
    emu.unplug(False)
    assert _texts(emu) == ["bear plug"]
    assert emu.handle(ping) == frame(1, 0x88, b"\x01\x01")  # answers again, damping; the cut packet is gone
    assert emu.handle(frame(3, 0x01)) == b""  # silenced before: still silent


def test_watchdog_expiry_is_detected_within_a_poll_period():
    """With something polling commands() every millisecond (the plant), a watchdog expiry is logged within a few
    milliseconds of the deadline, though no packet arrives."""
    emu = BearBusEmulator([1])
    emu.handle(frame(1, 0x05, b"\x1a" + u32(30)))
    last_packet = time.monotonic()  # before the packet: the BEAR stamps it on arrival, inside handle()
    emu.handle(frame(1, 0x03, b"\x00" + u32(1)))
    emu.unplug()
    stop = threading.Event()

    def poll() -> None:
        while not stop.is_set():
            emu.commands()
            time.sleep(0.001)

    poller = threading.Thread(target=poll)
    poller.start()
    time.sleep(0.1)
    stop.set()
    poller.join()
    (stamp, text), = [e for e in emu.drain_events() if "watchdog:" in e[1]]
    late_s = stamp - (last_packet + 0.030)
    assert 0.0 <= late_s < 0.02, late_s  # a loaded machine gets slack; typically about 1 ms


def test_driver_rides_out_one_percent_reply_loss(emulator):
    emulator.set_reply_loss(drop=0.01, corrupt=0.01, seed=2)
    timeouts = 0
    with BearBus(emulator.path, reply_timeout_s=0.01) as bus:
        for _ in range(300):
            try:
                reply = bus.bulk_cycle(IDS, "torque", goal_iq=np.zeros(10))
                assert reply.ids == tuple(IDS)
            except BusTimeout:
                timeouts += 1
        stats = bus.stats
    lost = emulator.reply_losses
    assert lost["drop"] > 0 and stats.retries > 0
    assert stats.rejected["checksum"] + stats.rejected["truncated"] >= lost["checksum"] > 0
    assert timeouts <= 5  # both tries lost for one motor: about 1e-4 per motor and cycle


# -- the driver over the emulator's pty -----------------------------------------------------------------------------
def test_every_instruction_round_trips(bus, emulator):
    for device_id in IDS:
        reply = bus.ping(device_id)
        assert (reply.id, reply.error, reply.flags, reply.data) == (device_id, 0x80, (), b"\x01\x01")
    config = bus.read_config(4, list(CONFIG_REGISTERS)).values
    assert config["id"] == 4 and isinstance(config["id"], int) and config["mode"] == 0
    assert config["p_gain_force"] == 10.0 and config["limit_position_max"] == 3.0
    status = bus.read_status(4, list(STATUS_REGISTERS))
    assert status["torque_enable"] == 0 and status["input_voltage"] == 24.0 and status.flags == ()

    bus.write_config(4, {"mode": 3, "p_gain_force": 12.5, "d_gain_force": 0.3, "limit_iq_max": 20.0})
    assert emulator.register_value(4, "mode", "config") == 3
    assert emulator.register_value(4, "d_gain_force", "config") == pytest.approx(0.3)
    bus.save_config(4)
    assert bus.read_config(4, "mode")["mode"] == 3  # the save has been processed before this answer
    assert emulator.saved_config(4)["p_gain_force"] == 12.5

    bus.write_status(4, {"goal_position": 0.5, "goal_velocity": -1.0, "goal_iq": 2.0})
    bus.set_torque_enable([4], 1)
    got = bus.read_status(4, ["torque_enable", "goal_position", "goal_velocity", "goal_iq"]).values
    assert got == {"torque_enable": 1, "goal_position": 0.5, "goal_velocity": -1.0, "goal_iq": 2.0}
    command = emulator.command(4)
    assert (command.mode, command.torque_enable, command.goal_iq) == (3, 1, 2.0)
    with pytest.raises(ValueError, match="read-only"):
        bus.write_status(4, {"present_position": 1.0})

    reply = bus.bulk_comm([3, 1], ["present_position", "torque_enable"], ["goal_velocity"], [[1.5], [-1.5]])
    assert reply.ids == (3, 1) and reply.values.shape == (2, 2) and reply.error.tolist() == [0x80, 0x80]
    assert emulator.commands([1, 3])["goal_velocity"].tolist() == [-1.5, 1.5]
    assert bus.stats.rejected_total == 0 and bus.stats.timeouts == 0 and bus.stats.retries == 0


def test_bulk_cycle_reads_all_motors_and_writes_the_modes_goals(bus, emulator):
    positions = np.linspace(-1.0, 1.0, 10)
    emulator.set_measured_many(IDS, positions, 2 * positions, -positions)
    goal_position, goal_velocity, goal_iq = 0.1 * np.arange(10), -0.5 * np.ones(10), np.arange(10) / 4.0
    reply = bus.bulk_cycle(IDS, "force", goal_position, goal_velocity, goal_iq)
    np.testing.assert_allclose(reply.position, positions, rtol=1e-6)
    np.testing.assert_allclose(reply.velocity, 2 * positions, rtol=1e-6)
    np.testing.assert_allclose(reply.iq, -positions, rtol=1e-6)
    assert reply.ids == tuple(IDS) and reply.error.dtype == np.uint8 and (reply.error == 0x80).all()
    goals = emulator.commands(IDS)
    np.testing.assert_allclose(goals["goal_position"], goal_position, rtol=1e-6)
    np.testing.assert_allclose(goals["goal_velocity"], goal_velocity)
    np.testing.assert_allclose(goals["goal_iq"], goal_iq)

    # torque mode writes goal_iq only; the position goal stays as it was
    bus.bulk_cycle(IDS, 0, goal_iq=np.full(10, -3.0))
    goals = emulator.commands(IDS)
    assert (goals["goal_iq"] == -3.0).all()
    np.testing.assert_allclose(goals["goal_position"], goal_position, rtol=1e-6)
    # read only (zero-torque start-up): nothing written; IDs in any order come back in that order
    reply = bus.bulk_cycle(IDS[::-1], None)
    np.testing.assert_allclose(reply.position, positions[::-1], rtol=1e-6)
    assert (emulator.commands(IDS)["goal_iq"] == -3.0).all()
    with pytest.raises(ValueError, match="goal_velocity"):
        bus.bulk_cycle(IDS, "force", goal_position, None, goal_iq)
    with pytest.raises(ValueError, match="9 values for 10 IDs"):
        bus.bulk_cycle(IDS, "torque", goal_iq=np.zeros(9))
    with pytest.raises(ValueError):
        bus.bulk_cycle(IDS, "torque", goal_iq=np.full(10, np.nan))  # never sent to a motor
    assert bus.stats.packets == 30


def test_bulk_writes_u32_registers_as_integers(bus, emulator):
    bus.bulk_comm(IDS, [], ["torque_enable"], [[1]] * 10)  # write-only: no reply to wait for
    bus.ping(IDS[0])  # the emulator answers in order, so the bulk write has been applied once this returns
    assert (emulator.commands(IDS)["torque_enable"] == 1).all()
    reply = bus.bulk_comm(IDS, ["torque_enable"], ["torque_enable"], [[3]] * 10)
    assert (reply.column("torque_enable") == 3).all() and (reply.error == 0x88).all()


def test_config_write_while_torque_is_enabled_is_refused(bus, emulator):
    bus.set_torque_enable([2], 1)
    with pytest.raises(DriverError, match="writable only while torque is disabled"):
        bus.write_config(2, {"mode": 3})
    assert emulator.register_value(2, "mode", "config") == 0
    bus.set_torque_enable([2], 0)
    bus.write_config(2, {"mode": 3})
    assert emulator.register_value(2, "mode", "config") == 3


def test_estop_bit_reaches_the_caller(bus, emulator):
    emulator.set_estop(True, ids=[3])
    reply = bus.bulk_cycle(IDS, "force", np.zeros(10), np.zeros(10), np.zeros(10))
    assert reply.estop_ids() == (3,) and reply.faulted_ids() == (3,) and "watchdog_estop" in reply.flags(3)
    with pytest.raises(DeviceFault) as info:
        reply.raise_for_faults()
    assert info.value.device_id == 3 and "watchdog_estop" in info.value.flags and emulator.path in str(info.value)
    assert bus.ping(3).flags == ("watchdog_estop",)
    assert bus.read_status(3, "torque_enable")["torque_enable"] == 3
    with pytest.raises(DeviceFault, match="release the E-stop"):
        bus.clear_errors(3)
    emulator.set_estop(False, ids=[3])
    assert bus.clear_errors(3).error == 0x80
    bus.bulk_cycle(IDS, None).raise_for_faults()  # nothing left to raise


def test_clear_errors_writes_torque_off_until_the_fault_clears(bus, emulator):
    emulator.set_error(2, BearError.ABSOLUTE_POSITION)
    assert bus.ping(2).flags == ("absolute_position",)
    assert bus.clear_errors(2).flags == ()
    emulator.set_register_value(5, "input_voltage", 60.0)  # a fault that writing 0 cannot clear
    with pytest.raises(DeviceFault, match="hardware"):
        bus.clear_errors(5)


def test_silent_ids_are_named_exactly(bus, emulator):
    emulator.silence([4, 7])
    with pytest.raises(BusTimeout) as info:
        bus.bulk_cycle(IDS, "torque", goal_iq=np.zeros(10))
    assert info.value.silent_ids == (4, 7) and info.value.bus == emulator.path
    assert "4, 7" in str(info.value) and emulator.path in str(info.value)
    assert bus.stats.timeouts == 1 and bus.stats.retries == 1  # the retry went to 4 and 7 only
    with pytest.raises(BusTimeout) as info:
        bus.ping(7)
    assert info.value.silent_ids == (7,)
    emulator.silence([4, 7], silent=False)
    assert bus.bulk_cycle(IDS, None).ids == tuple(IDS)


def test_silence_is_reported_within_the_default_budget(emulator):
    with BearBus(emulator.path) as bus:  # BRUCE's defaults: 2 ms reply budget, 2 tries
        assert bus.cycle_budget_s(10) <= 0.010  # the worst case fits the 10 ms the safety layer allows
        emulator.silence([6])
        start = time.monotonic()
        with pytest.raises(BusTimeout) as info:
            bus.bulk_cycle(IDS, "force", np.zeros(10), np.zeros(10), np.zeros(10))
        elapsed = time.monotonic() - start
    assert 6 in info.value.silent_ids
    assert elapsed < 0.5  # bounded, never blocking (generous: the machine is shared)


@pytest.mark.parametrize("kind, device_id, reason, retries", [
    ("checksum", 5, "checksum", 1),
    ("truncate", 5, "checksum", 1),  # the cut packet runs into the next one's bytes
    ("truncate", 10, "truncated", 1),  # the last packet stays incomplete
    ("garbage", 5, "garbage", 0),
    ("foreign", 5, "foreign", 0),
    ("drop", 5, None, 1),
])
def test_corrupted_replies_are_rejected_counted_and_retried(bus, emulator, kind, device_id, reason, retries):
    emulator.set_measured_many(IDS, np.arange(10) / 4, np.zeros(10), np.zeros(10))
    emulator.corrupt_next_reply(kind, device_id)
    reply = bus.bulk_cycle(IDS, "torque", goal_iq=np.ones(10))
    assert reply.position.tolist() == (np.arange(10) / 4).tolist()
    assert bus.stats.retries == retries and bus.stats.timeouts == 0
    if reason:
        assert bus.stats.rejected[reason] >= 1
    assert bus.ping(device_id).error == 0x80  # and the bus goes on


def test_single_reads_survive_a_corrupted_reply(bus, emulator):
    emulator.corrupt_next_reply("checksum", 2)
    assert bus.read_status(2, "input_voltage")["input_voltage"] == 24.0
    emulator.corrupt_next_reply("garbage", 2)
    assert bus.ping(2).id == 2
    assert bus.stats.rejected["checksum"] >= 1 and bus.stats.timeouts == 0


def test_unknown_port_fails_with_its_name():
    with pytest.raises(DriverError, match="/dev/no-such-bear"):
        BearBus("/dev/no-such-bear")


# -- an independent host: raw pyserial and hand-built bytes ---------------------------------------------------------
def _read_exactly(port: serial.Serial, n: int, timeout_s: float = 2.0) -> bytes:
    data = b""
    deadline = time.monotonic() + timeout_s
    while len(data) < n and time.monotonic() < deadline:
        data += port.read(n - len(data))
    return data


def test_independent_host_over_the_pty(emulator):
    emulator.set_measured_many([1, 2, 3], [0.5, 1.0, 1.5], [0.0, 0.0, 0.0], [0.25, 0.5, 0.75])
    with serial.Serial(emulator.path, 8_000_000, timeout=0.05) as port:
        port.write(b"\x13\x37\xff" + frame(1, 0x01))  # noise first: the device resynchronises on FF FF
        assert _read_exactly(port, 8) == frame(1, 0x80, b"\x01\x01")
        params = bytes([3, 0x33, 0x09, 0x08, 0x07, 0x05, 0x04, 0x03])
        for device_id in (1, 2, 3):
            params += bytes([device_id]) + f32(0.1 * device_id) + f32(0.0) + f32(-1.0)
        port.write(frame(0xFE, 0x12, params))
        data = _read_exactly(port, 3 * (4 + 14))
        assert data == b"".join(frame(i, 0x80, f32(p) + f32(0.0) + f32(q))
                                for i, p, q in ((1, 0.5, 0.25), (2, 1.0, 0.5), (3, 1.5, 0.75)))
        port.write(frame(2, 0x03, b"\x00" + u32(1)))  # a write: no reply
        assert _read_exactly(port, 1, timeout_s=0.1) == b""
    np.testing.assert_allclose(emulator.commands([1, 2, 3])["goal_position"], [0.1, 0.2, 0.3], rtol=1e-6)
    assert emulator.command(2).torque_enable == 1 and emulator.stats.rejected["garbage"] >= 1


# -- property tests -------------------------------------------------------------------------------------------------
# Valid replies whose bytes after the header hold no 0xFF (the checksum may): a false header can then only come
# from the garbage, which makes "the packet is found again after garbage" an exact statement.
no_ff = st.integers(0, 0xFE)
replies = st.builds(
    lambda device_id, error, data: StatusPacket(device_id, error, bytes(data)),
    st.integers(0, 0xFD), st.integers(0x80, 0xFE), st.lists(no_ff, max_size=24).map(lambda d: d[:len(d) // 4 * 4]))


def _feed(parser: StatusParser, data: bytes, chunk: int) -> list[StatusPacket]:
    found = []
    for k in range(0, len(data), chunk):
        found += parser.feed(data[k:k + chunk])
    return found


@PROPERTY
@given(data=st.binary(max_size=600), chunk=st.integers(1, 64), gate=st.booleans())
def test_parser_never_fails_on_random_bytes(data, chunk, gate):
    parser = StatusParser()
    if gate:
        parser.expect(14, range(1, 11))
    found = _feed(parser, data, chunk)
    assert parser.pending <= MAX_FRAME
    assert parser.stats.packets == len(found)
    for packet in found:  # only checksum-valid packets that really are in the stream
        assert encode_status(packet.id, packet.error, packet.data) in data
    if data and 0xFF not in data:
        assert parser.stats.rejected["garbage"] >= 1 and not found


@PROPERTY
@given(garbage=st.binary(max_size=300), packet=replies, chunk=st.integers(1, 64))
def test_parser_resynchronises_after_garbage(garbage, packet, chunk):
    wire = encode_status(packet.id, packet.error, packet.data)
    parser = StatusParser()
    parser.expect(len(packet.data) + 2)
    found = _feed(parser, garbage + wire + wire, chunk)
    assert found and found[-1] == packet  # a false frame in the garbage can cost the first copy, never the second
    assert parser.pending == 0
    clean = bytes(b for b in garbage if b != 0xFF)
    parser = StatusParser()
    parser.expect(len(packet.data) + 2)
    assert _feed(parser, clean + wire + wire, chunk) == [packet, packet]
    assert (parser.stats.rejected["garbage"] >= 1) == bool(clean) and parser.stats.rejected_total == \
        parser.stats.rejected["garbage"]


@PROPERTY
@given(packet=replies, where=st.integers(0, 10**6), new=st.integers(0, 0xFF), chunk=st.integers(1, 64))
def test_parser_rejects_every_single_byte_corruption(packet, where, new, chunk):
    wire = encode_status(packet.id, packet.error, packet.data)
    where %= len(wire)
    if new == wire[where]:
        new ^= 0x01
    corrupted = wire[:where] + bytes([new]) + wire[where + 1:]
    parser = StatusParser()
    parser.expect(len(packet.data) + 2)
    assert _feed(parser, corrupted + wire, chunk) == [packet]
    assert parser.stats.rejected_total >= 1 and parser.pending == 0


@PROPERTY
@given(packet=replies, cut=st.integers(1, 10**6), chunk=st.integers(1, 64))
def test_parser_recovers_from_a_truncated_packet(packet, cut, chunk):
    wire = encode_status(packet.id, packet.error, packet.data)
    parser = StatusParser()
    parser.expect(len(packet.data) + 2)
    found = _feed(parser, wire[:cut % len(wire)] + wire + wire, chunk)
    assert found[-1] == packet and len(found) <= 2


@PROPERTY
@given(data=st.binary(max_size=400))
def test_emulator_never_fails_on_random_bytes(data):
    emu = BearBusEmulator([1, 2, 3])
    reply = emu.handle(data)
    parser = StatusParser()
    parser.feed(reply)  # whatever random bytes made the devices say, it is well-formed replies
    assert parser.pending == 0 and parser.stats.rejected_total == 0
    assert len(emu._rx) <= MAX_FRAME


@PROPERTY
@given(device_id=st.sampled_from([1, 2, 0xFE, 9]), code=st.sampled_from([1, 2, 3, 4, 5, 6, 8, 0x12, 0x7F, 0x80]),
       params=st.binary(max_size=80))
def test_emulator_answers_any_framed_instruction_with_well_formed_replies(device_id, code, params):
    emu = BearBusEmulator([1, 2])
    reply = emu.handle(encode_frame(device_id, code, params))
    parser = StatusParser()
    found = parser.feed(reply)
    assert parser.pending == 0 and parser.stats.rejected_total == 0  # every byte out is part of a valid reply
    assert all(p.id in (1, 2) for p in found)
    if device_id == 0xFE and code != 0x12:
        assert found == []


def test_low_latency_mode_is_asked_for_and_reported(bus, emulator):
    """A pseudo-terminal has no ASYNC_LOW_LATENCY flag: the driver says so, naming the port, and runs on."""
    assert bus.low_latency.startswith("low-latency mode: not available on " + emulator.path), bus.low_latency
    assert bus.ping(1).id == 1


def test_a_lost_last_reply_costs_the_reply_gap_not_the_timeout(emulator, bus):
    """Replies come back to back: when the last ID is silent, the cycle ends a reply gap after the others arrived,
    long before the 200 ms reply timeout (which covers the bus delay before the first reply)."""
    emulator.silence([IDS[-1]])
    t0 = time.perf_counter()
    reply = bus.bulk_cycle(IDS, None, partial=True)
    elapsed = time.perf_counter() - t0
    assert reply.lost_ids == (IDS[-1],)
    assert elapsed < 0.1, elapsed  # typically ~2 ms; the timeout alone would be 200 ms
    emulator.silence(IDS)  # nothing answers: the whole timeout is waited
    t0 = time.perf_counter()
    reply = bus.bulk_cycle(IDS, None, partial=True)
    assert reply.lost_ids == tuple(IDS) and time.perf_counter() - t0 >= 0.2


def test_the_first_reply_that_carries_the_estop_bit_is_logged_when_it_leaves():
    """The moment the host could first know of an E-stop: the reply that carries bit 3 leaving the emulator (after
    any reply delay), logged once per press."""
    with BearBusEmulator([1, 2]) as emu, BearBus(emu.path, reply_timeout_s=0.05) as bus:
        emu.set_reply_delay(0.010)
        emu.drain_events()
        emu.set_estop(True)
        pressed = time.monotonic()
        bus.bulk_cycle([1, 2], None)
        received = time.monotonic()
        bus.bulk_cycle([1, 2], None)
        sent = [stamp for stamp, text in emu.drain_events() if text == "bear first reply with the E-stop bit sent"]
        assert len(sent) == 1 and pressed + 0.010 <= sent[0] <= received
        emu.set_estop(False)
        bus.bulk_cycle([1, 2], None)
        assert not [text for _, text in emu.drain_events() if "E-stop bit" in text]
        emu.set_estop(True)
        bus.bulk_cycle([1, 2], None)
        assert [text for _, text in emu.drain_events() if "E-stop bit" in text] == [
            "bear first reply with the E-stop bit sent"]


class _WireClock:
    """The BEAR emulator's wire handler driven by hand on a virtual clock: requests go in as bytes (`_on_bytes`), the
    replies it writes are kept, and nothing waits on the wall clock."""

    def __init__(self, monkeypatch, ids=(1, 2)):
        self.now = 100.0
        monkeypatch.setattr(bear_emulator, "time", types.SimpleNamespace(monotonic=lambda: self.now))
        self.emu = BearBusEmulator(list(ids))
        self.sent: list[tuple[float, bytes]] = []
        self.emu._pty = types.SimpleNamespace(send=lambda data: self.sent.append((self.now, data)))
        self.request = encode_bulk(list(ids), [status_register("present_position")])

    def exchange(self, after_s: float = 0.0) -> bytes:
        self.now += after_s
        self.emu._on_bytes(self.request)
        return self.sent[-1][1]


def test_a_reply_built_before_the_press_and_sent_after_it_is_not_the_one_that_carries_the_bit(monkeypatch):
    """With a reply delay, the press can fall between a request's arrival and its reply leaving: that reply was built
    without bit 3 (the host reads none in it), so the first one that carries the bit is the next request's."""
    wire = _WireClock(monkeypatch)
    emu, delay = wire.emu, wire.emu.reply_delay

    def pressed_in_the_delay(since: float) -> float:
        emu.set_estop(True)  # the E-stop input goes on while the reply waits out its 2 ms
        wire.now = since + 0.002
        return wire.now

    delay.wait = pressed_in_the_delay
    before = wire.exchange()
    assert not any(p.error & 0x08 for p in StatusParser().feed(before))  # built before the press: no bit
    assert not [text for _, text in emu.drain_events() if "E-stop bit" in text]
    delay.wait = lambda since: since
    after = wire.exchange(0.001)
    assert all(p.error & 0x08 for p in StatusParser().feed(after))
    assert emu.drain_events() == [(wire.now, "bear first reply with the E-stop bit sent")]


def test_the_emulator_logs_a_request_that_came_late_and_a_reply_that_left_late(monkeypatch):
    """What the emulated BEARs saw of an exchange gone wrong (bench_hw_emulated prints them before a trip): a request
    more than 4 ms after they last answered (not one 3 ms after, nor a host away for more than a second), a reply
    more than 1 ms after it was due (not 0.5 ms), stamped when it left; the request after a late reply is not late."""
    wire = _WireClock(monkeypatch)
    emu = wire.emu
    wire.exchange()
    wire.exchange(0.003)
    wire.exchange(0.020)
    asked = wire.now
    wire.exchange(1.1)

    def held(since: float, hold: float) -> float:
        wire.now += hold  # the BEARs' thread held this long after the reply was due
        return since

    emu.reply_delay.wait = lambda since: held(since, 0.0005)
    wire.exchange(0.001)
    emu.reply_delay.wait = lambda since: held(since, 0.005)
    wire.exchange(0.001)
    left = wire.sent[-1][0]
    emu.reply_delay.wait = lambda since: since
    wire.exchange(0.001)
    assert emu.drain_events() == [(asked, "bear request 20.0 ms after the last answer"),
                                  (left, "bear reply 5.0 ms after it was due")]
