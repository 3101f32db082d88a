"""How a run ends, on the mock: exit codes per fault class, stats on every path, models refused before the motors
are enabled, and a stop signal during start-up that enables nothing. (The same on hw:
tests/bruce_hw/test_hw_safety.py.)"""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from runtime.cli import main
from runtime.control.inference import ModelError
from runtime.loop.exit import ExitCode, StopFlag
from runtime.loop.run import run_session


class ActivationSpy(MujocoBackend):
    """The mock, counting activations (the moment motors would be enabled)."""

    activations = 0

    def _on_activate(self):
        type(self).activations += 1
        super()._on_activate()


def stats_of(path):
    return json.loads(path.read_text())


def test_a_one_tick_run_writes_its_stats(tmp_path, capsys):
    stats = tmp_path / "s.json"
    assert main(["--duration", "0.001", "--rerun", "off", "--stats", str(stats)]) == ExitCode.OK
    data = stats_of(stats)
    assert data["ticks"] == 1 and data["exit_code"] == 0 and data["fault_class"] is None
    assert data["period_us"]["p50"] is None  # one tick has no period; the summary says so instead of crashing
    assert "period p50 -" in capsys.readouterr().out


def folding_targets(config):
    """Within the joint limits, but the hips flex and the knees fold: the robot topples."""
    a = config.standing_pose.copy()
    a[config.joint_indices("hip_pitch")] = 2.0
    a[config.joint_indices("knee")] = -2.4
    return a


@pytest.mark.parametrize("case", ["safety", "bad_config", "bad_scenario", "nan_policy", "huge_policy",
                                  "huge_pinn"])
def test_each_fault_class_has_its_exit_code_and_writes_stats(case, config, constant_policy_onnx, offset_pinn_onnx,
                                                             tmp_path, capsys):
    stats = tmp_path / "s.json"
    argv = ["--duration", "3", "--rerun", "off", "--stats", str(stats)]
    if case == "safety":
        argv += ["--policy", str(constant_policy_onnx(folding_targets(config), "fold"))]
        expected, problem = ExitCode.SAFETY_TRIP, "tilt"
    elif case == "bad_config":
        binary = tmp_path / "robot.yaml"
        binary.write_bytes(bytes(range(256)) * 4)
        argv += ["--config", str(binary)]
        expected, problem = ExitCode.BAD_INPUT, str(binary)
    elif case == "bad_scenario":
        scenario = tmp_path / "s.yaml"
        scenario.write_text("segments:\n  - {duration: .inf, cmd: [0.1, 0, 0]}\n")
        argv[:2] = ["--scenario", str(scenario)]
        expected, problem = ExitCode.BAD_INPUT, "segments[0].duration"
    elif case == "nan_policy":
        argv += ["--policy", str(constant_policy_onnx([np.nan] * 10, "nan"))]
        expected, problem = ExitCode.BAD_INPUT, "refused before the motors were enabled"
    elif case == "huge_policy":
        argv += ["--policy", str(constant_policy_onnx([1e6] * 10, "huge"))]
        expected, problem = ExitCode.BAD_INPUT, "1e+06 for r_hip_yaw outside"
    else:
        argv += ["--transfer", "pinn", "--pinn", str(offset_pinn_onnx(1e6, "huge_pinn"))]
        expected, problem = ExitCode.BAD_INPUT, "PINN model"
    assert main(argv) == expected
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    data = stats_of(stats)
    assert data["exit_code"] == expected and data["fault_class"] == {3: "safety", 2: "input"}[expected]
    assert problem in (data["stop_cause"] or "") + (data["error"] or ""), data
    if expected == ExitCode.BAD_INPUT:
        assert "backend active" not in captured.out  # refused before anything was enabled


@pytest.mark.parametrize("values", [[np.nan] * 10, [1e6] * 10, "outside"])
def test_a_model_with_bad_outputs_never_reaches_an_enabled_motor(values, config, constant_policy_onnx):
    if values == "outside":  # finite, but asking for more torque than the knee has from anywhere in its range
        values = config.standing_pose.copy()
        values[3] = config.q_lower[3] - 3.0 * config.tau_limit[3] / config.eq8.kp[3]
    policy = constant_policy_onnx(values, f"bad_{abs(hash(str(values)))}")
    ActivationSpy.activations = 0
    with pytest.raises(ModelError, match="refused before the motors were enabled") as info:
        run_session(ActivationSpy(config), config, duration=1.0, realtime=False, policy=policy)
    assert ActivationSpy.activations == 0
    assert str(policy) in str(info.value)


def test_a_pinn_far_off_on_the_measured_pose_is_refused(config, offset_pinn_onnx):
    ActivationSpy.activations = 0
    for offset, what in ((10.0, "q_next"), (float("nan"), "non-finite")):
        with pytest.raises(ModelError, match=what):
            run_session(ActivationSpy(config), config, duration=1.0, realtime=False, transfer="pinn",
                        pinn=offset_pinn_onnx(offset, f"off_{what}"))
    assert ActivationSpy.activations == 0
    # a PINN that is merely a little off passes the check (the loop judges its use)
    summary = run_session(ActivationSpy(config), config, duration=0.05, realtime=False, transfer="pinn",
                          pinn=offset_pinn_onnx(1e-3, "close"))
    assert ActivationSpy.activations == 1 and summary.exit_code == ExitCode.OK


