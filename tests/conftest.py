from pathlib import Path

import pytest
import yaml
from support.emulated_robot import BEAR_IDS, DXL_IDS, WALL_CLOCK_SLACK

from bruce_hw.config import DEFAULT_CONFIG, load_config, resolve_config_path


@pytest.fixture(scope="session")
def config():
    return load_config()


@pytest.fixture
def raw_config():
    """The default config as a YAML tree, to break on purpose."""
    return yaml.safe_load(resolve_config_path(DEFAULT_CONFIG).read_text())


@pytest.fixture
def write_config(tmp_path):
    """Write a YAML tree beside a copy of the model and return its path."""

    def write(tree, name="robot.yaml") -> Path:
        path = tmp_path / name
        path.write_text(yaml.safe_dump(tree))
        return path

    return write


# -- ONNX models with the runtime's signatures and random weights, made on the fly ---------------------------
def _onnx_graph(path: Path, inputs: dict, outputs: dict, nodes: list, initializers: list = ()) -> Path:
    """A hand-built ONNX graph (float32 tensors, opset 17), for signatures torch would not export."""
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        nodes, path.stem,
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, list(s)) for n, s in inputs.items()],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, list(s)) for n, s in outputs.items()],
        list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 9
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


@pytest.fixture(scope="session")
def onnx_graph():
    return _onnx_graph


@pytest.fixture(scope="session")
def stateful_pinn_onnx(tmp_path_factory):
    """The paper-sized PINN, random weights including the head, so its output depends on the LSTM state."""
    import torch

    from training.dynamics.export import export_pinn_onnx
    from training.dynamics.pinn import make_random_pinn

    model = make_random_pinn(seed=1)
    with torch.no_grad():
        torch.manual_seed(2)
        model.head.weight.normal_(std=1e-3)  # small: q' stays near q, the closed loop stays tame
        model.head.bias.normal_(std=1e-4)
    return export_pinn_onnx(model, tmp_path_factory.mktemp("models") / "pinn.onnx")


@pytest.fixture(scope="session")
def nan_pinn_onnx(tmp_path_factory):
    """The PINN signature with a call counter as its state: q_next = q + 0 * sqrt(49.5 - h) turns NaN on the
    51st call after a reset; otherwise q_next = q, qd_next = qd."""
    from onnx import TensorProto, helper

    joint, state = (1, 10), (1, 1, 1)
    constants = [helper.make_tensor("one", TensorProto.FLOAT, [], [1.0]),
                 helper.make_tensor("limit", TensorProto.FLOAT, [], [49.5]),
                 helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0]),
                 helper.make_tensor("shape_1x1", TensorProto.INT64, [2], [1, 1])]
    nodes = [helper.make_node("Add", ["h", "one"], ["h_next"]), helper.make_node("Identity", ["c"], ["c_next"]),
             helper.make_node("Sub", ["limit", "h"], ["left"]), helper.make_node("Sqrt", ["left"], ["root"]),
             helper.make_node("Reshape", ["root", "shape_1x1"], ["root_1x1"]),
             helper.make_node("Mul", ["root_1x1", "zero"], ["poison"]),
             helper.make_node("Add", ["q", "poison"], ["q_next"]), helper.make_node("Identity", ["qd"], ["qd_next"])]
    return _onnx_graph(tmp_path_factory.mktemp("models") / "nan_pinn.onnx",
                       {"q": joint, "qd": joint, "tau": joint, "h": state, "c": state},
                       {"q_next": joint, "qd_next": joint, "h_next": state, "c_next": state}, nodes, constants)


@pytest.fixture(scope="session")
def random_policy_onnx(tmp_path_factory):
    from runtime.observation.builder import ObservationBuilder
    from training.onnx_export import export_mlp_policy_onnx, make_random_policy

    obs_dim = ObservationBuilder(load_config()).size
    return export_mlp_policy_onnx(make_random_policy(obs_dim, 10, seed=3),
                                  tmp_path_factory.mktemp("models") / "policy.onnx", obs_dim, 10)


