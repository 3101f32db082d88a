"""The executors for independent runs (training/executor.py) and what the commands build on them: every call's result
comes back once, under its own index; a bad executor option is one line; seeds merge into one dataset in order;
the walking environment in shards steps as the plain environment. The cluster itself: tests/training/test_cluster.py."""

from __future__ import annotations

import argparse
import operator
import sys

import numpy as np
import pytest

from bruce_hw.config import load_config
from training.collect import merge
from training.dataset import Dataset
from training.evaluation.cli import main as bruce_eval
from training.executor import ExecutorError, LocalExecutor, add_executor_arguments, make_executor
from training.rl.env import BruceWalkEnv, WalkEnvConfig
from training.rl.env_shards import LocalShards, ShardedWalkEnv, shard_config, shard_seeds


@pytest.mark.parametrize("jobs", [1, 2])
def test_local_executor_returns_every_result_once_under_its_index(jobs):
    calls = [(i, 10 * i) for i in range(7)]
    results = dict(LocalExecutor(jobs).map(operator.add, calls))
    assert results == {i: 11 * i for i in range(7)}


def test_a_ray_address_without_the_ray_executor_is_refused():
    p = argparse.ArgumentParser()
    add_executor_arguments(p)
    with pytest.raises(ExecutorError, match="--ray-address: only with --executor ray"):
        make_executor(p.parse_args(["--ray-address", "auto"]), jobs=1)
    assert make_executor(p.parse_args([]), jobs=3).jobs == 3


def test_the_ray_executor_without_ray_installed_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    code = bruce_eval(["transfer", "--gap", "none", "--experiments", "tracking", "--seeds", "0", "--seconds", "3",
                       "--latencies-ms", "", "--gain-scales", "", "--schemes", "shadow", "--executor", "ray",
                       "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err == ["bruce-eval: error: --executor ray: Ray is not installed "
                                 "(pip install -e '.[cluster]')"]


def _part(seed: int, episodes: list[int]) -> Dataset:
    n = len(episodes)
    rng = np.random.default_rng(seed)
    q, qd, tau = (rng.standard_normal((n, 2)) for _ in range(3))
    ids = np.asarray(episodes)
    firsts = {e: int(np.flatnonzero(ids == e)[0]) for e in sorted(set(episodes))}
    meta = {"seed": seed, "seconds": n * 0.001, "samples": n, "joint_names": ["a", "b"], "config_hash": "x",
            "episodes": [{"episode": e, "first_index": i} for e, i in firsts.items()],
            "segments": [{"episode": e, "first_index": i, "cmd": [0.1, 0, 0]} for e, i in firsts.items()]}
    return Dataset(q, qd, tau, ids, 0.001, meta, "test")


def test_seeds_merge_into_one_dataset_in_order_with_episodes_numbered_on():
    a, b = _part(3, [0, 0, 1, 1, 1]), _part(5, [0, 0, 0])
    merged = merge([a, b], "bruce-collect --seeds 3,5")
    np.testing.assert_array_equal(merged.q, np.concatenate([a.q, b.q]))
    np.testing.assert_array_equal(merged.episode, [0, 0, 1, 1, 1, 2, 2, 2])
    meta = merged.metadata
    assert meta["seeds"] == [3, 5] and meta["samples"] == 8 and meta["command"] == "bruce-collect --seeds 3,5"
    assert [(e["episode"], e["first_index"], e["seed"]) for e in meta["episodes"]] == [(0, 0, 3), (1, 2, 3),
                                                                                       (2, 5, 5)]
    assert [(g["episode"], g["first_index"]) for g in meta["segments"]] == [(0, 0), (1, 2), (2, 5)]


def test_an_uneven_shard_split_names_the_key():
    with pytest.raises(ValueError, match=r"env.shards: 3 must divide env.num_envs \(8\)"):
        shard_config(WalkEnvConfig(num_envs=8, nthread=0), 3)


def test_one_shard_steps_as_the_plain_env_and_shards_checkpoint_and_restore():
    robot = load_config()
    config = WalkEnvConfig(num_envs=4, nthread=0, episode_s=0.1)
    plain = BruceWalkEnv(robot, config, seed=7)
    one = ShardedWalkEnv(robot, config, LocalShards(robot, config, shard_seeds(7, 1)))
    two = ShardedWalkEnv(robot, config, LocalShards(robot, shard_config(config, 2), shard_seeds(7, 2)))
    rng = np.random.default_rng(0)
    actions = [robot.standing_pose + 0.1 * rng.standard_normal((4, robot.n_joints)) for _ in range(14)]
    for a in actions[:12]:  # past one episode's end (10 steps): the restarts too
        expected, got = plain.step(a), one.step(a)
        for k in ("policy", "critic"):
            np.testing.assert_array_equal(expected[0][k], got[0][k])
        for i in (1, 2, 3):
            np.testing.assert_array_equal(expected[i], got[i])
        np.testing.assert_array_equal(expected[4]["reward_terms"]["alive"], got[4]["reward_terms"]["alive"])
        two.step(a)
    saved = two.get_state()
    after = [two.step(a)[1] for a in actions[12:]]
    two.set_state(saved)
    np.testing.assert_array_equal([two.step(a)[1] for a in actions[12:]], after)
    assert set(one.get_state()) == set(plain.get_state())  # one shard: the plain env's checkpoint


@pytest.mark.parametrize("address, says", [("127.0.0.1:1", "no Ray head answers there"),
                                           ("auto", "Could not find any running Ray instance")])
def test_no_cluster_at_the_address_is_one_line_in_seconds(address, says, tmp_path, capsys, monkeypatch):
    pytest.importorskip("ray")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    code = bruce_eval(["transfer", "--gap", "none", "--experiments", "tracking", "--seeds", "0", "--seconds", "3",
                       "--latencies-ms", "", "--gain-scales", "", "--schemes", "shadow", "--executor", "ray",
                       "--ray-address", address, "--out", str(tmp_path)])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("bruce-eval")]
    assert code == 1 and len(err) == 1 and f"--ray-address {address}: cannot join" in err[0] and says in err[0]
