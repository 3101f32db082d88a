"""Dynamixel arms: the Protocol 2.0 codec, the X-series bus emulator through ROBOTIS' own dynamixel-sdk over a pty,
and the `DynamixelArms` driver against the emulator (silence, hardware errors, corrupted replies).

The emulator runs in lockstep with the tests: its clock (Bus Watchdog, inter-byte gap, event stamps) is a `DeviceClock`
that moves only when a test advances it, and the hosts wait for an owed reply however long a busy machine keeps the
emulator's thread off the CPU; a request that must go unanswered is checked with a marker round trip, not a wait. So
these tests pass beside other load. The wall-clock behaviour itself (the SDK's fixed broadcast window, the driver's
bounded wait, the watchdog on time.monotonic) is checked by the `realtime` tests (skipped by default)."""

from __future__ import annotations

import functools
import math
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from bruce_hw.config import load_config
from drivers.dynamixel import DynamixelArms, collect_status
from drivers.dynamixel_codec import (
    ERR_ACCESS,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
    ERR_INSTRUCTION,
    ERR_RESULT_FAIL,
    INST_PING,
    INST_STATUS,
    Packet,
    PacketParser,
    crc16,
    decode_hardware_error,
    decode_status_error,
    encode_packet,
    encode_status,
    stuff,
    unstuff,
)
from drivers.dynamixel_registers import (
    BUS_WATCHDOG_UNIT_S,
    POSITION_UNIT,
    VELOCITY_UNIT,
    counts_to_joint,
    indirect_read_map,
    joint_to_counts,
    watchdog_counts,
)
from drivers.emulators.dynamixel import MAX_EVENTS, XM430_W350, DynamixelBusEmulator
from drivers.errors import BusTimeout, DeviceFault, LinkStats

sdk = pytest.importorskip("dynamixel_sdk")
sdk_port = pytest.importorskip("dynamixel_sdk.port_handler")
serial = pytest.importorskip("serial")

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
PING_11 = bytes.fromhex("ff ff fd 00 0b 03 00 01")  # completed with its CRC below
HOLD = [0.0, 0.0, 1.5708, 0.0, 0.0, 1.5708]

# BRUCE's arm bus as the robot config describes it (IDs, baud, how each servo is mounted)
_CONFIG = load_config()
ARM_IDS = tuple(_CONFIG.buses.dynamixel.ids)
ARM_SIGNS = tuple(float(v) for v in _CONFIG.arms.servo_signs)
BAUD = _CONFIG.buses.dynamixel.baud


# -- waiting on a busy machine -----------------------------------------------------------------------------------
# The emulator answers from a thread of this process, which busy processes can keep off the CPU for more than a
# second (measured beside three busy loops on two cores: SDK round trips up to 1.3 s, 12 % of them over the SDK's
# default 34 ms). Where a reply is owed, the hosts here wait up to REPLY_WAIT_S: a passing test never waits it out.
REPLY_WAIT_S = 10.0
# The SDK's packet timeout is wire time + 2 x LATENCY_TIMER + 2 ms: LATENCY_TIMER (port_handler, 16 ms) is the SDK's
# setting of the USB adapter's latency, which ROBOTIS has users edit to match theirs; here it covers the emulator's.
SDK_LATENCY_DEFAULT_MS = sdk_port.LATENCY_TIMER
SDK_LATENCY_PATIENT_MS = REPLY_WAIT_S * 1000 / 2
# The driver's packet timeout is 2 x latency_ms + 2 ms (+ wire time). Where a servo is silent on purpose the whole
# timeout is waited, so those tests use a shorter one that the other servos' replies still fit in.
DRIVER_LATENCY_MS = REPLY_WAIT_S * 1000 / 2
DRIVER_SILENCE_LATENCY_MS = 1000.0


class DeviceClock:
    """The emulator's time, in lockstep with the test: it moves only when the test advances it, so the servos see
    exactly the silences the test makes, however long the machine makes this process wait. Whole microseconds, so
    that steps add up exactly."""

    def __init__(self):
        self.us = 0

    def __call__(self) -> float:
        return self.us / 1e6

    def advance(self, seconds: float) -> None:
        self.us += round(seconds * 1e6)


@pytest.fixture
def clock():
    return DeviceClock()


@pytest.fixture
def emu(clock):
    with DynamixelBusEmulator(ARM_IDS, signs=ARM_SIGNS, clock=clock) as bus:
        yield bus


@pytest.fixture
def wall_emu():
    """The emulator on its default clock (time.monotonic), as bruce-emulate runs it: for the `realtime` tests."""
    with DynamixelBusEmulator(ARM_IDS, signs=ARM_SIGNS) as bus:
        yield bus


