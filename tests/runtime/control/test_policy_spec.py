"""Policy specs (runtime/control/policy_spec.py): the Table I spec is today's observation and actions bit for bit; a
policy with another layout (legged_gym's: other joint order, 50 Hz, scaled terms, last raw action), made here, runs
through bruce-run's path on the mock and sends exactly what onnxruntime gives on the observation recomputed here;
sizes, bad specs and the sidecar."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import onnxruntime as ort
import pytest
import yaml

from bruce_hw.config import ConfigError, load_config
from bruce_hw.mock import MujocoBackend
from runtime.cli import main as bruce_run
from runtime.control.commands import CommandSchedule
from runtime.control.controllers import build_controller
from runtime.control.inference import ModelError, OnnxPolicy
from runtime.control.policy_spec import load_policy_spec, parse_policy_spec, spec_file
from runtime.estimation import BaseEstimate, GroundTruthEstimator
from runtime.loop.observers import TickObserver
from runtime.loop.run import run_session
from runtime.observation.builder import ObservationBuilder

LEGGED_GYM_OBS = 3 + 3 + 3 + 3 + 3 * 10  # lin vel, ang vel, gravity, command, q - default, qd, last actions


def legged_gym_tree() -> dict:
    return yaml.safe_load(spec_file("legged_gym").read_text())


@pytest.fixture(scope="module")
def legged_gym_policy(onnx_graph, tmp_path_factory):
    """A random tanh layer of legged_gym's layout, `obs` [1, 42] -> `actions` [1, 10], as Isaac Lab exports it."""
    from onnx import TensorProto, helper

    rng = np.random.default_rng(7)
    weights = helper.make_tensor("w", TensorProto.FLOAT, [LEGGED_GYM_OBS, 10],
                                 rng.normal(0.0, 0.3, LEGGED_GYM_OBS * 10).tolist())
    bias = helper.make_tensor("b", TensorProto.FLOAT, [1, 10], rng.normal(0.0, 0.2, 10).tolist())
    nodes = [helper.make_node("MatMul", ["obs", "w"], ["z"]), helper.make_node("Add", ["z", "b"], ["y"]),
             helper.make_node("Tanh", ["y"], ["actions"])]
    return onnx_graph(tmp_path_factory.mktemp("lg") / "legged_gym_policy.onnx", {"obs": (1, LEGGED_GYM_OBS)},
                      {"actions": (1, 10)}, nodes, [weights, bias])


class RecordingController:
    """The controller's inputs and outputs at every call (copies), from its last reset on."""

    def __init__(self, inner):
        self.inner = inner
        self.calls = []

    def reset(self, q):
        self.inner.reset(q)
        self.q0 = np.array(q, dtype=float)
        self.calls = []

    def __call__(self, state, base, command):
        a = self.inner(state, base, command)
        copied = BaseEstimate(*(np.array(v, dtype=float) for v in (base.quat, base.linvel, base.angvel, base.euler)))
        self.calls.append((state.joints.q.copy(), state.joints.qd.copy(), copied, np.array(command, dtype=float),
                           self.inner.obs.copy(), a.copy()))
        return a


def test_table1_spec_is_todays_observation_and_actions(config):
    """The default controller (the committed policy with the shipped Table I spec) over a mock walk against today's
    pipeline, ObservationBuilder + OnnxPolicy with a_{t-1} as the last action: identical bits."""
    controller, name = build_controller(config, None)
    assert "spec table1.yaml" in name
    recording = RecordingController(controller)
    summary = run_session(MujocoBackend(config), config, duration=1.0, realtime=False, controller=recording,
                          commands=CommandSchedule.constant(0.4, 0.1, 0.3))
    assert summary.exit_code == 0 and len(recording.calls) == 100

    builder = ObservationBuilder(config)
    policy = OnnxPolicy(config.models.policy, builder.size, config.n_joints)
    last_action = recording.q0
    for q, qd, base, command, obs, a in recording.calls:
        expected_obs = builder.build(command, SimpleNamespace(joints=SimpleNamespace(q=q, qd=qd)), base, last_action)
        np.testing.assert_array_equal(obs, expected_obs)
        last_action = policy(expected_obs)
        np.testing.assert_array_equal(a, last_action)
    walked = np.array([call[5] for call in recording.calls])
    assert np.ptp(walked, axis=0).max() > 0.05  # the targets moved: the comparison saw a walk, not a pose


