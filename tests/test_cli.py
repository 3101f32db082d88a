import json
import os
import signal
import subprocess
import sys
import time

import pytest

from runtime.cli import main

STATS_KEYS = {"ticks", "sim_time", "fell", "base_height_min", "base_height_max", "base_xy_start", "base_xy_end",
              "base_yaw_end", "final_state", "stop_cause"}


def test_mock_run_writes_stats_with_ground_truth(tmp_path, capsys):
    stats = tmp_path / "out" / "stats.json"
    assert main(["--backend", "mock", "--duration", "0.5", "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert STATS_KEYS <= data.keys()
    assert data["ticks"] == 500 and data["fell"] is False and data["stop_cause"] == "duration reached"
    assert "500 ticks" in capsys.readouterr().out


def test_realtime_run_is_paced_to_the_wall_clock(tmp_path):
    stats = tmp_path / "stats.json"
    start = time.monotonic()
    assert main(["--duration", "0.3", "--realtime", "--stats", str(stats)]) == 0
    assert time.monotonic() - start >= 0.3
    data = json.loads(stats.read_text())
    assert data["realtime"] is True and data["ticks"] + data["skipped_ticks"] >= 300


def test_hw_backend_answers_with_what_is_missing(capsys):
    assert main(["--backend", "hw", "--set", "buses.bear.port=/dev/does-not-exist"]) == 2
    err = capsys.readouterr().err
    assert "backend 'hw' cannot start" in err and "/dev/does-not-exist (buses.bear.port)" in err


def test_bad_override_names_the_key(capsys):
    assert main(["--set", "buses.bear.prot=/dev/ttyUSB3", "--duration", "0.1"]) == 2
    assert "buses.bear.prot" in capsys.readouterr().err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_ends_in_damping_with_a_clean_exit_and_stats(tmp_path, sig):
    stats = tmp_path / "stats.json"
    proc = subprocess.Popen([sys.executable, "-m", "runtime.cli", "--realtime", "--stats", str(stats)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        started = proc.stdout.readline()  # printed once the backend is active and the handlers are in place
        assert "backend active" in started, proc.communicate()
        time.sleep(0.5)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    data = json.loads(stats.read_text())
    assert data["stop_cause"] == sig.name
    assert data["final_state"] == "fault: damping"
    assert data["ticks"] > 0 and data["fell"] is False
    assert f"final state: fault: damping ({sig.name})" in started + out
    assert f"damping ({sig.name})" in err  # the one log line of the transition


def test_saved_rrd_is_complete_after_ctrl_c(tmp_path):
    from test_telemetry import rrd_entity_paths

    recording = tmp_path / "runs" / "run.rrd"
    proc = subprocess.Popen([sys.executable, "-m", "runtime.cli", "--realtime", "--rerun", f"save={recording}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        started = proc.stdout.readline()
        assert "backend active" in started, proc.communicate()
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "final state: fault: damping (SIGINT)" in out
    paths = rrd_entity_paths(recording)  # reads the footer: fails on a file that was not closed properly
    expected = {"joints/r_knee/position", "joints/l_ankle/velocity", "joints/r_hip_yaw/torque", "loop/period_us",
                "loop/work_us", "safety/state", "safety/events", "world/robot/base", "world/robot/r_foot",
                "world/base_trajectory"}
    assert expected <= paths, expected - paths
