"""Sweeps, collection and PPO on a real two-node Ray cluster on this machine (`ray.cluster_utils.Cluster`: two raylets,
each with its own workers), against the local executor's results; a worker or an actor killed mid-run.

Marked `cluster`: they run by default (and in CI) wherever Ray is installed (`pip install -e '.[cluster]'`)."""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pytest

ray = pytest.importorskip("ray")
torch = pytest.importorskip("torch")

from training.collect import main as collect_main  # noqa: E402
from training.evaluation.cli import main as bruce_eval  # noqa: E402
from training.rl.train_cli import main as train_policy  # noqa: E402

pytestmark = pytest.mark.cluster

SWEEP = ["transfer", "--gap", "default,none", "--experiments", "tracking", "--seeds", "0,1", "--seconds", "3",
         "--latencies-ms", "", "--gain-scales", "", "--schemes", "shadow"]
PPO = ["--set", "env.num_envs=8", "--set", "env.shards=2", "--set", "ppo.num_steps_per_env=6",
       "--set", "train.iterations=3", "--set", "train.checkpoint_every=1", "--set", "env.episode_s=0.3",
       "--set", "ppo.actor.hidden_dims=[16]", "--set", "ppo.critic.hidden_dims=[16]", "--set", "env.nthread=1",
       "--no-progress"]


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    yield cluster
    if ray.is_initialized():
        ray.shutdown()
    cluster.shutdown()


@pytest.fixture(scope="module")
def local_table(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    assert bruce_eval([*SWEEP, "--jobs", "2", "--out", str(out)]) == 0
    return _table(out)


def _table(out) -> dict:
    """transfer.json less the command line that made it."""
    document = json.loads((out / "transfer.json").read_text())
    del document["meta"]["command"]
    return document


def _ray(cluster) -> list[str]:
    return ["--executor", "ray", "--ray-address", cluster.address]


class Killer(threading.Thread):
    """SIGKILLs the first process titled `ray::<name>` (Ray titles a worker by the task or actor it runs), once
    `ready()` holds."""

    def __init__(self, name: str, ready=lambda: True):
        super().__init__(daemon=True)
        self.title, self.ready, self.killed, self.stop = f"ray::{name}".encode(), ready, None, False

    def run(self) -> None:
        while not self.stop and self.killed is None:
            if self.ready():
                for pid in (p for p in os.listdir("/proc") if p.isdigit()):
                    try:
                        with open(f"/proc/{pid}/cmdline", "rb") as f:
                            command = f.read()
                    except OSError:
                        continue
                    if command.startswith(self.title):
                        os.kill(int(pid), signal.SIGKILL)
                        self.killed = int(pid)
                        return
            time.sleep(0.05)


def test_a_sweep_on_two_nodes_gives_the_local_table_and_resumes(cluster, local_table, tmp_path, capsys):
    out = tmp_path / "ray"
    assert bruce_eval([*SWEEP, *_ray(cluster), "--out", str(out)]) == 0
    assert _table(out) == local_table
    assert len(cluster.list_all_nodes()) == 2
    # a resumed sweep runs only what is missing: drop two finished runs, run again
    finished = sorted((out / "runs").glob("*.json"))
    dropped = [p for p in finished if json.loads(p.read_text())["spec"]["mode"] != "nominal"][:2]
    for path in dropped:
        path.unlink()
        path.with_suffix(".npz").unlink(missing_ok=True)
    capsys.readouterr()
    assert bruce_eval([*SWEEP, *_ray(cluster), "--out", str(out)]) == 0
    progress = [line for line in capsys.readouterr().err.splitlines() if line.startswith("bruce-eval transfer:")]
    assert len(progress) == len(finished)
    assert len([line for line in progress if not line.endswith(" cached")]) == len(dropped)
    assert _table(out) == local_table


def test_a_worker_killed_mid_sweep_has_its_run_retried_and_the_table_unchanged(cluster, local_table, tmp_path):
    killer = Killer("_run_scored")
    killer.start()
    try:
        assert bruce_eval([*SWEEP, *_ray(cluster), "--out", str(tmp_path)]) == 0
    finally:
        killer.stop = True
    assert killer.killed is not None  # a run really was cut off
    assert _table(tmp_path) == local_table
    runs = [json.loads(p.read_text()) for p in (tmp_path / "runs").glob("*.json")]
    assert len(runs) == len({json.dumps(r["spec"], sort_keys=True) for r in runs})  # none counted twice


def test_collection_over_seeds_on_the_cluster_is_the_local_dataset(cluster, tmp_path):
    args = ["--seconds", "1", "--seeds", "0,1", "--no-progress"]
    assert collect_main([*args, "--jobs", "2", "--out", str(tmp_path / "local.npz")]) == 0
    assert collect_main([*args, *_ray(cluster), "--out", str(tmp_path / "ray.npz")]) == 0
    local, remote = np.load(tmp_path / "local.npz"), np.load(tmp_path / "ray.npz")
    for key in ("q", "qd", "tau", "episode"):
        np.testing.assert_array_equal(local[key], remote[key])
    meta = json.loads(str(remote["metadata"]))
    assert meta["seeds"] == [0, 1] and {e["seed"] for e in meta["episodes"]} == {0, 1}


def test_policies_and_the_walking_grid_on_the_cluster_are_the_local_tables(cluster, tmp_path):
    from bruce_hw.config import load_config

    policy = str(load_config().models.policy)
    policies = ["policies", "--policy", f"distilled={policy}", "--gap", "none", "--experiments", "tracking",
                "--seeds", "0", "--seconds", "3"]
    assert bruce_eval([*policies, "--jobs", "2", "--out", str(tmp_path / "pl")]) == 0
    assert bruce_eval([*policies, *_ray(cluster), "--out", str(tmp_path / "pr")]) == 0
    assert (tmp_path / "pl" / "policies.md").read_text() == (tmp_path / "pr" / "policies.md").read_text()
    walking = ["walking", "--policy", policy, "--seconds", "2.5"]
    assert bruce_eval([*walking, "--jobs", "2", "--out", str(tmp_path / "wl")]) == 0
    assert bruce_eval([*walking, *_ray(cluster), "--out", str(tmp_path / "wr")]) == 0
    local, remote = (json.loads((tmp_path / d / "walking.json").read_text()) for d in ("wl", "wr"))
    assert local == remote and len(local["grid"]) == 17


def _networks(run) -> dict:
    return torch.load(run / "checkpoint.pt", weights_only=False)["trainer"]["alg"]


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, torch.Tensor):
        return torch.equal(a, b)
    return a == b


