"""Dynamixel arms: the Protocol 2.0 codec, the X-series bus emulator through ROBOTIS' own dynamixel-sdk over a pty,
and the `DynamixelArms` driver against the emulator (silence, hardware errors, corrupted replies)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from drivers.dynamixel import (
    ARM_IDS,
    ARM_SIGNS,
    ERR_ACCESS,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
    ERR_INSTRUCTION,
    ERR_RESULT_FAIL,
    POSITION_UNIT,
    VELOCITY_UNIT,
    DynamixelArms,
    Packet,
    PacketParser,
    collect_status,
    counts_to_joint,
    crc16,
    decode_hardware_error,
    decode_status_error,
    encode_packet,
    encode_status,
    indirect_read_map,
    joint_to_counts,
    stuff,
    unstuff,
)
from drivers.emulators.dynamixel import XM430_W350, DynamixelBusEmulator
from drivers.errors import BusTimeout, DeviceFault, LinkStats

sdk = pytest.importorskip("dynamixel_sdk")
serial = pytest.importorskip("serial")

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
PING_11 = bytes.fromhex("ff ff fd 00 0b 03 00 01")  # completed with its CRC below
HOLD = [0.0, 0.0, 1.5708, 0.0, 0.0, 1.5708]


@pytest.fixture
def emu():
    with DynamixelBusEmulator() as bus:
        yield bus


@pytest.fixture
def port(emu):
    """The SDK's own PortHandler and PacketHandler(2.0) on the emulator's pty (default SDK timeouts)."""
    handler = sdk.PortHandler(emu.path)
    assert handler.openPort() and handler.setBaudRate(2_000_000)
    yield handler, sdk.PacketHandler(2.0)
    handler.closePort()


@pytest.fixture
def arms(emu):
    with DynamixelArms.open(emu.path, 2_000_000, ARM_IDS, latency_ms=10.0, hold_pose=HOLD,
                            lower=[-3.1416, -1.5708, -2.3, -3.1416, -1.9, -2.3],
                            upper=[3.1416, 1.9, 2.3, 3.1416, 1.5708, 2.3]) as driver:
        yield driver


class CapturePort:
    """Just enough of a PortHandler for the SDK's txPacket: captures what it would write."""

    is_using = False
    written = b""

    def clearPort(self):  # noqa: N802 (SDK name)
        pass

    def writePort(self, packet):  # noqa: N802 (SDK name)
        self.written = bytes(packet)
        return len(packet)


class ScriptedPort:
    """Just enough of a PortHandler for the SDK's rxPacket: serves fixed bytes, then times out."""

    def __init__(self, data: bytes):
        self.data = bytearray(data)
        self.is_using = True
        self.timed_out = False

    def readPort(self, length):  # noqa: N802 (SDK name)
        chunk = bytes(self.data[:max(0, length)])
        del self.data[:len(chunk)]
        return chunk

    def isPacketTimeout(self):  # noqa: N802 (SDK name)
        self.timed_out = self.timed_out or not self.data
        return self.timed_out


def raw_port(path: str):
    return serial.Serial(path, 2_000_000, timeout=0.5)


def read_packets(ser, n_bytes_hint: int = 64, wait: float = 0.3) -> list[Packet]:
    """Packets a raw serial port receives within `wait` seconds."""
    parser, found, deadline = PacketParser(), [], time.monotonic() + wait
    while time.monotonic() < deadline:
        found += parser.feed(ser.read(ser.in_waiting or 1))
        if found and not parser.pending:
            break
    return found


# -- codec ------------------------------------------------------------------------------------------------------
def test_crc_and_packet_match_the_manual_example():
    # ROBOTIS e-Manual, Protocol 2.0 PING example for ID 1: FF FF FD 00 01 03 00 01 19 4E.
    assert encode_packet(1, 0x01) == bytes.fromhex("ff ff fd 00 01 03 00 01 19 4e")
    assert crc16(bytes.fromhex("ff ff fd 00 01 03 00 01")) == 0x4E19


