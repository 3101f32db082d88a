"""The observation-term registry (runtime/observation/registry.py): our terms in their order and widths, what a
registration refuses, a term function of the wrong shape named, and one builder at batch 1 and batch N alike."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.control.policy_spec import load_policy_spec, parse_policy_spec
from runtime.observation.builder import ObservationBuilder
from runtime.observation.registry import OBSERVATION_TERMS, PER_JOINT, register_term


@pytest.fixture
def registry():
    saved = dict(OBSERVATION_TERMS)
    yield OBSERVATION_TERMS
    OBSERVATION_TERMS.clear()
    OBSERVATION_TERMS.update(saved)


def test_our_terms_in_order_with_their_widths():
    widths = {name: term.width for name, term in OBSERVATION_TERMS.items()}
    assert list(widths)[:11] == ["clock", "command", "raw_command", "q", "qd", "base_linvel", "base_angvel", "euler",
                                 "projected_gravity", "last_action", "last_raw_action"]
    assert widths["clock"] == 2 and widths["q"] == PER_JOINT and widths["projected_gravity"] == 3
    assert [n for n, t in OBSERVATION_TERMS.items() if t.joint_angles] == ["q", "last_action"]


@pytest.mark.parametrize("name, width, function, says", [
    ("q", 3, lambda x: x.q, "'q' is registered already"),
    ("two words", 1, lambda x: x.q, "expected an identifier"),
    ("new_term", 0, lambda x: x.q, "width: expected an integer >= 1 or 'per joint', got 0"),
    ("new_term", "joint", lambda x: x.q, "width: expected an integer >= 1 or 'per joint', got 'joint'"),
    ("new_term", 2, None, "function: expected a callable"),
])
def test_a_bad_registration_is_refused(registry, name, width, function, says):
    with pytest.raises(ValueError, match=says):
        register_term(name, width, function)


def test_a_term_function_of_the_wrong_shape_is_named(registry, config):
    register_term("too_wide", 2, lambda x: np.zeros((x.batch, 3)))
    builder = ObservationBuilder(config, parse_policy_spec({"observation": ["too_wide"]}, "wide.yaml", config), 4)
    with pytest.raises(ValueError, match=r"'too_wide': its function returned shape \(4, 3\), expected \(4, 2\)"):
        builder.observe(*(np.zeros((4, k)) for k in (3, 10, 10, 3, 3, 3, 4, 10, 10)))


def test_a_batch_is_its_robots_one_by_one(config):
    """Each row of a batch of 3 (legged_gym's spec with history) is what a builder of that one robot gives."""
    tree = {"joints": list(reversed(config.joints)),
            "observation": [{"term": "qd", "scale": 0.05, "history": 3}, "projected_gravity", "clock", "euler",
                            {"term": "last_raw_action", "history": 2, "history_order": "newest_first"}],
            "obs_clip": 1.5}
    spec = parse_policy_spec(tree, "batch.yaml", config)
    batch = ObservationBuilder(config, spec, num_envs=3)
    ones = [ObservationBuilder(config, spec, num_envs=1) for _ in range(3)]
    rng = np.random.default_rng(0)
    for tick in range(6):
        if tick == 3:
            batch.reset([1])
            ones[1].reset()
        args = [rng.normal(size=(3, k)) for k in (3, 10, 10, 3, 3, 3, 4, 10, 10)]
        args[6] /= np.linalg.norm(args[6], axis=1, keepdims=True)
        got = batch.observe(*args)
        for i, one in enumerate(ones):
            np.testing.assert_array_equal(got[i], one.observe(*(a[i:i + 1] for a in args))[0])
    assert np.abs(got).max() == 1.5  # obs_clip applied
    assert load_policy_spec("table1", config).obs_size == ObservationBuilder(config).size == 44