@pytest.fixture(scope="session")
def constant_policy_onnx(tmp_path_factory):
    """A policy with the runtime's signature whose action is `values` whatever it observes (NaN and huge ones
    included): make(values, name) -> path."""
    from onnx import TensorProto, helper

    from runtime.observation.builder import ObservationBuilder

    obs_dim = ObservationBuilder(load_config()).size
    folder = tmp_path_factory.mktemp("constant_policies")

    def make(values, name: str) -> Path:
        values = [float(v) for v in values]
        zero = helper.make_tensor("w", TensorProto.FLOAT, [obs_dim, len(values)], [0.0] * (obs_dim * len(values)))
        bias = helper.make_tensor("b", TensorProto.FLOAT, [1, len(values)], values)
        nodes = [helper.make_node("MatMul", ["obs", "w"], ["z"]), helper.make_node("Add", ["z", "b"], ["action"])]
        return _onnx_graph(folder / f"{name}.onnx", {"obs": (1, obs_dim)}, {"action": (1, len(values))}, nodes,
                           [zero, bias])

    return make


@pytest.fixture(scope="session")
def offset_pinn_onnx(tmp_path_factory):
    """The PINN signature predicting q_next = q + offset, qd_next = qd + offset (state passed through):
    make(offset, name) -> path."""
    from onnx import TensorProto, helper

    joint, state = (1, 10), (1, 1, 1)
    folder = tmp_path_factory.mktemp("offset_pinns")

    def make(offset: float, name: str) -> Path:
        constants = [helper.make_tensor("offset", TensorProto.FLOAT, [], [float(offset)])]
        nodes = [helper.make_node("Add", ["q", "offset"], ["q_next"]),
                 helper.make_node("Add", ["qd", "offset"], ["qd_next"]),
                 helper.make_node("Identity", ["h"], ["h_next"]), helper.make_node("Identity", ["c"], ["c_next"])]
        return _onnx_graph(folder / f"{name}.onnx", {"q": joint, "qd": joint, "tau": joint, "h": state, "c": state},
                           {"q_next": joint, "qd_next": joint, "h_next": state, "c_next": state}, nodes, constants)

    return make


# -- the hw backend against `bruce-emulate --lockstep` (bruce_hw/test_hw_backend.py, bruce_hw/test_hw_safety.py) --
# with the wall-clock slack of support/emulated_robot.py (WALL_CLOCK_SLACK, why it is there) --------------------


@pytest.fixture
def no_memory_lock(monkeypatch):
    """Paced in-process sessions without mlockall: in a pytest process that has loaded torch (the distillation
    tests) locking every mapping stalls the loop for seconds. bruce-run, in a process of its own, locks memory."""
    from runtime.loop import realtime, run

    monkeypatch.setattr(run, "request_realtime", lambda: realtime.request_realtime(lock_memory=False))


@pytest.fixture(scope="module")
def emulator():
    """`bruce-emulate --lockstep` in a child process: the physics steps once per host bulk cycle."""
    from bruce_hw.emulation.process import EmulatorProcess

    emu = EmulatorProcess("--realtime", "--lockstep")
    yield emu
    emu.close()


@pytest.fixture
def hw_config(emulator):
    """The robot config pointed at the emulators (with WALL_CLOCK_SLACK); every bus plugged, every device
    answering, no reply loss, no E-stop, the IMU streaming, the robot back on its feet (the previous test may have
    ended in damping, where the emulated robot sinks)."""
    for command in ("plug bear", f"answer bear {' '.join(map(str, BEAR_IDS))}",
                    f"answer dynamixel {' '.join(map(str, DXL_IDS))}", "loss bear 0 0", "estop off", "imu start",
                    "place"):
        emulator.send(command)
    return load_config(overrides=emulator.overrides + WALL_CLOCK_SLACK)


# Modules whose tests walk the mock for seconds, train or export networks, or drive the emulated buses: left out of
# the fast subset, `pytest -m "not slow and not hardware and not realtime"` (README), which runs in under a minute.
# A module of fast unit tests with a few slow ones marks those itself (`@pytest.mark.slow`) and stays out of this list.
SLOW_MODULES = {
    "test_walking", "test_kinematic_estimator", "test_transfer_eval", "test_transfer_eval_schemes", "test_distill",
    "test_collect", "test_observers", "test_hw_backend", "test_hw_safety", "test_hw_check", "test_emulator_timing",
    "test_emulator_cli", "test_train_dynamics", "test_pinn_export", "test_lstm_baseline", "test_analytic",
    "test_evaluate", "test_telemetry", "test_bear_reply_loss", "test_reality_gap", "test_run_outcomes", "test_cli",
    "test_loop", "test_standing", "test_olnn", "test_rl_train",
    "test_replay", "test_web_viewer", "test_robot_faithful", "test_host_stalls",
    "test_bringup_emulated", "test_cluster",
}