@FAST
@given(st.binary(max_size=300))
def test_crc_matches_the_sdk(data):
    assert crc16(data) == sdk.Protocol2PacketHandler().updateCRC(0, list(data), len(data))


@FAST
@given(st.integers(0, 0xFC), st.sampled_from([0x02, 0x03, 0x83, 0x92]),
       st.lists(st.sampled_from([0x00, 0xFF, 0xFD, 0x55, 0x12]), max_size=40))
def test_encoding_matches_the_sdk(dxl_id, instruction, params):
    """Stuffing, LEN and CRC as the SDK's addStuffing + updateCRC define them (params built from FF/FD to force
    stuffing), and byte-identical to what its txPacket writes when no stuffing is needed. (dynamixel-sdk 4.1.0's
    txPacket drops addStuffing's result, so it sends FF FF FD runs unstuffed.)"""
    ph = sdk.Protocol2PacketHandler()
    length = len(params) + 3
    stuffed = ph.addStuffing([0xFF, 0xFF, 0xFD, 0x00, dxl_id, length & 0xFF, length >> 8, instruction, *params, 0, 0])
    crc = ph.updateCRC(0, stuffed, len(stuffed) - 2)
    expected = bytes(stuffed[:-2]) + crc.to_bytes(2, "little")
    assert encode_packet(dxl_id, instruction, bytes(params)) == expected
    if b"\xff\xff\xfd" not in bytes(params):
        capture, tx = CapturePort(), [0, 0, 0, 0, dxl_id, length & 0xFF, length >> 8, instruction, *params, 0, 0]
        assert ph.txPacket(capture, tx) == sdk.COMM_SUCCESS
        assert capture.written == expected


@FAST
@given(st.lists(st.sampled_from([0x00, 0xFF, 0xFD, 0x01]), max_size=60).map(bytes))
def test_stuffing_round_trips_and_hides_the_header(body):
    stuffed = stuff(body)
    assert unstuff(stuffed) == body
    for i in range(len(stuffed) - 2):
        if stuffed[i:i + 3] == b"\xff\xff\xfd":
            assert stuffed[i + 3:i + 4] == b"\xfd"


def test_error_decoding_names_flags():
    assert decode_status_error(0) == []
    assert decode_status_error(0x87) == ["access error", "alert"]
    assert decode_hardware_error(0b100101) == ["input_voltage", "overheating", "overload"]
    assert decode_hardware_error(0x40) == ["bit 6"]


def test_joint_convention():
    signs = np.array(ARM_SIGNS)
    counts = joint_to_counts(np.zeros(6), signs)
    assert np.all(counts == 2048)  # 2048 counts = joint 0
    q = np.array([0.5, -0.5, 1.0, 0.5, -0.5, 1.0])
    counts = joint_to_counts(q, signs)
    assert counts[2] < 2048 < counts[0]  # elbows flipped
    assert np.allclose(counts_to_joint(counts, signs), q, atol=POSITION_UNIT)
    assert joint_to_counts(np.array([math.pi + 1.0] * 6), np.ones(6)).max() == 4095  # position-mode range


# -- the codec's parser, property-tested ---------------------------------------------------------------------------
packets_st = st.builds(encode_packet, st.integers(0, 0xFC), st.integers(0, 0xFF),
                       st.lists(st.sampled_from([0, 1, 0xFD, 0xFF, 0x55]), max_size=20).map(bytes))


@FAST
@given(st.binary(max_size=400), packets_st, st.integers(1, 50))
def test_parser_survives_garbage_and_resynchronises(garbage, packet, chunk):
    parser = PacketParser()
    stream = garbage + packet + packet
    found = []
    for i in range(0, len(stream), chunk):
        found += parser.feed(stream[i:i + chunk])
    expected = PacketParser().feed(packet)[0]
    assert found[-2:] == [expected, expected]  # garbage cost nothing after it
    assert parser.pending == 0
    if garbage and not found[:-2]:
        assert parser.stats.rejected_total >= 1


