"""Where the shadow's reference model steps: on the control thread, or beside the loop.

The shadow's step at tick k (`ShadowScheme.predict`) gives its state at tick k + 1: nothing on tick k uses it. So a
paced run (`--backend hw`, a paced mock) asks for it on a thread beside the loop (`ThreadShadowStepper`: the other
CPUs, below the loop, `runtime.loop.realtime.start_beside_the_loop`) and takes the answer at tick k + 1; the PINN's
call, the shadow's largest cost on the tick (docs/results/timing.md), leaves the control thread without adding a tick
of latency. onnxruntime releases the GIL while the network runs.

- The answer is waited for at most `ANSWER_WAIT_S` at tick k + 1. One not back by then is not used: that tick the
  shadow starts again from the measured state (a resync, as every `transfer.shadow.resync_ticks`; its torque is then
  tau*, direct transfer), counted as `late`.
- One step at a time: while one is still running, the next tick's is not asked (`skipped`), and the tick after it
  resyncs. The PINN's LSTM state then misses a tick of its history, as on a missed deadline (docs/timing.md).
- An error in the step (a non-finite prediction) reaches the control thread at the tick its answer was due, as a
  `ModelError`, and ends the run in damping there.
- Only a reference model whose step reads nothing but its arguments (`PinnReference.self_contained`) steps beside
  the loop; the nominal MuJoCo model reads the robot's base estimate as it steps, and stays on the tick.

Runs that are not paced (the rehearsal) step on the tick (`InlineShadowStepper`), the same on any machine; told to
`wait` (tests), the threaded stepper waits for every answer, and reproduces the inline one bit for bit.
"""

from __future__ import annotations

import queue
import threading

import numpy as np

from runtime.control.inference import ModelError
from runtime.loop.realtime import QueueWorker

# How long tick k + 1 waits for the step asked at tick k (which had the rest of tick k's period): an answer later
# than this is one whose thread was not run, and waiting longer would make the tick late for it.
ANSWER_WAIT_S = 0.0002


class InlineShadowStepper:
    """The reference model stepped on the control thread as it is asked."""

    where = "the control thread"

    def __init__(self, reference):
        self.reference = reference
        self.reset()

    def reset(self) -> None:
        self.late = 0      # answers not back in time (threaded only)
        self.skipped = 0   # ticks not asked because the step before was still running (threaded only)
        self._answer: tuple[int, object] | None = None  # (tick asked, its answer)
        self._taken: tuple[int, tuple[np.ndarray, np.ndarray] | None] | None = None  # answer() once per tick

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def ask(self, tick: int, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> None:
        """Step from (q, qd) under tau: the state at tick `tick` + 1. The arrays are the stepper's to keep."""
        self._answer = (tick, self.reference.step(q, qd, tau))

    def answer(self, tick: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The step asked at `tick`, or None: not asked, or not back in time. The same on every call for one tick."""
        if self._taken is None or self._taken[0] != tick:
            self._taken = (tick, self._take(tick))
        return self._taken[1]

    def _take(self, tick: int):
        return self._answer[1] if self._answer is not None and self._answer[0] == tick else None

    def report(self) -> dict:
        return {"steps_on": self.where, "late": self.late, "skipped": self.skipped}


class ThreadShadowStepper(InlineShadowStepper):
    """The reference model stepped on a thread beside the loop. `wait`: every answer is waited for (tests)."""

    where = "a thread beside the loop"

    def __init__(self, reference, wait: bool = False):
        self.wait = wait
        self._worker = QueueWorker("shadow-step", self._work)
        self._done = threading.Condition()
        super().__init__(reference)

    def reset(self) -> None:
        self.close()  # the worker is idle before the reference model is reset
        super().reset()
        self._asked: int | None = None  # the tick of the last step asked

    def start(self) -> None:
        """Start the thread (before the loop: a thread's first start costs the tick that makes it)."""
        self._worker.start()

    def close(self) -> None:
        self._worker.close()

    def ask(self, tick: int, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> None:
        asked = self._asked
        if asked is not None:
            with self._done:
                running = self._answer is None or self._answer[0] != asked
            if running:
                self.skipped += 1
                return
        self.start()
        self._asked = tick
        self._worker.put((tick, q, qd, np.array(tau, dtype=float)))

    def _work(self, inputs: queue.SimpleQueue) -> None:
        while (item := inputs.get()) is not None:
            tick, q, qd, tau = item
            try:
                result = self.reference.step(q, qd, tau)
            except BaseException as exc:  # raised on the control thread at the tick it was due
                result = exc
            with self._done:
                self._answer = (tick, result)
                self._done.notify_all()
            if isinstance(result, BaseException):
                return

    def _take(self, tick: int):
        if self._asked != tick:
            return None
        with self._done:
            self._done.wait_for(lambda: self._answer is not None and self._answer[0] == tick,
                                timeout=5.0 if self.wait else ANSWER_WAIT_S)
            answer = self._answer
        if answer is None or answer[0] != tick:
            self.late += 1
            return None
        result = answer[1]
        if isinstance(result, ModelError):
            raise result
        if isinstance(result, BaseException):
            raise ModelError(f"shadow's reference model: {type(result).__name__}: {result}")
        return result


def make_shadow_stepper(reference, paced: bool) -> InlineShadowStepper:
    """Beside the loop where the run is paced and the model's step reads nothing but its arguments; else on the
    tick."""
    if paced and getattr(reference, "self_contained", False):
        return ThreadShadowStepper(reference)
    return InlineShadowStepper(reference)