def open_sdk_port(path: str):
    handler = sdk.PortHandler(path)
    assert handler.openPort() and handler.setBaudRate(2_000_000)
    return handler, sdk.PacketHandler(2.0)


@pytest.fixture
def patient_sdk(monkeypatch):
    monkeypatch.setattr(sdk_port, "LATENCY_TIMER", SDK_LATENCY_PATIENT_MS)


@pytest.fixture
def port(emu, patient_sdk):
    """The SDK's own PortHandler and PacketHandler(2.0) on the emulator's pty; its latency timer set to wait for a
    reply up to REPLY_WAIT_S."""
    handler, ph = open_sdk_port(emu.path)
    yield handler, ph
    handler.closePort()


@pytest.fixture
def patient_driver(monkeypatch):
    """The driver's sync read waits up to its packet timeout and, whatever that is, 100 ms of wall clock
    (`collect_status`'s guard_s, the real-time bound the `realtime` test checks); here the guard is REPLY_WAIT_S, so
    that `latency_ms` alone sets the wait."""
    monkeypatch.setattr("drivers.dynamixel.collect_status", functools.partial(collect_status, guard_s=REPLY_WAIT_S))


@pytest.fixture
def arms(emu, patient_driver):
    with DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_LATENCY_MS, hold_pose=HOLD,
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


def read_packets(ser, count: int = 1, parser: PacketParser | None = None) -> list[Packet]:
    """The packets a raw serial port receives until `count` have come and no packet is cut short (or REPLY_WAIT_S)."""
    parser, found, deadline = parser or PacketParser(), [], time.monotonic() + REPLY_WAIT_S
    while time.monotonic() < deadline:
        found += parser.feed(ser.read(ser.in_waiting or 1))
        if len(found) >= count and not parser.pending:
            break
        if not ser.timeout:
            time.sleep(0.0005)   # the SDK's port does not block: do not spin
    return found


def unanswered(handler, call, *args, marker_id: int = 11):
    """`call(handler, *args)` through the SDK for a request that no servo may answer, and what it returned. The SDK
    waits its default time only; then a PING to `marker_id` shows that no reply was merely late: the emulator answers
    in order, so a late reply (or what the SDK left of one) would come before the PING's."""
    saved = sdk_port.LATENCY_TIMER
    sdk_port.LATENCY_TIMER = SDK_LATENCY_DEFAULT_MS
    try:
        out = call(handler, *args)
    finally:
        sdk_port.LATENCY_TIMER = saved
    handler.ser.write(encode_packet(marker_id, INST_PING))
    parser = PacketParser()
    late = read_packets(handler.ser, parser=parser)
    assert [(p.id, p.instruction) for p in late] == [(marker_id, INST_STATUS)], late
    assert parser.stats.rejected_total == 0, parser.stats
    return out


def wait_for(condition, what: str) -> None:
    """Until `condition()` holds (the emulator's thread has got to it), REPLY_WAIT_S at most."""
    deadline = time.monotonic() + REPLY_WAIT_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.001)


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
def test_sdk_ping(emu, port):
    handler, ph = port
    for dxl_id in ARM_IDS:
        model, result, error = ph.ping(handler, dxl_id)
        assert (model, result, error) == (XM430_W350, sdk.COMM_SUCCESS, 0)
    model, result, _ = unanswered(handler, ph.ping, 42)
    assert result == sdk.COMM_RX_TIMEOUT


class ReplayPort(ScriptedPort):
    """Just enough of a PortHandler for the SDK's broadcastPing: takes its request, serves recorded replies."""

    def __init__(self, data: bytes):
        super().__init__(data)
        self.is_using = False
        self.written = b""

    def clearPort(self):  # noqa: N802 (SDK name)
        pass

    def writePort(self, packet):  # noqa: N802 (SDK name)
        self.written += bytes(packet)
        return len(packet)

    def getBaudRate(self):  # noqa: N802 (SDK name)
        return 2_000_000

    def setPacketTimeoutMillis(self, msec):  # noqa: N802 (SDK name)
        pass


def test_broadcast_ping_is_answered_by_every_servo_in_id_order(emu):
    """The SDK's broadcastPing listens for a fixed 0.79 s (the `realtime` test below): here its request goes over the
    pty, the replies are collected without a deadline, and then the SDK parses them."""
    request = encode_packet(0xFE, INST_PING)
    with raw_port(emu.path) as ser:
        ser.write(request)
        replies = read_packets(ser, count=len(ARM_IDS))
    assert [(p.id, p.error, p.data) for p in replies] == [(i, 0, bytes([0xFC, 0x03, 52])) for i in sorted(ARM_IDS)]
    replay = ReplayPort(b"".join(encode_status(p.id, p.error, p.data) for p in replies))
    found, result = sdk.PacketHandler(2.0).broadcastPing(replay)
    assert replay.written == request
    assert result == sdk.COMM_SUCCESS and found == {i: [XM430_W350, 52] for i in ARM_IDS}


