"""ONNX export of the PINN step and of the walking policy, for the torch-free 1 kHz runtime.

Every export uses the legacy TorchScript exporter (`dynamo=False`, pinned: torch's default flipped to the dynamo
exporter, and for the PINN the legacy graph is smaller and faster), a fixed batch of 1 and
no dynamic axes. The file is then loaded back, checked with `onnx.checker`, its input/output names, shapes and
dtypes are verified, and a sidecar `<file>.json` records the versions, opset and the file's SHA-256, so the
runtime can tell which model it is running.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
import warnings
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import torch
from torch import nn

from training.checkpoint import kind_of
from training.dataset import file_sha256
from training.lstm_baseline import LstmStep
from training.pinn import PinnStep, make_random_pinn

__all__ = ["ExportError", "export_mlp_policy_onnx", "export_pinn_onnx", "make_random_pinn", "make_random_policy",
           "sidecar_path"]

_FLOAT = onnx.TensorProto.FLOAT


class ExportError(RuntimeError):
    """An exported graph that does not look like what the runtime expects."""


def sidecar_path(path: str | Path) -> Path:
    """Where the JSON sidecar of an exported model lives: `<path>.json`."""
    return Path(f"{path}.json")


def _check_io(values: Sequence[onnx.ValueInfoProto], names: Sequence[str], shapes: Sequence[tuple[int, ...]],
              what: str, path: Path) -> None:
    got = [v.name for v in values]
    if got != list(names):
        raise ExportError(f"{path}: graph {what}s are {got}, expected {list(names)}")
    for value, shape in zip(values, shapes, strict=True):
        tensor = value.type.tensor_type
        dims = tuple(d.dim_value if d.HasField("dim_value") else d.dim_param for d in tensor.shape.dim)
        if tensor.elem_type != _FLOAT or dims != tuple(shape):
            raise ExportError(f"{path}: {what} {value.name!r} is {onnx.TensorProto.DataType.Name(tensor.elem_type)}"
                              f"{list(dims)}, expected FLOAT{list(shape)}")


def _export_checked(model: nn.Module, example_inputs: tuple[torch.Tensor, ...], path: str | Path, *,
                    input_names: Sequence[str], output_names: Sequence[str], opset: int,
                    op_counts: Mapping[str, int], metadata: Mapping[str, object]) -> Path:
    """Export `model` at the example inputs' (fixed) shapes, verify the graph, write the sidecar.

    `op_counts` pins how many nodes of an op type the graph must have (e.g. {"LSTM": 3}); `metadata` goes into
    the sidecar next to the versions, opset, I/O shapes and SHA-256.
    """
    path = Path(path)
    for name, tensor in zip(input_names, example_inputs, strict=True):
        if tensor.dtype != torch.float32:
            raise ExportError(f"example input {name!r} is {tensor.dtype}, expected torch.float32")
    path.parent.mkdir(parents=True, exist_ok=True)

    was_training = model.training
    model.eval()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            # The legacy exporter is chosen on purpose (module docstring), and the LSTM batch-size warning's advice
            # (batch 1, h0/c0 as inputs) is what this export does; other warnings still show.
            warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX", category=DeprecationWarning)
            warnings.filterwarnings("ignore", message="The feature will be removed", category=DeprecationWarning)
            warnings.filterwarnings("ignore", message="Exporting a model to ONNX with a batch_size other than 1")
            # nn.LSTM's own input-shape checks; the shapes are fixed by design (no dynamic axes).
            warnings.filterwarnings("ignore", category=torch.jit.TracerWarning, module=r"torch\.nn\.modules\.rnn")
            outputs = model(*example_inputs)
            outputs = outputs if isinstance(outputs, tuple) else (outputs,)
            torch.onnx.export(model, example_inputs, str(path), input_names=list(input_names),
                              output_names=list(output_names), opset_version=opset, dynamo=False,
                              dynamic_axes=None, do_constant_folding=True, export_params=True,
                              keep_initializers_as_inputs=False)
    finally:
        model.train(was_training)

    proto = onnx.load(str(path))
    onnx.checker.check_model(proto)
    _check_io(proto.graph.input, input_names, [tuple(t.shape) for t in example_inputs], "input", path)
    _check_io(proto.graph.output, output_names, [tuple(t.shape) for t in outputs], "output", path)
    counts = Counter(node.op_type for node in proto.graph.node)
    for op_type, expected in op_counts.items():
        if counts[op_type] != expected:
            raise ExportError(f"{path}: expected exactly {expected} {op_type} node(s), the graph has "
                              f"{counts[op_type]} (ops: {dict(sorted(counts.items()))})")

    sidecar = {
        "file": path.name,
        "sha256": file_sha256(path),
        "opset": opset,
        "exporter": "torch.onnx.export(dynamo=False)",
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "inputs": {name: list(t.shape) for name, t in zip(input_names, example_inputs, strict=True)},
        "outputs": {name: list(t.shape) for name, t in zip(output_names, outputs, strict=True)},
        "dtype": "float32",
        "n_nodes": len(proto.graph.node),
        **metadata,
    }
    sidecar_path(path).write_text(json.dumps(sidecar, indent=2) + "\n")
    return path


def export_pinn_onnx(model: PinnStep | LstmStep, path: str | Path, *, opset: int = 17) -> Path:
    """Export one tick of a recurrent dynamics model with the PINN's tensor contract (the PINN, or the pure-LSTM
    baseline): q, qd, tau [1, n], h, c [layers, 1, hidden] -> q_next, qd_next, h_next, c_next.

    What is exported is `model.folded()`: the same function with the normalisation and output scales folded into
    the weights (fewer graph nodes, so a cheaper tick); `model` itself is not changed."""
    config = model.config
    n = config.n_joints
    example = (torch.zeros(1, n), torch.zeros(1, n), torch.zeros(1, n), *model.initial_state(1))
    dtypes = {p.dtype for p in model.parameters()}
    if dtypes != {torch.float32}:
        raise ExportError(f"the model's parameters are {sorted(map(str, dtypes))}; export a float32 model")
    kind = f"{kind_of(model)}_step"
    return _export_checked(
        model.folded(), example, path,
        input_names=("q", "qd", "tau", "h", "c"), output_names=("q_next", "qd_next", "h_next", "c_next"),
        opset=opset, op_counts={"LSTM": config.lstm_layers},
        metadata={"kind": kind, "n_joints": n, "hidden": config.lstm_hidden, "layers": config.lstm_layers,
                  "dt": config.dt, "config": dataclasses.asdict(config), "folded_affine_stages": True},
    )


def export_mlp_policy_onnx(model: nn.Module, path: str | Path, obs_dim: int, n_joints: int, *,
                           opset: int = 17) -> Path:
    """Export a feed-forward policy: obs [1, obs_dim] -> action [1, n_joints]."""
    if obs_dim <= 0 or n_joints <= 0:
        raise ValueError(f"obs_dim and n_joints must be > 0, got {obs_dim} and {n_joints}")
    obs = torch.zeros(1, obs_dim)
    with torch.no_grad():
        action = model(obs)
    if not isinstance(action, torch.Tensor) or tuple(action.shape) != (1, n_joints):
        got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
        raise ValueError(f"the policy maps obs [1, {obs_dim}] to {got}, expected action [1, {n_joints}]")
    return _export_checked(model, (obs,), path, input_names=("obs",), output_names=("action",), opset=opset,
                           op_counts={}, metadata={"kind": "mlp_policy", "obs_dim": obs_dim, "n_joints": n_joints})


def make_random_policy(obs_dim: int, n_joints: int, hidden: Sequence[int] = (64, 64), seed: int = 0) -> nn.Module:
    """An MLP policy with ELU and random weights drawn from `seed`, a stand-in until the trained policy exists.
    The global RNG is left untouched."""
    sizes = [obs_dim, *hidden, n_joints]
    layers: list[nn.Module] = []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        for i, (w_in, w_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            if i:
                layers.append(nn.ELU())
            layers.append(nn.Linear(w_in, w_out))
    return nn.Sequential(*layers)


def smooth_inputs(n_joints: int, dt: float, stats: dict | None = None, steps: int = 1000, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, tau) float32 [steps, n_joints]: smooth seeded sinusoids of one std about the training means
    (`stats`, a DatasetStats.to_json() dict; zero means and unit stds without)."""
    rng = np.random.default_rng(seed)
    stat = {key: np.asarray(stats[key]) if stats else np.full(n_joints, float(key.endswith("std")))
            for key in ("q_mean", "q_std", "qd_mean", "qd_std", "tau_mean", "tau_std")}
    t = np.arange(steps)[:, None] * dt
    frequency, phase = rng.uniform(0.5, 3.0, (3, n_joints)), rng.uniform(0, 2 * np.pi, (3, n_joints))
    wave = np.sin(2 * np.pi * frequency[:, None] * t[None] + phase[:, None])  # [3, steps, n]
    q, qd, tau = ((stat[f"{k}_mean"] + stat[f"{k}_std"] * wave[i]).astype(np.float32)
                  for i, k in enumerate(("q", "qd", "tau")))
    return q, qd, tau