class RecordingTruth(GroundTruthEstimator):
    """The simulator's truth, and each tick's estimate (copies) by loop tick."""

    def __init__(self, backend):
        self.backend = backend  # configured by the session

    def reset(self, state):
        self.ticks, self.by_tick = 0, {}

    def update(self, state):
        self.ticks += 1

    def estimate(self):
        e = super().estimate()
        self.by_tick[self.ticks - 1] = BaseEstimate(*(np.array(v, dtype=float)
                                                      for v in (e.quat, e.linvel, e.angvel, e.euler)))
        return e


class SentTargets(TickObserver):
    def __init__(self):
        self.ticks = []

    def on_tick(self, view):
        self.ticks.append((view.q.copy(), view.qd.copy(), np.array(view.command, dtype=float), view.a.copy()))


def gravity_in_base(quat: np.ndarray) -> np.ndarray:
    """(0, 0, -1) rotated into the base frame: R(quat)^T g, R from the unit quaternion (w, x, y, z)."""
    w, x, y, z = quat
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return rotation.T @ np.array([0.0, 0.0, -1.0])


def test_a_legged_gym_policy_runs_through_the_mock_and_sends_what_its_onnx_gives(config, legged_gym_policy):
    """bruce-run's session on the mock with --policy-spec legged_gym (via policy.spec): every target sent is the
    ONNX's output on legged_gym's observation, recomputed here from the recorded state, put through the action map
    into our joint order, and held for two 100 Hz policy ticks (the policy runs at 50 Hz)."""
    spec_config = load_config(overrides=[f"policy.spec={spec_file('legged_gym')}"])
    backend = MujocoBackend(spec_config)
    truth = RecordingTruth(backend)
    sent = SentTargets()
    summary = run_session(backend, spec_config, duration=0.5, realtime=False, policy=legged_gym_policy,
                          estimator=truth, commands=CommandSchedule.constant(0.3, 0.0, 0.2), observers=[sent])
    assert summary.exit_code == 0 and len(sent.ticks) == 500
    assert sorted(truth.by_tick) == list(range(0, 500, 10))  # the loop asks at 100 Hz

    session = ort.InferenceSession(str(legged_gym_policy), providers=["CPUExecutionProvider"])
    order = [config.joints.index(name) for name in sorted(config.joints)]  # the policy's (alphabetical) order
    default = config.standing_pose[order]
    last_raw = np.zeros(10)
    expected = None
    computed, raws = [], []
    for tick, (q, qd, command, a) in enumerate(sent.ticks):
        if tick % 20 == 0:  # the policy's own 50 Hz tick
            base = truth.by_tick[tick]
            obs = np.concatenate([base.linvel * 2.0, base.angvel * 0.25, gravity_in_base(base.quat),
                                  command * [2.0, 2.0, 0.25], (q[order] - default) * 1.0, qd[order] * 0.05, last_raw])
            obs = np.clip(obs, -100.0, 100.0)
            raw = session.run(["actions"], {"obs": obs[None].astype(np.float32)})[0][0].astype(np.float64)
            last_raw = np.clip(raw, -100.0, 100.0)
            expected = np.empty(10)
            expected[order] = default + 0.25 * last_raw
            computed.append(expected)
            raws.append(last_raw)
        np.testing.assert_allclose(a, expected, rtol=0, atol=1e-6, err_msg=f"tick {tick}")
    computed, raws = np.array(computed), np.array(raws)
    assert np.abs(np.diff(computed, axis=0)).max() > 1e-3  # the policy acted: its targets changed tick to tick
    assert not np.allclose(computed, config.standing_pose + 0.25 * raws, atol=1e-3)  # and its joint order mattered