@pytest.mark.realtime
def test_sdk_broadcast_ping_within_its_window(wall_emu, patient_sdk):
    handler, ph = open_sdk_port(wall_emu.path)
    try:
        found, result = ph.broadcastPing(handler)
    finally:
        handler.closePort()
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
    assert ph.write1ByteTxRx(handler, 11, 11, 3) == (sdk.COMM_SUCCESS, 0)   # a timeout's error byte is 0 too
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
    assert ph.action(handler, 13) == sdk.COMM_SUCCESS                # not answered ...
    assert ph.ping(handler, 12)[1] == sdk.COMM_SUCCESS               # ... but carried out before the next packet
    assert emu.item(13, "led") == 1 and emu.item(13, "registered_instruction") == 0
    ph.write1ByteTxRx(handler, 13, 64, 1)
    emu.set_hardware_error(13, ["overheating"])
    assert not emu.torque_enabled(13)
    assert ph.write1ByteTxRx(handler, 13, 64, 1) == (sdk.COMM_SUCCESS, ERR_RESULT_FAIL | 0x80)
    assert ph.read1ByteTxRx(handler, 13, 70) == (0b100, sdk.COMM_SUCCESS, 0x80)
    assert ph.reboot(handler, 13) == (sdk.COMM_SUCCESS, 0x80)       # answered before it reboots
    assert ph.read1ByteTxRx(handler, 13, 70) == (0, sdk.COMM_SUCCESS, 0)
    assert emu.item(13, "led") == 0                                   # RAM back to initial values
    assert ph.write1ByteTxRx(handler, 13, 11, 1) == (sdk.COMM_SUCCESS, 0)
    assert ph.factoryReset(handler, 13, 0x02) == (sdk.COMM_SUCCESS, 0)
    assert emu.item(13, "operating_mode") == 3 and emu.item(13, "id") == 13
    assert ph.factoryReset(handler, 13, 0xFF) == (sdk.COMM_SUCCESS, 0)
    assert ph.ping(handler, 1)[0] == XM430_W350                       # ID back to 1
    assert unanswered(handler, ph.ping, 13)[1] == sdk.COMM_RX_TIMEOUT


def test_sdk_stuffing_both_directions(emu, port):
    handler, ph = port
    # Indirect Data 20..22 map to themselves by default: any byte values may be written there.
    assert ph.writeTxRx(handler, 15, 243, 3, [0xFF, 0xFF, 0xFD]) == (sdk.COMM_SUCCESS, 0)
    assert [emu.item(15, f"indirect_data_{n}") for n in (20, 21, 22)] == [0xFF, 0xFF, 0xFD]
    assert ph.readTxRx(handler, 15, 243, 3) == ([0xFF, 0xFF, 0xFD], sdk.COMM_SUCCESS, 0)
    with raw_port(emu.path) as ser:
        ser.write(encode_packet(15, 0x02, bytes([243, 0, 3, 0])))
        reply = b""
        deadline = time.monotonic() + REPLY_WAIT_S
        while len(reply) < 15 and time.monotonic() < deadline:
            reply += ser.read(ser.in_waiting or 1)
    # FF FF FD 00 | 0F | LEN 08 00 | 55 | 00 | FF FF FD FD | CRC: LEN counts the stuffing byte.
    assert reply[:9] == bytes.fromhex("ff ff fd 00 0f 08 00 55 00") and reply[9:13] == bytes.fromhex("ff ff fd fd")
    assert crc16(reply[:13]) == int.from_bytes(reply[13:15], "little")


def test_crc_errors_and_unknown_instructions_are_answered(emu, clock):
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
        wait_for(lambda: emu._parser.pending == 6, "the emulator has the first 6 bytes")
        clock.advance(0.05)                              # 50 ms without a byte (frame_gap_s: 10 ms)
        ser.write(encode_packet(11, 0x01))
        assert [(p.id, p.data) for p in read_packets(ser)] == [(11, bytes([0xFC, 0x03, 52]))]
    assert emu.stats.rejected["crc"] == 1 and emu.stats.rejected["truncated"] == 1


def test_status_return_level(emu, port):
    handler, ph = port
    assert ph.write1ByteTxRx(handler, 16, 68, 0) == (sdk.COMM_SUCCESS, 0)   # answered at the old level
    assert unanswered(handler, ph.write1ByteTxRx, 16, 65, 1)[0] == sdk.COMM_RX_TIMEOUT   # writes no longer answered ...
    assert ph.ping(handler, 16)[1] == sdk.COMM_SUCCESS                      # ... pings still are
    assert emu.item(16, "led") == 1


