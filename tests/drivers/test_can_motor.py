"""MIT-mode CAN motors: frame layout, the driver against the emulator over python-can's virtual bus, the reply
parser under random frames, and configs/robots/bruce_can.yaml."""

import time
import uuid

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bruce_hw.config import ConfigError, load_config
from drivers.can_motor import CanMotorBus, CanMotorGroup
from drivers.can_motor_codec import (
    AK80_9_V1P1,
    ENTER_MOTOR_MODE,
    EXIT_MOTOR_MODE,
    SET_ZERO,
    MitCommand,
    MitRanges,
    ReplyDecoder,
    decode_command,
    decode_reply,
    encode_command,
    encode_reply,
    special_kind,
    step,
    worst_case_cycle_s,
)
from drivers.emulators.can_motor import GARBAGE_KINDS, CanMotorEmulator, emulators_from_config
from drivers.errors import BusTimeout

can = pytest.importorskip("can")

R = AK80_9_V1P1
IDS = (1, 2, 3)
CAN_CONFIG = "configs/robots/bruce_can.yaml"


# -- an independent reading of the published layout: fields as bit ranges of one big-endian word ----------------
def spec_uint(x, lo, hi, bits):
    return int((min(max(x, lo), hi) - lo) * (2**bits - 1) / (hi - lo))


def spec_command_fields(data):
    word = int.from_bytes(data, "big")
    return word >> 48, (word >> 36) & 0xFFF, (word >> 24) & 0xFFF, (word >> 12) & 0xFFF, word & 0xFFF


def spec_reply_fields(data):
    word = int.from_bytes(data[:6], "big")
    return word >> 40, (word >> 24) & 0xFFFF, (word >> 12) & 0xFFF, word & 0xFFF


def spec_float(value, lo, hi, bits):
    return value * (hi - lo) / (2**bits - 1) + lo


# -- pure frames ------------------------------------------------------------------------------------------------
def test_zero_command_and_special_frames_are_the_published_bytes():
    # p = v = t = 0 sit mid-range; kp = kd = 0 at the bottom: the well-known "zero command" frame
    assert encode_command(MitCommand(0, 0, 0, 0, 0), R) == bytes.fromhex("7FFF7FF0000007FF")
    assert ENTER_MOTOR_MODE == bytes.fromhex("FFFFFFFFFFFFFFFC")
    assert EXIT_MOTOR_MODE == bytes.fromhex("FFFFFFFFFFFFFFFD")
    assert SET_ZERO == bytes.fromhex("FFFFFFFFFFFFFFFE")
    assert [special_kind(f) for f in (ENTER_MOTOR_MODE, EXIT_MOTOR_MODE, SET_ZERO)] == [
        "enter_motor_mode", "exit_motor_mode", "set_zero"]
    assert special_kind(bytes.fromhex("7FFF7FF0000007FF")) is None
    assert special_kind(ENTER_MOTOR_MODE[:7]) is None


def test_a_full_scale_command_never_reads_as_a_special_frame():
    for torque in (17.97, 17.98, 17.99, 18.0):
        frame = encode_command(MitCommand(99, 99, 999, 9, torque), R)
        assert special_kind(frame) is None
        assert spec_command_fields(frame)[:4] == (0xFFFF, 0xFFF, 0xFFF, 0xFFF)


finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(p=finite, v=finite, kp=finite, kd=finite, t=finite)
def test_command_bits_and_round_trip_follow_the_spec(p, v, kp, kd, t):
    frame = encode_command(MitCommand(p, v, kp, kd, t), R)
    assert len(frame) == 8
    expected = (spec_uint(p, *R.p, 16), spec_uint(v, *R.v, 12), spec_uint(kp, *R.kp, 12), spec_uint(kd, *R.kd, 12),
                spec_uint(t, *R.t, 12))
    fields = spec_command_fields(frame)
    assert fields[:4] == expected[:4]
    assert fields[4] == expected[4] or (expected[4] >= 0xFFC and fields[4] == 0xFFB)  # special-frame guard
    decoded = decode_command(frame, R)
    for got, x, (lo, hi), bits in zip(decoded, (p, v, kp, kd, t), (R.p, R.v, R.kp, R.kd, R.t), (16, 12, 12, 12, 12),
                                      strict=True):
        assert abs(got - min(max(x, lo), hi)) <= 2 * step(lo, hi, bits) + 1e-9


