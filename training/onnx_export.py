"""Writing the ONNX files the torch-free runtime loads: `export_checked` (export, verify, sidecar) and the walking
policy's export (`export_mlp_policy_onnx`); the dynamics models' exporter is `training.dynamics.export`.

Every export uses the legacy TorchScript exporter (`dynamo=False`, pinned: torch's default flipped to the dynamo
exporter, and for the PINN the legacy graph is smaller and faster), a fixed batch of 1 and no dynamic axes. The file
is loaded back, checked with `onnx.checker` and its input/output names, shapes and dtypes verified; a sidecar
`<file>.json` records the versions, opset and the file's SHA-256, so the runtime can tell which model it runs.
"""

from __future__ import annotations

import json
import warnings
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import onnx
import onnxruntime
import torch
from torch import nn

from runtime.loop.recorder import file_sha256

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


def export_checked(model: nn.Module, example_inputs: tuple[torch.Tensor, ...], path: str | Path, *,
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


def export_mlp_policy_onnx(model: nn.Module, path: str | Path, obs_dim: int, n_joints: int, *,
                           opset: int = 17, input_name: str = "obs", output_name: str = "action") -> Path:
    """Export a feed-forward policy: obs [1, obs_dim] -> action [1, n_joints] (tensors named as a spec names them)."""
    if obs_dim <= 0 or n_joints <= 0:
        raise ValueError(f"obs_dim and n_joints must be > 0, got {obs_dim} and {n_joints}")
    obs = torch.zeros(1, obs_dim)
    with torch.no_grad():
        action = model(obs)
    if not isinstance(action, torch.Tensor) or tuple(action.shape) != (1, n_joints):
        got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
        raise ValueError(f"the policy maps obs [1, {obs_dim}] to {got}, expected action [1, {n_joints}]")
    return export_checked(model, (obs,), path, input_names=(input_name,), output_names=(output_name,), opset=opset,
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