@FAST
@given(st.binary(max_size=300), st.data())
def test_emulator_survives_random_bytes_and_corruptions(garbage, data):
    bus = DynamixelBusEmulator(ARM_IDS, signs=ARM_SIGNS)   # no pty: bytes in, bytes out
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


def test_from_config(emu, config, patient_driver):
    counts = watchdog_counts(config.buses.dynamixel.watchdog_s)
    with DynamixelArms.from_config(config, port=emu.path, latency_ms=DRIVER_LATENCY_MS) as driver:
        assert driver.names == config.arms.names and driver.ids == config.buses.dynamixel.ids
        assert driver.watchdog_counts == counts and driver.read_watchdog() == {i: counts for i in driver.ids}
        driver.hold(ramp_s=0.06, rate_hz=50)
        driver.read()
        assert np.allclose(emu.goal_joint_positions(), config.arms.hold_pose, atol=POSITION_UNIT)
    assert not emu.torque_enabled_all().any()      # close() turned torque off ...
    assert all(emu.item(i, "bus_watchdog") == 0 for i in config.buses.dynamixel.ids)   # ... and the watchdog off
    with DynamixelArms.from_config(config, port=emu.path, latency_ms=DRIVER_LATENCY_MS, watchdog_s=0.0) as driver:
        assert driver.watchdog_counts == 0          # an explicit option wins over the config


def test_default_sync_read_timeout_is_short():
    """With the default latency term the SDK's timeout for the 6-servo sync read is well under 10 ms."""
    from drivers.dynamixel import _bounded_port_class

    port = _bounded_port_class()("/dev/null", 2.0)
    port.tx_time_per_byte = 1000.0 / 2_000_000 * 10.0
    port.setPacketTimeout((11 + 8) * 6)
    assert 4.0 < port.packet_timeout < 8.0   # ms


@pytest.mark.slow  # waits out the SDK's packet timeouts (2 s)
def test_silent_servos_are_named_after_the_packet_timeout(emu, patient_driver):
    with DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_SILENCE_LATENCY_MS) as driver:
        driver.read()
        emu.silence([12, 15])
        started = time.monotonic()
        with pytest.raises(BusTimeout) as caught:
            driver.read()
        assert time.monotonic() - started >= 2 * DRIVER_SILENCE_LATENCY_MS / 1000   # it waited its timeout out
        assert caught.value.silent_ids == (12, 15)
        assert emu.path in str(caught.value) and "12, 15" in str(caught.value) and "dynamixel" in str(caught.value)
        assert driver.stats.timeouts == 1
        emu.silence([12, 15], silent=False)
        driver.read()


@pytest.mark.realtime
def test_silent_servos_are_named_within_bounded_time(wall_emu):
    with DynamixelArms.open(wall_emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=10.0) as driver:
        driver.read()
        wall_emu.silence([12, 15])
        started = time.monotonic()
        with pytest.raises(BusTimeout) as caught:
            driver.read()
        assert time.monotonic() - started < 0.25
        assert caught.value.silent_ids == (12, 15)
        assert driver.stats.timeouts == 1
        wall_emu.silence([12, 15], silent=False)
        driver.read()


@pytest.mark.slow  # waits out the SDK's packet timeouts (2 s)
def test_open_names_missing_servos(emu):
    emu.silence([14])
    with pytest.raises(BusTimeout) as caught:
        DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_SILENCE_LATENCY_MS, retries=0)
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


@pytest.mark.slow  # waits out the SDK's packet timeouts (2 s)
@pytest.mark.parametrize("mode, reason", [("crc", "crc"), ("truncate", "truncated"), ("foreign", "foreign")])
def test_corrupted_replies_are_rejected_and_counted(emu, patient_driver, mode, reason):
    # 12's reply never comes intact: the driver waits its whole timeout, a shorter one.
    with DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_SILENCE_LATENCY_MS) as arms:
        arms.read()
        emu.corrupt_replies([12], mode, count=1)
        with pytest.raises(BusTimeout) as caught:
            arms.read()
        assert caught.value.silent_ids == (12,)
        assert arms.stats.rejected[reason] >= 1
        q, _ = arms.read()                          # the next cycle is clean again
        assert q.shape == (6,)


def test_noise_before_replies_is_skipped(emu, arms):
    emu.corrupt_replies(None, "noise", count=2)
    q, qd = arms.read()
    assert np.allclose(q, 0.0, atol=POSITION_UNIT)