@settings(max_examples=200, deadline=None)
@given(motor_id=st.integers(0, 255), p=finite, v=finite, t=finite)
def test_reply_bits_and_round_trip_follow_the_spec(motor_id, p, v, t):
    frame = encode_reply(motor_id, p, v, t, R)
    assert len(frame) == 6
    assert spec_reply_fields(frame) == (motor_id, spec_uint(p, *R.p, 16), spec_uint(v, *R.v, 12),
                                        spec_uint(t, *R.t, 12))
    reply = decode_reply(frame, R)
    assert reply.motor_id == motor_id
    for got, x, (lo, hi), bits in ((reply.position, p, R.p, 16), (reply.velocity, v, R.v, 12),
                                   (reply.torque, t, R.t, 12)):
        assert abs(got - min(max(x, lo), hi)) <= step(lo, hi, bits) + 1e-9


def test_ranges_are_validated():
    with pytest.raises(ValueError, match="MitRanges.kd"):
        MitRanges(p=(-1, 1), v=(-1, 1), kp=(0, 1), kd=(1, 1), t=(-1, 1))
    custom = MitRanges.of({"p": [-95.5, 95.5], "v": [-30, 30], "kp": [0, 500], "kd": [0, 5], "t": [-18, 18]})
    assert custom.p == (-95.5, 95.5)
    assert decode_reply(encode_reply(1, 50.0, 0, 0, custom), custom).position == pytest.approx(50.0, abs=0.01)


# -- the reply parser under arbitrary frames ----------------------------------------------------------------------
frames = st.tuples(
    st.integers(0, 0x1FFFFFFF),  # arbitration ID
    st.binary(min_size=0, max_size=64),  # data, CAN FD lengths included
    st.booleans(), st.booleans(), st.booleans(),  # extended, remote, error
) | st.tuples(st.just(0), st.binary(min_size=6, max_size=8), st.just(False), st.just(False), st.just(False))


@settings(max_examples=400, deadline=None)
@given(garbage=st.lists(frames, max_size=30), motor_id=st.sampled_from(IDS), p=finite)
def test_reply_parser_never_raises_counts_everything_and_resynchronises(garbage, motor_id, p):
    decoder = ReplyDecoder(dict.fromkeys(IDS, R), host_id=0)
    for arbitration_id, data, extended, remote, error in garbage:
        reply = decoder.decode(arbitration_id, data, is_extended_id=extended, is_remote_frame=remote,
                               is_error_frame=error)
        if reply is not None:
            assert reply.motor_id in IDS and arbitration_id == 0 and len(data) in (6, 8)
            assert R.p[0] <= reply.position <= R.p[1] and R.t[0] <= reply.torque <= R.t[1]
    assert decoder.stats.packets + decoder.stats.rejected_total == len(garbage)
    # a good frame right after the garbage is still read: CAN frames carry their own boundaries
    reply = decoder.decode(0, encode_reply(motor_id, p, 1.0, -2.0, R))
    assert reply is not None and reply.motor_id == motor_id
    assert reply.position == pytest.approx(min(max(p, -12.5), 12.5), abs=step(*R.p, 16))


