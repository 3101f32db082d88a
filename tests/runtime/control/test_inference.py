import numpy as np
import onnxruntime as ort
import pytest

from runtime.control.inference import ModelError, OnnxPinn, OnnxPolicy
from runtime.observation.builder import ObservationBuilder


def test_pinn_carries_its_lstm_state_and_resets(stateful_pinn_onnx, config):
    pinn = OnnxPinn(stateful_pinn_onnx, config.n_joints)
    pinn.warmup(20)
    assert not pinn.h.any() and not pinn.c.any()  # warm-up leaves the state reset
    q, qd, tau = config.standing_pose, np.full(10, 0.1), np.full(10, 0.5)
    first = pinn.step(q, qd, tau)
    second = pinn.step(q, qd, tau)
    assert np.abs(second[0] - first[0]).max() > 1e-7  # same inputs, carried state: a different answer

    stateless = ort.InferenceSession(str(stateful_pinn_onnx), providers=["CPUExecutionProvider"])
    shape = pinn.state_shape
    feeds = {"q": q[None].astype(np.float32), "qd": qd[None].astype(np.float32),
             "tau": tau[None].astype(np.float32), "h": np.zeros(shape, np.float32), "c": np.zeros(shape, np.float32)}
    q_zero_state = stateless.run(["q_next"], feeds)[0][0]
    np.testing.assert_allclose(first[0], q_zero_state, atol=1e-6)
    assert np.abs(second[0] - q_zero_state).max() > 1e-7

    feeds["h"], feeds["c"] = stateless.run(["h_next", "c_next"], feeds)  # the state after call 1
    np.testing.assert_allclose(second[0], stateless.run(["q_next"], feeds)[0][0], atol=1e-6)

    pinn.reset()
    again = pinn.step(q, qd, tau)
    np.testing.assert_array_equal(again[0], first[0])


@pytest.mark.parametrize("lookahead", [1, 3])
def test_pinn_lookahead_rolls_its_own_prediction_on_and_carries_the_one_step_state(stateful_pinn_onnx, config,
                                                                                   lookahead):
    ahead = OnnxPinn(stateful_pinn_onnx, config.n_joints, lookahead=lookahead)
    one = OnnxPinn(stateful_pinn_onnx, config.n_joints)
    stateless = ort.InferenceSession(str(stateful_pinn_onnx), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(3)
    names = ["q_next", "qd_next", "h_next", "c_next"]
    for _ in range(5):
        q, qd, tau = config.standing_pose + rng.normal(0, 0.05, 10), rng.normal(0, 0.5, 10), rng.normal(0, 1, 10)
        h, c = one.h.copy(), one.c.copy()
        one_step = one.step(q, qd, tau)
        result = ahead.step(q, qd, tau)
        np.testing.assert_array_equal(ahead.h, one.h)  # the carried state advanced one tick, like the plain one
        np.testing.assert_array_equal(ahead.c, one.c)
        feeds = {"q": q[None].astype(np.float32), "qd": qd[None].astype(np.float32),
                 "tau": tau[None].astype(np.float32), "h": h, "c": c}
        for _ in range(1 + lookahead):  # the next tick, then `lookahead` more on its own prediction, tau held
            q_next, qd_next, feeds["h"], feeds["c"] = stateless.run(names, feeds)
            feeds["q"], feeds["qd"] = q_next, qd_next
        np.testing.assert_allclose(result[0], q_next[0], atol=1e-6)
        np.testing.assert_allclose(result[1], qd_next[0], atol=1e-5)
        assert np.abs(result[1] - one_step[1]).max() > 1e-6  # further ahead is not the one-step answer
    with pytest.raises(ValueError, match="lookahead"):
        OnnxPinn(stateful_pinn_onnx, config.n_joints, lookahead=-1)


def test_policy_runs_on_bound_buffers(random_policy_onnx, config):
    obs_dim = ObservationBuilder(config).size
    policy = OnnxPolicy(random_policy_onnx, obs_dim, config.n_joints)
    policy.warmup(5)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=obs_dim)
    expected = ort.InferenceSession(str(random_policy_onnx)).run(["action"], {"obs": obs[None].astype(np.float32)})
    np.testing.assert_allclose(policy(obs), expected[0][0], atol=1e-6)
    assert not np.allclose(policy(obs + 1.0), expected[0][0])


