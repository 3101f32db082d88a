"""The arms: six Dynamixels held at `arms.hold_pose` on a 50 Hz thread of their own, and the rule by which their bus
counts as lost (`ArmSilence`)."""

from __future__ import annotations

import logging
import math
import threading
import time

from bruce_hw.bus_startup import StartupError, ids_text
from bruce_hw.config import RobotConfig

log = logging.getLogger("bruce_hw.hw")

ARM_PERIOD_S = 0.02           # BRUCE runs its arms at 50 Hz
# No good arm cycle for this long counts as a lost arm bus. Single cycles get lost on a loaded host: the driver's
# collect_status tests the SDK's packet timeout before reading what arrived meanwhile, so a thread kept off the CPU
# (or the GIL, e.g. while the runtime compiles its MuJoCo models) past the timeout drops a reply that was there.
ARM_SILENCE_TO_FAULT_S = 0.3
# ... and only after this many failed cycles in a row: a thread that could not run (a long collection holding the
# GIL, a busy machine) fails one cycle, however long it waited; a silent bus fails every cycle of the 0.3 s.
ARM_FAILED_CYCLES_TO_FAULT = 5


class ArmSilence:
    """When the arm bus counts as lost: no good cycle for ARM_SILENCE_TO_FAULT_S and at least
    ARM_FAILED_CYCLES_TO_FAULT failed cycles in a row."""

    def __init__(self, now: float):
        self.last_good = now
        self.failed_in_row = 0

    def good(self, now: float) -> None:
        self.last_good, self.failed_in_row = now, 0

    def failed(self, now: float) -> float | None:
        """Count a failed cycle; the silence so far (s) when the bus counts as lost, else None."""
        self.failed_in_row += 1
        silent_s = now - self.last_good
        if silent_s > ARM_SILENCE_TO_FAULT_S and self.failed_in_row >= ARM_FAILED_CYCLES_TO_FAULT:
            return silent_s
        return None


class ArmHolder:
    """The arms on their own thread at 50 Hz: a sync read every cycle and, once asked to hold, goal positions
    ramped from the measured pose to arms.hold_pose. A servo error, or no good cycle for `ARM_SILENCE_TO_FAULT_S`,
    sets `error` (the backend faults on it). The port belongs to the thread once it runs."""

    def __init__(self, config: RobotConfig, *, ping_rounds: int, ping_retry_s: float, ramp_s: float = 1.0,
                 period_s: float = ARM_PERIOD_S):
        self.config = config
        self.name = f"Dynamixel bus {config.buses.dynamixel.port}"
        self.ping_rounds, self.ping_retry_s = ping_rounds, ping_retry_s
        self.ramp_s, self.period_s = ramp_s, period_s
        self.arms = None
        self.error: str | None = None
        self.q = self.qd = None
        self.stamp = -math.inf
        self.cycles = 0
        self.failed_cycles = 0
        self._hold = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> None:
        from drivers.dynamixel import DynamixelArms
        from drivers.errors import BusTimeout, DriverError

        missing: tuple[int, ...] = ()
        for attempt in range(self.ping_rounds):
            if attempt:
                time.sleep(self.ping_retry_s)
            try:
                self.arms = DynamixelArms.from_config(self.config)  # ping all, set up with torque off
                return
            except BusTimeout as exc:
                missing = exc.silent_ids
            except DriverError as exc:
                raise StartupError([f"{self.name}: {exc}"]) from exc
        raise StartupError([f"{self.name}: no reply from Dynamixel ID(s) {ids_text(missing)} after "
                            f"{self.ping_rounds} ping rounds"])

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="hw-arms", daemon=True)
        self._thread.start()

    @property
    def thread(self) -> threading.Thread | None:
        return self._thread

    def hold(self) -> None:
        """Torque on and ramp to the hold pose (done by the thread)."""
        self._hold.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        if self.arms is not None:
            self.arms.close()  # torque off, as BRUCE-OP's run_dxl on exit
            self.arms = None

    def _run(self) -> None:
        from drivers.errors import DeviceFault

        arms, target = self.arms, self.config.arms.hold_pose
        start = None
        ramp_t0 = 0.0
        silence = ArmSilence(time.monotonic())
        deadline = time.monotonic()
        while not self._stop.wait(max(0.0, deadline - time.monotonic())):
            deadline = max(deadline + self.period_s, time.monotonic())
            try:
                if self._hold.is_set():
                    if start is None:
                        measured = arms.read()[0]
                        arms.write_positions(measured)  # goal = measured before torque on: no jump
                        arms.enable_torque()
                        start, ramp_t0 = measured, time.monotonic()
                    share = min(1.0, (time.monotonic() - ramp_t0) / self.ramp_s) if self.ramp_s > 0 else 1.0
                    arms.write_positions(start + (target - start) * share)
                self.q, self.qd = arms.read()
                self.stamp = time.monotonic()
                silence.good(self.stamp)
                self.cycles += 1
            except DeviceFault as exc:
                self.error = self.error or f"arm bus {exc}"
            except Exception as exc:  # DriverError, and whatever a vanished port raises (termios.error, OSError)
                self.failed_cycles += 1
                log.debug("arms: %s", exc)
                silent_s = silence.failed(time.monotonic())
                if silent_s is not None:
                    self.error = self.error or f"arm bus {exc} (no good cycle for {1e3 * silent_s:.0f} ms)"