# -- Bus Watchdog (control table 98) -------------------------------------------------------------------------------
PLANT_STEP_S = 0.001          # a physics adapter touches the emulator every 1 ms (of device time, in lockstep)


def run_plant(emu, clock, until: str, limit_s: float = 2.0) -> list[tuple[float, str]]:
    """Advance device time a plant step at a time, touching the emulator after each step as a physics adapter does,
    until an event containing `until` (or `limit_s` of device time): the events drained."""
    events = []
    for _ in range(round(limit_s / PLANT_STEP_S)):
        clock.advance(PLANT_STEP_S)
        emu.torque_enabled_all()
        events += emu.drain_events()
        if any(until in text for _, text in events):
            break
    return events


def stamp_of(events, text: str) -> float:
    stamps = [t for t, e in events if e == text]
    assert len(stamps) == 1, (text, events)
    return stamps[0]


def expiry(events, dxl_id: int) -> tuple[float, str]:
    found = [(t, e) for t, e in events if e.startswith(f"dynamixel {dxl_id} bus watchdog: stopped after ")]
    assert len(found) == 1, events
    return found[0]


def assert_expired_on_time(last_packet: float, configured_s: float, expired: float, step_s: float = PLANT_STEP_S):
    """Stopped at the first touch after its time: more than `configured_s` after the last packet, at most one step
    of the touches (the plant's, or the host's packets') later."""
    assert configured_s < expired - last_packet <= configured_s + step_s + 1e-9, expired - last_packet


def silence_in(text: str) -> int:
    """The milliseconds an expiry's event reports ("... stopped after 41 ms without a packet")."""
    return int(text.split("after ")[1].split(" ms")[0])


def test_watchdog_stops_a_torque_on_servo_after_its_time_without_packets(emu, port, clock):
    handler, ph = port
    emu.track_goals = False                                          # a physics adapter: present is measured
    emu.set_present(11, 1500)
    assert ph.write1ByteTxRx(handler, 11, 64, 1) == (sdk.COMM_SUCCESS, 0)            # torque on: goal 1500
    assert ph.write4ByteTxRx(handler, 11, 116, 2500) == (sdk.COMM_SUCCESS, 0)        # moving towards 2500
    assert ph.write1ByteTxRx(handler, 11, 98, 2) == (sdk.COMM_SUCCESS, 0)            # 40 ms; the last packet
    events = run_plant(emu, clock, "bus watchdog: stopped")
    last_packet = stamp_of(events, "dynamixel 11 bus watchdog 2 (40 ms)")
    expired, text = expiry(events, 11)
    assert_expired_on_time(last_packet, 0.040, expired)
    assert silence_in(text) == round((expired - last_packet) * 1000)
    # Stopped: torque still on, holding where it is (goal := present, which a physics adapter sees), Bus Watchdog -1.
    assert emu.torque_enabled(11) and emu.goal_position(11) == 1500 == emu.item(11, "present_position")
    assert emu.item(11, "bus_watchdog") == -1
    assert ph.read1ByteTxRx(handler, 11, 98) == (0xFF, sdk.COMM_SUCCESS, 0)
    assert not [e for _, e in events if "stopped" in e and not e.startswith("dynamixel 11 ")]   # torque off: no


# The same on the emulator's default clock (time.monotonic, as bruce-emulate runs it): the expiry is noticed within
# WATCHDOG_SLACK_S of its time by a physics adapter polling every 1 ms of wall clock, unless the polling itself is late.
WATCHDOG_SLACK_S = 0.030


def poll_like_a_plant(emu, until: str, timeout: float = 2.0):
    """Touch the emulator every ~1 ms of wall clock as a physics adapter does, until an event containing `until` (or
    timeout): (events drained, [(start, end) of each poll])."""
    events, polls = [], []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        start = time.monotonic()
        emu.torque_enabled_all()
        events += emu.drain_events()
        polls.append((start, time.monotonic()))
        if any(until in text for _, text in events):
            break
        time.sleep(0.001)
    return events, polls


def assert_expiry_timing(events, polls, last_packet: float, configured_s: float, expired: float) -> None:
    """Strictly after its time; noticed by the first poll after its time, and within WATCHDOG_SLACK_S of it unless the
    test's own polling was late (a loaded machine) by more."""
    late_polls = [p for p in polls if p[1] > last_packet + configured_s]
    assert late_polls, "no poll after the watchdog's time"
    first_start, first_end = late_polls[0]
    assert expired - last_packet > configured_s
    assert expired <= first_end
    poller_lateness = max(0.0, first_start - (last_packet + configured_s) - 0.001)
    assert expired - last_packet <= configured_s + WATCHDOG_SLACK_S + poller_lateness


