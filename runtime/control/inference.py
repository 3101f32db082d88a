"""onnxruntime sessions for the 1 kHz loop: the walking policy (`OnnxPolicy`, 100 Hz) and the PINN (`OnnxPinn`,
every tick).

Tensor names are a contract with the exporters in `training/`: the policy maps `obs` [1, obs_dim] to `action`
[1, n_joints]; the PINN maps `q`, `qd`, `tau` [1, n_joints] and its LSTM state `h`, `c` [layers, 1, hidden]
to `q_next`, `qd_next`, `h_next`, `c_next`, all float32. A model is checked against that contract and the
robot config when it loads, so a wrong file fails before the robot moves, naming the file, the tensor and
the expected shape. The PINN's recurrent state ping-pongs between two bindings: step t writes h/c into the buffers
that step t+1 reads, so nothing is copied.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnxruntime as ort

from bruce_hw.types import all_finite

WARMUP_CALLS = 200


class ModelError(RuntimeError):
    """A model file that cannot be used: missing, corrupt, or with the wrong signature."""


def session_options() -> ort.SessionOptions:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # with inter = intra = 1 onnxruntime runs on the calling thread
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Tiny fixed-shape graphs: the arena's bookkeeping costs more than it saves (~1 µs of a ~23 µs PINN tick,
    # bench/bench_pinn_step.py); the memory pattern planned at the first run is kept.
    options.enable_cpu_mem_arena = False
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # never steal the other core
    options.log_severity_level = 3
    return options


def open_session(path: str | Path, what: str) -> ort.InferenceSession:
    """A CPU session on `path`; a missing or unreadable file is a ModelError naming it."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{what} model {path}: file not found")
    try:
        return ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own Fail/InvalidProtobuf/... types
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{what} model {path}: not a loadable ONNX model ({first_line})") from exc


def _shape_text(shape) -> str:
    return "[" + ", ".join(str(d) for d in shape) + "]"


def check_signature(session: ort.InferenceSession, path: Path, what: str,
                    inputs: dict[str, tuple[int, ...] | None], outputs: dict[str, tuple[int, ...] | None]) -> dict:
    """Check tensor names, float32 type and shapes; a shape of None is read from the model (its rank-3 state).

    Returns the shapes as the model declares them, name -> tuple.
    """
    declared = {}
    for kind, expected, actual in (("input", inputs, session.get_inputs()), ("output", outputs, session.get_outputs())):
        found = {t.name: t for t in actual}
        extra = sorted(set(found) - set(expected))
        missing = [name for name in expected if name not in found]
        if missing or extra:
            raise ModelError(f"{what} model {path}: {kind} tensors are {sorted(found)}, expected exactly "
                             f"{list(expected)}" + (f" (missing {missing[0]!r})" if missing else
                                                    f" (unexpected {extra[0]!r})"))
        for name, shape in expected.items():
            tensor = found[name]
            if tensor.type != "tensor(float)":
                raise ModelError(f"{what} model {path}: {kind} {name!r} has type {tensor.type}, expected "
                                 "tensor(float) (float32)")
            dims = tuple(tensor.shape)
            if not all(isinstance(d, int) for d in dims):
                raise ModelError(f"{what} model {path}: {kind} {name!r} has shape {_shape_text(dims)} with "
                                 f"symbolic dimensions, expected fixed {_shape_text(shape or ('layers', 1, 'hidden'))}"
                                 " (export with batch 1 and no dynamic axes)")
            if shape is not None and dims != tuple(shape):
                raise ModelError(f"{what} model {path}: {kind} {name!r} has shape {_shape_text(dims)}, "
                                 f"expected {_shape_text(shape)}")
            declared[name] = dims
    return declared


class _Bound:
    """Fixed float32 buffers bound to a session's inputs and outputs (OrtValues that share the numpy memory), bound
    once. Each tick calls `run_with_iobinding(io)` without RunOptions, a few µs over the kernels; passing RunOptions
    or `run_with_ort_values` adds ~30 µs in onnxruntime 1.31 (measured: bench/bench_pinn_step.py). Sessions run with
    one intra-op thread, no thread pool, sequential execution, no spinning (`session_options`)."""

    def __init__(self, session: ort.InferenceSession, buffers: dict[str, np.ndarray]):
        self.io = session.io_binding()
        inputs = {t.name for t in session.get_inputs()}
        for name, array in buffers.items():
            value = ort.OrtValue.ortvalue_from_numpy(array)  # shares the numpy memory on the CPU
            if name in inputs:
                self.io.bind_ortvalue_input(name, value)
            else:
                self.io.bind_ortvalue_output(name, value)


class OnnxPolicy:
    """The walking policy: `obs` [1, obs_dim] -> `action` [1, n_joints] (joint targets a_t, rad, or what a policy
    spec maps to them); `names`: the two tensors' names when a policy spec gives others."""

    def __init__(self, path: str | Path, obs_dim: int, n_joints: int, names: tuple[str, str] = ("obs", "action"),
                 sized_by: tuple[str, str] | None = None):
        """`sized_by`: what sets each size (e.g. "spec X builds 44 values (...)"), for an error that names both."""
        self.path = Path(path)
        self.session = open_session(self.path, "policy")
        obs_name, action_name = names
        if sized_by is not None:  # a size that differs is named with what set it; names and types are checked next
            sides = (("takes", self.session.get_inputs(), obs_name, obs_dim, sized_by[0]),
                     ("gives", self.session.get_outputs(), action_name, n_joints, sized_by[1]))
            for verb, tensors, name, size, why in sides:
                dims = next((tuple(t.shape) for t in tensors if t.name == name), (1, size))
                if all(isinstance(d, int) for d in dims) and dims != (1, size):
                    raise ModelError(f"policy model {self.path} {verb} {name} {_shape_text(dims)} but {why}")
        check_signature(self.session, self.path, "policy", {obs_name: (1, obs_dim)}, {action_name: (1, n_joints)})
        self.obs = np.zeros((1, obs_dim), np.float32)
        self.action = np.zeros((1, n_joints), np.float32)
        self._bound = _Bound(self.session, {obs_name: self.obs, action_name: self.action})

    def warmup(self, calls: int = WARMUP_CALLS) -> None:
        for _ in range(calls):
            self.session.run_with_iobinding(self._bound.io)
        self.action[:] = 0.0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """a_t for one observation (float64 copy); non-finite outputs are a ModelError."""
        self.obs[0] = obs
        self.session.run_with_iobinding(self._bound.io)
        action = self.action[0].astype(np.float64)
        if not all_finite(action):
            raise ModelError(f"policy model {self.path}: returned non-finite action")
        return action