def test_reply_parser_names_its_rejections():
    decoder = ReplyDecoder(dict.fromkeys(IDS, R), host_id=0)
    good = encode_reply(2, 0.5, 0, 0, R)
    decoder.decode(0, good[:5])
    decoder.decode(5, good)
    decoder.decode(0, good, is_extended_id=True)
    decoder.decode(0, encode_reply(9, 0.5, 0, 0, R))
    decoder.decode(0, b"", is_error_frame=True)
    decoder.decode(0, b"", is_remote_frame=True)
    assert decoder.decode(0, good + b"\x1e\x00") is not None  # newer firmware: + temperature, error code
    assert dict(decoder.stats.rejected) == {"length": 1, "foreign": 2, "unknown_id": 1, "error_frame": 1,
                                            "remote": 1}
    assert decoder.stats.packets == 1


# -- driver <-> emulator over the virtual bus ----------------------------------------------------------------------
@pytest.fixture
def channel():
    return f"test-can-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def rig(channel):
    emulator = CanMotorEmulator(channel, IDS).start()
    bus = CanMotorBus(channel, IDS, interface="virtual", timeout_s=0.5)
    yield emulator, bus
    bus.close()
    emulator.close()


def test_motor_mode_commands_and_torque_follow_the_mit_law(rig):
    emulator, bus = rig
    emulator.set_state([0.1, -0.2, 0.3], [0.5, 0.0, -1.0])
    state = bus.read()  # rest mode: replies, no torque
    np.testing.assert_allclose(state.position, [0.1, -0.2, 0.3], atol=step(*R.p, 16))
    np.testing.assert_allclose(state.velocity, [0.5, 0.0, -1.0], atol=step(*R.v, 12))
    assert np.isfinite(state.stamp) and not any(emulator.in_motor_mode(i) for i in IDS)

    bus.exchange([1.0, 1.0, 1.0], 0.0, 20.0, 0.5, 0.25)
    np.testing.assert_array_equal(emulator.torques(), 0.0)  # commands are ignored outside motor mode

    bus.enter_motor_mode()
    assert all(emulator.in_motor_mode(i) for i in IDS)
    np.testing.assert_array_equal(emulator.torques(), 0.0)  # entering clears the command
    p_des, v_des, kp, kd, t_ff = [0.4, -0.4, 0.0], [0.0, 1.0, 0.0], [20.0, 10.0, 0.0], [0.5, 0.2, 1.0], [0.25, 0, -1]
    state = bus.exchange(p_des, v_des, kp, kd, t_ff)
    steps = (step(*R.p, 16), step(*R.v, 12), step(*R.kp, 12), step(*R.kd, 12), step(*R.t, 12))
    for k, mid in enumerate(IDS):
        sent = (p_des[k], v_des[k], kp[k], kd[k], t_ff[k])
        for got, want, quantum in zip(emulator.command(mid), sent, steps, strict=True):
            assert abs(got - want) <= quantum + 1e-9
    p, v = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.0, -1.0])
    commands = [emulator.command(mid) for mid in IDS]
    expected = [c.kp * (c.position - p[k]) + c.kd * (c.velocity - v[k]) + c.torque for k, c in enumerate(commands)]
    np.testing.assert_allclose(emulator.torques(), expected, atol=1e-9)
    np.testing.assert_allclose(state.torque, expected, atol=step(*R.t, 12))  # the reply reports it

    state = bus.exchange(12.0, 0.0, 500.0, 0.0, 0.0)  # far from target: clamped to the torque range
    assert emulator.commanded_torque(1) == R.t[1]
    bus.exit_motor_mode()
    np.testing.assert_array_equal(emulator.torques(), 0.0)
    assert bus.stats.packets > 0 and bus.stats.rejected_total == 0 and bus.stats.timeouts == 0


def test_set_zero_makes_the_present_position_zero(rig):
    emulator, bus = rig
    emulator.set_state([1.0, 2.0, -3.0], 0.0)
    state = bus.set_zero()
    np.testing.assert_allclose(state.position, 0.0, atol=step(*R.p, 16))
    emulator.set_measured(2, 2.5, 0.0)
    assert bus.read().position[1] == pytest.approx(0.5, abs=step(*R.p, 16))
    assert emulator.zero_offset(3) == -3.0