def test_ppo_on_ray_actors_is_the_local_run_and_resumes(cluster, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert train_policy(["--out", str(local), *PPO]) == 0
    assert train_policy(["--out", str(remote), *PPO, *_ray(cluster), "--stop-after", "1"]) == 0
    assert torch.load(remote / "checkpoint.pt", weights_only=False)["trainer"]["iteration"] == 1
    assert train_policy(["--out", str(remote), *PPO, *_ray(cluster), "--resume"]) == 0
    assert _same(_networks(local), _networks(remote))


def test_a_killed_env_actor_is_restarted_and_training_goes_on(cluster, caplog):
    """Through the same calls bruce-train-policy makes: an actor killed between two iterations is replaced, the step
    it missed counts as time-outs, and PPO goes on with the current policy."""
    from bruce_hw.config import load_config
    from training.executor import RayExecutor
    from training.rl.ppo_loop import PolicyTrainer
    from training.rl.train_cli import make_env
    from training.rl.train_config import load_training_config
    from training.rl.vec_env import RslVecEnv

    overrides = [item for i, item in enumerate(PPO) if i and PPO[i - 1] == "--set"]
    config = load_training_config(overrides=overrides)
    robot = load_config()
    with RayExecutor(cluster.address, ship=[robot.path.parent]) as executor:
        env = make_env(robot, config, executor)
        trainer = PolicyTrainer(RslVecEnv(env, config.action_scale, config.reward_scale), config.ppo, seed=0)
        trainer.step_iteration()
        victim = env.shards.pids()[1]
        os.kill(victim, signal.SIGKILL)
        with caplog.at_level("WARNING", logger="bruce-train-policy"):
            stats = [trainer.step_iteration() for _ in range(2)]
        assert env.shards.restarts == 1 and env.shards.pids()[1] != victim
        assert any("env shard 1: its actor died" in r.getMessage() for r in caplog.records)
        assert trainer.iteration == 3 and all(s.steps == config.env.num_envs * 6 for s in stats)
        assert all(np.isfinite(v) for s in stats for v in s.losses.values())
        env.close()