def rollout_parity(model: nn.Module, path: str | Path, inputs: Sequence[np.ndarray]) -> float:
    """Worst |torch - onnxruntime| over the ticks of `inputs` ((q, qd, tau), each [steps, n_joints]), which each
    side runs with its own recurrent state (h, c) carried from tick to tick: of q' and qd' (absolute) and of the
    state (relative to max(1, |value|): an LSTM's cell state grows to tens, where float32 resolves ~2e-6). The
    inputs are shared rather than fed back: a learnt model run open loop amplifies float32 rounding like any
    chaotic system, so a fed-back comparison measures its Lyapunov exponent, not the export. The session is the
    runtime's (`runtime.inference.open_session`)."""
    from runtime.inference import open_session

    session = open_session(path, "dynamics")
    names = [i.name for i in session.get_inputs()]  # q, qd, tau, then the state: the export's checked order
    outputs = [o.name for o in session.get_outputs()]
    torch_state = list(model.initial_state(1))
    ort_state = [s.numpy().copy() for s in torch_state]
    worst = 0.0
    with torch.no_grad():
        for q, qd, tau in zip(*(np.asarray(x, np.float32)[:, None] for x in inputs), strict=True):
            q_t, qd_t, *torch_state = model(torch.from_numpy(q), torch.from_numpy(qd), torch.from_numpy(tau),
                                            *torch_state)
            q_o, qd_o, *ort_state = session.run(outputs, dict(zip(names, [q, qd, tau, *ort_state], strict=True)))
            worst = max(worst, float(np.abs(q_t.numpy() - q_o).max()), float(np.abs(qd_t.numpy() - qd_o).max()),
                        *(float((np.abs(a.numpy() - b) / np.maximum(1.0, np.abs(b))).max())
                          for a, b in zip(torch_state, ort_state, strict=True)))
    return worst


