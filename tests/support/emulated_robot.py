"""The emulated robot's settings for tests of the hw backend against `bruce-emulate --lockstep`
(bruce_hw/test_hw_backend.py, bruce_hw/test_hw_safety.py, bruce_hw/test_host_stalls.py, the emulated bring-up,
runtime/transfer/test_robot_faithful.py) and the root conftest's `hw_config` fixture."""

# These tests check what happens (which fault, which device, damping, watchdogs), not the 1 kHz timing (benchmarked
# in bench/): beside the host on two shared cores, an IMU packet is sometimes late by tens of milliseconds, so the
# rate-floor and data-age trips get the widest room the config allows, the host-stall bound too (with the BEARs'
# watchdog at 100 ms to stay above it; bruce_hw/test_host_stalls.py tests the bound itself at the shipped 50 ms
# watchdog), and so does a BEAR reply's wait (an emulator
# or a kernel tty worker kept off its CPU by a busy process, not a lost reply). Lost replies are tested at the config's
# bounds.
WALL_CLOCK_SLACK = ["safety.min_rate_hz=50", "safety.rate_window_s=1.0", "safety.max_sensor_age_s=0.05",
                    "buses.bear.reply_timeout_s=0.02", "buses.bear.watchdog_s=0.1", "safety.host_stall_max_s=0.09"]
BEAR_IDS = tuple(range(1, 11))
DXL_IDS = tuple(range(11, 17))

# A torque pattern with every joint's sign and size different, so a mixed-up joint or coupling shows
TEST_TORQUES = (0.5, 1.0, -1.0, 0.5, 0.2, -0.5, 1.0, -1.0, -0.5, -0.2)


def drive_torques(backend, ticks: int = 20):
    """Activate an in-process hw backend and send TEST_TORQUES for `ticks` ticks; the joint torques sent and the last
    state read. The read after the last write sends it (the bus thread posts on read)."""
    import time

    import numpy as np

    from bruce_hw import JointCommand

    tau = np.array(TEST_TORQUES)
    backend.activate()
    state = None
    for _ in range(ticks):
        state = backend.read()
        backend.write(JointCommand(tau_ff=tau))
        time.sleep(0.001)
    backend.read()
    return tau, state
