"""Where the nominal controller runs (`rates.policy_lag_ticks`): on the tick, held back a tick, or on a thread of its
own beside the loop, and what the loop does with targets that come late."""

import contextlib
import io
import os
import threading
import time

import numpy as np
import pytest

from bruce_hw.config import ConfigError, load_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import FootContacts, ImuSample, JointState, RobotState
from runtime.control.commands import CommandSchedule
from runtime.control.controller_runner import (
    InlineControllerRunner,
    ThreadControllerRunner,
    make_controller_runner,
)
from runtime.control.inference import ModelError
from runtime.estimation import BaseEstimate
from runtime.loop import realtime
from runtime.loop.observers import TickObserver
from runtime.loop.run import run_session

N = 10
BASE = BaseEstimate(quat=np.array([1.0, 0, 0, 0]), linvel=np.zeros(3), angvel=np.zeros(3), euler=np.zeros(3))


def reading(value: float) -> RobotState:
    return RobotState(JointState(np.full(N, value), np.zeros(N), np.zeros(N), np.zeros(N), value),
                      ImuSample(np.zeros(3), np.array([0, 0, 9.81]), None, value),
                      FootContacts(np.zeros(4, bool), value))


def echoed(q, call: int, vx: float):
    """What `Echo` answers on its `call`-th call (a few mrad from the reading: inside every joint's target range)."""
    return q + 1e-3 * call + 1e-2 * vx


class Echo:
    """Targets = the reading's q plus its call count and the command's vx: each result says what it saw and when."""

    def __init__(self, delay_s: float = 0.0, fail_at: int | None = None):
        self.calls, self.delay_s, self.fail_at = 0, delay_s, fail_at
        self.seen, self.vx = [], []

    def reset(self, q):
        self.calls = 0
        self.seen, self.vx = [], []

    def __call__(self, state, base, command):
        self.calls += 1
        if self.fail_at == self.calls:
            raise ModelError("policy model echo.onnx: returned non-finite action")
        if self.delay_s:
            time.sleep(self.delay_s)
        self.seen.append(state.joints.q[0])
        self.vx.append(command[0])
        return echoed(state.joints.q, self.calls, command[0])


def drive(runner, ticks: int, decimation: int = 10) -> list:
    """The loop's use of a runner: post on every policy tick, ask for targets on every tick."""
    runner.reset()
    runner.start()
    out = []
    try:
        for tick in range(ticks):
            if tick % decimation == 0:
                runner.post(tick, reading(float(tick)), BASE, np.array([0.5, 0.0, 0.0]))
            targets = runner.targets(tick)
            out.append(None if targets is None else targets.copy())
    finally:
        runner.close()
    return out


def test_lag_zero_gives_the_targets_on_the_tick_that_read_them_and_lag_one_on_the_next():
    now = drive(InlineControllerRunner(Echo(), 0), 25)
    assert [t is not None for t in now] == [tick % 10 == 0 for tick in range(25)]
    np.testing.assert_array_equal(now[10], echoed(np.full(N, 10.0), 2, 0.5))
    late = drive(InlineControllerRunner(Echo(), 1), 25)
    assert [t is not None for t in late] == [tick % 10 == 1 for tick in range(25)]
    np.testing.assert_array_equal(late[11], now[10])
    with pytest.raises(ValueError, match="lag"):
        InlineControllerRunner(Echo(), -1)


