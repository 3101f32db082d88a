import math
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from support.rrd import rrd_entity_paths, rrd_rows, rrd_timelines

from bruce_hw import make_backend
from runtime.telemetry import RerunSink, Telemetry, TelemetryError, grpc_url, make_telemetry, parse_sink


@pytest.fixture(scope="module")
def model(config):
    mock = make_backend("mock", config)
    mock.configure()
    return mock


def joint_row(config, tick: int, with_pinn: bool):
    """Distinct, checkable values: joint j of quantity k at tick t is t + j / 100 + k / 1000."""
    n = config.n_joints
    values = [tick + np.arange(n) / 100 + k / 1000 for k in range(7)]
    q, qd, q_hat, qd_hat, a, tau_star, tau = values
    return (q, qd, q_hat if with_pinn else None, qd_hat if with_pinn else None, a, tau_star, tau,
            1000.0 + tick, 50.0, tick % 3)


@pytest.mark.parametrize("text, kind, target", [
    ("spawn", "spawn", None), ("connect", "connect", None), ("connect=robot:9876", "connect", "robot:9876"),
    ("connect=rerun+http://10.0.0.2:9876/proxy", "connect", "rerun+http://10.0.0.2:9876/proxy"),
    ("serve", "serve", None), ("serve=9877", "serve", "9877"), ("save=runs/a b.rrd", "save", "runs/a b.rrd"),
    ("off", "off", None),
])
def test_parse_sink_accepts_each_form(text, kind, target):
    assert parse_sink(text) == RerunSink(kind, target)


@pytest.mark.parametrize("text", ["", "spwan", "save", "save=", "off=1", "spawn=now", "serve=http", "serve=70000",
                                  "connect=", "file=x.rrd"])
def test_parse_sink_rejects_junk_naming_the_value(text):
    with pytest.raises(ValueError, match=f"{text!r}.*expected one of spawn, connect"):
        parse_sink(text)


@pytest.mark.parametrize("text, expected", [
    ("save=run.rrd,max_mb=200", RerunSink("save", "run.rrd", max_mb=200.0)),
    ("save=run.rrd,max_mb=0.5,keep=3", RerunSink("save", "run.rrd", max_mb=0.5, keep=3)),
    ("save=run.rrd,max_mb=0", RerunSink("save", "run.rrd", max_mb=0.0)),
    ("save=a,b.rrd", RerunSink("save", "a,b.rrd")),  # a comma not followed by key= stays in the path
    ("serve,buffer_mb=64", RerunSink("serve", None, buffer_mb=64)),
    ("serve=9877,buffer_mb=64", RerunSink("serve", "9877", buffer_mb=64)),
])
def test_parse_sink_reads_the_size_options(text, expected):
    assert parse_sink(text) == expected
    assert parse_sink(str(expected)) == expected


@pytest.mark.parametrize("text, says", [
    ("save=run.rrd,max_mb=big", "max_mb must be a number of megabytes >= 0"),
    ("save=run.rrd,max_mb=-1", "max_mb must be"),
    ("save=run.rrd,max_mb=inf", "max_mb must be"),
    ("save=run.rrd,keep=0", "keep must be an integer >= 1"),
    ("save=run.rrd,keep=2.5", "keep must be"),
    ("save=run.rrd,max_mb=0,keep=2", "keep= needs rotation"),
    ("save=run.rrd,keep=2,keep=3", "option keep given twice"),
    ("save=run.rrd,max_MB=3", "unknown option 'max_MB' (save takes max_mb=, keep=)"),
    ("spawn,max_mb=3", "unknown option 'max_mb' (spawn takes no options)"),
    ("connect=robot:9876,keep=2", "unknown option 'keep' (connect takes no options)"),
    ("serve,buffer_mb=0", "buffer_mb must be an integer number of megabytes >= 1"),
    ("serve=9877,max_mb=5", "unknown option 'max_mb' (serve takes buffer_mb=)"),
])
def test_a_bad_option_is_one_line_naming_it(text, says):
    with pytest.raises(ValueError) as error:
        parse_sink(text)
    message = str(error.value)
    assert says in message and repr(text) in message and "\n" not in message