@pytest.mark.realtime
def test_watchdog_stops_a_torque_on_servo_on_the_wall_clock(wall_emu, patient_sdk):
    handler, ph = open_sdk_port(wall_emu.path)
    try:
        assert ph.write1ByteTxRx(handler, 11, 64, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(handler, 11, 98, 2) == (sdk.COMM_SUCCESS, 0)        # 40 ms; the last packet
        events, polls = poll_like_a_plant(wall_emu, "bus watchdog: stopped")
    finally:
        handler.closePort()
    last_packet = stamp_of(events, "dynamixel 11 bus watchdog 2 (40 ms)")
    expired, text = expiry(events, 11)
    assert_expiry_timing(events, polls, last_packet, 0.040, expired)
    assert silence_in(text) >= 40 and wall_emu.item(11, "bus_watchdog") == -1


def test_watchdog_is_quiet_while_packets_keep_coming_from_any_id(emu, port, clock):
    handler, ph = port
    for dxl_id in (11, 12):
        assert ph.write1ByteTxRx(handler, dxl_id, 64, 1) == (sdk.COMM_SUCCESS, 0)
        assert ph.write1ByteTxRx(handler, dxl_id, 98, 10) == (sdk.COMM_SUCCESS, 0)   # 200 ms
    armed = clock()                      # 12's last packet
    emu.silence([12])                    # unplugged: 12 hears nothing from here on
    emu.drain_events()
    for _ in range(60):                  # 600 ms of device time, 3 watchdog periods: servo 13 pinged every 10 ms
        clock.advance(0.010)
        assert ph.ping(handler, 13)[1] == sdk.COMM_SUCCESS
        assert emu.item(11, "bus_watchdog") == 10
    assert emu.item(11, "bus_watchdog") == 10 and emu.torque_enabled(11)   # any packet on the bus counts ...
    assert emu.item(12, "bus_watchdog") == -1                              # ... but not for an unplugged servo
    events = emu.drain_events()
    assert [e for _, e in events if "stopped" in e] == [expiry(events, 12)[1]]
    assert_expired_on_time(armed, 0.200, expiry(events, 12)[0], step_s=0.010)
    # Torque off: not monitored, however long the silence.
    assert ph.write1ByteTxRx(handler, 11, 64, 0) == (sdk.COMM_SUCCESS, 0)
    clock.advance(10.0)
    assert emu.item(11, "bus_watchdog") == 10 and not emu.drain_events()[1:]   # only "torque off"
    # Torque on again: the timer starts at that packet, and the host now stays silent.
    assert ph.write1ByteTxRx(handler, 11, 64, 1) == (sdk.COMM_SUCCESS, 0)
    events = run_plant(emu, clock, "dynamixel 11 bus watchdog: stopped")
    assert_expired_on_time(stamp_of(events, "dynamixel 11 torque on"), 0.200, expiry(events, 11)[0])


def test_goal_writes_are_refused_in_watchdog_error_until_it_is_cleared(emu, port, clock):
    handler, ph = port
    assert ph.write1ByteTxRx(handler, 14, 64, 1) == (sdk.COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(handler, 14, 116, 1000) == (sdk.COMM_SUCCESS, 0)
    for raw in (0x80, 0xFE, 128):                                    # -128, -2, 128 (2 bytes): outside -1..127
        assert ph.write1ByteTxRx(handler, 14, 98, raw)[1] == ERR_DATA_RANGE
    assert ph.write2ByteTxRx(handler, 14, 98, 128)[1] == ERR_ACCESS   # 99 is a reserved gap
    assert ph.write1ByteTxRx(handler, 14, 98, 2) == (sdk.COMM_SUCCESS, 0)
    clock.advance(0.1)                   # silent for 100 ms: the next packet finds it expired (checked before it)
    goals = {100: (2, 300), 102: (2, 500), 104: (4, 50), 116: (4, 2000)}   # goal PWM, current, velocity, position
    before = {name: emu.item(14, name) for name in ("goal_pwm", "goal_current", "goal_velocity", "goal_position")}
    writes = {1: ph.write1ByteTxRx, 2: ph.write2ByteTxRx, 4: ph.write4ByteTxRx}
    for address, (size, value) in goals.items():
        assert writes[size](handler, 14, address, value) == (sdk.COMM_SUCCESS, ERR_DATA_RANGE), address
    assert emu.item(14, "bus_watchdog") == -1
    assert ph.write2ByteTxRx(handler, 14, 168, 116) == (sdk.COMM_SUCCESS, 0)   # Indirect Address 1 -> goal position
    assert ph.write1ByteTxRx(handler, 14, 224, 7)[1] == ERR_DATA_RANGE          # ... refused through it too
    writer = sdk.GroupSyncWrite(handler, ph, 116, 4)
    assert writer.addParam(14, list((3000).to_bytes(4, "little"))) and writer.txPacket() == sdk.COMM_SUCCESS
    assert ph.write1ByteTxRx(handler, 14, 98, 5)[1] == ERR_DATA_RANGE          # only 0 clears the error
    assert ph.write1ByteTxRx(handler, 14, 65, 1) == (sdk.COMM_SUCCESS, 0)      # other items still writable
    assert {name: emu.item(14, name) for name in before} == before and emu.item(14, "bus_watchdog") == -1
    assert ph.write1ByteTxRx(handler, 14, 98, 0) == (sdk.COMM_SUCCESS, 0)      # cleared
    assert ph.read1ByteTxRx(handler, 14, 98) == (0, sdk.COMM_SUCCESS, 0)
    for address, (size, value) in goals.items():
        assert writes[size](handler, 14, address, value) == (sdk.COMM_SUCCESS, 0), address
    assert emu.item(14, "goal_position") == 2000 and emu.torque_enabled(14)
    texts = [e for _, e in emu.drain_events()]
    assert texts[-2:] == ["dynamixel 14 bus watchdog: stopped after 100 ms without a packet",
                          "dynamixel 14 bus watchdog 0 (off, error cleared)"]
    # A host's -1 is the error too; REBOOT (RAM to initial values) clears it.
    assert ph.write1ByteTxRx(handler, 14, 98, 0xFF) == (sdk.COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(handler, 14, 116, 2100)[1] == ERR_DATA_RANGE
    assert ph.reboot(handler, 14) == (sdk.COMM_SUCCESS, 0)
    assert emu.item(14, "bus_watchdog") == 0 and not emu.torque_enabled(14)
    assert [e for _, e in emu.drain_events()] == [
        "dynamixel 14 bus watchdog -1 (error written by the host: stopped)", "dynamixel 14 torque off",
        "dynamixel 14 bus watchdog 0 (off, reboot, error cleared)"]


def test_driver_writes_reads_back_and_clears_the_watchdog(emu, clock, patient_driver):
    with raw_port(emu.path) as ser:                  # a previous run left servo 13 in Bus Watchdog Error
        ser.write(encode_packet(13, 0x03, bytes([98, 0, 0xFF])))
        read_packets(ser)
    assert emu.item(13, "bus_watchdog") == -1
    emu.drain_events()
    with DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_LATENCY_MS, hold_pose=HOLD,
                            watchdog_s=0.2) as arms:
        assert arms.watchdog_counts == 10
        assert arms.read_watchdog() == {i: 10 for i in ARM_IDS}
        assert all(emu.item(i, "bus_watchdog") == 10 for i in ARM_IDS)
        texts = [e for _, e in emu.drain_events()]
        assert texts[:2] == ["dynamixel 11 bus watchdog 0 (off)", "dynamixel 11 bus watchdog 10 (200 ms)"]
        assert "dynamixel 13 bus watchdog 0 (off, error cleared)" in texts
        arms.hold()
        for _ in range(15):                          # a 50 Hz loop for 300 ms of device time, longer than 200 ms
            arms.read()
            arms.write_positions(HOLD)
            clock.advance(0.02)
        assert arms.read_watchdog() == {i: 10 for i in ARM_IDS}
    assert not emu.torque_enabled_all().any() and all(emu.item(i, "bus_watchdog") == 0 for i in ARM_IDS)
    texts = [e for _, e in emu.drain_events()]
    assert [e for e in texts if "torque" in e] == [f"dynamixel {i} torque {s}" for s in ("on", "off") for i in ARM_IDS]
    assert texts.index("dynamixel 16 torque off") < texts.index("dynamixel 11 bus watchdog 0 (off)")  # off first
    assert not [e for e in texts if "stopped" in e]


@pytest.mark.slow  # waits out the SDK's packet timeouts (2 s)
def test_driver_close_keeps_the_watchdog_of_a_servo_it_could_not_turn_off(emu, clock, patient_driver):
    arms = DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_SILENCE_LATENCY_MS,
                              hold_pose=HOLD, watchdog_s=0.04, retries=0)
    arms.hold()
    emu.silence([12])                                # unplugged: its torque cannot be turned off
    arms.close()
    assert emu.torque_enabled(12) and emu.item(12, "bus_watchdog") == 2   # no device time has passed
    assert all(emu.item(i, "bus_watchdog") == 0 and not emu.torque_enabled(i) for i in ARM_IDS if i != 12)
    events = run_plant(emu, clock, "dynamixel 12 bus watchdog: stopped")
    assert_expired_on_time(0.0, 0.040, expiry(events, 12)[0])           # 12 heard its last packet at device time 0
    assert emu.item(12, "bus_watchdog") == -1                          # it stops by itself
    # torque_off_on_close=False: the servos stay on, so their watchdog stays armed.
    emu.clear_faults()
    with DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_LATENCY_MS, hold_pose=HOLD,
                            watchdog_s=0.04, torque_off_on_close=False) as arms:
        arms.hold()
    assert emu.torque_enabled_all().all() and all(emu.item(i, "bus_watchdog") == 2 for i in ARM_IDS)