def test_a_threaded_runner_told_to_wait_reproduces_the_inline_one_bit_for_bit():
    inline = drive(InlineControllerRunner(Echo(), 2), 95)
    threaded = ThreadControllerRunner(Echo(delay_s=0.002), 2, wait=True)
    result = drive(threaded, 95)
    assert len(result) == len(inline)
    for a, b in zip(inline, result, strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_array_equal(a, b)
    assert threaded.report()["runs_on"] == "a thread of its own" and threaded.report()["calls"] == 10
    with pytest.raises(ValueError, match="policy_lag_ticks >= 1"):
        ThreadControllerRunner(Echo(), 0)


class Held(Echo):
    """A controller that answers only once `release` is set: a result that is late for as long as a test says."""

    def __init__(self):
        super().__init__()
        self.release = threading.Event()

    def __call__(self, state, base, command):
        self.release.wait(5.0)
        return super().__call__(state, base, command)


def test_targets_not_back_by_their_tick_leave_the_ones_in_force_and_are_used_when_they_come():
    controller = Held()
    runner = ThreadControllerRunner(controller, 1)
    runner.reset()
    runner.start()
    try:
        runner.post(0, reading(3.0), BASE, np.zeros(3))
        assert runner.targets(0) is None    # not due yet
        assert runner.targets(1) is None    # due, still computing: the loop keeps what it has
        assert runner.targets(2) is None
        controller.release.set()
        deadline = time.monotonic() + 5.0
        targets = None
        tick = 3
        while targets is None and time.monotonic() < deadline:
            time.sleep(0.005)
            targets = runner.targets(tick)
            tick += 1
        np.testing.assert_array_equal(targets, echoed(np.full(N, 3.0), 1, 0.0))
        assert runner.late >= 2 and runner.worst_late >= 2
        assert runner.targets(tick) is None  # handed out once
    finally:
        runner.close()


def test_the_thread_computes_on_a_copy_of_the_reading():
    controller = Echo(delay_s=0.02)
    runner = ThreadControllerRunner(controller, 1, wait=True)
    runner.reset()
    runner.start()
    try:
        state = reading(1.0)
        runner.post(0, state, BASE, np.zeros(3))
        state.joints.q[:] = 99.0  # the backend refills its arrays at the next read
        np.testing.assert_array_equal(runner.targets(1), echoed(np.full(N, 1.0), 1, 0.0))
        assert controller.seen == [1.0]
    finally:
        runner.close()


class Broken(Echo):
    """A controller with a bug of its own (not a model error)."""

    def __call__(self, state, base, command):
        raise ZeroDivisionError("a controller's own bug")


def test_any_failure_on_the_thread_reaches_the_control_thread_not_only_a_model_error():
    runner = ThreadControllerRunner(Broken(), 1, wait=True)
    runner.reset()
    runner.start()
    try:
        runner.post(0, reading(0.0), BASE, np.zeros(3))
        with pytest.raises(ZeroDivisionError, match="own bug"):  # the loop then ends the run in damping
            runner.targets(1)
    finally:
        runner.close()


@pytest.mark.parametrize("threaded", [False, True])
def test_a_controller_error_reaches_the_control_thread_at_the_tick_it_was_due(threaded):
    runner = ThreadControllerRunner(Echo(fail_at=2), 1, wait=True) if threaded \
        else InlineControllerRunner(Echo(fail_at=2), 1)
    runner.reset()
    runner.start()
    try:
        runner.post(0, reading(0.0), BASE, np.zeros(3))
        assert runner.targets(1) is not None
        runner.post(10, reading(10.0), BASE, np.zeros(3))
        assert runner.targets(10) is None
        with pytest.raises(ModelError, match="non-finite action"):
            runner.targets(11)
    finally:
        runner.close()


def test_only_a_paced_run_with_a_lag_puts_the_controller_on_its_own_thread():
    assert type(make_controller_runner(Echo(), 0, paced=True)) is InlineControllerRunner
    assert type(make_controller_runner(Echo(), 1, paced=False)) is InlineControllerRunner
    assert type(make_controller_runner(Echo(), 1, paced=True)) is ThreadControllerRunner


def test_a_thread_beside_the_loop_leaves_the_loop_cpu_and_is_not_put_above_the_loop(monkeypatch):
    if not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs Linux affinity and two CPUs")
    allowed = sorted(os.sched_getaffinity(0))
    monkeypatch.setattr(realtime, "_loop_cpu", (allowed[-1], allowed, 50))  # as while a grant of SCHED_FIFO 50 holds
    seen = {}
    release = threading.Event()

    recorded = threading.Event()

    def work():
        seen["cpus"] = os.sched_getaffinity(0)
        seen["policy"], seen["priority"] = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
        recorded.set()
        release.wait(5.0)

    thread = realtime.start_beside_the_loop("beside-test", work)
    try:
        assert recorded.wait(5.0)
        assert seen["cpus"] == set(allowed[:-1])
        if _may_use_fifo():  # below the loop and its I/O threads, above normal work
            assert (seen["policy"], seen["priority"]) == (os.SCHED_FIFO, 50 - realtime.BESIDE_PRIORITY_STEPS)
        assert thread not in realtime.helper_threads()
        assert threading.current_thread() not in realtime.helper_threads()
    finally:
        release.set()
        thread.join(5.0)


def _may_use_fifo() -> bool:
    try:
        previous = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (AttributeError, OSError):
        return False
    os.sched_setscheduler(0, previous[0], previous[1])
    return True


def test_the_policy_lag_must_be_shorter_than_a_policy_period():
    assert load_config(overrides=["rates.policy_lag_ticks=9"]).policy_lag_ticks == 9
    with pytest.raises(ConfigError, match=r"rates\.policy_lag_ticks: expected fewer ticks than one policy period "
                                          r"\(10 ticks"):
        load_config(overrides=["rates.policy_lag_ticks=10"])
    with pytest.raises(ConfigError, match=r"rates\.policy_lag_ticks: expected an integer"):
        load_config(overrides=["rates.policy_lag_ticks=0.5"])


class TargetLog(TickObserver):
    def __init__(self):
        self.ticks = []

    def on_tick(self, view):
        self.ticks.append((view.tick, view.robot.joints.q.copy(), view.a.copy()))


def test_in_the_loop_the_targets_in_force_come_from_the_reading_lag_ticks_before(config):
    """A mock walk, not paced: with a lag of 3 ticks, the targets in force at tick t are the controller's answer to
    the reading of the last policy tick at or before t - 3, and the pose it was reset to before the first."""
    lagged = load_config(overrides=["rates.policy_lag_ticks=3"])
    controller = Echo()
    log = TargetLog()
    with contextlib.redirect_stdout(io.StringIO()):
        summary = run_session(MujocoBackend(lagged), lagged, duration=0.1, realtime=False, controller=controller,
                              estimator="kinematic", commands=CommandSchedule.constant(0.1, 0.0, 0.0),
                              observers=[log])
    assert summary.exit_code == 0 and summary.controller["lag_ticks"] == 3 and summary.controller["calls"] == 10
    start_pose = log.ticks[0][2]
    for _, _, a in log.ticks[:3]:
        np.testing.assert_array_equal(a, start_pose)
    readings = {tick: q for tick, q, _ in log.ticks}
    for tick, _, a in log.ticks[3:]:
        policy_tick = (tick - 3) // 10 * 10
        call = policy_tick // 10 + 1
        np.testing.assert_allclose(a, echoed(readings[policy_tick], call, controller.vx[call - 1]))
    assert controller.vx[-1] > controller.vx[0]  # the command (ramped up) reached the controller


def test_a_paced_mock_walk_runs_its_policy_on_a_thread_of_its_own(config):
    lagged = load_config(overrides=["rates.policy_lag_ticks=1"])
    with contextlib.redirect_stdout(io.StringIO()) as out:
        summary = run_session(MujocoBackend(lagged), lagged, duration=0.5, realtime=True,
                              commands=CommandSchedule.constant(0.4, 0.0, 0.0))
    assert summary.exit_code == 0 and summary.truth is not None and not summary.truth.fell
    report = summary.controller
    assert report["runs_on"] == "a thread of its own" and report["calls"] == 50
    assert report["cpu_us"]["p50"] > 0
    assert "controller: on a thread of its own, its targets 1 tick(s) after its reading" in out.getvalue()
    assert not any(t.name == "nominal-controller" for t in threading.enumerate())  # closed with the run
