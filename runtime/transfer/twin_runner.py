"""Where the nominal twin runs, and the integral it feeds (`TwinIntegral`).

The twin scheme's integral has a time constant of seconds, so the twin's answer for tick k may arrive a few ticks
late without changing what the integral does. The control thread posts each tick's `TwinInput` and reads the
integral as it stood `lag_ticks` ago (`transfer.twin.lag_ticks`):

- `InlineTwinRunner`: the twin steps on the control thread as the input is posted. Runs that are not paced (the
  rehearsal) use it: the result is the same on any machine.
- `ThreadTwinRunner`: the twin steps on a thread of its own; the control thread's share is a queue put and a
  read. Paced runs (`--backend hw`, a paced mock) use it: the control thread never waits for the twin. MuJoCo's
  step and onnxruntime release the GIL, so the twin's physics and policy run beside the loop on the other core.
  Told to `wait` (tests), the control thread waits for exactly the lagged tick, so a threaded run reproduces an
  inline one bit for bit.

A twin that falls more than `MAX_BACKLOG_TICKS` behind (a paced run on a starved machine) is not posted to: the
integral holds, and the twin is resynchronised at the next policy tick once it has caught up (`TwinScheme`).
"""

from __future__ import annotations

import queue
import threading
from typing import NamedTuple

import numpy as np

from runtime.control.inference import ModelError
from runtime.loop.realtime import QueueWorker
from runtime.transfer.nominal_twin import NominalTwin, TwinInput

MAX_BACKLOG_TICKS = 200  # 0.2 s: beyond it the twin's offsets are too old to integrate on a 2 s time constant


# The command correction stays within these (vx m/s, vy m/s, yaw rate rad/s): a quarter of the policy's range.
COMMAND_CLIP = np.array([0.1, 0.1, 0.25])
# A change of the measured angle below this is not an encoder step (float round-off of a held reading).
RESOLUTION_FLOOR_RAD = 1e-9


class TwinOutput(NamedTuple):
    """What the integral gives the control thread at a tick."""

    u: np.ndarray         # the torque added to the inner scheme's: the integral less its dead band
    command: np.ndarray   # the command correction (vx, vy, yaw rate)
    engaged: np.ndarray   # per joint, 0..1: how far the integral is past its dead band (the inner correction's share)


