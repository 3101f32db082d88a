"""The BEAR driver's tick under lost and corrupted replies: the partial bulk cycle (no retry, the missing rows
marked), and the parser refusing a cut reply that the next reply's bytes complete with a matching checksum."""

import struct
import time

import numpy as np
import pytest
from support.ports import wait_readable

from drivers.bear import MAX_STALL_CREDIT_S, BearBus
from drivers.bear_codec import StatusParser, encode_status, reply_length
from drivers.bear_registers import ERROR_OK, RATED_CURRENT_A, config_register, status_register
from drivers.emulators.bear import BearBusEmulator

IDS = list(range(1, 11))


@pytest.fixture
def emulator():
    with BearBusEmulator(IDS) as emu:
        yield emu


def test_a_partial_bulk_cycle_marks_the_silent_motors_and_never_retries(emulator):
    emulator.silence([4, 7])
    # The wait is long enough for an emulator thread that a busy machine keeps off the CPU: what is asserted is
    # which motors are marked and that nobody is asked again, not how long the wait is.
    with BearBus(emulator.path, reply_timeout_s=0.05) as bus:
        started = time.monotonic()
        reply = bus.bulk_cycle(IDS, "torque", goal_iq=np.zeros(10), partial=True)
        elapsed = time.monotonic() - started
        assert bus.stats.retries == 0 and reply.lost_ids == (4, 7)
        assert np.isnan(reply.position[[3, 6]]).all() and np.isfinite(np.delete(reply.position, [3, 6])).all()
        assert elapsed < bus.cycle_budget_s(10) / bus.tries + 0.05  # one try's budget (and the host's scheduling)
        emulator.silence([4, 7], False)
        emulator.silence([10])  # the last one: nothing after it to say it is lost, so the deadline does
        assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == (10,)
        emulator.silence([10], False)
        whole = bus.bulk_cycle(IDS, None, partial=True)
        assert whole.answered is None and whole.lost_ids == ()


def test_no_current_register_is_written_beyond_the_bear_rating():
    for name in ("goal_iq", "goal_id"):
        assert status_register(name).check(RATED_CURRENT_A) == RATED_CURRENT_A
        with pytest.raises(ValueError, match=f"{name} 31 A is beyond the Koala BEAR's rated 30 A"):
            status_register(name).encode(31.0)
    with pytest.raises(ValueError, match="limit_i_max"):
        config_register("limit_i_max").encode(-45.0)


def _reply(device_id: int, *values: float) -> bytes:
    return encode_status(device_id, ERROR_OK, struct.pack("<3f", *values))


def test_a_cut_reply_completed_by_the_next_one_is_not_a_sample():
    """Reply A (ID 4) loses its tail on the wire; the bytes of reply B (ID 5) complete its length. Among B's
    possible positions, find one where the made-up frame's 8-bit checksum matches, as happens 1 time in 256."""
    cut = _reply(4, 0.5, 0.0, 1.0)[:9]
    for k in range(100000):
        b = _reply(5, 0.1 + 1e-6 * k, 0.0, 2.0)
        frame = cut + b[: 4 + reply_length(3) - len(cut)]
        body = frame[2:-1]
        if (~sum(body) & 0xFF) == frame[-1]:
            break
    else:
        pytest.fail("no colliding frame found")
    parser = StatusParser()
    parser.expect(reply_length(3), [4, 5])
    packets = parser.feed(cut + b)
    assert [p.id for p in packets] == [5]  # reply B, and nothing made up for ID 4
    assert struct.unpack("<3f", packets[0].data)[0] == pytest.approx(0.1 + 1e-6 * k)
    assert parser.stats.rejected["truncated"] >= 1


def test_a_reply_whose_data_holds_ff_ff_is_a_sample():
    """present_iq 4.28 A is the float32 bytes ff ff 88 40: a motor at rest sends them every cycle. FF FF that does not
    start an expected reply (ID, LEN, error byte) is data, not a cut reply."""
    iq = struct.unpack("<f", b"\xff\xff\x88\x40")[0]
    replies = _reply(9, 0.25, -0.5, iq) + _reply(10, 0.0, 0.0, iq)
    assert replies.count(b"\xff\xff") == 4  # two headers, two in the data
    for pieces in ([replies], [replies[:7], replies[7:19], replies[19:]]):  # at once, or as the wire delivers it
        parser = StatusParser()
        parser.expect(reply_length(3), range(1, 11))
        packets = [p for piece in pieces for p in parser.feed(piece)]
        assert [p.id for p in packets] == [9, 10]
    assert [struct.unpack("<3f", p.data)[2] for p in packets] == [iq, iq]
    assert not parser.stats.rejected_total


def stall_next_read(bus: BearBus, stall_s: float) -> None:
    """The bus's next serial read returns nothing after `stall_s`, as when the host ran neither the reading thread
    nor the kernel's tty delivery for that long; the reads after it are the port's own."""
    serial_port = bus._serial
    real_read = type(serial_port).read.__get__(serial_port)

    def stalled_read(n):
        serial_port.read = real_read
        time.sleep(stall_s)
        return b""

    serial_port.read = stalled_read


