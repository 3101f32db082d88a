"""The sense board: wire format, the driver over the emulator's pseudo-terminal, faults, and the parser's properties."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from drivers.emulators.sense import ACCEL_SCALE, GYRO_SCALE, SenseBoardEmulator
from drivers.errors import BusTimeout, DriverError, LinkStats
from drivers.sense import SenseBoard
from drivers.sense_codec import (
    PACKET_LEN,
    PicoMode,
    SenseParser,
    check_packet,
    decode_command,
    encode_command,
    encode_packet,
)

# Values whose float32 bytes hold no 0xFF, so a corrupted packet costs exactly one rejection.
PLAIN_ACCEL = [0.5, 0.25, 9.75]
PLAIN_GYRO = [0.125, -0.5, 1.0]


def wait_until(predicate, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


@pytest.fixture(params=[True], ids=["quantized"])
def emulator(request):
    # Commands are read every 50 ms instead of the board's 1 s, to keep the tests fast.
    with SenseBoardEmulator(command_poll_s=0.05, idle_poll_s=0.005, quantize=request.param) as emu:
        yield emu


plain_values = pytest.mark.parametrize("emulator", [False], ids=["float32"], indirect=True)


@pytest.fixture
def board(emulator):
    with SenseBoard(emulator.path) as b:
        yield b


# -- wire format ---------------------------------------------------------------------------------------------
def test_commands_are_the_spec_bytes():
    # 0xFF, 3, cooling << 2 | mode, NOT(3 + that byte), 0xFE, worked out by hand
    assert encode_command(PicoMode.IDLE) == bytes([0xFF, 3, 0, 252, 0xFE])  # the firmware's initial buffer
    assert encode_command("nominal") == bytes([0xFF, 3, 1, 251, 0xFE])
    assert encode_command(PicoMode.RESET, 0) == bytes([0xFF, 3, 2, 250, 0xFE])
    assert encode_command("calibration", 10) == bytes([0xFF, 3, 43, 209, 0xFE])
    for mode in PicoMode:
        for speed in range(11):
            assert decode_command(encode_command(mode, speed)) == (mode, speed)
    assert decode_command(bytes([0xFF, 3, 1, 250, 0xFE])) is None  # bad checksum
    for bad in (-1, 11, 2.5):
        with pytest.raises(ValueError):
            encode_command(PicoMode.NOMINAL, bad)
    with pytest.raises(ValueError):
        encode_command("fly")


def test_packet_is_the_spec_layout():
    packet = encode_packet([1.0, -2.0, 9.81], [0.1, 0.2, -0.3], [True, False, False, True])
    assert len(packet) == PACKET_LEN == 29
    assert packet[0] == 0xFF and packet[1] == 27 and packet[28] == 0xFE
    assert struct.unpack("<6f", packet[2:26]) == struct.unpack("<6f", struct.pack("<6f", 1, -2, 9.81, 0.1, 0.2, -0.3))
    assert packet[26] == 0b1000_1001  # marker bit 7, r_toe (bit 0), l_heel (bit 3)
    assert packet[27] == 255 - sum(packet[1:27]) % 256  # the official host's formula
    assert check_packet(packet) is None
    assert encode_packet([0.0] * 3, [0.0] * 3)[27] == 255 - (27 + 0x80)
    bias = encode_packet([0.0] * 3, [0.0] * 3, bias_report=True)
    assert bias[26] == 0xFF and check_packet(bias) is None


# -- driver over the emulator's pty --------------------------------------------------------------------------
def test_values_round_trip_within_the_imu_quantisation(emulator, board):
    accel, gyro, contacts = [0.31, -0.42, 9.79], [0.011, -0.52, 1.7], [True, True, False, True]
    emulator.set_measurement(accel=accel, gyro=gyro, contacts=contacts)
    board.start(check_imu=False)
    assert wait_until(lambda: board.sample_count > 5)
    sample, stamp = board.read()
    # int16 counts at the firmware's scales: error within half a count (plus float32 rounding)
    np.testing.assert_allclose(sample.accel, accel, rtol=0, atol=float(ACCEL_SCALE) / 2 + 1e-6)
    np.testing.assert_allclose(sample.gyro, gyro, rtol=0, atol=float(GYRO_SCALE) / 2 + 1e-6)
    assert sample.contact.tolist() == contacts
    assert 0.0 <= time.monotonic() - stamp < 1.0
    # beyond the chip's range the values saturate at the int16 limit (4 g, ~573 dps)
    emulator.set_measurement(accel=[100.0, -100.0, 9.8], gyro=[20.0, 0.0, 0.0])
    assert wait_until(lambda: board.latest()[0].accel[0] > 9.9)
    sample, _ = board.latest()
    np.testing.assert_allclose(sample.accel[:2], [32767 * ACCEL_SCALE, -32768 * ACCEL_SCALE], rtol=1e-6)
    np.testing.assert_allclose(sample.gyro[0], 32767 * GYRO_SCALE, rtol=1e-6)


def test_unquantised_values_round_trip_as_float32():
    with SenseBoardEmulator(command_poll_s=0.05, idle_poll_s=0.005, quantize=False) as emu, \
            SenseBoard(emu.path) as board:
        emu.set_measurement(accel=[0.1, 0.2, 9.3], gyro=[-3.0, 0.004, 12.5], contacts=[False, True, True, False])
        board.start(check_imu=False)
        sample, _ = board.latest()
        assert sample.accel.tolist() == np.float32([0.1, 0.2, 9.3]).tolist()
        assert sample.gyro.tolist() == np.float32([-3.0, 0.004, 12.5]).tolist()
        assert sample.contact.tolist() == [False, True, True, False]


def test_an_independent_spec_following_host_reads_the_emulator():
    """A host written from the spec alone (raw pyserial, the official reading algorithm) drives the emulator."""
    import serial

    with SenseBoardEmulator(command_poll_s=0.05, idle_poll_s=0.005, quantize=False) as emu:
        emu.set_measurement(accel=[0.5, -1.5, 9.75], gyro=[0.25, 0.0, -2.0], contacts=[False, False, True, True])
        with serial.Serial(emu.path, 115200, timeout=0.05) as port:
            port.write(bytes([0xFF, 3, 1, 251, 0xFE]))  # nominal, cooling 0
            deadline, found = time.monotonic() + 3.0, None
            while found is None and time.monotonic() < deadline:
                if port.read(1) != b"\xff":
                    continue
                rest = port.read(28)
                if (len(rest) == 28 and rest[0] == 27 and rest[26] == 255 - sum(rest[0:26]) % 256
                        and rest[27] == 0xFE):
                    found = rest
            assert found is not None, "no valid packet"
            assert struct.unpack("<3f3f", found[1:25]) == (0.5, -1.5, 9.75, 0.25, 0.0, -2.0)
            assert [found[25] >> k & 1 for k in range(4)] == [0, 0, 1, 1] and found[25] & 0x80
            port.write(bytes([0xFF, 3, 0, 252, 0xFE]))  # idle
            assert wait_until(lambda: emu.mode == PicoMode.IDLE)


def test_commands_reach_the_emulator(emulator, board):
    assert emulator.mode == PicoMode.IDLE  # boots idle, sends nothing
    board.start(check_imu=False)
    assert emulator.mode == PicoMode.NOMINAL and emulator.pump_speed is None
    board.set_cooling(7)
    assert wait_until(lambda: emulator.commands[-1:] == [(PicoMode.NOMINAL, 7)])
    assert wait_until(lambda: emulator.pump_speed == 65) and emulator.fan_on
    board.set_mode("idle")
    assert wait_until(lambda: emulator.mode == PicoMode.IDLE) and not emulator.fan_on
    assert wait_until(lambda: board.age() > 0.05)  # idle: the stream stops
    board._write(bytes([0xFF, 3, 1, 0, 0xFE]))  # a corrupted command: the firmware ignores it
    assert wait_until(lambda: emulator.commands_rejected == 1)
    time.sleep(0.05)
    assert emulator.mode == PicoMode.IDLE


def test_the_reader_thread_keeps_the_latest_sample(emulator, board):
    board.start(check_imu=False)
    for k in range(3):
        emulator.set_measurement(accel=[k, 0.0, 9.8], contacts=[k == 1, False, False, k == 2])
        assert wait_until(lambda k=k: abs(board.latest()[0].accel[0] - k) < 1e-2)
        sample, stamp = board.latest()
        assert sample.contact.tolist() == [k == 1, False, False, k == 2]
        assert board.age() < 0.5 and stamp <= time.monotonic()
    count = board.sample_count
    assert wait_until(lambda: board.sample_count > count + 50)
    t0 = time.perf_counter()
    for _ in range(1000):
        board.latest()
        board.age()
    assert time.perf_counter() - t0 < 0.5  # never waits on the reader


def test_a_stopped_stream_shows_in_age(emulator, board):
    board.start(check_imu=False)
    board.raise_if_stale(0.5)
    emulator.set_silent()
    assert wait_until(lambda: board.age() > 0.1)
    stamp = board.latest()[1]
    _, read_stamp = board.read()
    assert read_stamp == stamp  # stale data keep their stamp
    with pytest.raises(BusTimeout, match=emulator.path):
        board.raise_if_stale(0.05)
    assert board.stats.timeouts >= 1  # the stall was counted
    emulator.set_silent(False)
    assert wait_until(lambda: board.age() < 0.05)


@plain_values
@pytest.mark.parametrize("how, reason", [("checksum", "checksum"), ("trailer", "trailer"), ("length", "length"),
                                         ("flags", "flags"), ("truncate", "truncated"), ("header", "garbage")])
def test_corrupted_packets_are_rejected_counted_and_the_stream_resynchronises(emulator, board, how, reason):
    emulator.set_measurement(accel=PLAIN_ACCEL, gyro=PLAIN_GYRO, contacts=[True, False, False, False])
    board.start(check_imu=False)
    for k in range(1, 4):
        emulator.corrupt_next(how)
        assert wait_until(lambda k=k: board.stats.rejected_total == k)
        count = board.sample_count
        assert wait_until(lambda count=count: board.sample_count > count + 5)  # resynchronised, still streaming
    assert board.latest()[0].accel.tolist() == PLAIN_ACCEL
    board.set_mode("idle")
    assert wait_until(lambda: board.age() > 0.05)
    assert dict(board.stats.rejected) == {reason: 3}
    assert board.stats.packets == emulator.packets_sent - 3  # every good packet was kept
    assert board.alive


@plain_values
def test_garbage_between_packets_is_skipped(emulator, board):
    emulator.set_measurement(accel=PLAIN_ACCEL, gyro=PLAIN_GYRO)
    board.start(check_imu=False)
    emulator.inject_garbage(b"Pinging IMU ...\r\nPinging IMU Succeed.\r\n")
    assert wait_until(lambda: board.stats.rejected["garbage"] == 1)
    emulator.inject_garbage(bytes([0xFF, 0x00, 0xFF, 0xFF, 27, 1, 2, 3]))  # false headers, one with the length byte
    assert wait_until(lambda: board.stats.rejected_total >= 3)
    board.set_mode("idle")
    assert wait_until(lambda: board.age() > 0.05)
    assert board.stats.packets == emulator.packets_sent
    assert board.stats.rejected["garbage"] == 1 and board.stats.rejected["length"] == 2
    assert board.stats.rejected["truncated"] == 1  # 0xFF 27 followed by too few bytes before the next header


def test_startup_imu_check_resets_a_glitching_imu(emulator, board):
    emulator.set_imu_glitch(3.0)  # accel x std 3 m/s^2 until the IMU is reset
    board.start()
    assert PicoMode.RESET in [mode for mode, _ in emulator.commands]
    assert board.stats.retries == 1
    assert emulator.mode == PicoMode.NOMINAL and board.age() < 0.5


def test_startup_imu_check_fails_clearly_and_in_bounded_time(emulator, board):
    emulator.set_imu_glitch(3.0, persistent=True)
    t0 = time.monotonic()
    with pytest.raises(DriverError, match=f"{emulator.path}: IMU check failed 2 times"):
        board.start(imu_attempts=2, imu_samples=200)
    assert time.monotonic() - t0 < 10.0


def test_silent_board_and_missing_port_fail_naming_the_port(emulator, board):
    emulator.set_silent()
    t0 = time.monotonic()
    with pytest.raises(BusTimeout, match=emulator.path):
        board.start(stream_timeout_s=0.3)
    assert time.monotonic() - t0 < 2.0
    with pytest.raises(BusTimeout, match="no sense-board packet"):
        board.read()
    with pytest.raises(DriverError, match="/dev/no-such-sense-board"):
        SenseBoard("/dev/no-such-sense-board")


def test_close_idles_the_board_and_stops_the_reader(emulator):
    board = SenseBoard(emulator.path)
    board.start(check_imu=False)
    board.close()
    assert not board.alive
    assert wait_until(lambda: emulator.mode == PicoMode.IDLE)
    board.close()  # twice is fine


def test_an_unplugged_board_stops_the_reader_without_hanging(emulator, board):
    board.start(check_imu=False)
    emulator.close()  # the device disappears under the open port
    assert wait_until(lambda: not board.alive)
    assert board.error is not None and board.age() > 0.0
    with pytest.raises(BusTimeout, match=emulator.path):
        board.raise_if_stale(0.001)
    board.close()


def test_the_emulator_never_blocks_when_nobody_reads():
    with SenseBoardEmulator(mode=PicoMode.NOMINAL) as emu:  # streams from boot; no host has the port open
        assert wait_until(lambda: emu.packets_dropped > 10)
        assert 0 < emu.packets_sent * PACKET_LEN < 16384  # what piled up is bounded (2 KiB + the kernel's lag)
        with SenseBoard(emu.path) as board:  # opening flushes the backlog; the live stream is whole
            board.wait_for_stream(1.0)
            assert wait_until(lambda: board.sample_count > 50) and board.stats.rejected_total == 0


def test_calibration_measures_and_stores_the_bias():
    with SenseBoardEmulator(command_poll_s=0.05, idle_poll_s=0.005, calibration_samples=20,
                            calibration_wait_s=3.0, quantize=False) as emu, SenseBoard(emu.path) as board:
        emu.set_sensor_offset(accel=[0.25, -0.5, 0.125], gyro=[0.01, 0.0, -0.02])
        emu.set_measurement(accel=[0.0, 0.0, 9.80665], gyro=[0.0, 0.0, 0.0])
        board.start(check_imu=False)
        old, new = board.calibrate_imu(report_timeout_s=3.0, sampling_timeout_s=5.0)
        assert old.bias_report and old.accel.tolist() == [0.0] * 3 and old.gyro.tolist() == [0.0] * 3
        np.testing.assert_allclose(new.accel, [0.25, -0.5, 0.125], atol=1e-5)
        np.testing.assert_allclose(new.gyro, [0.01, 0.0, -0.02], atol=1e-6)
        assert wait_until(lambda: np.allclose(emu.bias()[0], new.accel)) and emu.mode == PicoMode.IDLE
        board.start(check_imu=False)  # calibration ends idle; the bias is now removed from the stream
        sample, _ = board.latest()
        np.testing.assert_allclose(sample.accel, [0.0, 0.0, 9.80665], atol=1e-5)
        np.testing.assert_allclose(sample.gyro, [0.0, 0.0, 0.0], atol=1e-6)


# -- parser properties ---------------------------------------------------------------------------------------
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
# Random bytes, rich in the protocol's own (header, length, trailer, marker) so that false packets start often.
noise = st.lists(st.one_of(st.sampled_from([0xFF, 27, 0xFE, 0x80]), st.integers(0, 255)), max_size=400).map(bytes)
packets = st.lists(st.tuples(st.lists(f32, min_size=3, max_size=3), st.lists(f32, min_size=3, max_size=3),
                             st.lists(st.booleans(), min_size=4, max_size=4)), min_size=1, max_size=6)


def feed_in_chunks(stream: bytes, cuts: list[int]) -> tuple[list, SenseParser]:
    parser = SenseParser(LinkStats())
    out, start = [], 0
    for cut in sorted({c % (len(stream) + 1) for c in cuts}) + [len(stream)]:
        out += parser.feed(stream[start:cut])
        start = cut
    return out, parser


def valid_starts(stream: bytes) -> list[int]:
    return [k for k in range(len(stream) - PACKET_LEN + 1) if check_packet(stream[k:k + PACKET_LEN]) is None]


def as_tuple(sample) -> tuple:
    return tuple(sample.accel.tolist()), tuple(sample.gyro.tolist()), tuple(sample.contact.tolist())


def expected(values) -> list[tuple]:
    return [(tuple(np.float32(a).tolist()), tuple(np.float32(g).tolist()), tuple(c)) for a, g, c in values]


@settings(max_examples=300, deadline=None, derandomize=True)
@given(noise, st.lists(st.integers(min_value=0), max_size=8))
def test_random_bytes_never_raise_and_chunking_does_not_matter(stream, cuts):
    whole, parser = feed_in_chunks(stream, [])
    chunked, chunked_parser = feed_in_chunks(stream, cuts)
    assert [as_tuple(s) for s in whole] == [as_tuple(s) for s in chunked]
    assert parser.stats == chunked_parser.stats
    starts = valid_starts(stream)
    assert parser.stats.packets == len(whole) <= len(starts)  # overlapping valid windows: the first one wins
    assert bool(whole) == bool(starts)
    assert parser.pending < PACKET_LEN
    # every byte is in a packet, still pending, or under a counted rejection
    assert parser.stats.rejected_total >= 1 or parser.pending + PACKET_LEN * len(whole) == len(stream)
    parser.drop_partial()
    assert parser.pending == 0


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.filter_too_much])
@given(noise.filter(bool), packets, st.lists(st.integers(min_value=0), max_size=6))
def test_valid_packets_are_found_after_garbage(garbage, values, cuts):
    good = b"".join(encode_packet(a, g, c) for a, g, c in values)
    stream = garbage + good
    # Without byte stuffing some garbage is itself a valid packet (or one overlapping the first real packet);
    # this property is about streams where the only valid windows are the real packets.
    assume(valid_starts(stream) == [len(garbage) + k * PACKET_LEN for k in range(len(values))])
    out, parser = feed_in_chunks(stream, cuts)
    assert [as_tuple(s) for s in out] == expected(values)
    assert parser.stats.packets == len(values) and parser.stats.rejected_total >= 1 and parser.pending == 0


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.filter_too_much])
@given(packets, st.data())
def test_a_corrupted_packet_costs_only_itself(values, data):
    encoded = [bytearray(encode_packet(a, g, c)) for a, g, c in values]
    victim = data.draw(st.integers(0, len(encoded) - 1))
    damage = data.draw(st.sampled_from(["byte", "truncate"]))
    if damage == "byte":
        pos = data.draw(st.integers(0, PACKET_LEN - 1))
        new = data.draw(st.integers(0, 255).filter(lambda b: b != encoded[victim][pos]))
        encoded[victim][pos] = new
    else:
        del encoded[victim][data.draw(st.integers(1, PACKET_LEN - 1)):]
    stream = b"".join(bytes(p) for p in encoded)
    starts, offset = [], 0
    for k, p in enumerate(encoded):
        if k != victim:
            starts.append(offset)
        offset += len(p)
    assume(valid_starts(stream) == starts)
    out, parser = feed_in_chunks(stream, data.draw(st.lists(st.integers(min_value=0), max_size=6)))
    parser.drop_partial()
    assert [as_tuple(s) for s in out] == [t for k, t in enumerate(expected(values)) if k != victim]
    assert parser.stats.packets == len(values) - 1 and parser.stats.rejected_total >= 1
