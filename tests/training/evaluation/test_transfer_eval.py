"""`bruce-eval transfer`: the metrics on paths and traces with known answers, and one short end-to-end run."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from bruce_hw.reality_gap import load_gap
from training.evaluation import transfer_eval, transfer_runs
from training.evaluation.cli import main as eval_main
from training.evaluation.transfer_cache import spec_key
from training.evaluation.transfer_eval import TransferSettings, plan_suite
from training.evaluation.transfer_metrics import (
    aggregate,
    circle_deviation,
    deviation_from_simulator,
    distance_to_path,
    drift,
    ideal_path,
    joint_rmse,
    offset_and_shape,
)
from training.evaluation.transfer_runs import EXPERIMENTS, RunRecord, RunSpec

DT = 1e-3


def record(t, q=None, xy=None, yaw=None, fell=False) -> RunRecord:
    n = len(t)
    q = np.zeros((n, 2)) if q is None else q
    return RunRecord(spec=RunSpec("x", (0.0, 0.0, 0.0), t[-1], "direct", None), t=t, q=q, qd=np.zeros_like(q),
                     tau=np.zeros_like(q), xy=np.zeros((n, 2)) if xy is None else xy,
                     yaw=np.zeros(n) if yaw is None else yaw, velocity=np.zeros((n, 3)), fell=fell, stop_cause="")


def test_joint_rmse_is_per_joint_after_the_skip_over_the_common_length():
    t = np.arange(5000) * DT
    rng = np.random.default_rng(0)
    reference = record(t, q=rng.normal(size=(5000, 2)))
    offset = np.array([0.1, -0.3])
    shorter = record(t[:4000], q=reference.q[:4000] + offset)
    shorter.q[:2000] += 5.0  # inside the start-up skip: not scored
    np.testing.assert_allclose(joint_rmse(shorter, reference, skip_s=2.0), np.abs(offset), rtol=1e-12)
    # hand-computed on a ramp
    ramp = record(t, q=reference.q + np.linspace(0, 1, 5000)[:, None])
    expected = np.sqrt(np.mean(np.linspace(0, 1, 5000)[2000:] ** 2))
    np.testing.assert_allclose(joint_rmse(ramp, reference, skip_s=2.0), [expected, expected], rtol=1e-12)


def test_offset_and_shape_split_the_rmse_per_joint():
    t = np.arange(5000) * DT
    rng = np.random.default_rng(1)
    reference = record(t, q=rng.normal(size=(5000, 2)))
    wobble = rng.normal(size=(5000, 2)) * [0.05, 0.2]
    run = record(t, q=reference.q + [0.1, -0.3] + wobble)
    offset, shape = offset_and_shape(run, reference, skip_s=2.0)
    error = run.q[2000:] - reference.q[2000:]
    np.testing.assert_allclose(offset, error.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(offset ** 2 + shape ** 2, joint_rmse(run, reference, skip_s=2.0) ** 2, rtol=1e-12)
    np.testing.assert_allclose(shape, wobble[2000:].std(axis=0), rtol=1e-12)
    still, _ = offset_and_shape(record(t, q=reference.q + [0.1, -0.3]), reference)
    np.testing.assert_allclose(still, [0.1, -0.3], rtol=1e-9)  # a pure offset has no shape
    assert np.all(offset_and_shape(record(t, q=reference.q + [0.1, -0.3]), reference)[1] < 1e-12)


def test_deviation_from_the_simulator_is_the_distance_at_the_same_tick():
    t = np.arange(0, 10.0, DT)
    simulator = ideal_path((0.4, 0.0, 0.4), t, np.zeros(2), 0.0, ramp_s=0.0)
    shifted = simulator + [0.3, 0.4]
    shifted[:1000] += 5.0  # inside the start-up skip: not scored
    d = deviation_from_simulator(record(t, xy=shifted), record(t, xy=simulator), skip_s=2.0)
    assert d["mean_deviation_from_simulator"] == pytest.approx(0.5) and d["max_deviation_from_simulator"] == \
        pytest.approx(0.5)
    # the same circle, 1 s late: on the ideal circle both, yet 0.4 m/s x 1 s behind (a chord of the unit circle)
    late = np.vstack([np.zeros((1000, 2)), simulator[:-1000]])
    chord = 2 * math.sin(0.4 * 1.0 / 2)
    d = deviation_from_simulator(record(t, xy=late), record(t, xy=simulator), skip_s=2.0)
    assert d["mean_deviation_from_simulator"] == pytest.approx(chord, rel=1e-3)
    assert circle_deviation(record(t, xy=late), (0.4, 0.0, 0.4), skip_s=2.0)["mean_radial_deviation"] < 1e-3
    # a run that stopped early is scored over the ticks both reached
    short = deviation_from_simulator(record(t[:4000], xy=shifted[:4000]), record(t, xy=simulator), skip_s=2.0)
    assert short["mean_deviation_from_simulator"] == pytest.approx(0.5)


def test_ideal_path_integrates_the_ramped_command():
    t = np.arange(0, 10.0 + DT / 2, DT)
    straight = ideal_path((-0.5, 0.0, 0.0), t, np.array([1.0, 2.0]), 0.0, ramp_s=1.0)
    # ramp 0 -> -0.5 over 1 s covers -0.25 m, then 9 s at -0.5
    np.testing.assert_allclose(straight[-1], [1.0 - 0.25 - 4.5, 2.0], atol=1e-6)
    turning = ideal_path((0.4, 0.0, 0.4), t, np.zeros(2), math.pi / 2, ramp_s=0.0)
    radius = 1.0
    centre = np.array([-radius, 0.0])  # left of a robot facing +y
    np.testing.assert_allclose(np.linalg.norm(turning - centre, axis=1), radius, atol=1e-4)


def test_circle_deviation_is_zero_on_the_ideal_circle_and_the_offset_on_a_wider_one():
    t = np.arange(0, 15.0, DT)
    vx, wz = 0.4, 0.4
    path = ideal_path((vx, 0.0, wz), t, np.zeros(2), 0.0, ramp_s=0.0)
    on = circle_deviation(record(t, xy=path), (vx, 0.0, wz))
    assert on["mean_radial_deviation"] < 1e-4 and on["radius"] == pytest.approx(1.0)
    centre = np.array([0.0, 1.0])
    wider = centre + (path - centre) * 1.2  # radius 1.2, same centre: deviation 0.2 (the start is moved too)
    wider[0] = 0.0  # the circle is placed through the start pose, which is the real start
    off = circle_deviation(record(t, xy=wider), (vx, 0.0, wz), skip_s=2.0)
    assert off["mean_radial_deviation"] == pytest.approx(0.2, abs=1e-6)
    right = circle_deviation(record(t, xy=path * [1, -1]), (vx, 0.0, -wz))  # a right turn mirrors it
    assert right["mean_radial_deviation"] < 1e-4


def test_drift_is_the_distance_from_the_commanded_path():
    t = np.arange(0, 20.0, DT)
    back = ideal_path((-0.5, 0.0, 0.0), t, np.zeros(2), 0.0)
    sideways = back + [0.0, 0.3]
    short = back * 0.9
    d = drift(record(t, xy=np.vstack([np.zeros((1, 2)), sideways[1:]])), (-0.5, 0.0, 0.0))
    assert d["drift"] == pytest.approx(0.3, abs=1e-9)
    assert d["endpoint_error"] == pytest.approx(0.3, abs=1e-9)
    s = drift(record(t, xy=short), (-0.5, 0.0, 0.0))
    assert s["drift"] < 1e-9 and s["endpoint_error"] == pytest.approx(0.1 * abs(back[-1, 0]), rel=1e-9)
    turn = drift(record(t, xy=np.vstack([np.zeros((len(t) - 1, 2)), [[0.3, 0.4]]])), (0.0, 0.0, 0.5))
    assert turn["drift"] == pytest.approx(0.5) and turn["distance_from_origin"] == pytest.approx(0.5)
    assert distance_to_path(np.array([2.0, 1.0]), np.array([[0.0, 0.0], [1.0, 0.0]])) == pytest.approx(math.sqrt(2))


def test_aggregate_means_over_seeds_and_counts_falls():
    seeds = [{"fell": False, "joint_rmse": 0.1, "per": [1.0, 2.0]}, {"fell": True, "joint_rmse": 0.3,
                                                                     "per": [3.0, 4.0]}]
    out = aggregate(seeds)
    assert out["fell"] is True and out["falls"] == 1 and out["seeds"] == 2
    assert out["joint_rmse"] == pytest.approx(0.2) and out["joint_rmse_std"] == pytest.approx(math.sqrt(0.02))
    assert out["per"] == [2.0, 3.0]


def test_bruce_eval_transfer_writes_the_table_and_figures(tmp_path, capsys):
    out = tmp_path / "transfer"
    code = eval_main(["transfer", "--gap", "mild", "--out", str(out), "--seconds", "2.6", "--seeds", "0,1",
                      "--sweep-seeds", "0", "--latencies-ms", "0,3", "--gain-scales", "0,1", "--jobs", "2"])
    assert code == 0
    report = json.loads((out / "transfer.json").read_text())
    for name in ("tracking", "circle", "reverse", "turn"):
        for mode in ("direct", "pinn"):
            entry = report[name][mode]
            assert entry["seeds"] == 2 and isinstance(entry["fell"], bool) and math.isfinite(entry["drift"])
    assert report["tracking"]["nominal"]["joint_rmse"] == 0.0
    for mode in ("direct", "pinn"):
        assert report["tracking"][mode]["joint_rmse"] > 0.0  # the gap moves the joints off the simulator's
        assert math.isfinite(report["circle"][mode]["mean_radial_deviation"])
        assert {"fell", "drift"} <= set(report["reverse"][mode]) and {"fell", "drift"} <= set(report["turn"][mode])
    # with the Eq. 9 gains at 0, PINN transfer is direct transfer: the same torques, the same run
    gain = {row["scale"]: row["pinn"]["joint_rmse"] for row in report["sweeps"]["eq9_gain"]}
    latency = {row["latency_ms"]: row for row in report["sweeps"]["latency"]}
    assert gain[0.0] == pytest.approx(report["tracking"]["direct"]["per_seed"][0]["joint_rmse"], rel=1e-12)
    assert latency[3.0]["direct"]["joint_rmse"] != latency[0.0]["direct"]["joint_rmse"]
    # the look-ahead variant rolls the reference over the gap's latency: mild has 1 ms, and the sweep follows it
    assert report["meta"]["lookahead"] == "auto (1)" and report["tracking"]["pinn_ahead"]["seeds"] == 2
    assert [latency[ms]["pinn_ahead"]["lookahead_ticks"] for ms in (0.0, 3.0)] == [0, 3]
    assert report["meta"]["gap_name"] == "mild" and report["meta"]["seeds"] == [0, 1]
    for name in ("transfer.md", *(e.figure for e in EXPERIMENTS), "fig10_sweeps.png"):
        assert (out / name).stat().st_size > 0, name
    assert "| tracking | joint RMSE (rad) |" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--gap", "no_such_profile"], "no_such_profile"),
    (["--experiments", "tracking,moonwalk"], "--experiments"),
    (["--seconds", "1"], "--seconds"),
    (["--latencies-ms", "1,x"], "--latencies-ms"),
])
def test_bad_options_are_named(tmp_path, capsys, args, message):
    assert eval_main(["transfer", "--out", str(tmp_path / "x"), *args]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


# -- several profiles, and the run cache ----------------------------------------------------------------------------
def suite_settings(**changes) -> TransferSettings:
    profiles = (("default", load_gap("default")), ("none", load_gap("none")))
    base = dict(gap=profiles[0][1], gap_name="default", profiles=profiles, seeds=(0, 1, 2), seconds=2.6,
                experiments=("tracking", "circle"), latencies_ms=(0.0, 4.0), gain_scales=(), sweep_seeds=(0,),
                schemes=("shadow",))
    return TransferSettings(**{**base, **changes})


def test_a_suite_plans_every_profile_and_sweeps_the_first_only():
    specs = plan_suite(suite_settings())
    by_profile = {}
    for spec in specs:
        by_profile.setdefault("nominal" if spec.gap is None else spec.gap.source.rsplit("/", 1)[-1], []).append(spec)
    runs = {name: {(s.experiment, s.mode, s.gap.seed) for s in group} for name, group in by_profile.items()
            if name != "nominal"}
    for name in ("default.yaml", "none.yaml"):
        assert {(e, m, seed) for e in ("tracking", "circle") for m in ("direct", "shadow") for seed in (0, 1, 2)} \
            <= runs[name]
    assert {s.experiment for s in by_profile["none.yaml"]} == {"tracking", "circle"}
    sweeps = [s for s in specs if s.experiment == "sweep_latency"]
    assert {s.gap.actuator_latency_s for s in sweeps} == {0.0, 0.004} and len(sweeps) == 4
    assert all(s.gap.sensor_latency_s == load_gap("default").sensor_latency_s for s in sweeps)  # default's sweep
    # the nominal runs are the profiles' shared reference: one run each
    assert len({spec_key(s) for s in by_profile["nominal"]}) == 2
    # a profile without noise makes the same run whatever its seed; one with noise does not
    none_keys = {spec_key(s) for s in by_profile["none.yaml"]}
    default_keys = {spec_key(s) for s in by_profile["default.yaml"] if s.experiment == "tracking"}
    assert len(none_keys) == 4 and len(default_keys) == 6


def fake_run(spec: RunSpec, calls: list) -> RunRecord:
    """A stand-in for a mock run: joints off the simulator by an amount the mode, the gap and the seed set."""
    calls.append(spec)
    t = np.arange(round(spec.seconds / DT)) * DT
    path = ideal_path(spec.command, t, np.zeros(2), 0.0)
    if spec.mode == "nominal":
        error = 0.0
    else:
        error = 0.01 * (1 + spec.gap.actuator_latency_s * 1e3 + spec.gap.seed) * (0.3 if spec.mode == "shadow" else 1)
    q = np.zeros((len(t), 10)) + error
    return RunRecord(spec=spec, t=t, q=q, qd=np.zeros_like(q), tau=np.zeros_like(q), xy=path + error,
                     yaw=np.zeros(len(t)), velocity=np.zeros((len(t), 3)), fell=False, stop_cause="duration reached")


def test_an_interrupted_suite_resumes_and_a_finished_one_runs_nothing(tmp_path, monkeypatch):
    calls: list = []
    budget = {"left": 7}

    def interrupted(spec):
        if budget["left"] == 0:
            raise KeyboardInterrupt
        budget["left"] -= 1
        return fake_run(spec, calls)

    args = ["transfer", "--gap", "default,none", "--out", str(tmp_path / "out"), "--seconds", "2.6", "--seeds",
            "0,1,2", "--experiments", "tracking,circle", "--latencies-ms", "0,4", "--sweep-seeds", "0",
            "--gain-scales", "", "--schemes", "shadow", "--jobs", "1", "--estimator", "truth"]  # issue 20's bars
    monkeypatch.setattr(transfer_eval, "run_one", interrupted)
    with pytest.raises(KeyboardInterrupt):
        eval_main(args)
    assert len(calls) == 7
    monkeypatch.setattr(transfer_eval, "run_one", lambda spec: fake_run(spec, calls))
    assert eval_main(args) == 0
    distinct = {spec_key(s) for s in calls}
    assert len(distinct) == len(calls)  # nothing ran twice
    first = json.loads((tmp_path / "out" / "transfer.json").read_text())
    ran = len(calls)
    assert eval_main(args) == 0
    assert len(calls) == ran  # the second call re-ran nothing
    again = json.loads((tmp_path / "out" / "transfer.json").read_text())
    first["meta"].pop("command"), again["meta"].pop("command")
    assert again == first
    # the layout: the first profile at the top, every profile under "profiles", the bars per scheme
    assert first["tracking"] == first["profiles"]["default"]["tracking"]
    assert first["profiles"]["none"]["tracking"]["shadow"]["joint_rmse"] == pytest.approx(0.003)
    assert first["tracking"]["shadow"]["joint_rmse"] == pytest.approx(0.003 * (1 + 2.0 + 1.0), rel=1e-6)
    assert first["profiles"]["none"]["tracking"]["shadow"]["joint_rmse_std"] < 1e-15  # one deterministic run
    assert first["acceptance"]["shadow"]["none"] == {"value": pytest.approx(0.003), "limit": 0.01, "pass": True,
                                                     "profile": "none"}
    assert first["sweeps"]["latency_tolerance_ms"] == {"direct": 4.0, "shadow": 4.0}
    assert first["recommended"] == "shadow"
    assert "| none | shadow |" in (tmp_path / "out" / "transfer.md").read_text()


@pytest.mark.parametrize("args, message", [
    (["--gap", "default,,none"], "--gap: an empty profile name"),
    (["--gap", "none,none"], "--gap: 'none' given twice"),
    (["--gap", "none", "--suite", "acceptance"], "--gap and --suite: give one"),
    (["--gap", "default,no_such_profile"], "no_such_profile"),
])
def test_bad_profile_lists_are_named(tmp_path, capsys, args, message):
    assert eval_main(["transfer", "--out", str(tmp_path / "x"), *args]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_bruce_eval_transfer_runs_without_torch_or_matplotlib(tmp_path):
    """The base install (`pip install -e .`) has neither: the rehearsal needs only onnxruntime and MuJoCo."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None; sys.modules['matplotlib'] = None\n"
            "from training.evaluation.cli import main\n"
            f"raise SystemExit(main(['transfer', '--gap', 'default', '--out', {str(tmp_path)!r}, '--seconds', '2.5', "
            "'--seeds', '0', '--experiments', 'tracking', '--latencies-ms', '', '--gain-scales', '', "
            "'--schemes', 'direct', '--jobs', '1']))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "transfer.json").exists() and "no figures (matplotlib is not installed" in done.stdout


@pytest.mark.parametrize("fall_time", [None, 7.25])
def test_a_cached_record_reads_back_with_its_fall(tmp_path, fall_time):
    """A resumed suite reads the kept records back (a run that fell among them)."""
    from training.evaluation.transfer_cache import RunCache

    t = np.arange(0, 1.0, DT)
    kept = record(t, xy=np.zeros((len(t), 2)))
    kept.fell, kept.fall_time = fall_time is not None, fall_time
    cache = RunCache(tmp_path)
    cache.save_record("k", kept)
    back = cache.record("k", kept.spec, RunRecord)
    assert back.fell is kept.fell and back.fall_time == fall_time
    np.testing.assert_array_equal(back.xy, kept.xy)


def test_a_run_cut_short_by_a_signal_is_not_a_result(monkeypatch):
    """SIGTERM to a worker ends its session through damping with stop cause "SIGTERM": run_one must not hand that
    back as a finished run (it would be cached, and a resumed suite would score a 0.3-s run)."""
    import runtime.loop.run
    from runtime.loop.run import RunSummary

    def stopped(backend, config, **kwargs):
        summary = RunSummary(backend="mock")
        summary.stop_cause = "SIGTERM"
        return summary

    monkeypatch.setattr(runtime.loop.run, "run_session", stopped)
    spec = RunSpec("tracking", (0.4, 0.0, 0.0), 1.0, "direct", load_gap("default"))
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        transfer_runs.run_one(spec)


def test_cache_key_changes_with_the_robot_config_and_not_with_where_it_lives(tmp_path):
    """A cached run is the run of its config: a changed setting (or model) in the config's folder is a new key; the
    same folder copied elsewhere (another checkout) keeps its keys."""
    import shutil

    from bruce_hw.config import DEFAULT_CONFIG

    spec = plan_suite(suite_settings())[0]
    one, two = tmp_path / "one" / "robots", tmp_path / "two" / "robots"
    for folder in (one, two):
        shutil.copytree(Path(DEFAULT_CONFIG).parent, folder)
    at_one = dataclasses.replace(spec, config=str(one / "bruce.yaml"))
    at_two = dataclasses.replace(spec, config=str(two / "bruce.yaml"))
    assert spec_key(at_one) == spec_key(at_two) == spec_key(dataclasses.replace(spec, config=None))
    yaml = two / "bruce.yaml"
    yaml.write_text(yaml.read_text().replace("dead_band_rad: 0.004", "dead_band_rad: 0.003"))
    assert spec_key(at_two) != spec_key(at_one)
    (one / "pinn" / "bruce_pinn.onnx").write_bytes(b"retrained")
    assert spec_key(at_one) not in (spec_key(at_two), spec_key(dataclasses.replace(spec, config=None)))
