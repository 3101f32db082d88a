"""bruce-collect: short walks in the mock, recorded by an observer of the runtime loop."""

import json

import numpy as np
import pytest

from bruce_hw.mock import MujocoBackend
from runtime.control.commands import COMMAND_AXES
from training.collect import POLICY_CLIP, SAMPLE_BOX, CollectError, CollectSettings, collect, main
from training.dataset import config_hash, load_dataset
from training.episodes import transition_indices

SHORT = CollectSettings(seconds=3.0, seed=3, segment_s=1.0)


class SpyMock(MujocoBackend):
    """The mock, logging per read the torque its motors applied during the step and the base state; an optional
    push of the base at a given read of the first mock made (`push_at`, `impulse`)."""

    made = 0

    def __init__(self, config, push_at=None, impulse=(0.0, 4.0, 0.0)):
        super().__init__(config)
        self.first = SpyMock.made == 0
        SpyMock.made += 1
        self.push_at, self.impulse = push_at, np.array(impulse)
        self.applied = []

    def _read(self):
        if self.first and len(self.applied) == self.push_at:
            self.push(self.impulse, 0.1)
        robot = super()._read()
        self.applied.append(self.data.actuator_force[self._acts].copy())
        return robot


def spy_factory(mocks, **kwargs):
    SpyMock.made = 0

    def make(config):
        mocks.append(SpyMock(config, **kwargs))
        return mocks[-1]

    return make


@pytest.fixture(scope="module")
def short_walk(config):
    """Three seconds of samples, one-second command segments, and the mocks that made them."""
    mocks = []
    return collect(config, SHORT, backend_factory=spy_factory(mocks)), mocks