def pytest_collection_modifyitems(config, items):
    unknown = SLOW_MODULES - {path.stem for path in Path(__file__).parent.rglob("test_*.py")}
    if unknown:  # a renamed or moved module would silently join the fast subset
        raise pytest.UsageError(f"tests/conftest.py SLOW_MODULES names no test module: {', '.join(sorted(unknown))}")
    for item in items:
        # the file's basename, whatever folder under tests/ it sits in and whatever the import mode names its module
        if item.path.stem in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


# -- the bring-up suite (tests/bruce_hw/test_bringup.py, marker `hardware`) -----------------------------------------
def pytest_addoption(parser):
    group = parser.getgroup("bruce bring-up (tests/bruce_hw/test_bringup.py, -m hardware)")
    group.addoption("--bruce-config", default=None, help="robot config with the robot's ports (default: BRUCE's)")
    group.addoption("--bruce-set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, as bruce-run's --set (repeatable)")
    group.addoption("--bruce-emulate", action="store_true",
                    help="run the bring-up against bruce-emulate --realtime --lockstep instead of a robot; the "
                         "emulator plays the person at the E-stop and the cable")


@pytest.hookimpl(tryfirst=True, hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Each phase's report on the item (`rep_setup`, `rep_call`): the bring-up skips the steps after a failed one."""
    outcome = yield
    report = outcome.get_result()
    setattr(item, f"rep_{report.when}", report)


@pytest.fixture(scope="module")
def bringup_target(request):
    """(config path, overrides, the emulator or None) of the bring-up: the robot's ports, or bruce-emulate's."""
    from bruce_hw.emulation.process import EmulatorProcess

    path = request.config.getoption("--bruce-config")
    overrides = list(request.config.getoption("--bruce-set"))
    if not request.config.getoption("--bruce-emulate"):
        yield path, overrides, None
        return
    emulator = EmulatorProcess("--realtime", "--lockstep")
    emulator.send("stand on")  # the robot on its bring-up stand, feet in the air
    try:
        yield path, [*emulator.overrides, *overrides], emulator
    finally:
        emulator.close()


@pytest.fixture
def bringup_config_with(bringup_target):
    """The bring-up's robot config with more overrides."""
    path, overrides, _ = bringup_target

    def load(*extra: str):
        return load_config(path or DEFAULT_CONFIG, [*overrides, *extra])
    return load


@pytest.fixture
def bringup_config(bringup_config_with):
    return bringup_config_with()


class PersonOperator:
    """The person at the robot: told what to do, then given `wait_s` to do it (the run ends when they have)."""

    wait_s = 30.0
    ASK = {"estop": "press the E-stop within 30 s (the robot holds its pose until then).",
           "cable": "pull the leg bus's cable (the BEARs' RS-485) within 30 s; keep a hand near the robot."}

    def asks(self, what: str) -> str:
        return self.ASK[what]

    def at(self, t: float, what: str):
        return None  # stand still until the person acts

    def undo(self, what: str) -> None:
        input(f"\n[bring-up] {'release the E-stop' if what == 'estop' else 'plug the cable back in'}, then Enter: ")


class EmulatedOperator(PersonOperator):
    """bruce-emulate in the person's place: the E-stop and the unplugged bus as its fault commands, 1 s in."""

    wait_s = 5.0
    COMMANDS = {"estop": ("estop on", "estop off"), "cable": ("unplug bear", "plug bear")}

    def __init__(self, emulator):
        self.emulator = emulator

    def asks(self, what: str) -> str:
        return f"(emulated: `{self.COMMANDS[what][0]}` 1 s in)"

    def at(self, t: float, what: str):
        from bruce_hw.emulation.process import FaultAt

        return FaultAt(self.emulator, self.COMMANDS[what][0], t)

    def undo(self, what: str) -> None:
        self.emulator.send(self.COMMANDS[what][1])
        self.emulator.send("stand on")  # back up, at rest


@pytest.fixture
def operator(bringup_target):
    emulator = bringup_target[2]
    return PersonOperator() if emulator is None else EmulatedOperator(emulator)