class DampsItselfInRead(MujocoBackend):
    """The mock, going to damping inside its read at tick `at` without raising and with a reading the safety stage
    passes: as the hw backend does on an IMU stream it judges stopped a tick ahead of the stage's own age check."""

    at = 30
    reads = 0

    def _read(self):
        type(self).reads += 1
        if type(self).reads == self.at:
            self.fault("sense board /dev/ttyACM0: IMU stream stopped: last packet 7.6 ms ago")
        return super()._read()


def test_a_backend_that_damps_itself_in_its_read_ends_the_run_on_its_cause(config, tmp_path):
    """Not on the refusal of the write after it ("command refused, the backend is fault", an internal error): the
    backend's own cause, one line, the safety class, the stats written, the damping hold as for any trip."""
    DampsItselfInRead.reads = 0
    backend = DampsItselfInRead(config)
    stats = tmp_path / "s.json"
    summary = run_session(backend, config, duration=0.2, realtime=False, controller_kind="standing",
                          stats_path=stats)
    assert summary.exit_code == ExitCode.SAFETY_TRIP
    assert summary.stop_cause == "sense board /dev/ttyACM0: IMU stream stopped: last packet 7.6 ms ago"
    data = stats_of(stats)
    assert 0 < data["ticks"] < DampsItselfInRead.at and data["final_state"] == "fault: damping", data
    assert data["error"] is None and DampsItselfInRead.reads > DampsItselfInRead.at  # the hold read on


class SignalDuringConfigure(ActivationSpy):
    def _on_configure(self):
        super()._on_configure()
        os.kill(os.getpid(), signal.SIGTERM)  # delivered to the handler at the next bytecode: mid start-up


def test_a_missing_model_file_is_bad_input_and_no_damping_event(config, tmp_path, capsys, caplog):
    """A --policy that names no file is refused while the motors are still off: exit code 2, the backend never
    enabled nor put into damping (its state stays inactive), one summary line naming the file, the stats written."""
    ActivationSpy.activations = 0
    backend = ActivationSpy(config)
    stats = tmp_path / "s.json"
    with pytest.raises(ModelError, match="nope.onnx: file not found"):
        run_session(backend, config, duration=1.0, realtime=False, policy=tmp_path / "nope.onnx", stats_path=stats)
    assert ActivationSpy.activations == 0 and backend.state.value == "unconfigured"  # shut down, never faulted
    data = stats_of(stats)
    assert data["exit_code"] == ExitCode.BAD_INPUT and data["final_state"] == "inactive", data
    assert "damping" not in caplog.text and "damping" not in capsys.readouterr().err


def test_sigterm_during_start_up_enables_nothing_and_ends_cleanly(config, tmp_path):
    ActivationSpy.activations = 0
    stats = tmp_path / "s.json"
    stop = StopFlag()
    summary = run_session(SignalDuringConfigure(config), config, duration=5.0, realtime=False, stats_path=stats,
                          stop=stop)
    assert ActivationSpy.activations == 0
    assert summary.exit_code == ExitCode.OK and summary.error is None and summary.ticks == 0
    assert "SIGTERM received before activation: no motor was enabled" == summary.stop_cause
    assert stats_of(stats)["stop_cause"] == summary.stop_cause
    assert signal.getsignal(signal.SIGTERM) is not stop  # the handlers are given back


def test_sigterm_while_bruce_run_starts_on_silent_buses_ends_cleanly(tmp_path):
    """A real `bruce-run --backend hw` process whose three ports are pseudo-terminals nobody answers on: start-up
    pings them for seconds and can never activate, so a SIGTERM at any moment of it (while the modules load or
    while the buses are scanned) must end it with one line, exit 0, and the stats."""
    stats = tmp_path / "s.json"
    terminals = [os.openpty() for _ in range(3)]
    ports = [os.ttyname(follower) for _, follower in terminals]
    sets = [w for key, port in zip(("bear", "dynamixel", "sense"), ports, strict=True)
            for w in ("--set", f"buses.{key}.port={port}")]
    proc = subprocess.Popen([sys.executable, "-m", "runtime.cli", "--backend", "hw", *sets, "--duration", "5",
                             "--rerun", "off", "--stats", str(stats)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        time.sleep(1.5)  # any moment before activation will do: activation cannot come
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        for leader, follower in terminals:
            os.close(leader)
            os.close(follower)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "backend active" not in out
    assert "SIGTERM received before activation: no motor was enabled" in out + err
    data = stats_of(stats)
    assert data["exit_code"] == 0 and data["ticks"] == 0 and "no motor was enabled" in data["stop_cause"]
