"""When the arm bus counts as lost (bruce_hw.arm_holder.ArmSilence, the arms' thread's rule), on hand-made cycle
times: a silent bus becomes lost after ARM_SILENCE_TO_FAULT_S of failed cycles; a thread that could not run
for that long (a collection holding the GIL, a busy machine) fails one cycle and is not a lost bus."""

from bruce_hw.arm_holder import ARM_FAILED_CYCLES_TO_FAULT, ARM_PERIOD_S, ARM_SILENCE_TO_FAULT_S, ArmSilence


def test_a_silent_arm_bus_is_lost_after_the_silence_bound():
    silence = ArmSilence(now=0.0)
    verdicts = [silence.failed(k * ARM_PERIOD_S) for k in range(1, 40)]  # every cycle fails, 20 ms apart
    lost = [k for k, v in enumerate(verdicts, 1) if v is not None]
    assert lost, "never lost"
    first = lost[0]
    assert first * ARM_PERIOD_S > ARM_SILENCE_TO_FAULT_S >= (first - 1) * ARM_PERIOD_S  # the first cycle past it
    assert verdicts[first - 1] == first * ARM_PERIOD_S and first >= ARM_FAILED_CYCLES_TO_FAULT


def test_a_thread_that_could_not_run_fails_one_cycle_not_the_bus():
    silence = ArmSilence(now=0.0)
    silence.good(0.02)
    stalled = 0.02 + ARM_SILENCE_TO_FAULT_S + 0.1  # the next cycle ran this late, and failed
    assert silence.failed(stalled) is None
    silence.good(stalled + ARM_PERIOD_S)
    assert silence.failed(stalled + 2 * ARM_PERIOD_S) is None  # counted afresh after the good cycle


def test_failed_cycles_in_row_alone_are_not_enough_before_the_silence_bound():
    silence = ArmSilence(now=0.0)
    assert all(silence.failed(1e-3 * k) is None for k in range(1, 4 * ARM_FAILED_CYCLES_TO_FAULT))
