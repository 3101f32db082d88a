"""The session loop end to end on the mock: stats, transfer modes, and every damping trigger."""

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from bruce_hw.backend import LifecycleState
from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import CommandSchedule
from runtime.control.inference import ModelError
from runtime.loop.run import run_session

LOOP_KEYS = {"ticks", "late_ticks", "late_share", "work_us", "cpu_us", "period_us", "sections_us",
             "worst_overruns_us"}
SECTIONS = {"read", "policy", "pinn", "mixing", "safety", "write", "telemetry"}


class SpyMock(MujocoBackend):
    """The mock, recording per read the torque its motors applied during the step and the lifecycle state;
    `inject(self, tick)` runs before each read, to break things on purpose."""

    def __init__(self, config, inject=None):
        super().__init__(config)
        self.inject = inject or (lambda backend, tick: None)
        self.reads = []  # (state, applied torque, qd before the step)
        self.writes = 0

    def _read(self):
        self.inject(self, len(self.reads))
        qd_before = self.data.qvel[self._dofs].copy()
        robot = super()._read()
        self.reads.append((self.state, self.data.ctrl[self._acts].copy(), qd_before))
        return robot

    def _write(self, command):
        self.writes += 1
        super()._write(command)


def assert_only_damping_after_the_fault(backend: SpyMock, config):
    faulted = [(applied, qd) for state, applied, qd in backend.reads if state is LifecycleState.FAULT]
    assert faulted, "the session held no damping ticks"
    for applied, qd in faulted:  # every step in FAULT applied -kd qd and nothing of the last command
        np.testing.assert_allclose(applied, -config.safety.damping_kd * qd, atol=1e-12)


def test_stats_file_has_the_loop_keys_and_sections(config, tmp_path):
    stats = tmp_path / "stats.json"
    summary = run_session(MujocoBackend(config), config, duration=0.3, realtime=False, stats_path=stats)
    data = json.loads(stats.read_text())
    assert LOOP_KEYS <= data.keys()
    assert data["ticks"] == 300 == summary.ticks
    for key in ("work_us", "period_us"):
        assert set(data[key]) == {"p50", "p99", "max"} and 0 < data[key]["p50"] <= data[key]["p99"]
    assert set(data["sections_us"]) == SECTIONS
    assert all(set(v) == {"p50", "p99"} for v in data["sections_us"].values())
    # The tick's CPU time: never more than its wall time (a thread cannot run longer than the time that passed)
    cpu = data["cpu_us"]
    assert set(cpu) == {"p50", "p99", "p99.9", "max"} and 0 < cpu["p50"] <= cpu["p99"] <= cpu["p99.9"] <= cpu["max"]
    assert cpu["max"] <= data["work_us"]["max"] + 20  # the two clocks are read 2 µs apart at each end
    assert data["late_ticks"] == 0 and data["late_share"] == 0.0  # unpaced: nothing can be late


def test_realtime_run_reports_what_the_os_granted(config, tmp_path, capsys):
    stats = tmp_path / "stats.json"
    run_session(MujocoBackend(config), config, duration=0.2, realtime=True, stats_path=stats)
    grant = json.loads(stats.read_text())["realtime_grant"]
    assert grant["scheduler"] in ("SCHED_OTHER", "SCHED_FIFO 50")
    assert (grant["scheduler"] == "SCHED_OTHER") == any(r.startswith("SCHED_FIFO") for r in grant["refused"])
    assert "bruce-run: realtime: " in capsys.readouterr().out
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # given back after the run


def test_transfer_pinn_runs_eq9_with_the_pinn(config, stateful_pinn_onnx, tmp_path):
    stats = tmp_path / "stats.json"
    summary = run_session(MujocoBackend(config), config, duration=1.0, realtime=False, stats_path=stats,
                          transfer="pinn", pinn=stateful_pinn_onnx)
    data = json.loads(stats.read_text())
    assert data["transfer"] == "pinn" and summary.ticks == 1000 and not summary.truth.fell
    assert data["sections_us"]["pinn"]["p50"] >= 5  # the network really ran every tick


def test_the_committed_pinn_is_the_default_and_walks_the_mock_with_eq9(config, tmp_path):
    """`--transfer pinn` without --pinn runs the committed, trained PINN (pinn.model), and its sidecar says how to
    regenerate it; the policy walks with Eq. 9 in the nominal mock, where the PINN's reference is what the
    simulator does anyway."""
    path = config.models.pinn
    assert path is not None and path.is_file()
    sidecar = json.loads(Path(f"{path}.json").read_text())
    assert sidecar["kind"] == "pinn_step" and "bruce-train" in sidecar["command"]
    assert sidecar["parity_1000_steps"] <= 1e-5
    stats = tmp_path / "stats.json"
    summary = run_session(MujocoBackend(config), config, duration=6.0, realtime=False, stats_path=stats,
                          transfer="pinn", commands=CommandSchedule.constant(0.3, 0.0, 0.0))
    data = json.loads(stats.read_text())
    assert data["transfer"] == "pinn" and not summary.truth.fell and data["sections_us"]["pinn"]["p50"] >= 5
    walked = np.subtract(summary.truth.base_xy_end, summary.truth.base_xy_start)
    assert walked[0] > 0.8  # 0.3 m/s after a 0.5 s ramp, like Eq. 8 alone (1.02 m); a PINN at odds with the mock trips