def test_driver_read_back_and_write_failures_name_the_servo_and_register(emu, monkeypatch):
    servo = emu.servos[ARM_IDS.index(14)]
    write = servo.write
    monkeypatch.setattr(servo, "write", lambda address, data: 0 if address == 98 else write(address, data))
    with pytest.raises(DeviceFault) as caught:       # servo 14 acknowledges but ignores the write
        DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_LATENCY_MS, watchdog_s=0.4)
    assert caught.value.device_id == 14 and "Bus Watchdog (98) reads back 0, expected 20" in str(caught.value)
    monkeypatch.setattr(servo, "write", lambda address, data: ERR_ACCESS if address == 98 else write(address, data))
    with pytest.raises(DeviceFault) as caught:       # e.g. a firmware without the item
        DynamixelArms.open(emu.path, BAUD, ARM_IDS, signs=ARM_SIGNS, latency_ms=DRIVER_LATENCY_MS, watchdog_s=0.4)
    assert caught.value.device_id == 14 and "access error" in caught.value.flags
    assert "Bus Watchdog (98)" in str(caught.value)


@pytest.mark.parametrize("seconds, counts", [(0.0, 0), (0.02, 1), (0.4, 20), (0.41, 20), (2.54, 127)])
def test_watchdog_seconds_to_counts(seconds, counts):
    assert watchdog_counts(seconds) == counts
    assert DynamixelArms("/dev/null", BAUD, ARM_IDS, watchdog_s=seconds).watchdog_counts == counts
    assert counts * BUS_WATCHDOG_UNIT_S == pytest.approx(round(seconds / 0.02) * 0.02)