def test_damping_is_computed_by_the_motors(rig):
    emulator, bus = rig
    bus.enter_motor_mode()
    emulator.set_state(0.3, [1.0, -2.0, 0.0])
    bus.damp(0.8)
    np.testing.assert_allclose(emulator.torques(), [-0.8, 1.6, 0.0], atol=0.01)


def test_silent_motors_raise_bus_timeout_naming_the_channel_and_ids(channel):
    with CanMotorEmulator(channel, IDS) as emulator, \
            CanMotorBus(channel, IDS, interface="virtual", timeout_s=0.05) as bus:
        bus.read()
        emulator.set_state([0.7, 0.8, 0.9], 0.0)
        emulator.silence([1, 3])
        started = time.monotonic()
        with pytest.raises(BusTimeout) as info:
            bus.read()
        assert time.monotonic() - started < 1.0  # bounded: 50 ms timeout, generous slack for a loaded machine
        assert info.value.bus == channel and info.value.silent_ids == (1, 3)
        assert channel in str(info.value) and "1, 3" in str(info.value)
        assert bus.stats.timeouts == 1
        assert bus.state.position[1] == pytest.approx(0.8, abs=step(*R.p, 16))  # who answered is kept
        with pytest.raises(BusTimeout, match="enter_motor_mode after 2 attempts"):
            bus.enter_motor_mode(attempts=2)
        assert bus.stats.retries == 1
        emulator.resume()
        bus.read()


@pytest.mark.parametrize("kind", GARBAGE_KINDS)
def test_garbage_is_rejected_and_counted_and_the_real_reply_still_read(rig, kind):
    emulator, bus = rig
    emulator.set_state([0.1, 0.2, 0.3], 0.0)
    emulator.inject_garbage([2], kind=kind, count=2)
    for _ in range(2):
        state = bus.read()
        np.testing.assert_allclose(state.position, [0.1, 0.2, 0.3], atol=step(*R.p, 16))
    assert bus.stats.rejected_total == 2 and bus.stats.timeouts == 0


def test_garbage_instead_of_a_reply_is_a_timeout_naming_the_motor(channel):
    with CanMotorEmulator(channel, IDS) as emulator, \
            CanMotorBus(channel, IDS, interface="virtual", timeout_s=0.05) as bus:
        emulator.inject_garbage([3], kind="length", replace=True)
        with pytest.raises(BusTimeout) as info:
            bus.read()
        assert info.value.silent_ids == (3,)
        assert bus.stats.rejected["length"] == 1
        bus.read()  # the motor answers properly again


def test_foreign_and_stale_frames_are_drained_and_counted(rig, channel):
    emulator, bus = rig
    bus.read()
    emulator.send_raw(0x123, b"\x01\x02")  # another node's traffic
    emulator.send_raw(0, encode_reply(1, 0.0, 0.0, 0.0, R))  # a late reply from an earlier tick
    time.sleep(0.05)
    bus.read()
    assert bus.stats.rejected["foreign"] == 1 and bus.stats.rejected["stale"] == 1


def test_gear_sign_and_offset_map_actuator_units_to_motor_units(channel):
    with CanMotorEmulator(channel, [5]) as emulator, \
            CanMotorBus(channel, [5], interface="virtual", timeout_s=0.5, gear=2.0, sign=-1, offset=0.3) as bus:
        emulator.set_measured(5, -1.0, 4.0)  # motor units
        state = bus.enter_motor_mode()
        assert state.position[0] == pytest.approx(-1.0 / -2.0 + 0.3, abs=step(*R.p, 16))
        assert state.velocity[0] == pytest.approx(4.0 / -2.0, abs=step(*R.v, 12))
        bus.exchange(0.5, 1.0, 40.0, 2.0, 3.0)
        cmd = emulator.command(5)
        assert cmd.position == pytest.approx(2.0 * -1.0 * (0.5 - 0.3), abs=step(*R.p, 16))
        assert cmd.velocity == pytest.approx(-2.0, abs=step(*R.v, 12))
        assert cmd.kp == pytest.approx(10.0, abs=step(*R.kp, 12)) and cmd.kd == pytest.approx(0.5, abs=0.01)
        assert cmd.torque == pytest.approx(-1.5, abs=step(*R.t, 12))