def test_transfer_pinn_without_a_model_fails_before_the_robot_moves():
    config = load_config(overrides=["pinn.model=null"])
    backend = SpyMock(config)
    with pytest.raises(ModelError, match="--transfer pinn needs a PINN model"):
        run_session(backend, config, duration=0.1, realtime=False, transfer="pinn")
    assert backend.writes == 0 and all(s is LifecycleState.INACTIVE for s, _, _ in backend.reads)


def test_a_wrong_model_file_fails_before_the_robot_moves(config, tmp_path):
    backend = SpyMock(config)
    bad = tmp_path / "policy.onnx"
    bad.write_bytes(b"\x08\x07garbage")
    with pytest.raises(ModelError, match="policy model .*policy.onnx"):
        run_session(backend, config, duration=0.1, realtime=False, policy=bad)
    assert backend.writes == 0 and backend.state is LifecycleState.UNCONFIGURED


def test_onnx_policy_drives_the_loop_at_the_policy_rate(config, random_policy_onnx, monkeypatch):
    from runtime.control.policy import PolicyController

    calls = []
    original = PolicyController.__call__

    def counting(self, state, base, command):
        calls.append(state.joints.stamp)
        return original(self, state, base, command)

    monkeypatch.setattr(PolicyController, "__call__", counting)
    summary = run_session(MujocoBackend(config), config, duration=0.5, realtime=False, policy=random_policy_onnx)
    # One call checks the model on the measured pose before activation. A random policy may topple the robot, or
    # aim outside the joint range (a trip on the tick of the call, before the tick is counted); the loop must have
    # run it every 10th tick until then.
    aimed_outside = summary.stop_cause is not None and summary.stop_cause.startswith("controller target")
    assert len(calls) == 1 + -(-summary.ticks // config.policy_decimation) + aimed_outside
    assert np.allclose(np.diff(calls[1:]), config.policy_decimation * config.dt)


class FrozenStamps(SpyMock):
    def _read(self):
        robot = super()._read()
        if len(self.reads) > 300:
            robot.joints.stamp = robot.imu.stamp = 0.3  # the encoders stopped updating
        return robot


class TiltedImu(SpyMock):
    def _read(self):
        robot = super()._read()
        if len(self.reads) > 300:
            robot.imu.orientation = np.array([0.8, 0.6, 0.0, 0.0])  # 74 deg of roll
        return robot


def estop_at(tick):
    def inject(backend, n):
        backend.estop_pressed = n >= tick
    return inject


class SlowLoop(SpyMock):
    """The mock on a clock of its own that, after tick 150, advances 3 ms per tick: a robot's loop that keeps
    running at 333 Hz (the simulator still steps 1 ms; the stamps follow the clock, so the data is fresh)."""

    def __init__(self, config):
        super().__init__(config)
        self.t = 0.0

    def clock(self):
        return self.t

    def _read(self):
        self.t += self.config.dt * (3 if len(self.reads) > 150 else 1)
        robot = super()._read()
        robot.joints.stamp = robot.imu.stamp = self.t
        return robot


@pytest.mark.parametrize("case", ["tilt", "stale", "estop", "slow", "model", "sigint", "sigterm"])
def test_each_trigger_ends_in_damping_with_no_stale_torque(config, nan_pinn_onnx, case, tmp_path):
    kwargs = {}
    realtime = False
    if case == "tilt":
        backend = TiltedImu(config)
        expected = "tilt 74 deg"
    elif case == "stale":
        backend = FrozenStamps(config)
        expected = "stale joint data"
    elif case == "estop":
        backend = SpyMock(config, estop_at(300))
        expected = "e-stop"
    elif case == "slow":
        backend = SlowLoop(config)
        expected = "below safety.min_rate_hz"
    elif case == "model":
        backend = SpyMock(config)
        kwargs = {"transfer": "pinn", "pinn": nan_pinn_onnx}
        expected = "non-finite"
    else:
        sig = signal.SIGINT if case == "sigint" else signal.SIGTERM
        backend = SpyMock(config, lambda b, n: n == 300 and os.kill(os.getpid(), sig))
        expected = sig.name
    stats = tmp_path / "stats.json"
    summary = run_session(backend, config, duration=3.0, realtime=realtime, stats_path=stats, **kwargs)
    assert expected in summary.stop_cause, summary.stop_cause
    assert summary.final_state == "fault: damping"
    assert 0 < summary.ticks < 3000  # the trigger, not the duration, ended the run
    assert_only_damping_after_the_fault(backend, config)
    assert json.loads(stats.read_text())["final_state"] == "fault: damping"
