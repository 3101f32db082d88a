"""How a run ends: its exit code, and what SIGINT/SIGTERM do before and after the motors can move.

Imports nothing heavy, so that `bruce-run` can take over the signals before it loads numpy, MuJoCo or onnxruntime.
"""

from __future__ import annotations

import enum
import signal

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# A run's stop cause when a signal ended it: a tool that runs sessions for data or evaluation stops there (a run cut
# short by the operator is not a result).
INTERRUPTS = tuple(sig.name for sig in STOP_SIGNALS)
NOTHING_ENABLED = "before activation: no motor was enabled"  # how a stop during start-up is reported, everywhere


class ExitCode(enum.IntEnum):
    """`bruce-run`'s exit status, the same on every backend."""

    OK = 0           # the duration (or the recorder) ended the run, or the operator stopped it (SIGINT, SIGTERM)
    INTERNAL = 1     # an unexpected error: a bug to report
    BAD_INPUT = 2    # a config, gap profile, scenario, model file or option was refused (argparse's own code too)
    SAFETY_TRIP = 3  # the safety stage went to damping: tilt, e-stop, stale data, a model's output, late ticks
    BUS_FAULT = 4    # the backend lost a device: silence, reply loss, a device fault, a start-up that reached none


FAULT_CLASSES = {ExitCode.BAD_INPUT: "input", ExitCode.SAFETY_TRIP: "safety", ExitCode.BUS_FAULT: "bus",
                 ExitCode.INTERNAL: "internal"}


class StopRequested(BaseException):
    """SIGINT or SIGTERM before activation. A BaseException, like KeyboardInterrupt, so that no `except Exception`
    on the start-up path (a bus scan, a model load) swallows it."""


class StopFlag:
    """The handler of SIGINT and SIGTERM for one run. It always records the signal in `cause`. While `abort` is set
    (start-up, after the imports: nothing is enabled yet) it also raises StopRequested at once, wherever start-up
    is. It does not raise while modules load (an exception raised inside a C extension's initialisation comes out
    as an ImportError) nor once the motors may be enabled: there the loop polls `cause` every tick, so that the
    robot goes down through damping."""

    def __init__(self) -> None:
        self.cause: str | None = None
        self.abort = False
        self._previous: dict = {}

    def arm(self) -> None:
        """From now until `abort` is cleared a signal aborts start-up; one that came before aborts now."""
        self.abort = True
        if self.cause is not None:
            raise StopRequested(f"{self.cause} received")

    def __call__(self, signum, _frame) -> None:
        self.cause = signal.Signals(signum).name
        if self.abort:
            raise StopRequested(f"{self.cause} received")

    def install(self) -> StopFlag:
        for sig in STOP_SIGNALS:
            previous = signal.signal(sig, self)
            self._previous.setdefault(sig, previous)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