@FAST
@given(packets_st, packets_st, st.data())
def test_parser_rejects_corrupted_and_truncated_packets(first, second, data):
    """A packet with one byte changed, or cut short, is never delivered; the packet after it still is."""
    if data.draw(st.booleans()):
        i = data.draw(st.integers(0, len(first) - 1))
        bad = first[:i] + bytes([first[i] ^ data.draw(st.integers(1, 255))]) + first[i + 1:]
    else:
        bad = first[:data.draw(st.integers(0, len(first) - 1))]
    parser = PacketParser()
    found = parser.feed(bad + second)
    good = PacketParser().feed(second)[0]
    assert found and found[-1] == good
    assert PacketParser().feed(first)[0] not in found[:-1]
    if bad:
        assert parser.stats.rejected_total >= 1


@FAST
@given(st.binary(max_size=300), st.lists(st.sampled_from(ARM_IDS), min_size=1, max_size=6, unique=True),
       st.binary(max_size=60), st.integers(0, 5))
@example(garbage=b"", ids=[11, 16, 12], between=b"\xb1", broken=1)  # the cut reply + 12's bytes pass the CRC
def test_driver_collector_on_random_bytes(garbage, ids, between, broken):
    """The driver's reply collector on random bytes before and between the replies, with one reply cut short:
    no exception, no hang, every intact reply found, the bad bytes counted."""
    blocks = {i: bytes([i, 0xFF, 0xFF, 0xFD, 0, 1, 2, i]) for i in ids}     # data that needs stuffing
    replies = [encode_status(i, 0, blocks[i]) for i in ids]
    cut = broken % len(ids)
    replies[cut] = replies[cut][:len(replies[cut]) // 2]
    stream = garbage + between.join(replies)
    stats = LinkStats()
    started = time.monotonic()
    data, errors = collect_status(ScriptedPort(stream), ids, 8, stats)
    assert time.monotonic() - started < 2.0
    assert data == {i: blocks[i] for k, i in enumerate(ids) if k != cut}
    assert stats.rejected_total >= 1


# -- the emulator through the real SDK -----------------------------------------------------------------------------
def test_sdk_ping_and_broadcast_ping(emu, port):
    handler, ph = port
    for dxl_id in ARM_IDS:
        model, result, error = ph.ping(handler, dxl_id)
        assert (model, result, error) == (XM430_W350, sdk.COMM_SUCCESS, 0)
    model, result, _ = ph.ping(handler, 42)
    assert result == sdk.COMM_RX_TIMEOUT
    found, result = ph.broadcastPing(handler)
    assert result == sdk.COMM_SUCCESS
    assert found == {i: [XM430_W350, 52] for i in ARM_IDS}


def test_sdk_read_write_round_trips(emu, port):
    handler, ph = port
    assert ph.write1ByteTxRx(handler, 12, 65, 1) == (sdk.COMM_SUCCESS, 0)                  # LED
    assert ph.write2ByteTxRx(handler, 12, 84, 640) == (sdk.COMM_SUCCESS, 0)                # position P gain
    assert ph.write4ByteTxRx(handler, 12, 104, (-300) & 0xFFFFFFFF) == (sdk.COMM_SUCCESS, 0)  # goal velocity
    assert ph.read1ByteTxRx(handler, 12, 65) == (1, sdk.COMM_SUCCESS, 0)
    assert ph.read2ByteTxRx(handler, 12, 84) == (640, sdk.COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(handler, 12, 104)[0] == (-300) & 0xFFFFFFFF
    assert emu.item(12, "goal_velocity") == -300 and emu.item(11, "position_p_gain") == 800
    data, result, error = ph.readTxRx(handler, 12, 0, 7)   # model number, model information, firmware
    assert result == sdk.COMM_SUCCESS and data[:2] == [XM430_W350 & 0xFF, XM430_W350 >> 8] and data[6] == 52


def test_sdk_access_rules(emu, port):
    handler, ph = port
    assert ph.write1ByteTxRx(handler, 11, 64, 1) == (sdk.COMM_SUCCESS, 0)                   # torque on
    assert ph.write1ByteTxRx(handler, 11, 11, 1) == (sdk.COMM_SUCCESS, ERR_ACCESS)          # EEPROM refused
    assert emu.item(11, "operating_mode") == 3
    assert ph.write1ByteTxRx(handler, 11, 64, 0) == (sdk.COMM_SUCCESS, 0)
    assert ph.write1ByteTxRx(handler, 11, 11, 1) == (sdk.COMM_SUCCESS, 0)                   # torque off: allowed
    assert emu.item(11, "operating_mode") == 1
    assert ph.write1ByteTxRx(handler, 11, 11, 2)[1] == ERR_DATA_RANGE                       # no mode 2
    assert ph.write4ByteTxRx(handler, 11, 132, 5)[1] == ERR_ACCESS                         # read-only
    assert ph.write1ByteTxRx(handler, 11, 14, 5)[1] == ERR_ACCESS                          # reserved gap
    assert ph.write1ByteTxRx(handler, 11, 11, 3)[1] == 0
    assert ph.write4ByteTxRx(handler, 11, 116, 5000)[1] == ERR_DATA_LIMIT                  # beyond max limit
    assert ph.readTxRx(handler, 11, 660, 8)[2] == ERR_ACCESS                               # beyond the table


def test_sdk_sync_read_and_sync_write(emu, port):
    handler, ph = port
    for dxl_id in ARM_IDS:
        ph.write1ByteTxRx(handler, dxl_id, 64, 1)
    writer = sdk.GroupSyncWrite(handler, ph, 116, 4)
    for k, dxl_id in enumerate(ARM_IDS):
        assert writer.addParam(dxl_id, list((1000 + 100 * k).to_bytes(4, "little")))
    assert writer.txPacket() == sdk.COMM_SUCCESS
    reader = sdk.GroupSyncRead(handler, ph, 116, 4)
    for dxl_id in ARM_IDS:
        reader.addParam(dxl_id)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    assert [reader.getData(i, 116, 4) for i in ARM_IDS] == [1000 + 100 * k for k in range(6)]
    # Ideal servos (no physics attached): present position follows the goal.
    reader = sdk.GroupSyncRead(handler, ph, 132, 4)
    for dxl_id in ARM_IDS:
        reader.addParam(dxl_id)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    assert [reader.getData(i, 132, 4) for i in ARM_IDS] == [1000 + 100 * k for k in range(6)]


def test_sdk_bulk_read_and_bulk_write(emu, port):
    handler, ph = port
    writer = sdk.GroupBulkWrite(handler, ph)
    assert writer.addParam(11, 65, 1, [1])
    assert writer.addParam(14, 84, 2, [0x20, 0x03])
    assert writer.txPacket() == sdk.COMM_SUCCESS
    reader = sdk.GroupBulkRead(handler, ph)
    assert reader.addParam(11, 65, 1) and reader.addParam(14, 84, 2) and reader.addParam(16, 0, 2)
    assert reader.txRxPacket() == sdk.COMM_SUCCESS
    assert reader.getData(11, 65, 1) == 1 and reader.getData(14, 84, 2) == 800 and reader.getData(16, 0, 2) == 1020


def test_sdk_reg_write_action_reboot_factory_reset(emu, port):
    handler, ph = port
    assert ph.regWriteTxRx(handler, 13, 65, 1, [1]) == (sdk.COMM_SUCCESS, 0)
    assert emu.item(13, "led") == 0 and emu.item(13, "registered_instruction") == 1
    assert ph.action(handler, 13) == sdk.COMM_SUCCESS
    time.sleep(0.05)
    assert emu.item(13, "led") == 1 and emu.item(13, "registered_instruction") == 0
    ph.write1ByteTxRx(handler, 13, 64, 1)
    emu.set_hardware_error(13, ["overheating"])
    assert not emu.torque_enabled(13)
    assert ph.write1ByteTxRx(handler, 13, 64, 1) == (sdk.COMM_SUCCESS, ERR_RESULT_FAIL | 0x80)
    assert ph.read1ByteTxRx(handler, 13, 70) == (0b100, sdk.COMM_SUCCESS, 0x80)
    assert ph.reboot(handler, 13) == (sdk.COMM_SUCCESS, 0x80)       # answered before it reboots
    assert ph.read1ByteTxRx(handler, 13, 70) == (0, sdk.COMM_SUCCESS, 0)
    assert emu.item(13, "led") == 0                                   # RAM back to initial values
    assert ph.write1ByteTxRx(handler, 13, 11, 1)[1] == 0
    assert ph.factoryReset(handler, 13, 0x02) == (sdk.COMM_SUCCESS, 0)
    assert emu.item(13, "operating_mode") == 3 and emu.item(13, "id") == 13
    assert ph.factoryReset(handler, 13, 0xFF) == (sdk.COMM_SUCCESS, 0)
    assert ph.ping(handler, 1)[0] == XM430_W350                       # ID back to 1
    assert ph.ping(handler, 13)[1] == sdk.COMM_RX_TIMEOUT


def test_sdk_stuffing_both_directions(emu, port):
    handler, ph = port
    # Indirect Data 20..22 map to themselves by default: any byte values may be written there.
    assert ph.writeTxRx(handler, 15, 243, 3, [0xFF, 0xFF, 0xFD]) == (sdk.COMM_SUCCESS, 0)
    assert [emu.item(15, f"indirect_data_{n}") for n in (20, 21, 22)] == [0xFF, 0xFF, 0xFD]
    assert ph.readTxRx(handler, 15, 243, 3) == ([0xFF, 0xFF, 0xFD], sdk.COMM_SUCCESS, 0)
    with raw_port(emu.path) as ser:
        ser.write(encode_packet(15, 0x02, bytes([243, 0, 3, 0])))
        reply = b""
        deadline = time.monotonic() + 1.0
        while len(reply) < 15 and time.monotonic() < deadline:
            reply += ser.read(ser.in_waiting or 1)
    # FF FF FD 00 | 0F | LEN 08 00 | 55 | 00 | FF FF FD FD | CRC: LEN counts the stuffing byte.
    assert reply[:9] == bytes.fromhex("ff ff fd 00 0f 08 00 55 00") and reply[9:13] == bytes.fromhex("ff ff fd fd")
    assert crc16(reply[:13]) == int.from_bytes(reply[13:15], "little")


def test_crc_errors_and_unknown_instructions_are_answered(emu):
    with raw_port(emu.path) as ser:
        ping = encode_packet(11, 0x01)
        ser.write(ping[:-1] + bytes([ping[-1] ^ 0x01]))
        replies = read_packets(ser)
        assert [(p.id, p.error) for p in replies] == [(11, ERR_CRC)]
        ser.write(encode_packet(12, 0x77))
        assert [(p.id, p.error) for p in read_packets(ser)] == [(12, ERR_INSTRUCTION)]
        ser.write(encode_packet(12, 0x02, b"\x00"))
        assert [(p.id, p.error) for p in read_packets(ser)] == [(12, ERR_DATA_LENGTH)]
        ser.write(encode_packet(11, 0x01)[:6])          # cut short: dropped after the inter-byte gap
        time.sleep(0.05)
        ser.write(encode_packet(11, 0x01))
        assert [(p.id, p.data) for p in read_packets(ser)] == [(11, bytes([0xFC, 0x03, 52]))]
    assert emu.stats.rejected["crc"] == 1 and emu.stats.rejected["truncated"] == 1


def test_status_return_level(emu, port):
    handler, ph = port
    assert ph.write1ByteTxRx(handler, 16, 68, 0) == (sdk.COMM_SUCCESS, 0)   # answered at the old level
    assert ph.write1ByteTxRx(handler, 16, 65, 1)[0] == sdk.COMM_RX_TIMEOUT   # writes no longer answered ...
    assert ph.ping(handler, 16)[1] == sdk.COMM_SUCCESS                      # ... pings still are
    assert emu.item(16, "led") == 1


@FAST
@given(st.binary(max_size=300), st.data())
def test_emulator_survives_random_bytes_and_corruptions(garbage, data):
    bus = DynamixelBusEmulator()   # no pty: bytes in, bytes out
    bus.handle(garbage)
    write = encode_packet(11, 0x03, bytes([65, 0, 1]))     # LED on
    i = data.draw(st.integers(0, len(write) - 1))
    corrupted = write[:i] + bytes([write[i] ^ data.draw(st.integers(1, 255))]) + write[i + 1:]
    reply = bus.handle(corrupted)
    for packet in PacketParser().feed(reply):                # only CRC-error statuses may come back
        assert packet.is_status and packet.error == ERR_CRC
    reply = bus.handle(encode_packet(11, 0x01))              # a valid packet is still found and answered
    assert any(p.id == 11 and p.data == bytes([0xFC, 0x03, 52]) for p in PacketParser().feed(reply))
    assert bus.item(11, "led") == 0


# -- the driver against the emulator -------------------------------------------------------------------------------
def test_open_pings_and_sets_up(emu, arms):
    assert arms.models == {i: XM430_W350 for i in ARM_IDS}
    for dxl_id in ARM_IDS:
        assert emu.item(dxl_id, "operating_mode") == 3
        assert emu.item(dxl_id, "position_p_gain") == 800
        assert emu.item(dxl_id, "position_i_gain") == 0 and emu.item(dxl_id, "position_d_gain") == 0
        assert not emu.torque_enabled(dxl_id)
        mapped = [emu.item(dxl_id, f"indirect_address_{n}") for n in range(6, 14)]
        assert mapped == [int.from_bytes(indirect_read_map()[k:k + 2], "little") for k in range(0, 16, 2)]
        assert mapped == [132, 133, 134, 135, 128, 129, 130, 131]


def test_hold_read_and_write(emu, arms):
    arms.hold()
    q, qd = arms.read()    # a round trip: the emulator has handled the (unanswered) sync write before it
    assert emu.torque_enabled_all().all()
    assert np.allclose(emu.goal_joint_positions(), HOLD, atol=POSITION_UNIT)
    assert emu.goal_position(13) == emu.goal_position(16) == 2048 - 1024   # elbows flipped: +pi/2 -> 1024 counts
    assert np.allclose(q, HOLD, atol=POSITION_UNIT) and np.all(qd == 0)
    goal = np.array([0.3, -0.2, 1.0, -0.3, 0.2, 1.0])
    arms.write_positions(goal)
    arms.read()
    assert np.allclose(emu.goal_joint_positions(), goal, atol=POSITION_UNIT)
    assert emu.goal_position(13) == round(2048 - 1.0 / POSITION_UNIT)
    # A physics adapter's measured values come back in joint units, in ID order.
    emu.track_goals = False
    measured_q, measured_qd = np.array([0.1, 0.2, 0.3, -0.1, -0.2, -0.3]), np.array([1.0, -2.0, 3.0, 0.5, 0, -1])
    emu.set_joint_state(measured_q, measured_qd)
    q, qd = arms.cycle(goal)
    assert np.allclose(q, measured_q, atol=POSITION_UNIT) and np.allclose(qd, measured_qd, atol=VELOCITY_UNIT)
    emu.set_present(13, position=2048 + 100, velocity=-10)      # raw counts on the right elbow
    q, qd = arms.read()
    assert q[2] == pytest.approx(-100 * POSITION_UNIT) and qd[2] == pytest.approx(10 * VELOCITY_UNIT)
    assert arms.stats.packets > 0 and arms.stats.rejected_total == 0


def test_goals_are_clipped_and_checked(emu, arms):
    arms.hold()
    arms.write_positions([10.0, 10.0, -10.0, -10.0, -10.0, 10.0])
    arms.read()
    assert np.allclose(emu.goal_joint_positions(), [3.1416, 1.9, -2.3, -3.1416, -1.9, 2.3], atol=2 * POSITION_UNIT)
    with pytest.raises(ValueError, match="non-finite"):
        arms.write_positions([0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="6 values"):
        arms.write_positions([0, 0])


def test_from_config(emu, config):
    with DynamixelArms.from_config(config, port=emu.path, latency_ms=10.0) as driver:
        assert driver.names == config.arms.names and driver.ids == config.buses.dynamixel.ids
        driver.hold(ramp_s=0.06, rate_hz=50)
        driver.read()
        assert np.allclose(emu.goal_joint_positions(), config.arms.hold_pose, atol=POSITION_UNIT)
    assert not emu.torque_enabled_all().any()      # close() turned torque off


def test_default_sync_read_timeout_is_short():
    """With the default latency term the SDK's timeout for the 6-servo sync read is well under 10 ms."""
    from drivers.dynamixel import _bounded_port_class

    port = _bounded_port_class()("/dev/null", 2.0)
    port.tx_time_per_byte = 1000.0 / 2_000_000 * 10.0
    port.setPacketTimeout((11 + 8) * 6)
    assert 4.0 < port.packet_timeout < 8.0   # ms


def test_silent_servos_are_named_within_bounded_time(emu):
    with DynamixelArms.open(emu.path, latency_ms=10.0) as driver:
        driver.read()
        emu.silence([12, 15])
        started = time.monotonic()
        with pytest.raises(BusTimeout) as caught:
            driver.read()
        assert time.monotonic() - started < 0.25
        assert caught.value.silent_ids == (12, 15)
        assert emu.path in str(caught.value) and "12, 15" in str(caught.value) and "dynamixel" in str(caught.value)
        assert driver.stats.timeouts == 1
        emu.silence([12, 15], silent=False)
        driver.read()


def test_open_names_missing_servos(emu):
    emu.silence([14])
    with pytest.raises(BusTimeout) as caught:
        DynamixelArms.open(emu.path, latency_ms=5.0)
    assert caught.value.silent_ids == (14,)


def test_hardware_error_raises_device_fault_with_named_flags(emu, arms):
    arms.hold()
    emu.set_hardware_error(13, ["overheating", "overload"])
    with pytest.raises(DeviceFault) as caught:
        arms.read()
    assert caught.value.device_id == 13 and set(caught.value.flags) == {"overheating", "overload"}
    assert arms.faults[13] == caught.value.flags
    assert not emu.torque_enabled(13)               # shut down by its Shutdown bits
    arms.close()
    assert not emu.torque_enabled_all().any()       # the others were still turned off


@pytest.mark.parametrize("mode, reason", [("crc", "crc"), ("truncate", "truncated"), ("foreign", "foreign")])
def test_corrupted_replies_are_rejected_and_counted(emu, arms, mode, reason):
    arms.read()
    emu.corrupt_replies([12], mode, count=1)
    with pytest.raises(BusTimeout) as caught:
        arms.read()
    assert caught.value.silent_ids == (12,)
    assert arms.stats.rejected[reason] >= 1
    q, _ = arms.read()                              # the next cycle is clean again
    assert q.shape == (6,)


def test_noise_before_replies_is_skipped(emu, arms):
    emu.corrupt_replies(None, "noise", count=2)
    q, qd = arms.read()
    assert np.allclose(q, 0.0, atol=POSITION_UNIT)