def test_bruce_run_refuses_a_bad_option_before_starting(capsys):
    from runtime.cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["--duration", "1", "--rerun", "save=/nonexistent/run.rrd,max_mb=lots"])
    assert exit_.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if "max_mb" in line]
    assert len(lines) == 1 and "--rerun: rerun sink 'save=/nonexistent/run.rrd,max_mb=lots': max_mb must be" in lines[0]


def test_grpc_url_completes_host_port_only():
    assert grpc_url("robot.local:9876") == "rerun+http://robot.local:9876/proxy"
    assert grpc_url("rerun+https://h:1/proxy") == "rerun+https://h:1/proxy"
    assert grpc_url(None) is None


def test_make_telemetry_is_none_for_off(config, tmp_path):
    assert make_telemetry(config, parse_sink("off")) is None
    telemetry = make_telemetry(config, parse_sink(f"save={tmp_path / 'x.rrd'}"), capacity=16)
    assert isinstance(telemetry, Telemetry) and telemetry.capacity == 16
    telemetry.close()


def test_a_full_buffer_drops_the_oldest_rows_and_counts_them(config, tmp_path):
    path = tmp_path / "overflow.rrd"
    # The telemetry process's first batch is a minute away, so nothing drains until close().
    telemetry = Telemetry(config, parse_sink(f"save={path}"), capacity=8, batch_period_s=60.0)
    telemetry.start()
    for tick in range(20):
        telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=False))
    assert telemetry.dropped == 12 and telemetry.sent_rows == 0
    telemetry.close()
    assert telemetry.dropped == 12 and telemetry.sent_rows == 8 and telemetry.error is None
    assert sorted(rrd_rows(path, "loop/period_us", "Scalars:scalars")) == list(range(12, 20))


def test_rows_appended_faster_than_the_child_drains_are_dropped_oldest_first(config, tmp_path):
    path = tmp_path / "lapped.rrd"
    capacity, bursts, per_burst = 16, 12, 250
    telemetry = Telemetry(config, parse_sink(f"save={path}"), capacity=capacity, batch_period_s=0.01)
    telemetry.start()
    tick = 0
    for _ in range(bursts):  # each burst laps the ring many times before the next batch
        for _ in range(per_burst):
            telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=tick % 2 == 0))
            telemetry.append_pose(tick, tick / 1000, np.zeros((3, 3)), np.zeros((3, 4)))  # no model: ignored
            tick += 1
        time.sleep(0.03)
    telemetry.close()
    total = bursts * per_burst
    assert telemetry.error is None and telemetry.sent_poses == telemetry.dropped_poses == 0
    assert telemetry.dropped > 0 and telemetry.sent_rows + telemetry.dropped == total
    assert telemetry.sent_rows >= capacity

    knee = config.joints.index("r_knee")
    knee_rows = rrd_rows(path, "joints/r_knee", "Scalars:scalars")
    assert len(knee_rows) == telemetry.sent_rows
    assert set(range(total - capacity, total)) <= set(knee_rows)  # the newest rows survive
    for t, (q, q_hat, a, *_) in knee_rows.items():  # no torn row: every value is the one appended at its tick
        assert q == pytest.approx(t + knee / 100) and a == pytest.approx(t + knee / 100 + 4 / 1000)
        assert math.isnan(q_hat) if t % 2 else q_hat == pytest.approx(t + knee / 100 + 2 / 1000)
    drops = rrd_rows(path, "telemetry/dropped", "Scalars:scalars")
    counts = [drops[t][0] for t in sorted(drops)]
    assert counts == sorted(counts) and 0 < counts[-1] <= telemetry.dropped