def test_non_finite_commands_are_refused_before_sending(rig):
    emulator, bus = rig
    seen = emulator.frames_seen
    with pytest.raises(ValueError, match=r"non-finite torque command for ID\(s\) \[2\]"):
        bus.exchange(0.0, 0.0, 0.0, 0.0, [0.0, np.nan, 0.0])
    time.sleep(0.02)
    assert emulator.frames_seen == seen


def test_emulator_talks_to_an_independent_spec_following_host(channel):
    host = can.Bus(interface="virtual", channel=channel)
    try:
        with CanMotorEmulator(channel, [7]) as emulator:
            emulator.set_measured(7, 1.25, -3.0)

            def ask(data):
                host.send(can.Message(arbitration_id=7, data=data, is_extended_id=False))
                reply = host.recv(timeout=2.0)
                assert reply is not None and reply.arbitration_id == 0 and not reply.is_extended_id
                return reply

            reply = ask(ENTER_MOTOR_MODE)
            motor_id, p, v, _ = spec_reply_fields(bytes(reply.data))
            assert len(reply.data) == 6 and motor_id == 7
            assert spec_float(p, *R.p, 16) == pytest.approx(1.25, abs=step(*R.p, 16))
            assert spec_float(v, *R.v, 12) == pytest.approx(-3.0, abs=step(*R.v, 12))
            fields = (spec_uint(1.0, *R.p, 16), spec_uint(0, *R.v, 12), spec_uint(4.0, *R.kp, 12),
                      spec_uint(0, *R.kd, 12), spec_uint(0.5, *R.t, 12))
            word = (fields[0] << 48) | (fields[1] << 36) | (fields[2] << 24) | (fields[3] << 12) | fields[4]
            reply = ask(word.to_bytes(8, "big"))
            tau = 4.0 * (1.0 - 1.25) + 0.5
            assert emulator.commanded_torque(7) == pytest.approx(tau, abs=0.05)
            assert spec_float(spec_reply_fields(bytes(reply.data))[3], *R.t, 12) == pytest.approx(tau, abs=0.05)
            ask(SET_ZERO)
            assert emulator.zero_offset(7) == 1.25
            ask(EXIT_MOTOR_MODE)
            assert emulator.commanded_torque(7) == 0.0
    finally:
        host.shutdown()


# -- configs/robots/bruce_can.yaml ----------------------------------------------------------------------------------
def test_bruce_can_config_loads_and_fits_the_bus_time():
    config = load_config(CAN_CONFIG)
    can_bus = config.buses.can
    assert [m.slot for m in can_bus.motors] == list(config.joints)
    assert [m.id for m in can_bus.motors] == list(range(1, 11))
    assert can_bus.channels == ("can0", "can1", "can2", "can3")
    assert can_bus.motor_type == "AK80-9 V1.1" and can_bus.bitrate == 1_000_000 and can_bus.host_id == 0
    assert all(MitRanges.of(m.ranges) == AK80_9_V1P1 for m in can_bus.motors)
    assert config.actuator_torque_limit <= AK80_9_V1P1.t[1]
    for channel in can_bus.channels:
        n = sum(m.channel == channel for m in can_bus.motors)
        assert worst_case_cycle_s(n, can_bus.bitrate) <= can_bus.timeout_s < config.dt
    assert worst_case_cycle_s(10, can_bus.bitrate) > config.dt  # why one channel would not do
    # the rest is BRUCE as in bruce.yaml
    bear = load_config()
    for section in ("rates", "joints", "gains", "coupling", "arms", "safety", "policy", "pinn"):
        assert config.raw[section] == bear.raw[section], section
    assert config.raw["buses"]["dynamixel"] == bear.raw["buses"]["dynamixel"]
    assert config.raw["buses"]["sense"] == bear.raw["buses"]["sense"]
    assert bear.buses.can.motors == ()


