"""Another simulator's trajectories (docs/byo_data.md): a CSV or .npz in its own joint order, units and rate becomes
our dataset (bruce-import-data) and trains a PINN (bruce-train --data, converted or directly); wrong names, units,
rates and values are refused with one line naming the file and the column."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bruce_hw.config import load_config
from training.collect import CollectSettings, collect
from training.dataset import load_dataset
from training.dynamics.checkpoint import read_checkpoint
from training.dynamics.train import main as bruce_train
from training.external_data import convert, read_external
from training.import_cli import main as bruce_import

STEP = 2  # the source keeps every 2nd sample of the mock's 1 kHz walk: 500 Hz
SPLIT = 1000  # the walk's sample where the source's second episode starts


@pytest.fixture(scope="module")
def walk():
    """2 s of the committed policy walking the mock at 1 kHz (the real collection path): the truth the 500 Hz file
    is cut from, and what the in-between resampled samples are compared with."""
    return collect(load_config(), CollectSettings(seconds=2.0, seed=1, segment_s=1.0))


def source_columns(walk, config, step=STEP, q_unit="rad", order_seed=0) -> dict[str, np.ndarray]:
    """The walk as another simulator's log: every `step`th sample, joints in a shuffled order, two episodes with
    ids 7 and 3, q in `q_unit` (the header says so)."""
    rows = np.arange(0, len(walk), step)
    columns = {"time[s]": rows * walk.dt, "episode": np.where(rows < SPLIT, 7, 3)}
    scale = np.degrees(1.0) if q_unit == "deg" else 1.0
    for j in np.random.default_rng(order_seed).permutation(config.n_joints):
        name = config.joints[j]
        columns[f"q.{name}[{q_unit}]"] = walk.q[rows, j] * scale
        columns[f"qd.{name}[rad/s]"] = walk.qd[rows, j]
        columns[f"tau.{name}[N*m]"] = walk.tau[rows, j]
    return columns


def write_csv(path, columns: dict[str, np.ndarray]):
    np.savetxt(path, np.column_stack(list(columns.values())), delimiter=",", header=",".join(columns),
               comments="", fmt="%.17g")
    return path


def run(command, argv, capsys) -> tuple[int, str, list[str]]:
    code = command([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err.strip().splitlines()


@pytest.mark.parametrize("q_unit", ["rad", "deg"])
def test_a_500hz_csv_in_another_joint_order_becomes_our_1khz_dataset(walk, config, tmp_path, capsys, q_unit):
    source = write_csv(tmp_path / "isaac.csv", source_columns(walk, config, q_unit=q_unit))
    code, out, err = run(bruce_import, [source, "--out", tmp_path / "walk.npz", "--resample"], capsys)
    assert code == 0, err
    assert "at 500 Hz" in out and "resampled to 1000 Hz" in out and "2 episode(s)" in out, out

    data = load_dataset(tmp_path / "walk.npz", config)
    # Episode 7 (source rows 0..499) spans truth samples 0..998, episode 3 (rows 500..999) truth 1000..1998.
    first, second = np.arange(0, SPLIT - 1), np.arange(SPLIT, len(walk) - 1)
    truth = np.concatenate([first, second])
    assert len(data) == len(truth) and np.bincount(data.episode).tolist() == [len(first), len(second)]
    shared = np.flatnonzero(truth % STEP == 0)
    between = np.flatnonzero(truth % STEP == 1)
    # At the source's instants the values are the source's, in config order (the shuffle undone by name).
    for name in ("q", "qd", "tau"):
        np.testing.assert_allclose(getattr(data, name)[shared], getattr(walk, name)[truth[shared]], atol=1e-12)
    # In between: q off by 1 % of a tick's motion at most (the spline: 0.3 %; a straight line would be 2.3 %), qd
    # by less than half what holding it would be (linear: 13 %; the spline's derivative would be 71 %), tau held.
    q_error = data.q[between] - walk.q[truth[between]]
    q_tick = walk.q[truth[between]] - walk.q[truth[between] - 1]
    assert np.sqrt(np.mean(q_error ** 2)) < 0.01 * np.sqrt(np.mean(q_tick ** 2))
    qd_error = data.qd[between] - walk.qd[truth[between]]
    qd_held = walk.qd[truth[between] - 1] - walk.qd[truth[between]]
    assert np.sqrt(np.mean(qd_error ** 2)) < 0.5 * np.sqrt(np.mean(qd_held ** 2))
    np.testing.assert_array_equal(data.tau[between], walk.tau[truth[between] - 1])

    meta = data.metadata
    assert meta["source"]["rate_hz"] == pytest.approx(500) and meta["source"]["episode_ids"] == [7, 3]
    assert meta["source"]["columns"]["r_knee"]["q"] == {"from": f"q.r_knee[{q_unit}]", "unit": q_unit}
    assert meta["resampling"]["method"] == "interpolate" and meta["command"].startswith("bruce-import-data ")


@pytest.mark.slow  # trains a PINN twice (seconds): left out of the fast subset
def test_the_converted_file_and_the_csv_itself_train_a_pinn(walk, config, tmp_path, capsys):
    source = write_csv(tmp_path / "isaac.csv", source_columns(walk, config))
    assert run(bruce_import, [source, "--out", tmp_path / "walk.npz", "--resample"], capsys)[0] == 0
    for data, extra in ((tmp_path / "walk.npz", []), (source, ["--resample"])):
        out = tmp_path / f"{data.stem}_{data.suffix[1:]}.pt"
        code, stdout, err = run(bruce_train, ["--data", data, "--model", "pinn", "--preset", "small", "--epochs", 1,
                                              "--out", out, "--no-progress", *extra], capsys)
        assert code == 0, err
        assert ("converted in memory" in stdout) == (data == source), stdout
        checkpoint = read_checkpoint(out)
        losses = [h["loss"] for h in checkpoint["train"]["history"]]
        assert len(losses) == 1 and np.isfinite(losses[0])
        assert checkpoint["data"]["config_hash"] == load_dataset(tmp_path / "walk.npz", config).metadata[
            "config_hash"]


def rename(columns, old, new):
    return {new if key == old else key: value for key, value in columns.items()}


def edited(column, transform):
    def edit(columns):
        columns = dict(columns)
        columns[column] = transform(columns[column])
        return columns
    return edit


def swap_rows(a, b):
    def edit(values):
        values = values.copy()
        values[[a, b]] = values[[b, a]]
        return values
    return edit


BAD = {
    # what is wrong: (edit of the columns, expected in the message)
    "a joint name typo": (lambda c: rename(c, "q.r_hip_yaw[rad]", "q.r_hip_yaww[rad]"),
                          ["column 'q.r_hip_yaww[rad]'", "did you mean 'r_hip_yaw'?"]),
    "an unknown unit": (lambda c: rename(c, "tau.r_knee[N*m]", "tau.r_knee[furlong]"),
                        ["column 'tau.r_knee[furlong]'", "[furlong]", "N*m"]),
    "an unknown quantity": (lambda c: {**c, "qdd.r_knee": c["qd.r_knee[rad/s]"]}, ["unknown column 'qdd.r_knee'"]),
    "degrees labelled rad": (edited("q.r_knee[rad]", np.degrees), ["column 'q.r_knee[rad]'", "looks like degrees",
                                                                   "q.r_knee[deg]"]),
    "deg/s labelled rad/s": (edited("qd.l_knee[rad/s]", np.degrees), ["column 'qd.l_knee[rad/s]'", "deg/s"]),
    "a torque over the limit": (edited("tau.r_knee[N*m]", lambda v: 10 * v), ["column 'tau.r_knee[N*m]'",
                                                                              "torque limit"]),
    "a missing joint": (lambda c: {k: v for k, v in c.items() if ".l_ankle[" not in k}, ["joint(s) ['l_ankle']"]),
    "a missing quantity": (lambda c: {k: v for k, v in c.items() if k != "qd.l_ankle[rad/s]"},
                           ["no column 'qd.l_ankle'"]),
    "an extra joint": (lambda c: {**c, "q.r_shoulder[rad]": 0 * c["time[s]"]}, ["'r_shoulder'", "--ignore-extra"]),
    "a non-finite value": (edited("qd.r_ankle[rad/s]", lambda v: np.where(np.arange(len(v)) == 40, np.nan, v)),
                           ["column 'qd.r_ankle[rad/s]'", "non-finite", "line 42"]),
    "an episode split in two": (edited("episode", lambda v: np.where(np.arange(len(v)) >= 900, 7, v)),
                                ["column 'episode'", "episode 7 comes back at line 902"]),
    "time going back": (edited("time[s]", swap_rows(10, 11)), ["column 'time[s]'", "does not increase", "line 12"]),
    "a dropped frame": (lambda c: {k: np.delete(v, 100) for k, v in c.items()}, ["not uniform", "line 102"]),
}


@pytest.mark.parametrize("case", BAD)
def test_a_bad_file_is_refused_with_one_line_naming_the_column(walk, config, tmp_path, capsys, case):
    edit, says = BAD[case]
    source = write_csv(tmp_path / "bad.csv", edit(source_columns(walk, config)))
    code, _, err = run(bruce_import, [source, "--out", tmp_path / "out.npz", "--resample"], capsys)
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"bruce-import-data: error: {source}: "), err
    assert all(text in err[0] for text in says), err
    assert not (tmp_path / "out.npz").exists()


@pytest.mark.parametrize("command, argv", [(bruce_import, ["--out", "out.npz"]),
                                           (bruce_train, ["--model", "pinn", "--out", "x.pt"])])
def test_another_rate_without_resample_is_refused_naming_both_rates(walk, config, tmp_path, capsys, monkeypatch,
                                                                    command, argv):
    monkeypatch.chdir(tmp_path)
    source = write_csv(tmp_path / "isaac.csv", source_columns(walk, config))
    code, _, err = run(command, [*argv, *(["--data"] if command is bruce_train else []), source], capsys)
    assert code == 2 and len(err) == 1, err
    assert all(text in err[0] for text in (str(source), "500 Hz", "rates.loop_hz = 1000 Hz", "--resample")), err


def test_a_bad_cell_and_a_too_coarse_log_are_refused(walk, config, tmp_path, capsys):
    source = write_csv(tmp_path / "text.csv", source_columns(walk, config))
    lines = source.read_text().splitlines()
    cells = lines[5].split(",")
    cells[3] = "abc"
    lines[5] = ",".join(cells)
    source.write_text("\n".join(lines) + "\n")
    header = lines[0].split(",")
    code, _, err = run(bruce_import, [source, "--out", tmp_path / "out.npz"], capsys)
    assert code == 2 and f"line 6, column {header[3]!r}: 'abc' is not a number" in err[-1], err

    coarse = write_csv(tmp_path / "coarse.csv", source_columns(walk, config, step=40))  # 25 Hz
    code, _, err = run(bruce_import, [coarse, "--out", tmp_path / "out.npz", "--resample"], capsys)
    assert code == 2 and "25 Hz is too coarse" in err[-1] and "at most 20x" in err[-1], err


def test_extra_joints_are_dropped_when_asked(walk, config, tmp_path, capsys):
    columns = source_columns(walk, config, step=1)
    columns.update({"q.r_shoulder": 0 * columns["time[s]"], "qd.r_shoulder": 0 * columns["time[s]"],
                    "tau.r_shoulder": 0 * columns["time[s]"]})
    source = write_csv(tmp_path / "arms.csv", columns)
    code, out, err = run(bruce_import, [source, "--out", tmp_path / "out.npz", "--ignore-extra"], capsys)
    assert code == 0, err
    assert "not resampled" in out and "dropped joints the config lacks: ['r_shoulder']" in out, out
    np.testing.assert_allclose(load_dataset(tmp_path / "out.npz", config).q, walk.q, atol=1e-12)


def test_an_external_npz_in_degrees_and_its_own_order_maps_by_name(walk, config, tmp_path, capsys):
    order = np.random.default_rng(5).permutation(config.n_joints)
    path = tmp_path / "playground.npz"
    np.savez(path, time=np.arange(len(walk)) * config.dt, q=np.degrees(walk.q[:, order]),
             qd=np.degrees(walk.qd[:, order]), tau=walk.tau[:, order], joint_names=np.array(config.joints)[order],
             units=np.array(json.dumps({"q": "deg", "qd": "deg/s", "tau": "Nm"})))
    code, out, err = run(bruce_import, [path, "--out", tmp_path / "out.npz", "--source-name", "MJX"], capsys)
    assert code == 0 and "not resampled" in out, err
    data = load_dataset(tmp_path / "out.npz", config)
    for name in ("q", "qd", "tau"):
        np.testing.assert_allclose(getattr(data, name), getattr(walk, name), atol=1e-12)
    assert data.metadata["source"]["name"] == "MJX" and data.metadata["source"]["format"] == "npz"

    np.savez(path, time=np.arange(len(walk)) * config.dt, q=walk.q, qd=walk.qd, tau=walk.tau,
             joint_names=np.array(config.joints), units=np.array(json.dumps({"tau": "lbf*ft"})))
    code, _, err = run(bruce_import, [path, "--out", tmp_path / "out.npz"], capsys)
    assert code == 2 and "array 'tau' has unit [lbf*ft]" in err[-1], err


def test_a_faster_log_is_decimated_only_by_an_integer_factor(walk, tmp_path):
    """A 1 kHz log for a 500 Hz loop: every 2nd sample, the torque the mean over the tick; at 1.5x: refused."""
    slow = load_config(overrides=["rates.loop_hz=500"])
    source = write_csv(tmp_path / "fast.csv", source_columns(walk, slow, step=1))
    data, conversion = convert(read_external(source), slow, resample=True)
    assert conversion.resampling["factor"] == 2 and data.dt == pytest.approx(2e-3)
    kept = np.concatenate([np.arange(0, SPLIT, 2), np.arange(SPLIT, len(walk), 2)])
    np.testing.assert_allclose(data.q, walk.q[kept], atol=1e-12)
    np.testing.assert_allclose(data.tau[:-1], (walk.tau[kept[:-1]] + walk.tau[kept[:-1] + 1]) / 2, atol=1e-12)

    columns = source_columns(walk, slow, step=1)
    columns["time[s]"] = columns["time[s]"] * 4 / 3  # 750 Hz
    with pytest.raises(ValueError, match="750 Hz is faster than rates.loop_hz = 500 Hz and not an integer"):
        convert(read_external(write_csv(tmp_path / "odd.csv", columns)), slow, resample=True)