def test_save_round_trip_with_the_mock_model(config, model, tmp_path):
    path = tmp_path / "nested" / "run.rrd"  # the parent is created
    ticks, half = 300, 150
    with Telemetry(config, parse_sink(f"save={path}"), model=model.model, batch_period_s=0.01) as telemetry:
        for tick in range(ticks):
            telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=tick >= half))
            if tick % telemetry.pose_decimation == 0:
                xpos, xquat = model.body_poses()
                xpos[1] += [0.001 * tick, 0.0, 0.0]  # the base walks forward along x
                telemetry.append_pose(tick, tick / 1000, xpos, xquat)
            if tick == 200:
                telemetry.event(tick, tick / 1000, "safety: damping: tilt", "warn")
    assert telemetry.error is None and telemetry.dropped == 0 and telemetry.sent_rows == ticks

    paths = rrd_entity_paths(path)
    expected = {f"joints/{name}" for name in config.joints}
    expected |= {"loop/period_us", "loop/work_us", "safety/state", "safety/events", "telemetry/dropped", "world",
                 "world/floor", "world/base_trajectory", "world/robot/base", "world/robot/r_shank"}
    assert expected <= paths
    assert rrd_timelines(path) == {"tick", "time"}  # send_columns/record batches add no log_time/log_tick

    knee = config.joints.index("r_knee")
    knee_rows = rrd_rows(path, "joints/r_knee", "Scalars:scalars")  # q, q_hat, a, qd, qd_hat, tau_star, tau
    assert sorted(knee_rows) == list(range(ticks))
    assert knee_rows[7][0] == pytest.approx(7 + knee / 100) and math.isnan(knee_rows[7][1])  # no PINN: NaN
    assert math.isnan(knee_rows[7][4]) and knee_rows[7][2] == pytest.approx(7 + knee / 100 + 4 / 1000)  # a
    # appended as q, qd, q_hat, qd_hat, a, tau_star, tau (k = 0..6)
    assert knee_rows[160] == pytest.approx([160 + knee / 100 + k / 1000 for k in (0, 2, 4, 1, 3, 5, 6)])
    assert rrd_rows(path, "safety/state", "Scalars:scalars")[5] == [2.0]
    assert rrd_rows(path, "safety/events", "TextLog:text") == {200: ["safety: damping: tilt"]}

    xpos, xquat = model.body_poses()
    base = rrd_rows(path, "world/robot/base", "Transform3D:translation")
    assert sorted(base) == list(range(0, ticks, telemetry.pose_decimation))
    t = 3 * telemetry.pose_decimation
    assert base[t][0] == pytest.approx(xpos[1] + [0.001 * t, 0.0, 0.0], abs=1e-6)
    w, x, y, z = xquat[2]  # rerun stores x, y, z, w
    hip = rrd_rows(path, "world/robot/r_hip_yaw_link", "Transform3D:quaternion")
    assert hip[0][0] == pytest.approx([x, y, z, w], abs=1e-6)

    from rerun.chunk import RrdReader

    assert RrdReader(path).blueprints(), "the default blueprint is saved with the recording"
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                            text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr


def test_close_is_idempotent_and_works_without_start(config, tmp_path):
    telemetry = Telemetry(config, parse_sink(f"save={tmp_path / 'never.rrd'}"))
    telemetry.append(0, 0.0, *joint_row(config, 0, with_pinn=False))
    telemetry.close()
    telemetry.close()
    assert telemetry.dropped == 1 and telemetry.sent_rows == 0
    assert not (tmp_path / "never.rrd").exists()
    with pytest.raises(TelemetryError, match="already started or closed"):
        telemetry.start()


def test_a_failed_start_names_the_sink_and_close_still_works(config, tmp_path):
    (tmp_path / "file").write_text("not a directory")
    telemetry = Telemetry(config, parse_sink(f"save={tmp_path / 'file' / 'run.rrd'}"))
    with pytest.raises(TelemetryError, match=r"rerun sink save=.*file/run\.rrd"):
        telemetry.start()
    telemetry.close()
    telemetry.close()


def test_a_failure_inside_the_telemetry_process_reaches_start(config, tmp_path):
    telemetry = Telemetry(config, parse_sink(f"save={tmp_path}"))  # a directory: rerun cannot create the file
    with pytest.raises(TelemetryError, match=f"rerun sink save={tmp_path}: .*[Dd]irectory"):
        telemetry.start()
    telemetry.close()
    assert telemetry._proc is None  # the telemetry process is gone


def test_spawn_without_a_display_fails_clearly(config, monkeypatch):
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is for Linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(TelemetryError, match="rerun sink spawn: no display.*serve.*save=PATH"):
        with Telemetry(config, parse_sink("spawn")):
            pass