@pytest.mark.parametrize("stall_s", [0.03, 0.045])
def test_replies_the_host_was_stalled_for_are_read_not_lost(emulator, stall_s):
    """The host does not run the reading thread for longer than the whole reply budget (a preempted thread, a paused
    VM), and the replies reach the tty only after it: they are read, nothing counts as lost, the stall is counted.
    Real silence after a stall still ends the call: the stall is not the device's time, the rest of the budget is.
    (A 20 ms reply wait, shorter than the stalls and room for an emulator thread on a busy machine.)"""
    with BearBus(emulator.path, reply_timeout_s=0.02) as bus:
        stall_next_read(bus, stall_s)
        reply = bus.bulk_cycle(IDS, None, partial=True)
        assert reply.lost_ids == () and reply.answered is None
        stalled = bus.stats.host_stalls  # ours, and any the busy machine adds
        assert stalled >= 1 and bus.stats.timeouts == 0

        stall_next_read(bus, stall_s)
        emulator.silence(IDS)
        started = time.monotonic()
        assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == tuple(IDS)
        elapsed = time.monotonic() - started
        assert bus.stats.host_stalls > stalled and bus.stats.timeouts == 1
        assert stall_s < elapsed < stall_s + bus.cycle_budget_s(10) / bus.tries + 0.05


def test_a_stall_beyond_the_credit_costs_the_replies(emulator):
    """The host's time is forgiven up to MAX_STALL_CREDIT_S: a call stays bounded, and data that old is stale for
    any data-age limit anyway."""
    with BearBus(emulator.path, reply_timeout_s=0.002) as bus:
        stall_next_read(bus, MAX_STALL_CREDIT_S + 0.03)
        assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == tuple(IDS)
        assert bus.stats.host_stalls >= 1


def test_a_send_the_host_holds_is_reported_as_the_hosts_time(emulator):
    """The kernel holds the flush before a request (its tty work for the port not run: docs/timing.md,
    "Scheduling"): the request has not gone out, so that time is reported to `on_host_stall`, and `held_since`
    says so while it lasts; a send that the host did not hold reports nothing."""
    held: list[tuple[float, float]] = []
    seen_while_held: list[float | None] = []
    with BearBus(emulator.path, reply_timeout_s=0.02) as bus:
        bus.on_host_stall = lambda start, end: held.append((start, end))
        for _ in range(5):  # a machine with other load on it may hold one for real: one of five is enough
            before = len(held)
            assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == ()
            if len(held) == before:
                break
        assert len(held) == before, f"every send reported as held: {held}"
        assert bus.held_since(time.monotonic()) is None
        serial_port = bus._serial
        real_flush = type(serial_port).reset_input_buffer.__get__(serial_port)

        def held_flush():
            serial_port.reset_input_buffer = real_flush
            time.sleep(0.012)
            seen_while_held.append(bus.held_since(time.monotonic()))
            real_flush()

        serial_port.reset_input_buffer = held_flush
        started = time.monotonic()
        reply = bus.bulk_cycle(IDS, None, partial=True)
        assert reply.lost_ids == ()  # the replies to the request sent after the hold
        assert seen_while_held and seen_while_held[0] is not None and seen_while_held[0] >= started
        assert bus.held_since(time.monotonic()) is None
        sends = [(start, end) for start, end in held if start == seen_while_held[0]]
        assert len(sends) == 1 and sends[0][1] - sends[0][0] >= 0.012, held
        assert bus.stats.host_stalls >= 1


def test_a_read_pass_the_host_holds_counts_from_the_end_of_its_slice_while_it_lasts(emulator):
    """A read pass has its slice to return in; past it (plus the scheduling tolerance) the host holds it, and
    `held_since` says so before the pass has ended; once it has, `on_host_stall` hears of the same interval."""
    held: list[tuple[float, float]] = []
    seen: list[tuple[float, float | None]] = []
    with BearBus(emulator.path, reply_timeout_s=0.02) as bus:
        bus.on_host_stall = lambda start, end: held.append((start, end))
        serial_port = bus._serial
        real_read = type(serial_port).read.__get__(serial_port)

        def held_read(n):
            serial_port.read = real_read
            started = time.monotonic()
            time.sleep(0.010)
            seen.append((started, bus.held_since(time.monotonic())))
            return real_read(n)

        serial_port.read = held_read
        assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == ()
        (started, since), = seen
        assert since is not None and started - 0.001 < since <= started + bus.read_slice_s + 0.001
        assert any(start <= since + 0.001 and end >= started + 0.010 for start, end in held), held
        assert bus.held_since(time.monotonic()) is None


# -- replies that come after their deadline -------------------------------------------------------------------------
REPLY_BYTES = 4 + reply_length(3)  # one BEAR's reply to the tick's bulk cycle