def main(argv: list[str] | None = None) -> int:
    """bruce-export: a trained checkpoint (bruce-train) -> ONNX for the runtime, with a parity check."""
    import argparse

    from training.checkpoint import MODEL_KINDS, CheckpointError, load_model_checkpoint

    parser = argparse.ArgumentParser(prog="bruce-export", description="Export a trained dynamics checkpoint to "
                                     "ONNX (one tick per call, explicit LSTM state) and check torch/onnxruntime "
                                     "parity over a 1000-step rollout of the carried state.")
    parser.add_argument("--checkpoint", required=True, help="checkpoint written by bruce-train")
    parser.add_argument("--out", required=True, help="ONNX file to write (its sidecar goes to <out>.json)")
    parser.add_argument("--tolerance", type=float, default=1e-5, help="worst allowed |torch - ORT| (default 1e-5)")
    args = parser.parse_args(argv)
    try:
        model, payload = load_model_checkpoint(args.checkpoint)
    except CheckpointError as exc:
        print(f"bruce-export: error: {exc}", file=sys.stderr)
        return 2
    exporter = MODEL_KINDS[payload["kind"]].onnx_exporter()
    if exporter is None:
        exportable = sorted(kind for kind, entry in MODEL_KINDS.items() if entry.exporter)
        parser.error(f"{args.checkpoint}: kind {payload['kind']!r} has no ONNX export ({', '.join(exportable)} do)")
    path = Path(exporter(model, args.out))
    worst = rollout_parity(model, path, smooth_inputs(model.n_joints, model.dt, payload.get("stats")))
    sidecar = json.loads(sidecar_path(path).read_text())
    train = payload.get("train", {})
    steps = [(payload.get("data") or {}).get("collect_command"), train.get("command"),
             shlex.join(["bruce-export", *(sys.argv[1:] if argv is None else argv)])]
    sidecar.update(command=" && ".join(step for step in steps if step), seed=(train.get("config") or {}).get("seed"))
    sidecar.update(checkpoint=str(args.checkpoint), checkpoint_sha256=file_sha256(args.checkpoint),
                   data=payload.get("data"), train=payload.get("train", {}).get("config"),
                   epochs=payload.get("train", {}).get("epoch"), parity_1000_steps=worst)
    sidecar_path(path).write_text(json.dumps(sidecar, indent=2) + "\n")
    print(f"bruce-export: {payload['kind']} -> {path}; torch/onnxruntime parity over a 1000-step rollout: "
          f"{worst:.2e} (tolerance {args.tolerance:g})")
    if not worst <= args.tolerance:
        print(f"bruce-export: parity {worst:.2e} exceeds {args.tolerance:g}", file=sys.stderr)
        return 1
    return 0