class OnnxPinn:
    """The PINN tick: (q, qd, tau*) -> the simulator's next (q^', qd^'); the LSTM state is carried here."""

    def __init__(self, path: str | Path, n_joints: int, lookahead: int = 0):
        """`lookahead` > 0: `step` returns the state that many ticks after the next one instead, rolled on from its
        own prediction at the same tau* on a scratch copy of the LSTM state (the carried state only ever advances
        one tick per call)."""
        if lookahead < 0:
            raise ValueError(f"PINN lookahead: expected ticks >= 0, got {lookahead}")
        self.path = Path(path)
        self.lookahead = lookahead
        self.session = open_session(self.path, "PINN")
        joint = (1, n_joints)
        shapes = check_signature(self.session, self.path, "PINN",
                                 {"q": joint, "qd": joint, "tau": joint, "h": None, "c": None},
                                 {"q_next": joint, "qd_next": joint, "h_next": None, "c_next": None})
        state_shape = shapes["h"]
        if len(state_shape) != 3 or state_shape[1] != 1:
            raise ModelError(f"PINN model {self.path}: input 'h' has shape {_shape_text(state_shape)}, expected "
                             "[layers, 1, hidden]")
        for name in ("c", "h_next", "c_next"):
            if shapes[name] != state_shape:
                raise ModelError(f"PINN model {self.path}: tensor {name!r} has shape {_shape_text(shapes[name])}, "
                                 f"expected {_shape_text(state_shape)} like 'h'")
        self.state_shape = state_shape
        self.q, self.qd, self.tau = (np.zeros(joint, np.float32) for _ in range(3))
        # q_next and qd_next are the two rows of one buffer: one conversion and one finiteness check per tick.
        self._next = np.zeros((2, *joint), np.float32)
        self.q_next, self.qd_next = self._next[0], self._next[1]
        self._h = (np.zeros(state_shape, np.float32), np.zeros(state_shape, np.float32))
        self._c = (np.zeros(state_shape, np.float32), np.zeros(state_shape, np.float32))
        common = {"q": self.q, "qd": self.qd, "tau": self.tau, "q_next": self.q_next, "qd_next": self.qd_next}
        self._bound = tuple(
            _Bound(self.session, {**common, "h": self._h[i], "c": self._c[i],
                                  "h_next": self._h[1 - i], "c_next": self._c[1 - i]})
            for i in (0, 1))
        self._ios = (self._bound[0].io, self._bound[1].io)
        # Look-ahead ticks ping-pong between two scratch states, inputs copied from the previous prediction.
        self._scratch_h = (np.zeros(state_shape, np.float32), np.zeros(state_shape, np.float32))
        self._scratch_c = (np.zeros(state_shape, np.float32), np.zeros(state_shape, np.float32))
        self._ahead = tuple(
            _Bound(self.session, {**common, "h": self._scratch_h[i], "c": self._scratch_c[i],
                                  "h_next": self._scratch_h[1 - i], "c_next": self._scratch_c[1 - i]}).io
            for i in (0, 1)) if lookahead else ()
        self._run = self.session.run_with_iobinding  # bound once: the tick pays no attribute lookups
        self._turn = 0

    @property
    def h(self) -> np.ndarray:
        """The LSTM state the next step reads."""
        return self._h[self._turn]

    @property
    def c(self) -> np.ndarray:
        return self._c[self._turn]

    def reset(self) -> None:
        """Zero the LSTM state: a run starts from the state the PINN was trained to start from."""
        for buffer in (*self._h, *self._c):
            buffer[:] = 0.0
        self._turn = 0

    def warmup(self, calls: int = WARMUP_CALLS) -> None:
        for _ in range(calls):
            self.session.run_with_iobinding(self._bound[0].io)
        self.reset()

    def step(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q^', qd^') as float64 copies; non-finite outputs are a ModelError."""
        self.q[0], self.qd[0], self.tau[0] = q, qd, tau
        turn = self._turn
        self._run(self._ios[turn])
        self._turn = 1 - turn
        if self.lookahead:
            self._scratch_h[0][:] = self._h[1 - turn]
            self._scratch_c[0][:] = self._c[1 - turn]
            for k in range(self.lookahead):
                self.q[:] = self.q_next
                self.qd[:] = self.qd_next
                self._run(self._ahead[k % 2])
        both = self._next.astype(np.float64).reshape(-1)  # a fresh copy: callers may keep the arrays
        if not math.isfinite(both @ both):  # all_finite's test, once for both outputs
            raise ModelError(f"PINN model {self.path}: returned non-finite q_next/qd_next")
        n = self.q.shape[1]
        return both[:n], both[n:]
