"""Where the nominal controller runs: on the control thread, or beside it (`rates.policy_lag_ticks`).

The controller's targets from the reading at a policy tick k take effect at tick k + lag:

- lag 0 (the default): computed on tick k and used on it, as every measured walk in docs/results was run.
- lag >= 1: the tick only hands the reading over; the targets are in force from tick k + lag on. On a robot
  computer this takes the policy's observation and ONNX call (on BRUCE's hw path the largest part of the tick's CPU
  time, on every 10th tick: docs/timing.md) off the control thread, as legged robots' deployments run the policy on a
  thread or process of its own beside a faster PD loop. `InlineControllerRunner` computes on the tick and holds the
  result back `lag` ticks: runs that are not paced (the rehearsal) use it, the same on any machine.
  `ThreadControllerRunner` computes on a thread of its own: paced runs (`--backend hw`, a paced mock) use it. A
  result not back by its tick is used from the first tick it is (counted: `late`); told to `wait` (tests), the tick
  waits for it, so a threaded run reproduces an inline one bit for bit. onnxruntime releases the GIL while the
  network runs; the observation's Python holds it for tens of µs (the hw backend keeps the switch interval short).

A controller error (a non-finite action) reaches the control thread at the tick the result was due, as a
`ModelError` there, and ends the run through damping as before.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from bruce_hw.types import FootContacts, ImuSample, JointState, RobotState
from runtime.control.inference import ModelError
from runtime.estimation import BaseEstimate
from runtime.loop.loopstats import Histogram
from runtime.loop.realtime import QueueWorker


@dataclass(slots=True)
class _Pending:
    tick: int           # the tick whose reading it is
    state: RobotState
    base: BaseEstimate
    command: np.ndarray


def snapshot(state: RobotState) -> RobotState:
    """A copy the control thread no longer touches (a backend may refill its arrays on the next read)."""
    j, imu, c = state.joints, state.imu, state.contacts
    return RobotState(
        joints=JointState(j.q.copy(), j.qd.copy(), j.tau.copy(), j.temperature.copy(), j.stamp),
        imu=ImuSample(imu.gyro.copy(), imu.accel.copy(), None if imu.orientation is None else imu.orientation.copy(),
                      imu.stamp),
        contacts=FootContacts(c.contact.copy(), c.stamp), estop=state.estop)


class InlineControllerRunner:
    """The controller on the control thread; its targets used `lag` ticks after the reading they came from."""

    where = "the control thread"

    def __init__(self, controller, lag_ticks: int):
        if lag_ticks < 0:
            raise ValueError(f"policy lag: expected ticks >= 0, got {lag_ticks}")
        self.controller, self.lag = controller, lag_ticks
        self.cpu = Histogram()  # the controller's own CPU time per call (µs): on its thread, apart from the tick's
        self.reset()

    def reset(self) -> None:
        self._due: list[tuple[int, np.ndarray | BaseException]] = []  # (tick due, targets or error), oldest first
        self.late = 0            # ticks a result was due and not yet back (threaded only)
        self.worst_late = 0      # the most ticks one result came after its due tick

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def post(self, tick: int, state: RobotState, base: BaseEstimate, command: np.ndarray) -> None:
        """The reading of policy tick `tick`: the controller runs on it."""
        self._due.append((tick + self.lag, self._run(state, base, command)))

    def _run(self, state: RobotState, base: BaseEstimate, command: np.ndarray) -> np.ndarray | BaseException:
        start = time.thread_time_ns()
        try:
            a = np.array(self.controller(state, base, command), dtype=np.float64)  # its own: the loop keeps it
        except ModelError as exc:  # raised on the control thread at the tick it was due
            a = exc
        self.cpu.add(time.thread_time_ns() - start)
        return a

    def targets(self, tick: int) -> np.ndarray | None:
        """The newest targets due at `tick` and not handed out before (None: none new)."""
        found = None
        while self._due and self._due[0][0] <= tick:
            found = self._due.pop(0)[1]
            if isinstance(found, BaseException):
                raise found
        return found

    def report(self) -> dict:
        cpu = {"p50": self.cpu.percentile(50), "p99": self.cpu.percentile(99)} if self.cpu.n else None
        return {"runs_on": self.where, "lag_ticks": self.lag, "calls": self.cpu.n, "cpu_us": cpu,
                "late_ticks": self.late, "worst_late_ticks": self.worst_late}


class ThreadControllerRunner(InlineControllerRunner):
    """The controller on a thread of its own (`lag_ticks` >= 1). `wait`: `targets` waits for a result due at the
    tick (reproducible, for tests); otherwise it never waits."""

    where = "a thread of its own"

    def __init__(self, controller, lag_ticks: int, wait: bool = False):
        if lag_ticks < 1:
            raise ValueError("a controller on its own thread needs rates.policy_lag_ticks >= 1 (its targets cannot "
                             "be used on the tick that asked for them without waiting for them)")
        self.wait = wait
        self._worker = QueueWorker("nominal-controller", self._work)
        self._done = threading.Condition()
        self._posted: list[int] = []  # due ticks posted and not yet handed out, oldest first (control thread only)
        super().__init__(controller, lag_ticks)

    def reset(self) -> None:
        self.close()
        super().reset()
        self._posted = []

    def start(self) -> None:
        """Start the thread, beside the loop (`runtime.loop.realtime.start_beside_the_loop`)."""
        self._worker.start()

    def close(self) -> None:
        self._worker.close()

    def post(self, tick: int, state: RobotState, base: BaseEstimate, command: np.ndarray) -> None:
        self.start()
        self._posted.append(tick + self.lag)
        self._worker.put(_Pending(tick + self.lag, snapshot(state), base, np.array(command, dtype=np.float64)))

    def _work(self, inputs: queue.SimpleQueue) -> None:
        while (pending := inputs.get()) is not None:
            try:
                result = self._run(pending.state, pending.base, pending.command)
            except BaseException as exc:  # any failure, not only a ModelError: raised on the control thread when due,
                result = exc              # which ends the run in damping (a dead worker would hold stale targets)
            with self._done:
                self._due.append((pending.tick, result))
                self._done.notify_all()
            if isinstance(result, BaseException):
                return

    def targets(self, tick: int) -> np.ndarray | None:
        if not self._posted or self._posted[0] > tick:
            return None
        with self._done:
            if self.wait:
                self._done.wait_for(lambda: len(self._due) > 0, timeout=5.0)
            found = None
            while self._due and self._due[0][0] <= tick:
                due, found = self._due.pop(0)
                self._posted.pop(0)
                self.worst_late = max(self.worst_late, tick - due)
                if isinstance(found, BaseException):
                    raise found
            if found is None:  # due and not back yet: the targets in force stay
                self.late += 1
            return found


def make_controller_runner(controller, lag_ticks: int, paced: bool) -> InlineControllerRunner:
    """On its own thread where the run is paced and the targets may come `lag_ticks` >= 1 late; else on the tick."""
    if paced and lag_ticks:
        return ThreadControllerRunner(controller, lag_ticks)
    return InlineControllerRunner(controller, lag_ticks)