def test_serve_on_a_busy_port_fails_clearly(config):
    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        telemetry = Telemetry(config, parse_sink(f"serve={port}"))
        with pytest.raises(TelemetryError, match=f"rerun sink serve={port}: cannot listen on port {port}"):
            telemetry.start()
        telemetry.close()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_connect_reaches_a_served_recording_and_fails_fast_without_one(config, capsys):
    port = free_port()
    with Telemetry(config, parse_sink(f"serve={port}"), recording_name="server") as server:
        assert server.url and str(port) in server.url
        assert f"rerun+http://{socket.gethostname()}:{port}/proxy" in capsys.readouterr().out
        with Telemetry(config, parse_sink(f"connect=127.0.0.1:{port}"), batch_period_s=0.01) as client:
            for tick in range(50):
                client.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=False))
        assert client.error is None and client.sent_rows == 50
    with pytest.raises(TelemetryError, match=f"rerun sink connect=127.0.0.1:{port}: no viewer reachable"):
        Telemetry(config, parse_sink(f"connect=127.0.0.1:{port}")).start()


def test_a_failing_batch_is_recorded_and_later_batches_still_go_out(config, tmp_path, capsys):
    path = tmp_path / "errors.rrd"
    telemetry = Telemetry(config, parse_sink(f"save={path}"), batch_period_s=0.005)
    telemetry.start()
    bad = np.zeros(3)  # wrong number of joints
    for tick in range(5):
        telemetry.append(tick, tick / 1000, bad, bad, None, None, bad, bad, bad, 1000.0, 50.0, 0)
    deadline = time.monotonic() + 5.0
    while telemetry.error is None and time.monotonic() < deadline:
        time.sleep(0.005)
    assert isinstance(telemetry.error, ValueError) and telemetry.dropped == 5
    for tick in range(5, 10):
        telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=True))
    telemetry.close()
    assert telemetry.sent_rows == 5 and telemetry.dropped == 5
    assert sorted(rrd_rows(path, "loop/work_us", "Scalars:scalars")) == list(range(5, 10))
    assert "count as dropped" in capsys.readouterr().err


CHILD = """
import os
import signal
import sys
import time
import numpy as np
from bruce_hw import load_config
from runtime.telemetry import Telemetry, parse_sink

# Ctrl-C as in a terminal, whatever this test inherited (a job started in the background has SIGINT ignored).
signal.signal(signal.SIGINT, signal.default_int_handler)
config = load_config()
telemetry = Telemetry(config, parse_sink(sys.argv[1]), batch_period_s=60.0)  # nothing is sent before exit
telemetry.start()
row = np.zeros(config.n_joints)
for tick in range(100):
    telemetry.append(tick, tick / 1000, row, row, None, None, row, row, row, 1000.0, 50.0, 0)
print("appended", flush=True)
if sys.argv[2] == "interrupt":
    raise KeyboardInterrupt  # what an unhandled Ctrl-C does
if sys.argv[2] == "sigint":
    time.sleep(60)  # the test sends SIGINT to the whole process group, as a terminal's Ctrl-C does
if sys.argv[2] == "sigkill":
    os.kill(os.getpid(), signal.SIGKILL)  # no atexit, no close(): the telemetry process is on its own
"""


