"""Robot logs against the simulator: `bruce-run --record DIR` writes a log that `bruce-eval replay --log DIR` reads
back and replays through the nominal simulator and the PINN. The mock with a gap profile plays the robot: the
replay's gap is nil on `--gap none` and grows with the profile. The log is closed readable on every exit path, is
bounded, never blocks the loop on a slow disk, and a missing or corrupt log is one line."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest

from bruce_hw.backend import BackendError
from bruce_hw.mock import MujocoBackend
from runtime.cli import main as bruce_run
from runtime.control.commands import CommandSchedule
from runtime.loop.exit import ExitCode
from runtime.loop.observers import EachTick
from runtime.loop.recorder import ROWS_FILE, RunRecorder, describe_run
from runtime.loop.run import run_session
from training.evaluation.cli import main as bruce_eval
from training.evaluation.replay import LoggedCommands, load_log

WALK = ["--backend", "mock", "--cmd", "0.4,0,0", "--rerun", "off"]


def record(folder, name, *extra, duration="3"):
    path, stats = folder / name, folder / f"{name}.json"
    code = bruce_run([*WALK, "--duration", duration, "--record", str(path), "--stats", str(stats), *extra])
    return code, path, json.loads(stats.read_text())


@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """Per gap profile: the recorded log, its run's stats and the replay's report (direct transfer, 3 s)."""
    folder = tmp_path_factory.mktemp("replay")
    out = {}
    for gap in ("none", "default", "harsh"):
        code, log, stats = record(folder, gap, "--gap", gap)
        assert code == ExitCode.OK
        assert bruce_eval(["replay", "--log", str(log), "--out", str(folder / f"{gap}_out")]) == 0
        out[gap] = (log, stats, json.loads((folder / f"{gap}_out" / "replay.json").read_text()),
                    folder / f"{gap}_out")
    return out


def test_the_recorded_log_reads_back_every_tick_of_the_run(replays, config):
    log_path, stats, _, _ = replays["none"]
    log = load_log(log_path)
    meta = log.meta
    assert len(log) == stats["ticks"] == 3000 and meta["rows_written"] == 3000 and meta["rows_dropped"] == 0
    assert np.array_equal(log.tick, np.arange(3000))
    assert np.allclose(np.diff(log.t), config.dt)
    assert log.joints == config.joints and meta["loop_hz"] == config.loop_hz
    assert meta["gap"]["profile"].endswith("none.yaml") and meta["gap"]["seed"] == 0
    assert meta["backend"] == "mock" and meta["transfer"] == "direct" and meta["controller"] == "policy"
    assert meta["policy"]["path"] == str(config.models.policy.resolve()) and len(meta["policy"]["sha256"]) == 64
    assert meta["ended"] == {"stop_cause": "duration reached", "exit_code": 0, "fault_class": None}
    assert sum(c["width"] for c in meta["columns"]) == meta["row_width"] == log.rows.shape[1]
    assert np.allclose(meta["initial_q"], config.standing_pose)
    # the stats' ground truth at the end is the last row's base position
    assert log.column("base_pos")[-1, :2].tolist() == stats["base_xy_end"]
    # the commands are the schedule's at each policy tick, held in between
    schedule = CommandSchedule.constant(0.4, 0.0, 0.0)
    command = log.column("command")
    for i in range(0, 3000, config.policy_decimation):
        assert np.array_equal(command[i:i + config.policy_decimation], np.tile(schedule.at(log.t[i]), (10, 1)))
    assert not np.isnan(log.rows).any()  # no reference model, an IMU quaternion: every column is filled


def test_each_row_is_what_the_loop_handed_its_observers(tmp_path, config):
    seen = {"q": [], "tau": [], "a": [], "gyro": [], "contacts": []}

    def keep(view):
        seen["q"].append(view.q.copy())
        seen["tau"].append(view.tau.copy())
        seen["a"].append(view.a.copy())
        seen["gyro"].append(view.robot.imu.gyro.copy())
        seen["contacts"].append(view.robot.contacts.contact.copy())

    run = describe_run(config, backend="mock", controller="policy", policy=None, transfer="direct", pinn=None,
                       estimator=None, overrides=[])
    recorder = RunRecorder(tmp_path / "log", config, run, block_rows=64)  # several blocks and a partial one
    try:
        run_session(MujocoBackend(config), config, duration=0.3, realtime=False,
                    commands=CommandSchedule.constant(0.3, 0.0, 0.2), observers=[recorder, EachTick(keep)])
    finally:
        recorder.close()
    log = load_log(tmp_path / "log")
    assert len(log) == 300
    for name, column in (("q", "q"), ("tau", "tau"), ("a", "a"), ("gyro", "imu_gyro"), ("contacts", "contacts")):
        assert np.array_equal(log.column(column), np.array(seen[name], dtype=float)), name


def test_a_gap_free_log_replays_onto_the_simulator(replays):
    _, _, report, _ = replays["none"]
    closed = report["closed_loop"]
    assert closed["ticks"] == 3000
    assert closed["joint_rmse"] < 0.005 and max(closed["joint_rmse_per_joint"].values()) < 0.005
    # one step along the log: the nominal model is the simulator itself; the PINN is its learned copy
    assert report["one_step"]["nominal"]["rmse_qd"] < 1e-9
    assert 0 < report["one_step"]["pinn"]["rmse_qd"] < 0.1
    assert report["gap_monitor"] is None  # direct transfer: no reference model, no live monitor


def test_the_reported_gap_grows_with_the_profile(replays):
    rmse = {gap: replays[gap][2]["closed_loop"]["joint_rmse"] for gap in ("none", "default", "harsh")}
    print("closed-loop joint RMSE vs the simulator (rad):", rmse)
    assert rmse["none"] < 0.005 < rmse["default"] < rmse["harsh"]
    nominal = {gap: replays[gap][2]["one_step"]["nominal"]["rmse_qd"] for gap in ("none", "default", "harsh")}
    pinn = {gap: replays[gap][2]["one_step"]["pinn"]["rmse_qd"] for gap in ("none", "default", "harsh")}
    assert nominal["none"] < nominal["default"] < nominal["harsh"]
    assert pinn["none"] < pinn["default"] < pinn["harsh"]


def test_the_replay_writes_its_report_and_figure(replays):
    log_path, _, report, out = replays["default"]
    figure = out / "fig6_replay.png"
    assert figure.stat().st_size > 10_000 and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = (out / "replay.md").read_text()
    assert "| r_hip_yaw |" in table and f"{report['closed_loop']['joint_rmse']:.4g}" in table
    assert report["meta"]["log_path"] == str(log_path) and report["meta"]["joint"] == "r_hip_yaw"
    simulation = load_log(out / "simulation")  # the simulated run, in the log's own format
    assert len(simulation) == 3000 and simulation.meta["gap"] is None


def test_the_live_gap_monitor_residual_is_logged_and_replayed(tmp_path):
    code, path, stats = record(tmp_path, "eq9", "--gap", "default", "--transfer", "eq9", duration="0.5")
    assert code == ExitCode.OK
    log = load_log(path)
    qd, qd_hat, gap_qd = log.column("qd"), log.column("qd_hat"), log.column("gap_qd")
    # the residual at tick i + 1 is what was read minus what the PINN predicted at tick i
    assert np.isnan(gap_qd[0]).all()
    assert np.array_equal(gap_qd[1:], qd[1:] - qd_hat[:-1])
    assert bruce_eval(["replay", "--log", str(path), "--out", str(tmp_path / "out")]) == 0
    gap = json.loads((tmp_path / "out" / "replay.json").read_text())["gap_monitor"]
    assert gap["samples"] == len(log) - 1 == stats["gap_samples"]
    assert gap["rms_qd_per_joint"] == pytest.approx(stats["gap_residual_rms"], rel=1e-9)


def test_a_safety_trip_leaves_a_closed_readable_log(tmp_path, config, constant_policy_onnx):
    a = config.standing_pose.copy()  # the hips flex and the knees fold: the robot topples, tilt trips
    a[config.joint_indices("hip_pitch")] = 2.0
    a[config.joint_indices("knee")] = -2.4
    code, path, stats = record(tmp_path, "trip", "--policy", str(constant_policy_onnx(a, "fold")))
    assert code == ExitCode.SAFETY_TRIP
    log = load_log(path)
    assert log.meta["ended"]["exit_code"] == 3 and "tilt" in log.meta["ended"]["stop_cause"]
    assert len(log) == log.meta["rows_written"] == stats["ticks"] > 0
    assert log.meta["closed_utc"] is not None


def test_a_lost_backend_leaves_a_closed_readable_log(tmp_path, monkeypatch):
    read = MujocoBackend._read
    calls = [0]

    def failing(self):
        calls[0] += 1
        if calls[0] > 1500:
            raise BackendError("mock backend: bus gone (test)")
        return read(self)

    monkeypatch.setattr(MujocoBackend, "_read", failing)
    code, path, _ = record(tmp_path, "lost")
    assert code == ExitCode.BUS_FAULT
    log = load_log(path)
    assert 1000 < len(log) == log.meta["rows_written"] < 1500  # the partial block is written at close
    assert "bus gone" in log.meta["ended"]["error"]


def test_a_crash_mid_write_leaves_the_rows_before_it(replays, tmp_path):
    source = replays["none"][0]
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    (crashed / "meta.json").write_bytes((source / "meta.json").read_bytes())
    data = (source / ROWS_FILE).read_bytes()
    width = 8 * load_log(source).rows.shape[1]
    (crashed / ROWS_FILE).write_bytes(data[:2000 * width + 100])  # two blocks and a torn row
    log = load_log(crashed)
    assert len(log) == 2000 and log.torn_bytes == 100


def test_the_recording_is_bounded_and_the_run_goes_on(tmp_path, caplog):
    code, path, stats = record(tmp_path, "bounded", "--record-max-s", "1", duration="2")
    assert code == ExitCode.OK and stats["ticks"] == 2000
    log = load_log(path)
    assert len(log) == 1000 and log.tick[-1] == 999
    assert "recording stopped after 1000 rows" in log.meta["recording_stopped"]
    assert "recording stopped" in caplog.text


def test_a_disk_that_falls_behind_drops_rows_and_never_blocks_the_loop(tmp_path, config, monkeypatch):
    import runtime.loop.recorder as recorder_module

    release = threading.Event()
    sync = recorder_module.os.fsync
    monkeypatch.setattr(recorder_module.os, "fsync", lambda fd: (release.wait(), sync(fd)))
    run = describe_run(config, backend="mock", controller="standing", policy=None, transfer="direct", pinn=None,
                       estimator=None, overrides=[])
    recorder = RunRecorder(tmp_path / "log", config, run, block_rows=10, pool_blocks=2)
    summary = run_session(MujocoBackend(config), config, duration=0.1, realtime=False, controller_kind="standing",
                          observers=[recorder])
    assert summary.ticks == 100  # the whole run, while the writer was stuck on its first block
    release.set()
    meta = recorder.close()
    assert meta["rows_written"] == 20 and meta["rows_dropped"] == 80
    assert np.array_equal(load_log(tmp_path / "log").tick, np.arange(20))


def test_logged_commands_replay_the_command_in_force():
    t = np.array([0.001, 0.002, 0.003, 0.004])
    command = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    commands = LoggedCommands(t, command, 0.001)
    assert commands.at(0.0)[0] == 0.0 and commands.at(0.002)[0] == 0.1 and commands.at(0.0034)[0] == 0.2
    assert commands.at(10.0)[0] == 0.3


@pytest.mark.parametrize("damage, says", [
    (None, "log directory not found"),
    ("meta", "meta.json: not readable as JSON"),
    ("rows", "rows.f64: ticks not increasing"),
    ("no_rows", "rows.f64: no complete row"),
])
def test_a_missing_or_corrupt_log_is_one_line(damage, says, replays, tmp_path, capsys):
    path = tmp_path / "log"
    if damage is not None:
        path.mkdir()
        source = replays["none"][0]
        (path / "meta.json").write_bytes((source / "meta.json").read_bytes())
        (path / ROWS_FILE).write_bytes((source / ROWS_FILE).read_bytes())
        if damage == "meta":
            (path / "meta.json").write_text('{"format": "bruce-run-log", ')
        elif damage == "rows":
            (path / ROWS_FILE).write_bytes(np.random.default_rng(0).random(96 * 50).tobytes())
        else:
            (path / ROWS_FILE).write_bytes(b"\0" * 100)
    assert bruce_eval(["replay", "--log", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and str(path) in err[0], err


def test_recording_over_an_existing_log_is_refused(replays, tmp_path, capsys):
    existing = replays["none"][0]
    assert bruce_run([*WALK, "--duration", "0.1", "--record", str(existing)]) == ExitCode.BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"bruce-run: --record {existing}: exists") and "Traceback" not in "".join(err)


def test_a_log_without_base_state_or_start_pose_replays_as_a_robot_log(replays, tmp_path):
    """A robot's log has no simulator truth and no placement pose: the simulation starts from its first joint
    angles, the PINN's one step and the closed loop compare, the nominal one step says why it cannot."""
    source = load_log(replays["default"][0])
    kept = [c for c in source.meta["columns"] if not c["name"].startswith("base_")]
    rows = np.concatenate([source.rows[:, c["offset"]:c["offset"] + c["width"]] for c in kept], axis=1)
    offset = 0
    for c in kept:
        c["offset"], offset = offset, offset + c["width"]
    meta = {**source.meta, "columns": kept, "row_width": offset, "initial_q": None, "backend": "hw",
            "estimator": "kinematic"}
    robot = tmp_path / "robot"
    robot.mkdir()
    (robot / "meta.json").write_text(json.dumps(meta))
    rows.astype("<f8").tofile(robot / ROWS_FILE)
    assert bruce_eval(["replay", "--log", str(robot), "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "replay.json").read_text())
    assert "no base state" in report["one_step"]["nominal"]["unavailable"]
    assert report["one_step"]["pinn"]["rmse_qd"] == pytest.approx(replays["default"][2]["one_step"]["pinn"]["rmse_qd"])
    assert report["meta"]["simulation_start"] == "the log's first joint angles"
    assert report["closed_loop"]["ticks"] == 3000 and report["closed_loop"]["joint_rmse"] > 0.005
    assert (tmp_path / "out" / "fig6_replay.png").stat().st_size > 10_000