@pytest.mark.parametrize("seconds", [0.005, 2.6, -0.02, float("nan"), float("inf")])
def test_watchdog_outside_its_range_is_refused(seconds):
    with pytest.raises(ValueError, match="watchdog_s"):
        DynamixelArms("/dev/null", BAUD, ARM_IDS, watchdog_s=seconds)


def test_event_log_records_torque_changes_bounded_and_thread_safe():
    bus = DynamixelBusEmulator(ARM_IDS, signs=ARM_SIGNS)                     # no pty: bytes in, bytes out

    def torque(on: int) -> bytes:                    # SYNC_WRITE of Torque Enable to every servo
        return encode_packet(0xFE, 0x83, bytes([64, 0, 1, 0]) + b"".join(bytes([i, on]) for i in ARM_IDS))

    bus.handle(torque(1))
    bus.handle(torque(1))                            # no change: no event
    bus.set_hardware_error(13, ["overheating"])      # shut down by its Shutdown bits
    events = bus.drain_events()
    assert [e for _, e in events] == [f"dynamixel {i} torque on" for i in ARM_IDS] + ["dynamixel 13 torque off"]
    stamps = [t for t, _ in events]
    assert stamps == sorted(stamps)
    assert bus.drain_events() == []                  # since the last drain
    # Thread-safe: a drainer racing the producer loses and duplicates nothing.
    drained: list = []
    stop = threading.Event()

    def drain():
        while not stop.is_set():
            drained.extend(bus.drain_events())

    thread = threading.Thread(target=drain)
    thread.start()
    for k in range(300):
        bus.handle(torque(k % 2))
    stop.set()
    thread.join()
    drained += bus.drain_events()
    expected = [f"dynamixel {i} torque {'on' if k % 2 else 'off'}" for k in range(300) for i in ARM_IDS if i != 13]
    assert [e for _, e in drained] == expected       # 13 stays off: its hardware error refuses torque on
    # Bounded: the newest MAX_EVENTS kept, the older ones counted.
    for k in range(MAX_EVENTS // 5 + 1):             # 5 events a packet (13 stays off), starting with torque off
        bus.handle(torque(k % 2))
    events = bus.drain_events()
    assert len(events) == MAX_EVENTS and events[-1][1] == "dynamixel 16 torque off"
    assert events[0][1] == "dynamixel 11 torque on" and bus.events_dropped == 5   # the first packet's