class TwinIntegral:
    """u <- clip(u + gain (q_twin - q), +- clip) on every tick from `hold_ticks` on; an offset above `disturbance`
    on any joint is a push the twin did not feel: not integrated, and a resync is asked for (`step`'s result).

    The torque given out is u less a dead band (`dead_band`, per joint, N·m): where the robot is the simulator but
    for noise, quantisation or chatter, u wanders within a few hundredths of a N·m, and acting on that only adds the
    twin's own noise to a robot that needs nothing. A gap holds an offset, and u integrates through the band and on
    until the offset is gone: the band costs the correction no steady-state accuracy, only the time to integrate
    through it. `engaged` = clip(|u| / dead_band - 1, 0, 1) per joint: whether the twin sees an offset its own noise
    does not explain, given to the inner scheme as the share of its correction to apply (`TwinScheme`).

    With `resolution_counts` > 0 the band is at least that many of the joint's encoder steps (at Eq. 8 Kp, `kp`):
    the smallest change of the measured angle seen so far, a robot's own figure (an encoder read in counts changes
    by whole counts; a continuous signal with noise by ever smaller amounts, leaving the band as set). An offset
    below what the encoder resolves is not one the twin can tell from the quantisation.

    With `command_gain` > 0, also the command correction: on policy ticks, du_cmd <- clip(du_cmd + command_gain
    (v_twin - v), +- COMMAND_CLIP), v the robot's estimated (vx, vy, yaw rate) and v_twin the twin's estimator's on
    the same command: an integral on the velocity the policy leaves to its own tracking, added to the robot's
    command (never the twin's). The two estimators share their errors where the robot is the simulator, so it
    stays at zero there."""

    def __init__(self, twin: NominalTwin, gain: np.ndarray, clip: np.ndarray, hold_ticks: int,
                 disturbance: float = np.inf, command_gain: float = 0.0, dead_band: np.ndarray | None = None,
                 resolution_counts: float = 0.0, kp: np.ndarray | None = None):
        self.twin = twin
        self.gain, self.clip, self.hold_ticks = gain, clip, hold_ticks  # gain: N·m per rad of offset, per tick
        self.disturbance = disturbance
        self.command_gain = command_gain  # per policy tick, per (m/s or rad/s) of velocity difference
        self.dead_band = np.zeros_like(gain) if dead_band is None else np.asarray(dead_band, float)
        self.resolution_counts = float(resolution_counts)
        self.kp = np.zeros_like(gain) if kp is None else np.asarray(kp, float)
        self.reset()

    def reset(self) -> None:
        self.twin.reset()
        self.u = np.zeros_like(self.gain)
        self.command = np.zeros(3)  # the command correction
        self._last_tick = -2
        self.band = self.dead_band.copy()  # the dead band in force (N·m): at least `resolution_counts` steps
        self.resolution = np.full_like(self.gain, np.inf)  # the smallest change of each measured angle seen (rad)
        self._q_last: np.ndarray | None = None

    @property
    def banded(self) -> bool:
        """Whether there is a dead band: the inner scheme's correction then waits for the integral to pass it."""
        return bool(self.dead_band.any()) or self.resolution_counts > 0

    def output(self) -> TwinOutput:
        """The integral as the control thread uses it (new arrays: the integral never writes into them)."""
        band = self.band
        past = np.maximum(np.abs(self.u) - band, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            engaged = np.where(band > 0, np.minimum(past / band, 1.0), 1.0)
        return TwinOutput(np.sign(self.u) * past, self.command.copy(), engaged)

    def _see_resolution(self, q: np.ndarray) -> None:
        if self._q_last is not None:
            change = np.abs(q - self._q_last)
            self.resolution = np.where(change > RESOLUTION_FLOOR_RAD, np.minimum(self.resolution, change),
                                       self.resolution)
            seen = np.where(np.isfinite(self.resolution), self.resolution, 0.0)
            self.band = np.maximum(self.dead_band, self.resolution_counts * self.kp * seen)
        self._q_last = q

    def step(self, step: TwinInput) -> bool:
        """Compare the twin's posture predicted for this tick with the measured one, integrate, advance the twin;
        True when the offset looks like a push (resync wanted). A tick after a gap in the input (the twin fell
        behind) is not compared: the twin's posture is from before the gap."""
        request = False
        if self.resolution_counts:
            self._see_resolution(step.q)
        if self.twin.q is not None and step.tick == self._last_tick + 1:
            offset = self.twin.q - step.q
            if np.abs(offset).max() > self.disturbance:
                request = True  # integrated, a push would be pulled back along the twin's path
            elif step.tick >= self.hold_ticks:
                self.u = np.clip(self.u + self.gain * offset, -self.clip, self.clip)
                if self.command_gain and step.velocity is not None and self.twin.velocity is not None:
                    self.command = np.clip(self.command + self.command_gain * (self.twin.velocity - step.velocity),
                                           -COMMAND_CLIP, COMMAND_CLIP)
        self._last_tick = step.tick
        self.twin.advance(step)
        return request


class InlineTwinRunner:
    """The twin on the control thread; the integral read `lag_ticks` late, as the threaded runner reads it."""

    def __init__(self, integral: TwinIntegral, lag_ticks: int):
        self.integral, self.lag = integral, lag_ticks
        self._ring = [self._zero()] * (lag_ticks + 1)  # the integral's output after tick t, at t % len
        self.reset()

    def _zero(self) -> TwinOutput:
        """Before the twin's first answer: no torque, no command correction, the inner scheme not engaged."""
        zeros = np.zeros_like(self.integral.gain)
        return TwinOutput(zeros, np.zeros(3), zeros if self.integral.banded else np.ones_like(zeros))

    def reset(self) -> None:
        self.integral.reset()
        self._before = self._zero()
        self._ring = [self._before] * len(self._ring)
        self.done = -1           # the last tick the twin has stepped
        self.posted = -1         # the last tick posted
        self.request_tick = -1   # the last tick whose offset asked for a resync

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def post(self, step: TwinInput) -> None:
        self.posted = step.tick
        self._publish(step.tick, self.integral.step(step))

    def _publish(self, tick: int, request: bool) -> None:
        self._ring[tick % len(self._ring)] = self.integral.output()
        if request:
            self.request_tick = tick
        self.done = tick

    def backlog(self) -> int:
        """Ticks posted and not yet stepped."""
        return self.posted - self.done

    def u_at(self, tick: int) -> TwinOutput:
        """The integral's output as it stood after tick `tick - lag` (or the latest the twin has reached, if
        behind); `_zero()` before the first."""
        have = min(self.done, tick - self.lag)
        return self._ring[have % len(self._ring)] if have >= 0 else self._before

    def resync_asked(self, since: int, tick: int) -> bool:
        """Whether an offset after tick `since` and no later than `tick - lag` asked for a resync."""
        return since < self.request_tick <= tick - self.lag


class ThreadTwinRunner(InlineTwinRunner):
    """The twin on a thread of its own. `wait`: `u_at` waits for the lagged tick (reproducible, for tests);
    otherwise it never waits."""

    def __init__(self, integral: TwinIntegral, lag_ticks: int, wait: bool = False):
        self.wait = wait
        # With the I/O threads, one priority above the loop on its CPU, not beside it: on two CPUs the loop keeps its
        # rate better so (docs/transfer.md, "Running a scheme on the robot").
        self._worker = QueueWorker("nominal-twin", self._work, beside=False)
        self._stepped = threading.Condition()
        self.error: BaseException | None = None
        super().__init__(integral, lag_ticks)

    def reset(self) -> None:
        self.close()  # the worker's queue and state go with it
        self.error = None
        super().reset()

    def start(self) -> None:
        self._worker.start()

    def close(self) -> None:
        self._worker.close()

    def post(self, step: TwinInput) -> None:
        if self.error is not None:
            raise ModelError(f"nominal twin: {type(self.error).__name__}: {self.error}")
        self.start()
        self.posted = step.tick
        self._worker.put(step)

    def _work(self, inputs: queue.SimpleQueue) -> None:
        while (step := inputs.get()) is not None:
            try:
                request = self.integral.step(step)
            except BaseException as exc:  # reported on the control thread at its next post
                self.error = exc
                with self._stepped:
                    self._stepped.notify_all()
                return
            self._publish(step.tick, request)
            if self.wait:
                with self._stepped:
                    self._stepped.notify_all()

    def u_at(self, tick: int) -> TwinOutput:
        if self.wait:
            wanted = min(tick - self.lag, self.posted)
            with self._stepped:
                self._stepped.wait_for(lambda: self.done >= wanted or self.error is not None, timeout=5.0)
            if self.error is not None:
                raise ModelError(f"nominal twin: {type(self.error).__name__}: {self.error}")
        return super().u_at(tick)