def identities(**pairs):
    from onnx import helper

    return [helper.make_node("Identity", [src], [dst]) for src, dst in pairs.items()]


def test_wrong_input_shape_is_refused_naming_model_tensor_and_shape(onnx_graph, tmp_path, config):
    joint, wrong, state = (1, 10), (1, 12), (1, 1, 4)
    path = onnx_graph(tmp_path / "pinn12.onnx", {"q": wrong, "qd": joint, "tau": joint, "h": state, "c": state},
                      {"q_next": joint, "qd_next": joint, "h_next": state, "c_next": state},
                      identities(qd="q_next", tau="qd_next", h="h_next", c="c_next"))
    with pytest.raises(ModelError) as err:
        OnnxPinn(path, config.n_joints)
    assert str(path) in str(err.value) and "'q'" in str(err.value) and "[1, 12]" in str(err.value) \
        and "expected [1, 10]" in str(err.value)


def test_wrong_tensor_names_are_refused(onnx_graph, tmp_path):
    from onnx import helper

    path = onnx_graph(tmp_path / "policy.onnx", {"observation": (1, 44)}, {"action": (1, 10)},
                      [helper.make_node("Slice", ["observation", "s", "e", "ax"], ["action"])],
                      [helper.make_tensor("s", 7, [1], [0]), helper.make_tensor("e", 7, [1], [10]),
                       helper.make_tensor("ax", 7, [1], [1])])
    with pytest.raises(ModelError, match=r"policy model .*policy\.onnx: input tensors are \['observation'\], "
                                         r"expected exactly \['obs'\] \(missing 'obs'\)"):
        OnnxPolicy(path, 44, 10)


def test_state_shapes_must_agree(onnx_graph, tmp_path, config):
    joint = (1, 10)
    path = onnx_graph(tmp_path / "pinn.onnx", {"q": joint, "qd": joint, "tau": joint, "h": (3, 1, 72), "c": (3, 1, 64)},
                      {"q_next": joint, "qd_next": joint, "h_next": (3, 1, 72), "c_next": (3, 1, 64)},
                      identities(q="q_next", qd="qd_next", h="h_next", c="c_next"))
    with pytest.raises(ModelError, match=r"tensor 'c' has shape \[3, 1, 64\], expected \[3, 1, 72\] like 'h'"):
        OnnxPinn(path, config.n_joints)


def test_corrupt_and_missing_files_are_refused(tmp_path, stateful_pinn_onnx):
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(stateful_pinn_onnx.read_bytes()[:5000])  # a truncated download
    with pytest.raises(ModelError, match=r"PINN model .*corrupt\.onnx: not a loadable ONNX model"):
        OnnxPinn(corrupt, 10)
    junk = tmp_path / "junk.onnx"
    junk.write_text("this is not a model")
    with pytest.raises(ModelError, match=r"policy model .*junk\.onnx: not a loadable ONNX model"):
        OnnxPolicy(junk, 44, 10)
    with pytest.raises(ModelError, match=r"nothere\.onnx: file not found"):
        OnnxPinn(tmp_path / "nothere.onnx", 10)


def test_non_finite_output_is_a_model_error(nan_pinn_onnx, config):
    pinn = OnnxPinn(nan_pinn_onnx, config.n_joints)
    pinn.warmup()
    for _ in range(50):
        q_next, _ = pinn.step(config.standing_pose, np.zeros(10), np.zeros(10))
        np.testing.assert_allclose(q_next, config.standing_pose, atol=1e-6)
    with pytest.raises(ModelError, match="non-finite"):
        pinn.step(config.standing_pose, np.zeros(10), np.zeros(10))