def test_replies_that_come_after_the_deadline_are_taken_before_the_next_request(emulator):
    """A cycle's replies that come after its deadline are that cycle's data all the same: the next bulk cycle reads
    them before its flush and hands them over as `late`, stamped with the request they answer."""
    emulator.set_measured_many(IDS, [0.1 * i for i in IDS], [0.01 * i for i in IDS], [0.5] * 10)
    emulator.set_reply_delay(0.02)  # ten times the reply wait
    with BearBus(emulator.path, reply_timeout_s=0.002) as bus:
        first = bus.bulk_cycle(IDS, None, partial=True)
        assert first.lost_ids == tuple(IDS) and first.late is None
        wait_readable(bus._serial)
        emulator.set_reply_delay(0.0)
        second = bus.bulk_cycle(IDS, None, partial=True)
        late = second.late
        assert late is not None and late.ids == tuple(IDS) and bus.stats.late_replies == 10
        assert late.sent_at == first.sent_at < second.sent_at
        np.testing.assert_allclose(late.position, [0.1 * i for i in IDS], rtol=1e-6)
        np.testing.assert_allclose(late.velocity, [0.01 * i for i in IDS], rtol=1e-6)
        assert late.answered is None and late.late is None
        assert bus.stats.rejected_total == 0


def test_late_replies_are_dropped_by_any_other_request(emulator):
    """Only the tick's next bulk cycle takes them: any other request flushes them, as before."""
    emulator.set_reply_delay(0.02)
    with BearBus(emulator.path, reply_timeout_s=0.002) as bus:
        assert bus.bulk_cycle(IDS, None, partial=True).lost_ids == tuple(IDS)
        wait_readable(bus._serial)
        emulator.set_reply_delay(0.0)
        bus.ping(1)  # its flush drops them
        assert bus.bulk_cycle(IDS, None, partial=True).late is None
        assert bus.stats.late_replies == 0


def test_a_reply_cut_by_the_deadline_is_completed_by_the_bytes_that_come_after_it():
    """The deadline falls inside ID 4's reply (the replies stopped coming for longer than REPLY_GAP_S): the parser
    keeps the cut bytes and the next cycle completes ID 4 and takes 5..10 from what came after."""
    import os
    import threading

    master, slave = os.openpty()
    replies = b"".join(_reply(i, 0.1 * i, 0.0, 1.0) for i in IDS)
    cut = 3 * REPLY_BYTES + REPLY_BYTES // 2
    asked = threading.Event()

    def answer_first_part():
        os.read(master, 4096)  # the bulk request
        asked.set()
        os.write(master, replies[:cut])

    responder = threading.Thread(target=answer_first_part, daemon=True)
    try:
        with BearBus(os.ttyname(slave), reply_timeout_s=0.5) as bus:  # the long wait is only before the first byte
            responder.start()
            first = bus.bulk_cycle(IDS, None, partial=True)
            assert asked.is_set() and first.lost_ids == tuple(range(4, 11))
            os.write(master, replies[cut:])  # in the pty's buffer now: the harvest's read waits for its hand-over
            second = bus.bulk_cycle(IDS, None, partial=True)
            os.read(master, 4096)
            assert second.late is not None and second.late.ids == tuple(range(4, 11))
            np.testing.assert_allclose(second.late.position, [0.1 * i for i in range(4, 11)], rtol=1e-6)
            assert bus.stats.rejected_total == 0 and bus.stats.late_replies == 7
    finally:
        responder.join(1)
        os.close(master)
        os.close(slave)


class _ScriptedPort:
    """A port whose reads return the given chunks, one per read, then nothing."""

    def __init__(self, chunks):
        self.chunks = list(chunks)

    def reset_input_buffer(self):
        pass

    def write(self, data):
        return len(data)

    def read(self, n):
        return self.chunks.pop(0) if self.chunks else b""


def test_an_earlier_requests_replies_in_another_order_do_not_end_the_wait(emulator):
    """The kernel held the last request and its replies come first, in that request's order (the legs turn it each
    cycle): this request's last ID answers first among them. That is no sign the rest are lost: the cycle reads on
    and takes one reply per ID."""
    order = IDS[1:] + IDS[:1]  # this request: 2..10, then 1
    earlier = [_reply(i, 0.1 * i, 0.0, 1.0) for i in IDS]  # the earlier one's replies: 1..10
    with BearBus(emulator.path, reply_timeout_s=0.05) as bus:
        port, bus._serial = bus._serial, _ScriptedPort([b"".join(earlier[:9]), earlier[9]])
        try:
            reply = bus.bulk_cycle(order, None, partial=True)
        finally:
            bus._serial = port
    assert reply.lost_ids == () and reply.ids == tuple(order)
    np.testing.assert_allclose(reply.in_order(IDS).position, [0.1 * i for i in IDS], rtol=1e-6)