def wait_for_complete_rrd(path, timeout_s: float = 30.0) -> None:
    """An orphaned telemetry process finishes the file by itself; wait until its footer is there."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            rrd_entity_paths(path)
            return
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@pytest.mark.parametrize("how", ["return", "interrupt", "sigint", "sigkill"])
def test_a_process_leaving_without_close_still_writes_a_complete_file(tmp_path, how):
    path = tmp_path / "child.rrd"
    script = tmp_path / "child.py"
    script.write_text(textwrap.dedent(CHILD))
    parent = subprocess.Popen([sys.executable, str(script), f"save={path}", how], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert parent.stdout.readline().strip() == "appended"
        if how == "sigint":
            os.killpg(parent.pid, signal.SIGINT)  # the parent and its telemetry process alike
        out, err = parent.communicate(timeout=60)
    finally:
        if parent.poll() is None:
            parent.kill()
    # An unhandled KeyboardInterrupt ends Python by SIGINT (older versions: exit status 1).
    expected = {"return": {0}, "interrupt": {1, -signal.SIGINT}, "sigint": {1, -signal.SIGINT},
                "sigkill": {-signal.SIGKILL}}[how]
    assert parent.returncode in expected, err
    if how == "sigkill":
        wait_for_complete_rrd(path)
    assert "loop/period_us" in rrd_entity_paths(path)  # raises if the footer is missing
    assert sorted(rrd_rows(path, "loop/period_us", "Scalars:scalars")) == list(range(100))


def append_paced(telemetry, config, ticks: range, per_burst: int = 100, pause_s: float = 0.02) -> None:
    """Rows in bursts, so the rings never overflow and the chunks stay small (~per_burst rows)."""
    for tick in ticks:
        telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=True))
        if tick % per_burst == per_burst - 1:
            time.sleep(pause_s)


def child_threads(telemetry) -> int | None:
    """Threads of the telemetry process (Linux), None where /proc cannot tell."""
    try:
        return len(os.listdir(f"/proc/{telemetry._proc.pid}/task"))
    except OSError:
        return None


def rrd_parts(path) -> list:
    """The files of a rotated recording at `path`, oldest first: path, path-stem.001.rrd, ..."""
    parts = sorted(path.parent.glob(f"{path.stem}.[0-9][0-9][0-9]*{path.suffix}"))
    return ([path] if path.exists() else []) + parts


ROTATE_MB = 0.8         # each part also carries ~0.5 MB of blueprint and static data
ROTATE_SLACK_MB = 1.0   # a part ends one chunk (+ its footer) past max_mb; a busy machine makes chunks bigger


def test_rotation_splits_the_recording_into_bounded_parts_that_lose_nothing(config, tmp_path, capfd):
    path = tmp_path / "run.rrd"
    (tmp_path / "run.999.rrd").write_text("a part of an earlier recording at this path: removed at start")
    (tmp_path / "run.notes.rrd").write_text("not a part: kept")
    total = 3000
    sink = parse_sink(f"save={path},max_mb={ROTATE_MB}")
    with Telemetry(config, sink, batch_period_s=0.01, chunk_s=0.05) as telemetry:
        append_paced(telemetry, config, range(50), per_burst=50, pause_s=0.2)
        threads = child_threads(telemetry)
        append_paced(telemetry, config, range(50, total), per_burst=50, pause_s=0.05)
        threads_after = child_threads(telemetry)
    assert telemetry.error is None and telemetry.sent_rows == total and telemetry.dropped == 0
    if threads is not None:  # a new part costs no thread (rerun's send_blueprint left two per call)
        assert threads_after <= threads + 1, (threads, threads_after)

    parts = rrd_parts(path)
    assert len(parts) >= 3, parts
    assert (tmp_path / "run.notes.rrd").exists() and not (tmp_path / "run.999.rrd").exists()
    seen = []
    for part in parts:
        assert part.stat().st_size <= (ROTATE_MB + ROTATE_SLACK_MB) * 1e6, (part, part.stat().st_size)
        assert {"joints/r_knee", "loop/period_us"} <= rrd_entity_paths(part)  # each part has its own footer
        from rerun.chunk import RrdReader

        assert RrdReader(part).blueprints(), f"{part.name} opens with the default blueprint"
        seen += sorted(rrd_rows(part, "joints/r_knee", "Scalars:scalars"))
    assert seen == list(range(total))  # every row in exactly one part, in order
    assert capfd.readouterr().err.count("telemetry: recording continues in") == len(parts) - 1


def test_keep_bounds_the_disk_to_the_newest_parts(config, tmp_path):
    path = tmp_path / "run.rrd"
    total = 3000
    with Telemetry(config, parse_sink(f"save={path},max_mb={ROTATE_MB},keep=2"), batch_period_s=0.01,
                   chunk_s=0.05) as telemetry:
        append_paced(telemetry, config, range(total), per_burst=50, pause_s=0.05)
    assert telemetry.error is None and telemetry.sent_rows == total
    parts = rrd_parts(path)
    assert len(parts) == 2 and not path.exists(), parts  # the oldest parts, PATH itself first, are gone
    assert sum(p.stat().st_size for p in parts) <= 2 * (ROTATE_MB + ROTATE_SLACK_MB) * 1e6
    newest = sorted(rrd_rows(parts[-1], "joints/r_knee", "Scalars:scalars"))
    assert newest[-1] == total - 1  # the newest rows are the ones kept


def test_rows_go_out_in_chunks_of_chunk_s_not_one_per_drain(config, tmp_path):
    """Few, large chunks per entity are what keep the file small and the telemetry process's memory flat
    (rerun keeps a manifest entry per chunk for the file's footer)."""
    from rerun.chunk import RrdReader

    path = tmp_path / "chunks.rrd"
    total, chunk_s = 1500, 0.5
    with Telemetry(config, parse_sink(f"save={path}"), batch_period_s=0.01, chunk_s=chunk_s) as telemetry:
        started = time.monotonic()
        append_paced(telemetry, config, range(total), per_burst=50, pause_s=0.05)  # ~1.5 s, ~150 drains
        elapsed = time.monotonic() - started
    assert telemetry.sent_rows == total
    chunks = [c for c in RrdReader(path).stream() if c.entity_path == "/joints/r_knee" and not c.is_static]
    assert sum(c.num_rows for c in chunks) == total
    # One chunk per chunk_s (+ the rest at close), where sending every drain made one per 50-row burst (30).
    assert len(chunks) <= elapsed / chunk_s + 2, ([c.num_rows for c in chunks], elapsed)


def test_safety_state_is_sent_where_it_steps(config, tmp_path):
    path = tmp_path / "steps.rrd"
    total = 1000
    with Telemetry(config, parse_sink(f"save={path}"), batch_period_s=0.01, chunk_s=0.1) as telemetry:
        for tick in range(total):
            row = list(joint_row(config, tick, with_pinn=False))
            row[-1] = 0 if tick < 600 else 2
            telemetry.append(tick, tick / 1000, *row)
            if tick % 100 == 99:
                time.sleep(0.02)
    assert telemetry.sent_rows == total
    state = rrd_rows(path, "safety/state", "Scalars:scalars")
    assert {0, 599, 600, total - 1} <= set(state)  # the step, drawn as one, and both ends
    assert all(value == [0.0 if tick < 600 else 2.0] for tick, value in state.items())
    assert len(state) < total / 10  # not every row
    assert len(rrd_rows(path, "loop/period_us", "Scalars:scalars")) == total  # loop timing: every row


def test_a_mock_run_logs_joints_every_tick_and_poses_at_display_rate(config, tmp_path):
    from runtime.cli import main
    from runtime.telemetry import FILE_CHUNK_S, POSE_HZ

    path = tmp_path / "walk.rrd"
    started = time.monotonic()
    assert main(["--backend", "mock", "--duration", "1", "--controller", "standing", "--rerun", f"save={path}"]) == 0
    elapsed = time.monotonic() - started
    knee = rrd_rows(path, "joints/r_knee", "Scalars:scalars")
    assert len(knee) == config.loop_hz  # 1 s of ticks, every one
    base = rrd_rows(path, "world/robot/base", "Transform3D:translation")
    ticks = sorted(base)
    spacing = set(np.diff(ticks))
    assert len(spacing) == 1 and config.loop_hz / spacing.pop() <= POSE_HZ  # evenly, at <= 30 Hz
    assert len(ticks) >= POSE_HZ * 0.8
    # The base trajectory: few segments (one per chunk) that together pass through every base pose in order.
    strips = rrd_rows(path, "world/base_trajectory", "LineStrips3D:strips")
    segments = [np.array(strips[t][0]) for t in sorted(strips)]
    assert 1 <= len(segments) <= elapsed / FILE_CHUNK_S + 2  # one per chunk (was one per 50 ms)
    points = np.vstack([segments[0]] + [s[1:] for s in segments[1:]])
    assert points == pytest.approx(np.array([base[t][0] for t in ticks]), abs=1e-6)


def test_gap_residuals_go_out_under_gap_joint_with_nan_where_none_was_scored(config, tmp_path):
    path = tmp_path / "gap.rrd"
    knee = config.joints.index("r_knee")
    n = config.n_joints
    with Telemetry(config, parse_sink(f"save={path}"), gap=True, batch_period_s=0.01) as telemetry:
        for tick in range(50):
            residual = None if tick == 0 else tuple(tick + np.arange(n) / 100 + k / 1000 for k in range(3))
            telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=True), gap=residual)
    assert telemetry.error is None and telemetry.sent_rows == 50
    assert {f"gap/{name}" for name in config.joints} <= rrd_entity_paths(path)
    rows = rrd_rows(path, "gap/r_knee", "Scalars:scalars")  # qd residual, q residual, qd window RMS
    assert sorted(rows) == list(range(50))
    assert all(math.isnan(v) for v in rows[0])  # no prediction scored on the first tick
    assert rows[20] == pytest.approx([20 + knee / 100 + k / 1000 for k in range(3)])
    # The joint series are where they were: the gap blocks do not shift them.
    assert rrd_rows(path, "joints/r_knee", "Scalars:scalars")[20] == pytest.approx(
        [20 + knee / 100 + k / 1000 for k in (0, 2, 4, 1, 3, 5, 6)])