def test_bruce_can_config_runs_the_group_against_emulators():
    config = load_config(CAN_CONFIG)
    emulators = emulators_from_config(config.buses.can)
    try:
        with CanMotorGroup.from_config(config.buses.can, interface="virtual", timeout_s=0.5) as group:
            assert group.motor_ids == tuple(range(1, 11))
            for emulator in emulators.values():
                emulator.set_state(np.array(emulator.motor_ids) / 10.0, 0.0)
            group.enter_motor_mode()
            state = group.exchange(np.arange(10) / 10.0, 0.0, 10.0, 0.1, 0.0)
            np.testing.assert_allclose(state.position, np.arange(1, 11) / 10.0, atol=step(*R.p, 16))
            assert emulators["can1"].motor_ids == (4, 5) and emulators["can1"].commanded_torque(5) == pytest.approx(
                10.0 * (0.4 - 0.5), abs=0.05)
            emulators["can2"].silence([7])
            for bus in group.buses:
                bus.timeout_s = 0.1
            with pytest.raises(BusTimeout) as info:
                group.exchange(np.arange(10) / 10.0, 0.0, 10.0, 0.1, 0.0)
            assert info.value.bus == "can2" and info.value.silent_ids == (7,)
            assert np.isfinite(group.state.position).all()  # the other channels' replies were taken
    finally:
        for emulator in emulators.values():
            emulator.close()


@pytest.mark.parametrize(("edit", "fragments"), [
    (lambda can_: can_["motors"]["r_knee"].update(sign=2), ("buses.can.motors.r_knee.sign", "1 or -1")),
    (lambda can_: can_["motors"]["l_ankle"].update(id=4), ("buses.can.motors", "unique motor IDs")),
    (lambda can_: can_["motors"].pop("l_knee"), ("buses.can.motors.l_knee", "missing joint")),
    (lambda can_: can_["ranges"].update(kd=[5.0, 0.0]), ("buses.can.ranges.kd", "min < max")),
    (lambda can_: can_["motors"]["r_ankle"].update(baud=1), ("buses.can.motors.r_ankle.baud", "unknown key")),
    (lambda can_: can_.pop("ranges"), ("buses.can.motors.r_hip_yaw.ranges", "missing key")),
])
def test_bad_can_descriptions_are_named(write_config, edit, fragments):
    import yaml

    from bruce_hw.config import resolve_config_path

    tree = yaml.safe_load(resolve_config_path(CAN_CONFIG).read_text())
    tree["mjcf"] = str(load_config().mjcf)
    edit(tree["buses"]["can"])
    path = write_config(tree)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(path) in str(info.value)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)


def test_per_motor_ranges_override_the_default(write_config):
    import yaml

    from bruce_hw.config import resolve_config_path

    tree = yaml.safe_load(resolve_config_path(CAN_CONFIG).read_text())
    tree["mjcf"] = str(load_config().mjcf)
    tree["buses"]["can"]["motors"]["r_knee"]["ranges"] = {"p": [-95.5, 95.5], "v": [-30, 30], "kp": [0, 500],
                                                          "kd": [0, 5], "t": [-54, 54]}
    config = load_config(write_config(tree))
    knee = config.buses.can.motors[3]
    assert knee.ranges.t == (-54.0, 54.0) and config.buses.can.motors[4].ranges.t == (-18.0, 18.0)