def test_bruce_run_runs_a_policy_with_its_spec(legged_gym_policy, tmp_path, capsys):
    stats = tmp_path / "run.json"
    code = bruce_run(["--backend", "mock", "--policy", str(legged_gym_policy), "--policy-spec", "legged_gym",
                      "--duration", "0.5", "--rerun", "off", "--stats", str(stats)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "spec legged_gym.yaml, 50 Hz" in out
    assert json.loads(stats.read_text())["ticks"] == 500


def test_onnx_sizes_are_checked_against_the_spec_naming_both(config, legged_gym_policy, onnx_graph, tmp_path,
                                                            capsys):
    with pytest.raises(ModelError) as err:  # legged_gym's layout under the default Table I spec
        build_controller(config, legged_gym_policy)
    assert str(err.value) == (f"policy model {legged_gym_policy} takes obs [1, 42] but spec table1.yaml builds 44 "
                              "values (clock 2 + command 3 + q 10 + qd 10 + base_linvel 3 + base_angvel 3 + euler 3 + "
                              "last_action 10)")
    from onnx import TensorProto, helper

    twelve = onnx_graph(tmp_path / "twelve.onnx", {"obs": (1, LEGGED_GYM_OBS)}, {"actions": (1, 12)},
                        [helper.make_node("MatMul", ["obs", "w"], ["actions"])],
                        [helper.make_tensor("w", TensorProto.FLOAT, [LEGGED_GYM_OBS, 12], [0.0] * LEGGED_GYM_OBS * 12)])
    spec_config = load_config(overrides=["policy.spec=legged_gym"])
    with pytest.raises(ModelError, match=r"twelve\.onnx gives actions \[1, 12\] but spec legged_gym\.yaml maps 10 "
                                         r"joints$"):
        build_controller(spec_config, twelve)
    code = bruce_run(["--backend", "mock", "--policy", str(legged_gym_policy), "--duration", "0.1", "--rerun", "off"])
    assert code == 2 and "takes obs [1, 42] but spec table1.yaml builds 44 values" in capsys.readouterr().err


BAD_SPECS = [
    # (change to the legged_gym spec, what the one line says after "<file>: ")
    (lambda t: t["observation"].__setitem__(2, "gravity"),
     "observation[2]: expected one of clock, command, raw_command, q, qd, base_linvel, base_angvel, euler, "
     "projected_gravity, last_action, last_raw_action, got 'gravity'"),
    (lambda t: t["observation"].__setitem__(0, {"term": "base_linvel", "scale": 2.0, "noise": 0.1}),
     "observation[0].noise: unknown key"),
    (lambda t: t["joints"].__setitem__(0, "l_toe"), "joints[0]: expected a joint of"),
    (lambda t: t["joints"].pop(), "joints: expected every joint of"),
    (lambda t: t.update(rate_hz=30), "rate_hz: expected a divisor of rates.policy_hz (100 Hz"),
    (lambda t: t.update(rate_hz=200), "rate_hz: expected a divisor of rates.policy_hz (100 Hz"),
    (lambda t: t.update(rate_hz=0), "rate_hz: expected an integer in [1, 10000] Hz"),
    (lambda t: t.update(frame="base"), "frame: unknown key"),
    (lambda t: t["observation"][3].update(scale=[2.0, 2.0]), "observation[3].scale: expected a list of 3 numbers, "
                                                               "got 2 entries"),
    (lambda t: t["observation"][0].update(offset="standing"), "observation[0].offset: expected a number"),
    (lambda t: t["observation"][4].update(offset={"r_knee": 0.1}), "observation[4].offset.l_ankle: missing joint"),
    (lambda t: t["observation"][5].update(history=0), "observation[5].history: expected an integer in [1, 100]"),
    (lambda t: t["action"].update(scale=50.0), "action.scale: expected a number in [-10, 10] rad"),
    (lambda t: t["action"].update(offset="stand"), "action.offset: expected a number"),
    (lambda t: t.pop("observation"), "observation: missing key"),
]


@pytest.mark.parametrize("change, says", BAD_SPECS, ids=[says.split(":")[0] + str(i) for i, (_, says)
                                                          in enumerate(BAD_SPECS)])
def test_a_bad_spec_is_one_line_naming_file_and_key(config, change, says, tmp_path):
    tree = legged_gym_tree()
    change(tree)
    path = tmp_path / "bad_spec.yaml"
    path.write_text(yaml.safe_dump(tree))
    with pytest.raises(ConfigError) as err:
        load_policy_spec(path, config)
    message = str(err.value)
    assert message.startswith(f"{path}: {says}"), message
    assert "\n" not in message


def test_bruce_run_refuses_a_bad_or_missing_spec_in_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "spec.yaml").write_text("observation: [q, qd, gravity]\n")
    for spec, says in (("spec.yaml", "spec.yaml: observation[2]: expected one of clock"),
                       ("nope.yaml", "nope.yaml: policy spec file not found"),
                       ("nope", "nope: no such policy spec file, nor a shipped one")):
        code = bruce_run(["--backend", "mock", "--policy-spec", spec, "--duration", "0.1", "--rerun", "off"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith("bruce-run: ") and says in err[0], err
    with pytest.raises(SystemExit):
        bruce_run(["--controller", "teacher", "--policy-spec", "table1"])
    assert "--policy-spec is for --controller policy" in capsys.readouterr().err


def test_the_spec_comes_from_the_sidecar_unless_the_config_names_one(config, legged_gym_policy, tmp_path):
    model = tmp_path / "walker.onnx"
    model.write_bytes(legged_gym_policy.read_bytes())
    sidecar = tmp_path / "walker.onnx.json"
    (tmp_path / "specs").mkdir()
    (tmp_path / "specs" / "mine.yaml").write_text(spec_file("legged_gym").read_text())
    sidecar.write_text(json.dumps({"file": "walker.onnx", "policy_spec": "specs/mine.yaml"}))
    assert build_controller(config, model)[1] == f"policy {model} (spec mine.yaml, 50 Hz)"
    inline = legged_gym_tree()
    sidecar.write_text(json.dumps({"policy_spec": inline}))
    controller, name = build_controller(config, model)
    assert name == f"policy {model} (spec walker.onnx.json, 50 Hz)" and controller.hold_calls == 2
    inline["rate_hz"] = 7
    sidecar.write_text(json.dumps({"policy_spec": inline}))
    with pytest.raises(ConfigError, match=r"walker\.onnx\.json: policy_spec: rate_hz: expected a divisor"):
        build_controller(config, model)
    sidecar.write_text("{not json")
    with pytest.raises(ConfigError, match=r"walker\.onnx\.json: not a readable JSON sidecar"):
        build_controller(config, model)
    # policy.spec in the config wins over the sidecar: Table I does not fit this model
    with pytest.raises(ModelError, match="spec table1.yaml builds 44 values"):
        build_controller(load_config(overrides=["policy.spec=table1"]), model)


def test_history_stacks_the_last_frames_in_the_order_asked(config):
    def observations(order: str) -> list[np.ndarray]:
        tree = {"joints": "config", "observation": [{"term": "q", "history": 3, "history_order": order}]}
        builder = ObservationBuilder(config, parse_policy_spec(tree, "history.yaml", config))
        base = BaseEstimate(np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), np.zeros(3), np.zeros(3))
        out = []
        for k in range(4):
            state = SimpleNamespace(joints=SimpleNamespace(q=np.full(10, float(k)), qd=np.zeros(10)))
            out.append(builder.build(np.zeros(3), state, base, np.zeros(10), np.zeros(10)).reshape(3, 10)[:, 0])
        return out

    newest = observations("newest_first")
    np.testing.assert_array_equal(newest, [[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 2, 1]])  # filled with the first
    np.testing.assert_array_equal(observations("oldest_first"), [frame[::-1] for frame in newest])
