"""A term added the way a newcomer adds one (tests/support/example_term.py: a function and its registration) reaches
the runtime's observation through `run_session` on the mock (batch 1) and the training environment's (batch N), in a
spec that reorders the joints, scales the term and stacks its history."""

from __future__ import annotations

import importlib
import sys

import numpy as np
import pytest
import yaml

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import CommandSchedule
from runtime.loop.run import run_session
from runtime.observation.registry import OBSERVATION_TERMS

SCALE = 2.0
# clock 2, tracking_error 2 frames x 10 joints, q 10
CLOCK, NEWEST, PREVIOUS, Q = slice(0, 2), slice(2, 12), slice(12, 22), slice(22, 32)
OBS_SIZE = 32


@pytest.fixture
def example_term():
    """The example term registered for one test (the registry is module state: the other tests see our terms)."""
    saved = dict(OBSERVATION_TERMS)
    sys.modules.pop("support.example_term", None)
    yield importlib.import_module("support.example_term")
    OBSERVATION_TERMS.clear()
    OBSERVATION_TERMS.update(saved)
    sys.modules.pop("support.example_term", None)


@pytest.fixture
def spec_path(config, tmp_path):
    tree = {"joints": list(reversed(config.joints)),  # not the config's order: the term is reordered
            "observation": ["clock", {"term": "tracking_error", "scale": SCALE, "history": 2,
                                      "history_order": "newest_first"}, "q"],
            "action": {"scale": 0.1, "offset": "standing"}}
    path = tmp_path / "tracking.yaml"
    path.write_text(yaml.safe_dump(tree))
    return path


@pytest.fixture
def tracking_policy(onnx_graph, tmp_path):
    """A random tanh layer, obs [1, 32] -> action [1, 10]."""
    from onnx import TensorProto, helper

    rng = np.random.default_rng(11)
    weights = helper.make_tensor("w", TensorProto.FLOAT, [OBS_SIZE, 10], rng.normal(0.0, 0.3, OBS_SIZE * 10).tolist())
    nodes = [helper.make_node("MatMul", ["obs", "w"], ["y"]), helper.make_node("Tanh", ["y"], ["action"])]
    return onnx_graph(tmp_path / "tracking.onnx", {"obs": (1, OBS_SIZE)}, {"action": (1, 10)}, nodes, [weights])


class Recording:
    """The controller's measured q, the targets in force before the call, and the observation, per policy call."""

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def reset(self, q):
        self.inner.reset(q)
        self.calls = []

    def __call__(self, state, base, command):
        before = self.inner.last_action.copy()
        a = self.inner(state, base, command)
        self.calls.append((state.joints.q.copy(), before, self.inner.obs.copy()))
        return a


def test_the_new_term_reaches_the_runtime_observation(example_term, spec_path, tracking_policy):
    from runtime.control.controllers import build_controller

    config = load_config(overrides=[f"policy.spec={spec_path}"])
    controller, name = build_controller(config, tracking_policy)
    assert "spec tracking.yaml" in name and controller.builder.size == OBS_SIZE
    recording = Recording(controller)
    summary = run_session(MujocoBackend(config), config, duration=0.3, realtime=False, controller=recording,
                          commands=CommandSchedule.constant(0.2, 0.0, 0.0))
    assert summary.exit_code == 0 and len(recording.calls) == 30
    order = controller.spec.order
    previous = None
    for q, before, obs in recording.calls:
        frame = SCALE * (q - before)[order]
        np.testing.assert_array_equal(obs[NEWEST], frame)
        np.testing.assert_array_equal(obs[PREVIOUS], frame if previous is None else previous)  # filled at the start
        np.testing.assert_array_equal(obs[Q], q[order])
        previous = frame
    assert np.abs(np.array([obs[NEWEST] for *_, obs in recording.calls])).max() > 1e-3  # not a zero term


def test_the_new_term_reaches_the_training_observation(example_term, spec_path, config):
    from training.rl.env import BruceWalkEnv, WalkEnvConfig
    from training.rl.randomisation import RandomisationRanges

    no_noise = RandomisationRanges(**{f"noise_{name}": (0.0, 0.0) for name in
                                      ("q_rad", "qd_rads", "linvel_ms", "angvel_rads", "euler_rad")})
    env = BruceWalkEnv(config, WalkEnvConfig(num_envs=3, nthread=1, policy_spec=str(spec_path),
                                             randomisation=no_noise), seed=2)
    order = np.array(list(reversed(range(10))))
    actions = config.standing_pose + np.random.default_rng(1).normal(0.0, 0.05, size=(4, 3, 10))
    obs, previous = env.get_observations()["policy"], None
    assert obs.shape == (3, OBS_SIZE) and env.get_observations()["critic"].shape[1] == OBS_SIZE + 18
    for t in range(len(actions) + 1):
        q = env.truth().q
        frame = SCALE * (q - env.last_action)[:, order]
        np.testing.assert_array_equal(obs[:, NEWEST], frame)
        np.testing.assert_array_equal(obs[:, PREVIOUS], frame if previous is None else previous)
        np.testing.assert_array_equal(obs[:, Q], q[:, order])
        assert t == 0 or np.abs(frame).max() > 1e-4  # 0 at the reset: the target in force is the pose
        if t == len(actions):
            break
        previous = frame
        obs, _, fell, time_out, _ = env.step(actions[t])
        obs = obs["policy"]
        assert not (fell | time_out).any()
    env.close()
