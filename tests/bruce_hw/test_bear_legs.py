"""The BEAR legs' bulk cycle against the driver's emulator on a pseudo-terminal (drivers/emulators/bear.py): the
temperatures and voltages ride in the bulk cycle's own request, never in one of their own."""

import logging
from collections import Counter

import numpy as np
import pytest
from support.ports import wait_readable

from bruce_hw.bear_legs import MONITOR_EVERY_TICKS, BearLegs
from bruce_hw.config import load_config
from drivers.emulators.bear import BearBusEmulator

IDS = list(range(1, 11))


@pytest.fixture
def legs():
    with BearBusEmulator(IDS) as emulator:
        config = load_config(overrides=[f"buses.bear.port={emulator.path}"])
        legs = BearLegs(config, ping_rounds=2, ping_retry_s=0.01, clear_attempts=2, reply_timeout_s=0.02)
        legs.open()
        try:
            yield legs, emulator
        finally:
            legs.close()


def test_temperatures_and_voltages_come_with_the_bulk_cycle_not_a_request_of_their_own(legs, caplog):
    legs, emulator = legs
    emulator.set_register_value(3, "winding_temperature", 80.0)
    emulator.set_register_value(7, "input_voltage", 13.0)
    assert np.isnan(legs.temperature).all() and legs.monitor_count == 0
    before = Counter(emulator.requests)
    with caplog.at_level(logging.WARNING, logger="bruce_hw.hw"):
        for _ in range(2 * MONITOR_EVERY_TICKS):
            reading = legs.cycle(None)
            assert reading.problem is None
    # one request per cycle, and nothing else on the bus (counted where the BEARs are: a reply that a busy machine
    # delivers late is not a request more)
    assert emulator.requests - before == Counter({"BULK_COMM": 2 * MONITOR_EVERY_TICKS})
    assert legs.monitor_count == 2
    assert legs.temperature[2] == pytest.approx(80.0) and legs.temperature[0] == pytest.approx(30.0)
    assert legs.voltage[6] == pytest.approx(13.0) and legs.voltage[0] == pytest.approx(24.0)
    warnings = [r.getMessage() for r in caplog.records]
    assert sum("ID 3 at 80 C" in w for w in warnings) == 1  # warned once, on crossing
    assert sum("ID 7 input 13.0 V" in w for w in warnings) == 1


def test_a_bear_that_does_not_answer_the_monitoring_cycle_keeps_its_last_figures(legs):
    legs, emulator = legs
    for _ in range(MONITOR_EVERY_TICKS):
        legs.cycle(None)
    assert legs.temperature[4] == pytest.approx(30.0)
    emulator.set_register_value(5, "winding_temperature", 60.0)
    emulator.silence([5])
    for _ in range(MONITOR_EVERY_TICKS):
        legs.cycle(None)
    assert legs.monitor_count == 2 and legs.temperature[4] == pytest.approx(30.0)  # its last figure, not NaN
    emulator.silence([5], False)
    for _ in range(MONITOR_EVERY_TICKS):
        legs.cycle(None)
    assert legs.temperature[4] == pytest.approx(60.0)


def test_replies_taken_late_are_samples_stamped_with_their_request_and_not_lost(legs):
    """A cycle whose replies all came after its deadline: the next cycle keeps them as samples as old as the request
    they answer (never newer ones it has), does not count them lost, and sees an E-stop bit they carry."""
    import time

    legs, emulator = legs
    legs.cycle(None)  # every reply in, at the fixture's 20 ms (at 2 ms a loaded machine lost this one's too)
    legs.bus.reply_timeout_s = 0.002
    emulator.set_measured_many(IDS, [0.05 * i for i in IDS], [0.0] * 10, [0.0] * 10)
    emulator.set_estop(True, ids=[6])
    emulator.set_reply_delay(0.02)
    asked = time.monotonic()
    lost = legs.cycle(None)
    returned = time.monotonic()
    assert (lost.stamps < asked).all() and legs.loss.total.sum() == 10 and lost.estop_ids == ()
    # until the emulator has answered (all ten replies in one write; the harvest's read waits for their hand-over)
    wait_readable(legs.bus._serial)
    emulator.silence(IDS)  # the next cycle's own request gets nothing: what it has came late
    reading = legs.cycle(None)
    assert legs.late_replies == 10 and legs.loss.total.sum() == 10  # this cycle's ten, not the last one's
    assert (asked <= reading.stamps).all() and (reading.stamps <= returned).all()
    np.testing.assert_allclose(reading.position, [0.05 * i for i in IDS], rtol=1e-6)
    assert reading.estop_ids == (6,)
    assert legs.link_report()["replies_late"] == 10


def _record_orders(legs: BearLegs) -> list[tuple[int, ...]]:
    """The ID order of every bulk request `legs` makes from now on (appended to the list returned)."""
    orders: list[tuple[int, ...]] = []
    bulk_cycle = legs.bus.bulk_cycle

    def recorded(ids, *args, **kwargs):
        orders.append(tuple(ids))
        return bulk_cycle(ids, *args, **kwargs)

    legs.bus.bulk_cycle = recorded
    return orders


def test_the_request_order_turns_and_every_actuator_keeps_its_own_sample_and_goal(legs):
    """The bulk request starts one ID later every cycle, so that a lost last reply (which alone costs the driver's
    reply gap) falls on each ID in turn; the replies, in that order, land in their own actuator's row, and each
    BEAR is written its own goal."""
    legs, emulator = legs
    positions, velocities = [0.1 * i for i in IDS], [0.01 * i for i in IDS]
    emulator.set_measured_many(IDS, positions, velocities, [0.0] * len(IDS))
    orders = _record_orders(legs)
    goal_iq = 0.5 * np.arange(1, len(IDS) + 1)  # A: one per actuator, all different
    for _ in range(len(IDS)):
        reading = legs.cycle(goal_iq * legs.kt)
        assert reading.problem is None
        np.testing.assert_allclose(reading.position, positions, rtol=1e-6)
        np.testing.assert_allclose(reading.velocity, velocities, rtol=1e-6)
        np.testing.assert_allclose(emulator.commands(IDS)["goal_iq"], goal_iq, rtol=1e-6)
    assert all(sorted(order) == IDS for order in orders)
    assert [order[-1] for order in orders] == IDS[-1:] + IDS[:-1]  # each ID last once in ten cycles


def test_with_the_order_fixed_every_cycle_asks_in_config_order_and_each_actuator_keeps_its_row():
    """`turn_order=False` (the order before the turning one, which bench/bench_last_reply_order.py compares)."""
    with BearBusEmulator(IDS) as emulator:
        config = load_config(overrides=[f"buses.bear.port={emulator.path}"])
        legs = BearLegs(config, ping_rounds=2, ping_retry_s=0.01, clear_attempts=2, reply_timeout_s=0.02,
                        turn_order=False)
        legs.open()
        try:
            positions = [0.1 * i for i in IDS]
            emulator.set_measured_many(IDS, positions, [0.0] * len(IDS), [0.0] * len(IDS))
            orders = _record_orders(legs)
            for _ in range(3):
                np.testing.assert_allclose(legs.cycle(None).position, positions, rtol=1e-6)
            assert orders == [tuple(IDS)] * 3
        finally:
            legs.close()