def test_cli_writes_the_documented_file(config, tmp_path, capsys):
    out = tmp_path / "walk.npz"
    assert main(["--seconds", "3", "--seed", "3", "--segment-s", "1", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "s simulated" in captured.err and "100%" in captured.err  # the progress bar, on stderr
    assert f"wrote {out}: 3000 samples" in captured.out
    with np.load(out) as raw:
        assert set(raw.files) == {"q", "qd", "tau", "episode", "dt", "metadata"}
        assert raw["q"].dtype == np.float64 and raw["episode"].dtype == np.int64 and raw["dt"].shape == ()
    data = load_dataset(out, config)
    assert data.q.shape == data.qd.shape == data.tau.shape == (3000, config.n_joints)
    assert data.episode.shape == (3000,) and data.dt == config.dt
    meta = data.metadata
    assert meta["joint_names"] == list(config.joints) and meta["config_hash"] == config_hash(config)
    assert meta["seed"] == 3 and meta["samples"] == 3000 and meta["commands"]["segment_s"] == 1.0
    assert meta["commands"]["clipped_to"] == {k: list(v) for k, v in POLICY_CLIP.items()}
    assert len(meta["policy_sha256"]) == 64 and meta["package_version"] and meta["created"]
    assert meta["command"].startswith("bruce-collect --seconds 3")


def test_samples_are_finite_within_torque_limits_and_walk(config, short_walk):
    data, _ = short_walk
    for name in ("q", "qd", "tau"):
        assert np.all(np.isfinite(getattr(data, name))), name
    assert np.all(np.abs(data.tau) <= config.tau_limit + 1e-12)
    motor = np.abs(data.tau @ config.coupling.joint_from_actuator)  # tau_motor = B^T tau_joint
    assert motor.max() <= config.actuator_torque_limit + 1e-9
    assert np.max(np.ptp(data.q, axis=0)) > 0.1 and np.std(data.qd) > 0.1  # it steps, not stands
    for episode in data.metadata["episodes"]:  # and it goes somewhere
        moved = np.hypot(*np.subtract(episode["base_xy_end"], episode["base_xy_start"]))
        assert moved > 0.05, episode


def test_tau_is_the_torque_the_simulator_applied(config, short_walk):
    data, mocks = short_walk
    episodes = data.metadata["episodes"]
    assert len(mocks) == len(episodes)  # one fresh mock per episode
    # run_session reads once before the loop; tick k is read k + 1, and its torque acts during read k + 2.
    warmup = round(config.safety.soft_start_s * config.loop_hz)
    for mock, episode in zip(mocks, episodes, strict=True):
        applied = np.array(mock.applied)
        tau = data.tau[episode["first_index"]:episode["first_index"] + episode["samples"]]
        # Equal up to rounding: the mock's per-actuator saturation maps the torque through the coupling and back.
        np.testing.assert_allclose(tau[:-1], applied[warmup + 2:warmup + len(tau) + 1], rtol=0, atol=1e-12)


def test_commands_are_sampled_from_the_box_and_clipped(short_walk):
    data, _ = short_walk
    segments = data.metadata["segments"]
    starts = {e["episode"]: e["first_index"] for e in data.metadata["episodes"]}
    # Every second within each episode (a fall starts a new episode, and its commands anew).
    assert [s["t_s"] for s in segments if s["episode"] == 0][:2] == [0.0, 1.0]
    for segment in segments:
        assert segment["first_index"] == starts[segment["episode"]] + round(segment["t_s"] * 1000)
        assert segment["t_s"] == round(segment["t_s"])
        for axis, sampled, cmd in zip(COMMAND_AXES, segment["sampled"], segment["cmd"], strict=True):
            assert SAMPLE_BOX[axis][0] <= sampled <= SAMPLE_BOX[axis][1]
            assert cmd == min(max(sampled, POLICY_CLIP[axis][0]), POLICY_CLIP[axis][1])


def test_clip_is_the_range_the_committed_policy_was_distilled_on(config):
    settings = json.loads(config.models.policy.with_name(config.models.policy.name + ".json").read_text())
    distilled = settings["distill"]["settings"]
    assert POLICY_CLIP == {axis: tuple(distilled[axis]) for axis in COMMAND_AXES}


def test_the_same_seed_gives_the_same_data(config, short_walk):
    first, _ = short_walk
    again = collect(config, SHORT)
    for name in ("q", "qd", "tau", "episode"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    assert {**again.metadata, "created": None} == {**first.metadata, "created": None}


def test_a_fall_ends_the_episode_and_drops_its_tail(config):
    mocks = []
    push_at = 2000  # read 2000: 0.5 s after the warm-up, 4 N s sideways
    data = collect(config, SHORT, backend_factory=spy_factory(mocks, push_at=push_at))
    episodes = data.metadata["episodes"]
    assert len(episodes) >= 2 and episodes[0]["end"].startswith("fell at") and episodes[-1]["end"] == "duration"
    warmup, trim = 1500, 500
    fell_at = round(episodes[0]["simulated_s"] * config.loop_hz) - 1  # the tick the fall was detected on
    assert episodes[0]["samples"] == fell_at - trim - warmup > 0
    first, second = episodes[0]["samples"], episodes[1]["first_index"]
    assert first == second and list(np.unique(data.episode)) == list(range(len(episodes)))
    assert first - 1 not in transition_indices(data.episode)  # no transition from the fall into the next episode
    # The new episode starts from the standing robot again, exactly as the first did.
    np.testing.assert_array_equal(data.q[second], data.q[0])
    assert len(mocks) == len(episodes)


def test_a_controller_that_always_falls_fails_instead_of_looping(config, monkeypatch):
    import training.collect as collect_module

    monkeypatch.setattr(collect_module, "MAX_EMPTY_EPISODES", 2)

    class FallsAtOnce(MujocoBackend):
        def _read(self):
            if self.data.time == 0.0:
                self.push(np.array([0.0, 8.0, 0.0]), 0.1)
            return super()._read()

    with pytest.raises(CollectError, match="2 episodes in a row ended before"):
        collect(config, SHORT, backend_factory=FallsAtOnce)
