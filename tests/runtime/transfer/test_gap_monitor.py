"""The live gap monitor (runtime/transfer/gap_monitor.py) and its place in the loop."""

import json
import logging

import numpy as np
import pytest

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import CommandSchedule
from runtime.loop.run import run_session
from runtime.transfer.gap_monitor import GapMonitor
from runtime.transfer.stage import settings_for

JOINTS = ("a", "b")


def test_residual_is_measured_minus_what_was_predicted_a_tick_earlier():
    monitor = GapMonitor(JOINTS, window_ticks=4, warn_rms=10.0)
    assert monitor.update(None, np.zeros(2), np.zeros(2)) is None and monitor.samples == 0
    predicted = (np.array([0.10, 0.20]), np.array([1.0, -1.0]))
    residual = monitor.update(predicted, np.array([0.12, 0.20]), np.array([0.5, -1.5]))
    np.testing.assert_allclose(residual.q, [0.02, 0.0], atol=1e-15)
    np.testing.assert_allclose(residual.qd, [-0.5, -0.5])
    stats = monitor.to_json()
    assert stats["gap_residual_rms"] == pytest.approx({"a": 0.5, "b": 0.5})
    assert stats["gap_residual_rms_q"] == pytest.approx({"a": 0.02, "b": 0.0})
    monitor.update(predicted, np.array([0.10, 0.20]), np.array([2.0, -1.0]))  # residual qd +1, 0
    assert monitor.to_json()["gap_residual_mean"] == pytest.approx({"a": 0.25, "b": -0.25})  # signed: the bias


def test_window_rms_covers_the_last_window_and_the_stats_the_whole_run():
    monitor = GapMonitor(JOINTS, window_ticks=2, warn_rms=100.0)
    zero = (np.zeros(2), np.zeros(2))
    for qd in (3.0, 4.0, 0.0):
        monitor.update(zero, np.zeros(2), np.array([qd, 0.0]))
    np.testing.assert_allclose(monitor.window_rms, [np.sqrt((16 + 0) / 2), 0.0])
    assert monitor.to_json()["gap_residual_rms"]["a"] == pytest.approx(np.sqrt((9 + 16 + 0) / 3))


def test_a_large_gap_logs_one_warning_per_crossing_and_never_faults(caplog):
    monitor = GapMonitor(JOINTS, window_ticks=2, warn_rms=1.0)
    zero = (np.zeros(2), np.zeros(2))
    with caplog.at_level(logging.WARNING, logger="runtime.transfer.gap_monitor"):
        for qd in (2.0, 2.0, 2.0, 2.0):  # above the threshold for several windows: one line
            monitor.update(zero, np.zeros(2), np.array([qd, 0.0]))
        assert monitor.warnings == 1
        for qd in (0.8, 0.8):  # below the threshold but above half of it: still armed off
            monitor.update(zero, np.zeros(2), np.array([qd, 0.0]))
        for qd in (2.0, 2.0):
            monitor.update(zero, np.zeros(2), np.array([qd, 0.0]))
        assert monitor.warnings == 1
        for qd in (0.0, 0.0, 2.0, 2.0):  # fell below half: the next crossing warns again
            monitor.update(zero, np.zeros(2), np.array([qd, 0.0]))
    assert monitor.warnings == 2
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and all(line.startswith("gap: a one-step velocity residual") for line in lines)


def test_the_loop_reports_the_gap_per_joint_in_the_stats(tmp_path):
    config = load_config(overrides=["transfer.reference_model=nominal"])
    stats = tmp_path / "stats.json"
    # The shadow's resynchronised ticks predict from the measured state under tau*, and send tau* itself: on the
    # nominal mock with the nominal model, once the safety stage's torque ramp is over (it sends less than tau*),
    # the one-step residual is rounding noise.
    summary = run_session(MujocoBackend(config), config, duration=0.3, realtime=False, stats_path=stats,
                          transfer="shadow", commands=CommandSchedule.constant(0.0, 0.0, 0.0))
    data = json.loads(stats.read_text())
    assert set(data["gap_residual_rms"]) == set(config.joints) and set(data["gap_residual_mean"]) == set(config.joints)
    resyncs = summary.ticks // settings_for(config).of("shadow").resync_ticks
    assert data["gap_samples"] == resyncs  # the prediction of every resynchronisation is scored a tick later
    assert 0.01 < max(data["gap_residual_rms"].values())  # the ramp's ticks ...
    assert np.abs(summary.gap.last.qd).max() < 1e-9  # ... and after it, none
    direct = run_session(MujocoBackend(config), config, duration=0.05, realtime=False, stats_path=stats)
    assert direct.gap is None and "gap_residual_rms" not in json.loads(stats.read_text())
