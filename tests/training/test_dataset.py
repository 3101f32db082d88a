"""The dataset layer: file checks against the robot config, the time split, statistics and BPTT windows."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bruce_hw.config import load_config
from training.dataset import (
    STD_FLOOR,
    Dataset,
    DatasetError,
    DatasetStats,
    compute_stats,
    config_hash,
    load_dataset,
    save_dataset,
    split_by_time,
    windows,
)
from training.episodes import episode_runs, transition_indices

DT = 1e-3


def synthetic(episode_lengths, n=10, seed=0, metadata=None) -> Dataset:
    """Random joint arrays with episodes of the given lengths (ids 0, 1, ...)."""
    rng = np.random.default_rng(seed)
    total = sum(episode_lengths)
    episode = np.repeat(np.arange(len(episode_lengths)), episode_lengths)
    return Dataset(rng.normal(size=(total, n)), rng.normal(size=(total, n)) * 3, rng.normal(size=(total, n)) * 2,
                   episode, DT, metadata or {})


@pytest.fixture
def saved(config, tmp_path):
    """A valid dataset file for `config`, and a writer of broken variants of it."""
    data = synthetic([30, 20], metadata={"joint_names": list(config.joints), "config_hash": config_hash(config),
                                         "seed": 7})
    path = save_dataset(tmp_path / "good.npz", data)

    def variant(name="bad.npz", drop=(), **arrays):
        with np.load(path) as raw:
            content = {k: raw[k] for k in raw.files if k not in drop}
        content.update(arrays)
        np.savez(tmp_path / name, **content)
        return tmp_path / name

    return path, data, variant


def metadata_with(path, **changes):
    with np.load(path) as raw:
        meta = json.loads(str(raw["metadata"]))
    meta.update(changes)
    return np.array(json.dumps(meta))


# -- the file ----------------------------------------------------------------------------------------------------
def test_a_saved_file_loads_back_unchanged(config, saved):
    path, data, _ = saved
    loaded = load_dataset(path, config)
    for name in ("q", "qd", "tau", "episode"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(data, name))
    assert loaded.dt == config.dt and loaded.metadata["seed"] == 7 and loaded.metadata["format_version"] == 1
    assert loaded.source == str(path) and loaded.span == (0, 50)


def test_save_keeps_the_name_it_is_given(config, tmp_path):
    data = synthetic([5], metadata={"joint_names": list(config.joints), "config_hash": config_hash(config)})
    assert save_dataset(tmp_path / "walk.data", data).name == "walk.data"  # no ".npz" appended
    assert (tmp_path / "walk.data").is_file() and not list(tmp_path.glob("*.partial"))


@pytest.mark.parametrize("case, match", [
    ("missing", r"missing array 'tau'"),
    ("joint_count", r"array 'q' has shape \[50, 9\], expected \[T, 10\]"),
    ("joint_names", r"joint_names .* do not match joints.names"),
    ("hash", r"config_hash 'f+' does not match"),
    ("dt", r"dt = 0.002 s does not match the control period"),
    ("nan", r"array 'qd' has 1 non-finite value\(s\), the first at sample 5, r_knee"),
    ("episode_order", r"array 'episode' must be non-decreasing .* at sample 30"),
    ("episode_length", r"array 'episode' has shape \[49\], expected \[50\]"),
    ("version", r"format_version is 99, expected 1"),
])
def test_a_mismatched_file_is_rejected_naming_the_file_and_the_problem(config, saved, case, match):
    path, data, variant = saved
    qd = data.qd.copy()
    qd[5, config.joints.index("r_knee")] = np.nan
    episode = data.episode.copy()
    episode[30:] = 0
    episode[:30] = 1
    bad = {
        "missing": lambda: variant(drop=("tau",)),
        "joint_count": lambda: variant(q=data.q[:, :9], qd=data.qd[:, :9], tau=data.tau[:, :9]),
        "joint_names": lambda: variant(metadata=metadata_with(path, joint_names=list(config.joints)[::-1])),
        "hash": lambda: variant(metadata=metadata_with(path, config_hash="f" * 64)),
        "dt": lambda: variant(dt=np.float64(0.002)),
        "nan": lambda: variant(qd=qd),
        "episode_order": lambda: variant(episode=episode),
        "episode_length": lambda: variant(episode=data.episode[:49]),
        "version": lambda: variant(metadata=metadata_with(path, format_version=99)),
    }[case]()
    with pytest.raises(DatasetError, match=match) as failure:
        load_dataset(bad, config)
    assert str(bad) in str(failure.value)


def test_what_is_not_a_dataset_is_rejected(config, tmp_path):
    with pytest.raises(DatasetError, match="dataset file not found"):
        load_dataset(tmp_path / "absent.npz", config)
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(DatasetError, match=r"text.npz: not a dataset .npz"):
        load_dataset(tmp_path / "text.npz", config)


def test_the_config_hash_follows_the_robot_not_the_plumbing(config):
    assert config_hash(load_config(overrides=["buses.bear.port=/dev/ttyUSB7"])) == config_hash(config)
    assert config_hash(load_config(overrides=["gains.eq8.kp.r_knee=21.0"])) != config_hash(config)
    assert config_hash(load_config(overrides=["rates.policy_hz=50"])) != config_hash(config)


def test_a_dataset_never_freezes_or_shares_the_callers_arrays():
    q = np.zeros((4, 2))
    data = Dataset(q, q, q, np.zeros(4, dtype=int), DT)
    q[0, 0] = 1.0  # still writeable, and the dataset kept its own copy
    assert data.q[0, 0] == 0.0 and not data.q.flags.writeable


# -- the split ---------------------------------------------------------------------------------------------------
def test_the_split_is_contiguous_and_uses_no_transition_across_a_boundary():
    data = synthetic([37, 50, 13])  # the split (80 of 100) falls inside episode 1
    train, test = split_by_time(data)
    assert train.span == (0, 80) and test.span == (80, 100) and len(train) + len(test) == len(data)
    np.testing.assert_array_equal(train.q, data.q[:80])
    np.testing.assert_array_equal(test.tau, data.tau[80:])
    used = set((transition_indices(train.episode) + train.span[0]).tolist()) | set(
        (transition_indices(test.episode) + test.span[0]).tolist())
    every = set(range(99)) - {36, 86}  # 36 -> 37 and 86 -> 87 cross episodes
    assert used == every - {79}  # 79 -> 80 crosses the split
    assert "train: samples 0..80" in train.source and "test: samples 80..100" in test.source


@pytest.mark.parametrize("fraction", [0.0, 1.0, -0.2])
def test_a_split_fraction_outside_0_1_is_refused(fraction):
    with pytest.raises(ValueError, match="train_fraction"):
        split_by_time(synthetic([10]), fraction)


# -- statistics --------------------------------------------------------------------------------------------------
def test_stats_equal_a_hand_computation_over_the_valid_transitions():
    data = synthetic([6, 1, 5], n=3, seed=4)
    valid = [0, 1, 2, 3, 4, 7, 8, 9, 10]  # not 5 (-> episode 1), 6 (a lone sample), 11 (the last)
    stats = compute_stats(data)
    q, qd, tau = data.q, data.qd, data.tau
    for name, values in (("q", q), ("qd", qd), ("tau", tau)):
        rows = np.array([values[t] for t in valid])
        np.testing.assert_allclose(getattr(stats, f"{name}_mean"), rows.sum(axis=0) / 9, rtol=1e-12)
        spread = np.sqrt(((rows - rows.mean(axis=0)) ** 2).sum(axis=0) / 9)
        np.testing.assert_allclose(getattr(stats, f"{name}_std"), spread, rtol=1e-12)
    residual = np.array([q[t + 1] - q[t] - qd[t] * DT for t in valid])
    step = np.array([qd[t + 1] - qd[t] for t in valid])
    np.testing.assert_allclose(stats.q_inc_std, residual.std(axis=0), rtol=1e-12)
    np.testing.assert_allclose(stats.qd_inc_std, step.std(axis=0), rtol=1e-12)


def test_stats_come_from_the_training_part_only():
    data = synthetic([100])
    changed = Dataset(data.q, data.qd, np.concatenate([data.tau[:80], data.tau[80:] * 100]), data.episode, DT)
    assert np.array_equal(compute_stats(split_by_time(data)[0]).tau_std,
                          compute_stats(split_by_time(changed)[0]).tau_std)
    assert not np.array_equal(compute_stats(data).tau_std, compute_stats(changed).tau_std)


def test_a_channel_that_never_changes_gets_the_floor_not_zero():
    data = synthetic([20], n=2)
    still = Dataset(np.zeros_like(data.q), np.zeros_like(data.qd), data.tau, data.episode, DT)
    stats = compute_stats(still)
    assert np.all(stats.q_std == STD_FLOOR) and np.all(stats.q_inc_std == STD_FLOOR)
    assert np.all(stats.tau_std > STD_FLOOR)


def test_stats_check_their_fields_and_round_trip_through_json():
    stats = compute_stats(synthetic([30], n=4))
    assert DatasetStats.from_json(json.loads(json.dumps(stats.to_json()))).to_json() == stats.to_json()
    fields = stats.to_json()
    with pytest.raises(ValueError, match="qd_std: a std must be > 0"):
        DatasetStats(**{**fields, "qd_std": [1.0, 0.0, 1.0, 1.0]})
    with pytest.raises(ValueError, match=r"tau_mean: expected shape \[4\]"):
        DatasetStats(**{**fields, "tau_mean": [0.0, 0.0]})


# -- windows -----------------------------------------------------------------------------------------------------
def test_windows_chain_within_an_episode_and_gather_the_samples():
    data = synthetic([25, 9, 31], n=3)  # episode 1 is too short for a window of 10 transitions
    w = windows(data, 10)
    np.testing.assert_array_equal(w.start, [0, 10, 34, 44, 54])
    np.testing.assert_array_equal(w.episode, [0, 0, 2, 2, 2])
    np.testing.assert_array_equal(w.continues, [-1, 0, -1, 2, 3])
    batch = w.gather(data, [1, 3], dtype=np.float32)
    assert batch["q"].shape == (2, 11, 3) and batch["tau"].dtype == np.float32
    np.testing.assert_array_equal(batch["qd"][1], data.qd[44:55].astype(np.float32))


def test_windows_with_another_stride_or_an_offset():
    data = synthetic([40])
    overlapping = windows(data, 10, stride=5)
    np.testing.assert_array_equal(overlapping.start, [0, 5, 10, 15, 20, 25])
    assert np.all(overlapping.continues == -1)
    np.testing.assert_array_equal(windows(data, 10, offset=3).start, [3, 13, 23])
    with pytest.raises(ValueError, match="offset"):
        windows(data, 10, offset=10)


@settings(max_examples=60, deadline=None)
@given(lengths=st.lists(st.integers(1, 40), min_size=2, max_size=6), length=st.integers(1, 12),
       offset=st.integers(0, 11), n_streams=st.integers(1, 4))
def test_windows_never_cross_an_episode_and_streams_carry_only_continuations(lengths, length, offset, n_streams):
    data = synthetic(lengths, n=1)
    w = windows(data, length, offset=offset % length)
    ranges = episode_runs(data.episode)
    expected = sum(len(range(begin + offset % length, end - length, length)) for begin, end in ranges)
    assert len(w) == expected
    for i, start in enumerate(w.start):
        span = data.episode[start:start + length + 1]
        assert len(span) == length + 1 and np.all(span == w.episode[i])
        if w.continues[i] >= 0:
            assert w.start[w.continues[i]] + length == start
    if len(w) >= n_streams:
        index, fresh = w.streams(n_streams)
        assert index.shape == (len(w) // n_streams, n_streams) and fresh[0].all()
        for k in range(1, len(index)):
            for b in range(n_streams):
                continues = w.continues[index[k, b]] == index[k - 1, b]
                assert fresh[k, b] != continues
