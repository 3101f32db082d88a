"""The pacer on a fake clock (runtime/loop/pacing.py, docs/timing.md "The loop after an overrun"): an on-time tick
sleeps to its deadline, a late one runs at once, whole periods missed are skipped and counted, never run in a burst."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from runtime.loop import pacing

PERIOD_NS = 1_000_000
SPIN_TURN_NS = 1_000


class FakeClock:
    """time.monotonic_ns and time.sleep on a clock that only sleeps and `work` advance; each sleep is recorded."""

    def __init__(self):
        self.now_ns = 0
        self.sleeps_ns: list[int] = []
        self.naps: list[tuple[int, int]] = []  # (start, end) of each sleep longer than a spin's turn

    def monotonic_ns(self) -> int:
        return self.now_ns

    def sleep(self, seconds: float) -> None:
        self.sleeps_ns.append(round(seconds * 1e9))
        start = self.now_ns
        self.now_ns += max(round(seconds * 1e9), SPIN_TURN_NS)  # sleep(0), a turn of the spin, takes 1 us here
        if seconds > 0:
            self.naps.append((start, self.now_ns))

    def work(self, ns: int) -> None:
        self.now_ns += ns


@pytest.fixture
def clock(monkeypatch):
    fake = FakeClock()
    monkeypatch.setattr(pacing, "time", SimpleNamespace(monotonic_ns=fake.monotonic_ns, sleep=fake.sleep))
    return fake


def _pacer(monkeypatch, fifo: bool, **options) -> pacing.Pacer:
    monkeypatch.setattr(pacing, "_fifo", lambda: fifo)
    pacer = pacing.Pacer(PERIOD_NS / 1e9, **options)
    pacer.start()
    return pacer


def test_a_late_tick_runs_after_a_breath_and_skips_the_periods_it_missed(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=True)
    clock.work(3_400_000)  # the tick overran its deadline by 2.4 ms
    clock.sleeps_ns.clear()
    behind = pacer.wait()
    # 3.4 ms without a sleep: the real-time loop sleeps 50 us (the tty worker on its CPU runs then), no longer
    assert clock.sleeps_ns == [50_000] and behind == 2_450_000 and pacer.breaths == 1
    assert pacer.late_ticks == 1 and pacer.skipped_ticks == 2  # two whole periods missed, not run in a burst
    assert pacer.deadline_ns == 4_000_000  # this tick stands for the period from 3 ms; the next one is due at 4


def test_a_real_time_loop_never_goes_a_period_without_a_sleep(clock, monkeypatch):
    """Ticks of 0.3-1.2 ms of work: the on-time ones sleep to their deadline and do not breathe; a tick that starts
    after a period without a sleep (late or not) breathes first. No stretch without a sleep is longer than a period
    and the tick that noticed it."""
    pacer = _pacer(monkeypatch, fifo=True)
    for work_ns in [900_000, 1_150_000, 1_100_000, 1_200_000, 300_000, 900_000, 1_050_000, 400_000] * 20:
        clock.work(work_ns)
        pacer.wait()
    awake = [start - end for (_, end), (start, _) in zip(clock.naps[:-1], clock.naps[1:], strict=True)]
    assert pacer.breaths > 0 and clock.sleeps_ns.count(50_000) == pacer.breaths
    assert max(awake) <= PERIOD_NS + 1_200_000
    on_time = _pacer(monkeypatch, fifo=True)
    for _ in range(50):
        clock.work(900_000)
        on_time.wait()
    assert on_time.breaths == 0


def test_at_normal_priority_it_never_breathes(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=False)
    for _ in range(10):
        clock.work(3_400_000)
        pacer.wait()
    assert pacer.breaths == 0 and 50_000 not in clock.sleeps_ns


def test_a_tick_within_late_after_s_is_on_time(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=True, breath_s=0.0)
    clock.work(PERIOD_NS + 200_000)  # 200 us past the deadline: not late (late_after_s 250 us)
    assert pacer.wait() == 200_000 and pacer.late_ticks == 0 and pacer.skipped_ticks == 0


def test_on_time_it_sleeps_to_the_deadline(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=True)
    clock.work(300_000)
    clock.sleeps_ns.clear()
    assert pacer.wait() == 0
    assert clock.sleeps_ns == [700_000] and pacer.late_ticks == 0


def test_at_normal_priority_it_sleeps_then_spins_to_the_deadline(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=False)
    clock.work(300_000)
    clock.sleeps_ns.clear()
    assert pacer.wait() == 0
    assert clock.sleeps_ns == [500_000] + [0] * 200  # the last 200 us spun on sleep(0), which yields the GIL
    assert pacer.late_ticks == 0


def test_at_normal_priority_a_late_tick_runs_at_once(clock, monkeypatch):
    pacer = _pacer(monkeypatch, fifo=False)
    clock.work(1_600_000)
    clock.sleeps_ns.clear()
    assert pacer.wait() == 600_000
    assert clock.sleeps_ns == [] and pacer.late_ticks == 1 and pacer.skipped_ticks == 0


def test_late_ticks_are_split_into_the_machine_s_the_loop_s_own_and_the_loop_not_run():
    """A late tick with a host stall in the period before it is the machine's; one whose own CPU time since the
    previous tick's start alone ran past the deadline by more than the late bound is the loop's; the rest had the
    loop ready and not run."""
    from runtime.loop.loopstats import LoopStats

    stats = LoopStats()
    stats.period_s, stats.late_after_s = 1e-3, 250e-6
    stats.overrun(3_000_000, at_s=10.0, own_ns=100_000)    # a stall covers it: the machine's, whatever the CPU
    stats.overrun(600_000, at_s=20.0, own_ns=400_000)      # 400 µs past on its own CPU time alone: the loop's
    stats.overrun(600_000, at_s=30.0, own_ns=200_000)      # its CPU alone would have been 200 µs late: not run
    stats.overrun(300_000, at_s=40.0, own_ns=-500_000)     # woke late from its sleep: not run
    stats.late_ticks, stats.ticks = 4, 1000
    stats.attribute(lambda t0, t1: 0.003 if t0 <= 10.0 <= t1 + 0.001 and t1 <= 10.0 else 0.0)
    j = stats.to_json()
    assert (j["late_ticks_machine"], j["late_ticks_loop"], j["late_ticks_not_run"]) == (1, 1, 2)
    assert j["late_share_loop"] == pytest.approx(0.001)
    assert "1 with the host stalled, 1 of the loop's own CPU time, 2 with the loop ready and not run" in stats.text()
    stats.attribute(None)  # no witness (the paced mock): nothing is the machine's
    assert (stats.late_machine, stats.late_own, stats.late_not_run) == (0, 1, 3)


def test_the_costliest_tick_is_kept_with_its_sections():
    """One tick whose policy took 9 ms of CPU among ticks of 200 µs: the stats name it and the section it went to."""
    from runtime.loop.loopstats import LoopStats

    def marks(policy_us: int, base: int) -> tuple[int, ...]:
        steps = (40, policy_us, 10, 0, 20, 30, 50, 10)  # read, policy, Eq. 8, PINN, mixing, safety, write, telemetry
        out = [base]
        for step in steps:
            out.append(out[-1] + 1000 * step)
        return tuple(out)

    stats = LoopStats()
    assert stats.to_json()["costliest_tick"] is None
    for tick in range(50):
        policy = 9000 if tick == 17 else 40
        stats.add_sections(marks(policy, 10_000_000 * tick), marks(policy, 5_000_000 * tick))
        stats.ticks = tick + 1
    costliest = stats.to_json()["costliest_tick"]
    assert costliest["tick"] == 17 and costliest["cpu_us"] == pytest.approx(9160)
    assert max(costliest["sections_cpu_us"], key=costliest["sections_cpu_us"].get) == "policy"
    assert costliest["sections_cpu_us"]["policy"] == pytest.approx(9000)


def test_a_long_tick_breathes_inside_once_it_has_gone_mid_tick_s_without_a_sleep(clock, monkeypatch):
    """The loop calls `breathe` after its costliest section: a tick that has run 0.5 ms since the loop last slept
    sleeps 50 us there (a worker on its CPU runs), once; a shorter one does not, and neither does a loop at normal
    priority."""
    pacer = _pacer(monkeypatch, fifo=True)
    clock.work(300_000)
    pacer.wait()  # sleeps to the deadline
    clock.sleeps_ns.clear()
    clock.work(400_000)
    pacer.breathe()
    assert clock.sleeps_ns == [] and pacer.breaths == 0
    clock.work(200_000)
    pacer.breathe()
    assert clock.sleeps_ns == [50_000] and pacer.breaths == 1
    clock.work(300_000)  # 0.3 ms since that breath
    pacer.breathe()
    assert pacer.breaths == 1
    assert pacer.wait() == 0 and pacer.late_ticks == 0  # the tick still ends before its deadline
    normal = _pacer(monkeypatch, fifo=False)
    clock.work(3_000_000)
    normal.breathe()
    assert normal.breaths == 0
