"""The arms' thread (bruce_hw.hw.ArmHolder) on a fake arm bus: a silent bus becomes an error after
ARM_SILENCE_TO_FAULT_S of failed cycles; a thread that could not run for that long (a collection holding the GIL, a
busy machine) fails one cycle and is not a lost bus."""

import time

import numpy as np

from bruce_hw.config import load_config
from bruce_hw.hw import ARM_FAILED_CYCLES_TO_FAULT, ARM_SILENCE_TO_FAULT_S, ArmHolder
from drivers.errors import DriverError


class FakeArms:
    def __init__(self, script):
        self.script = list(script)  # per read: "ok", "fail", or ("stall", seconds) then fail
        self.reads = 0

    def read(self):
        self.reads += 1
        step = self.script.pop(0) if self.script else "ok"
        if isinstance(step, tuple):
            time.sleep(step[1])
            raise DriverError("no reply from ID(s) 11 (sync read)")
        if step == "fail":
            raise DriverError("no reply from ID(s) 11 (sync read)")
        return np.zeros(6), np.zeros(6)

    def close(self):
        pass


def run_holder(script, seconds: float, period_s: float = 0.02) -> ArmHolder:
    holder = ArmHolder(load_config(), ping_rounds=1, ping_retry_s=0.0, period_s=period_s)
    holder.arms = FakeArms(script)
    holder.start()
    time.sleep(seconds)
    holder._stop.set()
    holder.thread.join(timeout=2.0)
    return holder


def test_a_silent_arm_bus_becomes_an_error_after_the_silence_bound():
    holder = run_holder(["fail"] * 1000, ARM_SILENCE_TO_FAULT_S + 0.3)
    assert holder.error is not None and "no good cycle for" in holder.error, holder.error
    assert holder.failed_cycles >= ARM_FAILED_CYCLES_TO_FAULT and holder.cycles == 0


def test_a_thread_that_could_not_run_fails_one_cycle_not_the_bus():
    holder = run_holder([("stall", ARM_SILENCE_TO_FAULT_S + 0.1)], ARM_SILENCE_TO_FAULT_S + 0.4)
    assert holder.error is None
    assert holder.failed_cycles == 1 and holder.cycles > 0
