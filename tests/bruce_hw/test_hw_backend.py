"""The hw backend through the real stack: `bruce-emulate` in a child process (the emulated robot is other hardware,
as the real one is: byte-exact BEAR, Dynamixel and sense-board emulators on pseudo-terminals, driven by the MuJoCo
physics stepped once per host bulk cycle: `--lockstep`), the drivers, the hw backend and the runtime's session
loop. Faults are injected through bruce-emulate's stdin commands from inside the control loop (a command source's
`at()`), so their moment is known.

Fault -> damping is bounded in bulk cycles, the emulators' virtual time (the physics steps once per cycle), as the
emulator counts them (FaultInCycles), not in seconds: a busy machine slows the cycles, not the count. The 10 ms damping
goal is a timing goal, measured in bench/bench_hw_emulated.py. (A stopped IMU stream is judged by its data age, wall
clock by design: that test still says "not before max_sensor_age_s" in seconds.)
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from support.emulated_robot import WALL_CLOCK_SLACK, drive_torques

from bruce_hw import BackendError, LifecycleState
from bruce_hw.attitude import MahonyAttitude
from bruce_hw.bear_legs import actuator_position_limits
from bruce_hw.config import load_config
from bruce_hw.emulation.process import FaultAt, reply_time
from bruce_hw.hw import HwBackend, make_hw_backend, missing_for_hw
from runtime.loop.exit import ExitCode
from runtime.loop.observers import TickObserver
from runtime.loop.run import run_session

pytestmark = pytest.mark.usefixtures("no_memory_lock")
# Paced, as every hw run is (the legs' bus thread cycles on the loop's writes; an unpaced loop would spin on one
# reading). The emulators run in lockstep (the physics steps once per host bulk cycle), and WALL_CLOCK_SLACK keeps
# the rate floor and the data age out of the way of a loaded machine; 1 kHz timing is benchmarked in
# bench/bench_hw_emulated.py.
REALTIME = True
# Cycles a fault's count may hold beside the ones its rule needs: the tick that reads the reading which trips may
# have started one more (its own write, or the bus thread's own cycle a period after the last), and the fault waits for
# the one in flight when it stops the bus thread. While the loop runs late the bus thread cycles on its own, at most
# once a period: the run's skipped ticks are added.
CYCLE_SLACK = 3


class FaultInCycles(FaultAt, TickObserver):
    """FaultAt that counts the bulk cycles from its fault to the backend's damping as the emulator saw them (its
    virtual time: the physics steps once per cycle); pass it as the session's command source and as an observer.
    `status` is posted right after the command and answered after it (one stdin thread, in order): the count starts
    at that status's BULK_COMM count, at or after the fault, so it can miss a cycle but never adds one, and an upper
    bound on it holds however late the emulator answers. It ends once the loop has ended and the bus thread stopped,
    before the damping hold reads on (`on_end`), or after the run when the loop raised."""

    def __init__(self, emulator, command: str):
        super().__init__(emulator, command)
        self.cycles: int | None = None
        self.took_effect: float | None = None  # monotonic, the emulator's "ok" stamp

    def at(self, t: float):
        sending = t >= self.t and not self.sent
        command = super().at(t)
        if sending:
            self.emulator.post("status")
        return command

    def on_end(self, summary) -> None:
        self.count()

    def count(self) -> tuple[int, float]:
        """(bulk cycles from the fault to now, when the fault took effect); counted once."""
        if self.cycles is None:
            self.took_effect = reply_time(self.emulator.reply())
            start = json.loads(self.emulator.reply().removeprefix("status "))["bear"]["bulk_comm"]
            self.cycles = self.emulator.status()["bear"]["bulk_comm"] - start
        return self.cycles, self.took_effect


def test_bruce_emulate_prints_the_command_line(emulator):
    assert emulator.command_line[:3] == ["bruce-run", "--backend", "hw"]
    keys = [item.split("=")[0] for item in emulator.overrides]
    assert keys == ["buses.bear.port", "buses.dynamixel.port", "buses.sense.port"]


def test_silent_bear_ids_reach_damping_naming_bus_and_ids(emulator, hw_config, tmp_path):
    backend = make_hw_backend(hw_config, check_imu=False)
    stats = tmp_path / "stats.json"
    fault = FaultInCycles(emulator, "silence bear 3 4")
    with pytest.raises(BackendError) as info:
        run_session(backend, hw_config, duration=3.0, realtime=REALTIME, controller_kind="standing", commands=fault,
                    observers=[fault], stats_path=stats)
    cycles, silenced_at = fault.count()
    message = str(info.value)
    assert hw_config.buses.bear.port in message and "ID(s) 3, 4" in message, message
    assert backend.fault_cause is not None and "3, 4" in backend.fault_cause
    assert backend.fault_stamp > silenced_at
    # The backend counts a silent BEAR's missed replies per bulk cycle (bear_legs.ReplyLoss): more than
    # safety.reply_loss_max of the window, i.e. the 31st missed reply in a row at 3 % of 1000 cycles, is silence. The
    # data-age bound (max_sensor_age_s of wall clock, 50 cycles at 1 kHz here) can only trip it in fewer cycles, on a
    # slow machine.
    safety = hw_config.safety
    window = max(1, round(safety.reply_loss_window_s * hw_config.loop_hz))
    rule = math.floor(safety.reply_loss_max * window) + 1
    skipped = json.loads(stats.read_text())["skipped_ticks"]
    print(f"BEAR silence -> damping: {cycles} bulk cycles (rule {rule}, {skipped} skipped ticks; "
          f"{1e3 * (backend.fault_stamp - silenced_at):.1f} ms)")
    assert 0 < cycles <= rule + CYCLE_SLACK + skipped
    enables = emulator.status()["bear"]["torque_enable"]
    assert [e for i, e in enumerate(enables, 1) if i not in (3, 4)] == [3] * 8  # every reachable BEAR damps


def test_estop_bit_reaches_damping(emulator, hw_config):
    backend = make_hw_backend(hw_config, check_imu=False)
    fault = FaultInCycles(emulator, "estop on")
    summary = run_session(backend, hw_config, duration=3.0, realtime=REALTIME, controller_kind="standing",
                          commands=fault, observers=[fault])
    cycles, pressed_at = fault.count()
    assert summary.stop_cause == "e-stop input asserted" and summary.final_state == "fault: damping"
    assert "E-stop" in backend.fault_cause and hw_config.buses.bear.port in backend.fault_cause
    assert backend.fault_stamp > pressed_at
    assert summary.ticks < 1000  # stopped at the E-stop, not at the end of the duration
    # Damped by the bus thread on the cycle that brought the bit, before the control thread's tick saw it; the bus
    # thread ends on that cycle, so the press is one bulk cycle from damping.
    assert backend.damped_by_bus_thread
    print(f"E-stop -> damping: {cycles} bulk cycles ({1e3 * (backend.fault_stamp - pressed_at):.1f} ms)")
    assert cycles <= 1
    events = [text for _, text in emulator.events() if "torque_enable" in text]
    assert all(any(f" {i} torque_enable " in t and t.split("->")[1].split()[0] == "3" for t in events)
               for i in range(1, 11)), events
    assert emulator.status()["bear"]["torque_enable"] == [3] * 10
    assert summary.exit_code == ExitCode.SAFETY_TRIP and summary.fault_class == "safety"  # as on the mock


def test_stopped_imu_stream_reaches_damping(emulator, hw_config):
    backend = make_hw_backend(hw_config, check_imu=False)
    fault = FaultInCycles(emulator, "imu stop")
    summary = run_session(backend, hw_config, duration=3.0, realtime=REALTIME, controller_kind="standing",
                          commands=fault, observers=[fault])
    cycles, stopped_at = fault.count()
    assert summary.stop_cause.startswith("stale IMU data"), summary.stop_cause
    assert hw_config.buses.sense.port in backend.fault_cause and "IMU stream stopped" in backend.fault_cause
    latency = backend.fault_stamp - stopped_at
    age_s = hw_config.safety.max_sensor_age_s
    # The data-age bound is wall clock, and the bus cycles once a loop period (each tick's write starts a cycle), so
    # it is passed within age_s * loop_hz cycles of the last packet (on a slow machine, in fewer), plus one: that
    # packet, sent before the stop, may still be on its way when the stop takes effect.
    bound = math.ceil(age_s * hw_config.loop_hz) + 1 + CYCLE_SLACK + summary.loop.skipped_ticks
    print(f"IMU stop -> damping: {cycles} bulk cycles (bound {bound}; {1e3 * latency:.1f} ms)")
    assert 0 < cycles <= bound
    # Tripped by the data-age bound, not before (seconds: the bound's own unit): the last packet came a few ticks
    # before the stop command at most.
    assert age_s - 0.005 < latency


def test_startup_names_every_missing_device(emulator, hw_config):
    emulator.send("silence bear 7")
    emulator.send("silence dynamixel 12")
    backend = make_hw_backend(hw_config, ping_rounds=2, ping_retry_s=0.01)
    with pytest.raises(BackendError) as info:
        backend.configure()
    message = str(info.value)
    assert f"BEAR bus {hw_config.buses.bear.port}: no reply from BEAR ID(s) 7 " in message, message
    assert f"Dynamixel bus {hw_config.buses.dynamixel.port}: no reply from Dynamixel ID(s) 12 " in message, message
    assert backend.state is LifecycleState.UNCONFIGURED


def test_hw_check_reports_ok_then_names_a_silent_id(emulator, hw_config, capsys):
    from bruce_hw.hw_check import main

    argv = [w for item in emulator.overrides for w in ("--set", item)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "bruce-hw-check: OK" in out and "temperature" in out and " V" in out
    emulator.send("silence bear 5")
    assert main(argv) == 1
    out = capsys.readouterr().out
    assert "missing ID(s): 5" in out and "ID 5: MISSING" in out


def test_can_legs_compose_with_the_virtual_bus():
    """CAN legs (configs/robots/bruce_can.yaml) on python-can's in-process virtual bus: torque goes out through
    the coupling as the MIT torque field, damping is a damping-only command kept after shutdown."""
    from bruce_hw.emulation.robot import EmulatedRobot

    base = load_config("configs/robots/bruce_can.yaml")
    with EmulatedRobot(base) as robot:
        # In-process, the emulators share the GIL with the host: slack on the reply timeout and on the IMU's age
        # (a late IMU packet would fault the backend between two of this test's reads), and on the wall clock a VM
        # that stops the process for more than 15 ms (CI: 17.6 ms) would end it on the ride-through bound, which
        # tests/bruce_hw/test_host_stalls.py tests; here only the composition is.
        config = load_config("configs/robots/bruce_can.yaml",
                             [*robot.port_overrides(), "buses.can.timeout_s=0.05", "safety.max_sensor_age_s=0.05",
                              "safety.host_stall_max_s=0.045"])
        assert not any("buses.bear" in line for line in missing_for_hw(config))
        backend = HwBackend(config, check_imu=False, switch_interval_s=None)
        backend.configure()
        try:
            tau, state = drive_torques(backend)
            assert np.all(np.isfinite(state.joints.q))
            sent = [robot.can[m.channel].command(m.id).torque for m in config.buses.can.motors]
            np.testing.assert_allclose(sent, config.coupling.actuator_torques(tau), atol=0.02)
            backend.fault("test")
            kd = [robot.can[m.channel].command(m.id).kd for m in config.buses.can.motors]
            np.testing.assert_allclose(kd, config.safety.damping_kd, atol=0.01)
        finally:
            backend.shutdown()
        assert all(robot.can[m.channel].in_motor_mode(m.id) for m in config.buses.can.motors)


def test_actuator_limits_cover_the_joint_box(config):
    low, high = actuator_position_limits(config)
    rng = np.random.default_rng(0)
    q = rng.uniform(config.q_lower, config.q_upper, size=(1000, config.n_joints))
    m = q @ config.coupling.actuator_from_joint.T
    assert np.all(m > low) and np.all(m < high)
    np.testing.assert_allclose(high[0], np.pi / 2 + 0.1, atol=1e-3)  # hip yaw: BRUCE's +-pi/2 (plus margin)


def test_attitude_filter_levels_and_ignores_reaction_spikes():
    f = MahonyAttitude(9.80665)
    g = np.array([0.0, 0.0, 9.80665])
    quat = f.update(np.zeros(3), g, 0.0)
    np.testing.assert_allclose(quat, [1, 0, 0, 0], atol=1e-12)
    for k in range(1, 20):  # motor reaction forces: 3 g sideways for 20 ms, the base not turning
        quat = f.update(np.zeros(3), np.array([0.0, 30.0, 9.8]), k * 0.001)
    assert 1 - 2 * (quat[1] ** 2 + quat[2] ** 2) > np.cos(np.radians(1.0))  # still level within 1 deg
    tilted = np.array([0.0, 9.80665 * np.sin(0.3), 9.80665 * np.cos(0.3)])
    for k in range(20, 80000):  # the bias integral settles in ~80 s (poles -0.04, -0.26 1/s)
        quat = f.update(np.zeros(3), tilted, k * 0.001)
    np.testing.assert_allclose(np.arccos(1 - 2 * (quat[1] ** 2 + quat[2] ** 2)), 0.3, atol=0.01)


# Last in the module: it ends with the emulated robot in damping, lying down, for whatever runs after it.
# bruce-run on the hw backend is always paced to the wall clock: on a loaded machine its I/O threads can be starved.
@pytest.mark.realtime
def test_bruce_run_hw_stands_and_shuts_down_into_damping(emulator, hw_config, tmp_path):
    stats = tmp_path / "stats.json"
    argv = ["--backend", "hw", *(w for item in emulator.overrides + WALL_CLOCK_SLACK for w in ("--set", item)),
            "--duration", "3",
            "--controller", "standing", "--rerun", "off", "--stats", str(stats)]
    # A process of its own, as on the robot: threads and real-time settings left by other tests cannot starve it.
    run = subprocess.run([sys.executable, "-c", "from runtime.cli import main; raise SystemExit(main())", *argv],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    summary = json.loads(stats.read_text())
    assert summary["error"] is None and summary["stop_cause"] == "duration reached", summary
    assert summary["ticks"] == 3000
    status = emulator.status()
    plant = status["plant"]
    assert abs(plant["base_height"] - plant["nominal_base_height"]) < 0.05, plant  # standing, not fallen
    assert status["bear"]["torque_enable"] == [3] * 10      # shutdown: every BEAR damping
    assert not any(status["dynamixel"]["torque_enabled"])   # arms: torque off on exit, as BRUCE-OP
    np.testing.assert_allclose(plant["arm_q"], hw_config.arms.hold_pose, atol=0.02)  # they were held
    assert status["bear"]["bulk_comm"] >= 3000


def test_start_up_writes_the_configs_bear_gains_and_reads_them_back(emulator, hw_config):
    config = load_config(overrides=emulator.overrides + WALL_CLOCK_SLACK + ["buses.bear.gains.p_gain_iq=0.25"])
    backend = make_hw_backend(config, check_imu=False)
    backend.configure()
    try:
        bus = backend.legs.bus
        for device_id in config.buses.bear.ids:
            written = bus.read_config(device_id, ["p_gain_iq", "i_gain_iq", "p_gain_force"])
            assert written["p_gain_iq"] == pytest.approx(0.25) and written["i_gain_iq"] == pytest.approx(0.061)
            assert written["p_gain_force"] == pytest.approx(10.0)
    finally:
        backend.shutdown()