def test_without_a_gap_monitor_there_is_no_gap_entity(config, tmp_path):
    path = tmp_path / "nogap.rrd"
    with Telemetry(config, parse_sink(f"save={path}"), batch_period_s=0.01) as telemetry:
        for tick in range(10):
            telemetry.append(tick, tick / 1000, *joint_row(config, tick, with_pinn=False),
                             gap=(np.ones(config.n_joints),) * 3)  # ignored: made without gap=True
    assert not any(p.startswith("gap/") for p in rrd_entity_paths(path))
    assert sorted(rrd_rows(path, "joints/r_knee", "Scalars:scalars")) == list(range(10))


def test_a_saved_recording_says_where_it_went(config, tmp_path, capsys):
    path = tmp_path / "where.rrd"
    with Telemetry(config, parse_sink(f"save={path}"), batch_period_s=0.01) as telemetry:
        telemetry.append(0, 0.0, *joint_row(config, 0, with_pinn=False))
    out = capsys.readouterr().out
    assert f"rerun recording saved to {path}" in out and path.exists()


def test_a_run_with_a_reference_model_streams_its_gap_monitor(config, tmp_path):
    from runtime.cli import main

    path = tmp_path / "gap_run.rrd"
    stats = tmp_path / "stats.json"
    assert main(["--backend", "mock", "--duration", "0.2", "--controller", "standing", "--transfer", "eq9",
                 "--gap", "default", "--rerun", f"save={path}", "--stats", str(stats)]) == 0
    rows = rrd_rows(path, "gap/r_knee", "Scalars:scalars")  # qd residual, q residual, qd window RMS
    assert len(rows) == 200 and all(math.isnan(v) for v in rows[0])  # nothing predicted before the first tick
    scored = [rows[t] for t in range(1, 200)]
    assert all(math.isfinite(v) for row in scored for v in row) and max(abs(r[0]) for r in scored) > 0
    # The window RMS is the RMS of the last window's velocity residuals (window_s 0.1 s = 100 ticks).
    last = [rows[t][0] for t in range(100, 200)]
    assert rows[199][2] == pytest.approx(math.sqrt(sum(v * v for v in last) / len(last)), rel=1e-9)
    import json

    summary = json.loads(stats.read_text())
    assert summary["gap_samples"] == 199 and summary["gap_residual_rms"]["r_knee"] > 0


def test_a_host_stall_is_an_event_on_the_timeline(tmp_path):
    """A host stall the backend's witness saw goes to the safety/events log at the tick after it, with its length
    (here a backend whose witness reports 10 ms not run before its 100th reading: within the bound, ridden through)."""
    from bruce_hw import load_config
    from bruce_hw.echo import EchoBackend
    from runtime.loop.run import run_session

    class StalledOnce(EchoBackend):
        host_witness = True

        def __init__(self, config):
            super().__init__(config)
            self.reads, self.stall_at = 0, None

        def _read(self):
            state = super()._read()
            self.reads += 1
            if self.reads == 100:
                self.stall_at = self.clock()
            return state

        def stalled_between(self, t0, t1):
            return 0.010 if self.stall_at is not None and t0 < self.stall_at <= t1 else 0.0

    config = load_config()
    path = tmp_path / "run.rrd"
    run_session(StalledOnce(config), config, duration=0.3, realtime=False, controller_kind="standing",
                rerun=parse_sink(f"save={path}"))
    events = [text for texts in rrd_rows(path, "safety/events", "TextLog:text").values() for text in texts]
    assert events.count("host stall: not run for 10.0 ms") == 1, events
