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
    from support.rrd import rrd_entity_paths

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
    expected = {"joints/r_knee", "joints/l_ankle", "joints/r_hip_yaw", "loop/period_us",
                "loop/work_us", "safety/state", "safety/events", "world/robot/base", "world/robot/r_foot",
                "world/base_trajectory"}
    assert expected <= paths, expected - paths


# -- velocity commands, controller and estimator choice -------------------------------------------------------
def parse_error(argv, capsys) -> str:
    from runtime.cli import build_parser

    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(argv)
    assert exit_.value.code == 2
    return capsys.readouterr().err


def test_cmd_is_a_constant_command():
    from runtime.cli import build_parser

    args = build_parser().parse_args(["--cmd", "0.4,0,0"])
    assert args.cmd.duration == float("inf") and list(args.cmd.at(10.0)) == [0.4, 0.0, 0.0]
    args = build_parser().parse_args(["--cmd=-0.3,0.1,-0.5"])  # a leading minus needs the = form
    assert list(args.cmd.at(10.0)) == [-0.3, 0.1, -0.5]


@pytest.mark.parametrize("text", ["0.4,0", "0.4,0,0,0", "fast,0,0", "0.4;0;0", "nan,0,0", ""])
def test_cmd_format_errors(text, capsys):
    assert f"expected VX,VY,WZ (three numbers: m/s, m/s, rad/s), got {text!r}" in parse_error(["--cmd", text], capsys)


@pytest.mark.parametrize("text, problem", [
    ("1.5,0,0", "vx = 1.5 m/s is outside the supported range [-0.5, 1] m/s"),
    ("0,0.4,0", "vy = 0.4 m/s is outside the supported range [-0.3, 0.3] m/s"),
    ("0,0,0.6", "wz = 0.6 rad/s is outside the supported range [-0.5, 0.5] rad/s"),
])
def test_cmd_out_of_range(text, problem, capsys):
    assert problem in parse_error(["--cmd", text], capsys)


def test_a_negative_cmd_works_in_the_natural_form(tmp_path):
    from runtime.cli import join_option_values

    assert join_option_values(["--cmd", "-0.3,0,0", "--duration", "1"]) == ["--cmd=-0.3,0,0", "--duration", "1"]
    assert join_option_values(["--cmd", "--duration"]) == ["--cmd", "--duration"]  # an option stays an option
    stats = tmp_path / "s.json"
    assert main(["--backend", "mock", "--cmd", "-0.3,0,0", "--duration", "0.05", "--rerun", "off",
                 "--stats", str(stats)]) == 0
    assert json.loads(stats.read_text())["exit_code"] == 0


def test_a_pinn_without_a_scheme_that_uses_one_is_refused_in_one_line(tmp_path, capsys):
    code = main(["--backend", "mock", "--pinn", str(tmp_path / "p.onnx"), "--duration", "0.05", "--rerun", "off"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "--pinn" in err[0] and "transfer direct" in err[0] and "--transfer eq9" in err[0]


def test_cmd_and_scenario_are_mutually_exclusive(capsys):
    err = parse_error(["--cmd", "0.4,0,0", "--scenario", "configs/scenarios/walk_then_turn.yaml"], capsys)
    assert "not allowed with argument" in err


def test_policy_is_for_the_policy_controller_only(capsys):
    with pytest.raises(SystemExit):
        main(["--controller", "standing", "--policy", "policy.onnx"])
    assert "--policy is for --controller policy, not standing" in capsys.readouterr().err


def test_bad_scenario_is_named(tmp_path, capsys):
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text("segments: [{duration: 1.0, cmd: [2.0, 0, 0]}]\n")
    assert main(["--scenario", str(scenario)]) == 2
    assert f"{scenario}: segments[0].cmd.vx: expected a number in [-0.5, 1] m/s" in capsys.readouterr().err


def test_scenario_sets_the_duration_and_the_summary_has_the_tracking(tmp_path, capsys):
    scenario, stats = tmp_path / "scenario.yaml", tmp_path / "stats.json"
    scenario.write_text("segments:\n  - {duration: 1.0, cmd: [0.2, 0.0, 0.0]}\n  - {duration: 1.5, cmd: [0, 0, 0.1]}\n")
    assert main(["--scenario", str(scenario), "--controller", "standing", "--estimator", "truth",
                 "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert data["ticks"] == 2500 and data["stop_cause"] == "duration reached"
    assert data["tracking_samples"] == 50
    assert set(data["tracking_error"]) == set(data["tracking_rmse"]) == {"vx", "vy", "wz"}
    assert data["command_mean"] == pytest.approx({"vx": 0.0, "vy": 0.0, "wz": 0.1})  # ramped before 2 s
    out = capsys.readouterr().out
    assert f"standing controller, scenario {scenario}, transfer direct, for 2.5 s" in out
    assert "tracking error |mean(v) - mean(cmd)|" in out


def test_controller_teacher_runs_the_walking_teacher(monkeypatch, capsys):
    import types

    from runtime.control.standing import StandingController

    teacher = types.ModuleType("runtime.walking.teacher")
    teacher.WalkingTeacher = StandingController  # the plumbing only: the real teacher has its own tests
    monkeypatch.setitem(sys.modules, "runtime.walking.teacher", teacher)
    assert main(["--controller", "teacher", "--cmd", "0.4,0,0", "--duration", "0.1"]) == 0
    assert "walking teacher, constant command (0.4, 0, 0), transfer direct, for 0.1 s" in capsys.readouterr().out
