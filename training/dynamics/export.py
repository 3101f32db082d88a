"""`bruce-export`: a trained dynamics checkpoint -> one tick as ONNX for the 1 kHz runtime (`export_pinn_onnx`, the
PINN's tensor contract, which the LSTM baseline shares), checked against torch over a rollout (`rollout_parity`).
The writing and checking of the file is `training.onnx_export`'s.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import nn

from runtime.loop.recorder import file_sha256
from training.dynamics.checkpoint import kind_of
from training.dynamics.lstm_baseline import LstmStep
from training.dynamics.pinn import PinnStep
from training.onnx_export import ExportError, export_checked, sidecar_path


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
    return export_checked(
        model.folded(), example, path,
        input_names=("q", "qd", "tau", "h", "c"), output_names=("q_next", "qd_next", "h_next", "c_next"),
        opset=opset, op_counts={"LSTM": config.lstm_layers},
        metadata={"kind": kind, "n_joints": n, "hidden": config.lstm_hidden, "layers": config.lstm_layers,
                  "dt": config.dt, "config": dataclasses.asdict(config), "folded_affine_stages": True},
    )


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
    runtime's (`runtime.control.inference.open_session`)."""
    from runtime.control.inference import open_session

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

    from training.dynamics.checkpoint import MODEL_KINDS, CheckpointError, load_model_checkpoint

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
