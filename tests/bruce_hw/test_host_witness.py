"""Host stalls are not device silence (bruce_hw.host_witness): the witness's record on a virtual clock, and what the
silence rule, the safety stage and the bus thread make of it. The witness thread itself is checked one-sidedly
against a real stall of its own process (a loaded machine can only add stalls, never hide one)."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.paths import REPO
from support.safety_fixtures import robot, running_stage

from bruce_hw.host_witness import HostWitness, StallLog, stalled_union
from bruce_hw.leg_bus import LegReading, silence

IDS = (1, 2, 3)
DT, MAX_AGE = 0.001, 0.008


def reading(stamps) -> LegReading:
    n = len(IDS)
    stamps = np.array(stamps, float)
    return LegReading(np.zeros(n), np.zeros(n), np.zeros(n), float(stamps.min()), stamps)


def test_stalled_between_counts_only_the_overlap():
    witness = HostWitness()
    witness.record(10.0, 10.020)
    witness.record(11.0, 11.005)
    assert witness.stalled_between(9.0, 12.0) == pytest.approx(0.025)
    assert witness.stalled_between(10.010, 10.5) == pytest.approx(0.010)
    assert witness.stalled_between(10.5, 10.9) == 0.0
    assert [round(s.length, 3) for s in witness.stalls_since(10.015)] == [0.02, 0.005]
    assert witness.report() == {"count": 2, "worst_ms": pytest.approx(20.0), "total_ms": pytest.approx(25.0)}



def test_a_port_held_by_the_host_counts_once_beside_a_stall_and_while_it_lasts():
    """The leg bus's own log (a flush held in the kernel) and the witness's: an interval both cover counts once, and
    a send still held at `t1` counts from its start, before it has been recorded."""
    witness = HostWitness()
    sending = {"since": None}
    port = StallLog(open_since=lambda now: sending["since"])
    witness.record(10.0, 10.010)
    port.record(10.005, 10.012)  # held across the end of the process's stall
    port.record(11.0, 11.004)
    both = stalled_union(witness, port)
    assert both(9.0, 12.0) == pytest.approx(0.016)
    assert both(10.008, 11.002) == pytest.approx(0.006)
    assert port.report() == {"count": 2, "worst_ms": pytest.approx(7.0), "total_ms": pytest.approx(11.0)}
    sending["since"] = 11.5  # a send held since 11.5, still in progress
    assert port.stalled_between(11.0, 11.52) == pytest.approx(0.024)
    assert both(11.4, 11.52) == pytest.approx(0.02)
    # joint data aged only while the port was held is not silent; the same age without the hold is
    now = 11.52
    held = reading([11.509, 11.509, 11.509])
    assert silence(IDS, held, now, DT, MAX_AGE, both) is None
    assert "ID(s) 1, 2, 3" in silence(IDS, held, now, DT, MAX_AGE, witness.stalled_between)

def test_an_actuator_is_silent_on_the_time_the_process_ran():
    now = 100.0
    stale = reading([now - 0.0005, now - 0.030, now - 0.0005])  # ID 2's sample is 30 ms old
    witness = HostWitness()
    # no stall: 30 ms without a reply from ID 2 is silence
    assert "no reply from ID(s) 2 for 30.0 ms" in silence(IDS, stale, now, DT, MAX_AGE, witness.stalled_between)
    # the process was not run for 25 of those 30 ms: nobody asked; 5 ms (+ a tick) is within the bound
    witness.record(now - 0.027, now - 0.002)
    assert silence(IDS, stale, now, DT, MAX_AGE, witness.stalled_between) is None
    # a device silent for 10 ms of the time the process ran, beside the same stall, is silent
    older = reading([now - 0.0005, now - 0.035, now - 0.0005])
    assert "no reply from ID(s) 2 for 10.0 ms" in silence(IDS, older, now, DT, MAX_AGE, witness.stalled_between)


def test_the_safety_stage_judges_age_and_rate_on_the_time_the_process_ran(config):
    witness = HostWitness()
    stage = running_stage(config)
    stage.stalled = witness.stalled_between
    stage.host_stall_max = 0.045  # the bound is a setting of its own (tested below): here the discount alone
    now = 1.0
    for _ in range(3 * stage.rate_ticks):
        now += config.dt
        stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
    # 40 ms not run: the data read right after are 41 ms old and the window holds too few ticks, both excused
    witness.record(now, now + 0.040)
    stamp, now = now, now + 0.041
    stage.check(robot(config, stamp=stamp, imu_stamp=stamp), now=now)
    for _ in range(stage.rate_ticks):
        now += config.dt
        stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
    assert not stage.tripped, stage.cause
    # the same age with no stall recorded is stale data
    plain = running_stage(config)
    plain.check(robot(config, stamp=stamp, imu_stamp=stamp), now=stamp + 0.041)
    assert plain.tripped and "stale joint data" in plain.cause


def test_the_bus_thread_holds_the_command_on_the_time_the_process_ran():
    """No post for 60 ms: a hung control thread (the cycles stop after hold_s, the motors' watchdogs take over),
    unless that time was a host stall, after which the thread cycles on at once with the command it has."""
    from support.fake_bus import FakeBus, wait_for

    from bruce_hw.bus_thread import BusThread

    for stalled in (False, True):
        witness = HostWitness()
        bus = FakeBus()
        thread = BusThread("test-bus", bus.cycle, period_s=0.001, hold_s=0.010, stalled=witness.stalled_between)
        thread.start()
        thread.begin(("first", 0, None))
        try:
            thread.post("tau")
            if stalled:  # the process "not run" from the post on (the witness's record, on the real clock)
                witness.record(time.monotonic(), time.monotonic() + 10.0)
            time.sleep(0.060)
            if stalled:
                assert thread.idle_waits == 0 and len(bus.sent) > 20
            else:
                assert wait_for(lambda bus_thread=thread: bus_thread.idle_waits >= 1)
                assert len(bus.sent) < 50  # stopped after about hold_s of cycles
        finally:
            thread.stop()


WITNESS_CHILD = """
import sys, time
sys.path.insert(0, {root!r})
from bruce_hw.host_witness import HostWitness, StallLog, stalled_union
w = HostWitness(); w.start()
print("ready", flush=True)
sys.stdin.readline()  # the parent stops and continues us, then writes a line
time.sleep(0.05)
print(w.worst_s, flush=True)
"""


def test_the_witness_sees_its_process_stopped():
    """SIGSTOP for 60 ms: every thread of the process stops, as in a VM stall; the witness records at least that."""
    root = str(REPO)
    child = subprocess.Popen([sys.executable, "-c", WITNESS_CHILD.format(root=root)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        time.sleep(0.05)
        os.kill(child.pid, signal.SIGSTOP)
        time.sleep(0.060)
        os.kill(child.pid, signal.SIGCONT)
        child.stdin.write("\n")
        child.stdin.flush()
        worst = float(child.stdout.readline())
    finally:
        child.kill()
        child.wait()
    assert worst >= 0.055


def test_a_stall_beyond_the_bound_trips_the_safety_stage_naming_its_length(config):
    witness = HostWitness()
    stage = running_stage(config)
    stage.stalled = witness.stalled_between
    bound = config.safety.host_stall_max_s
    now = 1.0
    stage.check(robot(config, stamp=now, imu_stamp=now), now=now)
    witness.record(now, now + bound + 0.010)
    now += bound + 0.011
    stage.check(robot(config, stamp=now, imu_stamp=now), now=now)  # fresh data after it: the stall itself trips
    assert stage.tripped and "host stall: this process was not run for" in stage.cause
    assert f"since the previous tick > safety.host_stall_max_s {1e3 * bound:g} ms" in stage.cause


def test_the_counts_restart_at_activation_and_the_log_stays():
    witness = HostWitness()
    witness.record(1.0, 1.030)  # during start-up
    witness.reset_counts(1.5)
    witness.record(2.0, 2.005)
    assert witness.report() == {"count": 1, "worst_ms": pytest.approx(5.0), "total_ms": pytest.approx(5.0)}
    assert witness.stalled_between(0.0, 3.0) == pytest.approx(0.035)


def test_a_stall_that_began_before_activation_is_not_the_runs():
    """The witness records a stall when it wakes: one that start-up began (the interpreter lock held by the full
    collection before the loop) and that ends after the activation is recorded then, and is start-up's; what
    follows it is counted again."""
    witness = HostWitness()
    witness.reset_counts(1.5)
    witness.record(1.48, 1.55)  # held from before the activation
    witness.record(1.48, 1.56)  # ... seen again, longer
    assert witness.report() == {"count": 0, "worst_ms": 0.0, "total_ms": 0.0}
    assert witness.stalled_between(1.5, 1.6) == pytest.approx(0.06)  # still left out of the data's age
    witness.record(1.6, 1.603)  # after it: the run's
    witness.record(2.0, 2.004)
    assert witness.report() == {"count": 2, "worst_ms": pytest.approx(4.0), "total_ms": pytest.approx(7.0)}


def test_a_stall_recorded_twice_is_counted_once():
    """The backend records a stall the witness has not yet woken to record; the witness's own record of it, later,
    extends that one stall by what lies beyond."""
    witness = HostWitness()
    witness.record(1.001, 1.031)  # the backend, from the witness's silence
    witness.record(1.001, 1.032)  # the witness, on waking
    assert witness.stalled_between(0.0, 2.0) == pytest.approx(0.031)
    assert witness.report() == {"count": 1, "worst_ms": pytest.approx(31.0), "total_ms": pytest.approx(31.0)}
    witness.record(1.010, 1.020)  # wholly inside: nothing
    assert witness.report()["count"] == 1
    assert witness.silent_since(witness.last_wake + 0.010) is None  # not watching: it cannot say
    witness.running = True
    assert witness.silent_since(witness.last_wake + 0.001) is None
    assert witness.silent_since(witness.last_wake + 0.010) == witness.last_wake


def test_a_stall_not_yet_recorded_counts_up_to_the_moment_asked():
    """Right after the process resumes, the loop may ask before the witness has woken: the witness's silence is the
    stall (here 30 ms since its last wake at t = 10)."""
    witness = HostWitness()
    witness.running, witness.last_wake = True, 10.0  # its thread, as if it had last woken at t = 10
    assert witness.stalled_between(9.990, 10.031) == pytest.approx(0.030)  # from its due wake-up, 10.001
    assert witness.stalled_between(9.990, 10.0015) == 0.0  # within its tolerance: not a stall
    witness.record(10.001, 10.031)  # then it wakes and records the same stall: counted once
    assert witness.stalled_between(9.990, 10.031) == pytest.approx(0.030)


# A few ms apart on a 0.1-ms grid: stalls that touch, overlap, extend one another or lie apart, and asks around them.
_ms = st.integers(0, 400).map(lambda k: k / 1e4)


@given(st.lists(st.tuples(_ms, st.integers(1, 300).map(lambda k: k / 1e4)), max_size=6),
       st.lists(st.tuples(_ms, _ms), min_size=1, max_size=8), st.one_of(st.none(), _ms))
def test_the_early_answers_agree_with_the_log(stalls, asks, open_since):
    """`stalled_between` answers 0 without the log when nothing recorded reaches the interval and no stall is in
    progress, and the silence rule passes a reading whose oldest sample cannot be stale without looking at each: both
    must give what the full computation gives (the log's intervals; each sample's age less the stalls)."""
    log = StallLog(open_since=lambda now: None if open_since is None or now <= open_since else open_since)
    start = 0.0
    for gap, length in stalls:  # recorded in time order, as the witness records them
        start += gap
        log.record(start, start + length)
    for a, b in asks:
        t0, t1 = min(a, b), max(a, b)
        assert log.stalled_between(t0, t1) == pytest.approx(sum(end - s for s, end in log.intervals(t0, t1)))
        now = t1 + 0.002
        samples = reading([t0, t1, now - 0.0005])
        ages = [now - t - log.stalled_between(t, now) for t in samples.stamps]
        judged = silence(IDS, samples, now, DT, MAX_AGE, log.stalled_between)
        assert (judged is None) == all(age + DT <= MAX_AGE for age in ages), (ages, judged)
