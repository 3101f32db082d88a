"""The legs' bus thread (bruce_hw.bus_thread) on a fake cycle: commands reach the bus, read() never waits for a slow
cycle, a hung control thread stops the cycles (the motors' watchdogs take over), a failing cycle is kept for the
control thread. Bounds are one-sided where a loaded machine could only make them pass later, never earlier."""

import time

from support.fake_bus import FakeBus, wait_for

from bruce_hw.bus_thread import BusThread


def cycling(bus: FakeBus, period_s: float, hold_s: float) -> BusThread:
    thread = BusThread("test-bus", bus.cycle, period_s=period_s, hold_s=hold_s)
    thread.start()
    thread.begin(("first", 0, None))
    return thread


def test_a_posted_command_reaches_the_bus_and_its_reading_comes_back():
    bus = FakeBus()
    thread = BusThread("test-bus", bus.cycle, period_s=0.001, hold_s=1.0)
    thread.start()
    time.sleep(0.02)
    assert not bus.sent  # started, but no cycle before begin()
    thread.begin(("first", 0, None))
    assert thread.latest[0] in ("first", "reading")
    try:
        assert wait_for(lambda: thread.cycles >= 1)
        assert bus.sent[0] is None  # before the first command: read-only cycles
        thread.post("tau-1")
        assert wait_for(lambda: thread.latest[2] == "tau-1")
        assert "tau-1" in bus.sent
    finally:
        assert thread.stop()
    assert thread.cycles == len(bus.sent) and thread.cycle_us()["p50"] is not None


def test_latest_never_waits_for_a_slow_cycle():
    bus = FakeBus(cycle_s=0.05)
    thread = cycling(bus, period_s=0.001, hold_s=1.0)
    try:
        assert wait_for(lambda: thread.cycles >= 1)
        thread.post("tau")
        t0 = time.perf_counter()
        reading = thread.latest
        assert time.perf_counter() - t0 < 0.01  # a reference, not a wait for the 50 ms cycle in flight
        assert reading[2] != "tau"  # that cycle has not finished
        assert wait_for(lambda: thread.latest[2] == "tau")
    finally:
        thread.stop(0.5)


def test_the_cycles_stop_when_no_command_comes_for_hold_s():
    """A hung control thread must not keep feeding the motors its last torque: the cycles stop, so the motors'
    own watchdogs see silence."""
    bus = FakeBus()
    thread = cycling(bus, period_s=0.001, hold_s=0.02)
    try:
        thread.post("tau")
        assert wait_for(lambda: thread.idle_waits >= 1)
        stopped_at = len(bus.sent)
        time.sleep(0.1)
        assert len(bus.sent) == stopped_at  # silent while nobody posts
        assert all(c in (None, "tau") for c in bus.sent)
        thread.post("tau-2")  # the control thread is back: cycles resume
        assert wait_for(lambda: thread.latest[2] == "tau-2")
    finally:
        thread.stop()


def test_self_paced_cycles_repeat_the_newest_command_between_posts():
    bus = FakeBus()
    thread = cycling(bus, period_s=0.002, hold_s=0.5)
    try:
        thread.post("tau")
        posted = len(bus.sent)
        assert wait_for(lambda: len(bus.sent) >= posted + 5)  # no further posts: the thread cycles on its own
        assert bus.sent[-1] == "tau"
    finally:
        thread.stop()


def test_a_failing_cycle_ends_the_thread_and_is_kept_for_the_control_thread():
    bus = FakeBus(fail_at=3)
    thread = cycling(bus, period_s=0.001, hold_s=1.0)
    thread.post("tau")
    assert wait_for(lambda: thread.error is not None)
    assert isinstance(thread.error, OSError) and "adapter is gone" in str(thread.error)
    assert wait_for(lambda: not thread.thread.is_alive())
    assert thread.stop()


def test_stop_ends_the_thread_after_the_cycle_in_flight():
    bus = FakeBus(cycle_s=0.02)
    thread = cycling(bus, period_s=0.001, hold_s=1.0)
    thread.post("tau")
    assert wait_for(lambda: len(bus.sent) >= 1)
    assert thread.stop(timeout_s=2.0)
    n = len(bus.sent)
    time.sleep(0.05)
    assert len(bus.sent) == n


def test_halt_acts_on_the_cycle_that_brought_the_reading_and_ends_the_thread():
    bus = FakeBus()
    acted = []

    def halt(reading):
        if reading[1] >= 3:  # the third cycle's reading cannot wait for the next tick
            acted.append((reading, len(bus.sent)))
            return "E-stop"
        return None

    thread = BusThread("test-bus", bus.cycle, period_s=0.001, hold_s=1.0, halt=halt)
    thread.start()
    before = time.monotonic()
    thread.begin(("first", 0, None))
    assert wait_for(lambda: not thread.thread.is_alive())
    assert thread.halted == "E-stop" and before <= thread.halted_at <= time.monotonic()
    assert acted == [(("reading", 3, None), 3)]  # on the cycle's own thread, before any further cycle
    assert thread.latest == ("reading", 3, None) and thread.error is None
    thread.post("torque")  # the control thread's next write starts nothing
    time.sleep(0.01)
    assert len(bus.sent) == 3


def test_an_exception_in_halt_is_kept_like_a_failing_cycle():
    def halt(reading):
        raise OSError("damping write failed")

    thread = BusThread("test-bus", FakeBus().cycle, period_s=0.001, hold_s=1.0, halt=halt)
    thread.start()
    thread.begin(("first", 0, None))
    assert wait_for(lambda: not thread.thread.is_alive())
    assert isinstance(thread.error, OSError) and thread.halted is None
