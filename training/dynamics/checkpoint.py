"""Dynamics-model checkpoints (`save_checkpoint`, `load_model_checkpoint`) and the registry of model kinds
(`MODEL_KINDS`), shared by the trainer, the exporter and the evaluator.

A checkpoint is a `torch.save` dict loaded with `weights_only=True` (plain tensors, numbers, strings, lists and
dicts only); its keys: docs/dynamics.md ("Checkpoints"). Model kinds resolve lazily ("module:Class"), so a kind's
module is imported only when it is used.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn


@dataclass(frozen=True)
class ModelKind:
    model: str   # "module:Class" of the nn.Module
    config: str  # "module:Class" of its frozen config dataclass
    exporter: str | None = None  # "module:function" writing one tick as ONNX: (model, path) -> path; None: none

    def classes(self) -> tuple[type[nn.Module], type]:
        return _resolve(self.model), _resolve(self.config)

    def onnx_exporter(self):
        """The kind's ONNX exporter, or None where the kind has no ONNX form."""
        return None if self.exporter is None else _resolve(self.exporter)


# The LSTM baseline has the PINN's tensor names, so the PINN's exporter (and the runtime's OnnxPinn) serve it too.
MODEL_KINDS: dict[str, ModelKind] = {
    "pinn": ModelKind("training.dynamics.pinn:PinnStep", "training.dynamics.pinn:PinnConfig",
                      "training.dynamics.export:export_pinn_onnx"),
    "lstm": ModelKind("training.dynamics.lstm_baseline:LstmStep", "training.dynamics.lstm_baseline:LstmConfig",
                      "training.dynamics.export:export_pinn_onnx"),
    "olnn": ModelKind("training.dynamics.olnn:OlnnStep", "training.dynamics.olnn:OlnnConfig",
                      "training.dynamics.olnn:export_olnn_onnx"),
    "analytic": ModelKind("training.dynamics.analytic:AnalyticModel", "training.dynamics.analytic:AnalyticConfig"),
}


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used; the message names the file and the problem."""


def _resolve(target: str):
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def kind_of(model: nn.Module) -> str:
    """The registry key of a model instance."""
    for kind, entry in MODEL_KINDS.items():
        module, _, name = entry.model.partition(":")
        if type(model).__module__ == module and type(model).__name__ == name:
            return kind
    raise CheckpointError(f"{type(model).__name__} is not a registered model kind ({sorted(MODEL_KINDS)})")


def build_model(kind: str, config: dict | None = None) -> nn.Module:
    """A fresh model of `kind` from its config dict (None: the kind's defaults, i.e. the paper's sizes)."""
    if kind not in MODEL_KINDS:
        raise CheckpointError(f"unknown model kind {kind!r}; known: {sorted(MODEL_KINDS)}")
    model_class, config_class = MODEL_KINDS[kind].classes()
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    config = dict(config or {})
    unknown = sorted(set(config) - set(fields))
    if unknown:
        raise CheckpointError(f"{kind} config: unknown key(s) {unknown}; known: {sorted(fields)}")
    # JSON/torch round trips turn tuples into lists; the config dataclasses want tuples.
    config = {k: tuple(v) if isinstance(v, list) else v for k, v in config.items()}
    return model_class(config_class(**config))


def save_checkpoint(path: str | Path, model: nn.Module, **extra) -> Path:
    """Write a checkpoint for `model` (plus the other keys of docs/dynamics.md in `extra`) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"kind": kind_of(model), "config": dataclasses.asdict(model.config), "state_dict": model.state_dict(),
               **extra}
    partial = path.with_name(path.name + ".partial")
    torch.save(payload, partial)
    os.replace(partial, path)  # a crash mid-write leaves the previous checkpoint intact
    return path


def read_checkpoint(path: str | Path) -> dict:
    """The raw checkpoint dict; a missing or unreadable file is a CheckpointError naming it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: file not found")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        # Not torch's message: it runs to many lines and advises weights_only=False, which would run the file's code.
        raise CheckpointError(f"checkpoint {path}: not a torch checkpoint that loads with weights_only=True "
                              f"({type(exc).__name__})") from exc
    missing = [key for key in ("kind", "config", "state_dict") if key not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path}: missing key(s) {missing}")
    return payload


def load_model_checkpoint(path: str | Path) -> tuple[nn.Module, dict]:
    """(model in eval mode with the checkpoint's weights, the raw checkpoint dict)."""
    payload = read_checkpoint(path)
    try:
        model = build_model(payload["kind"], payload["config"])
        model.load_state_dict(payload["state_dict"])
    except (CheckpointError, RuntimeError, TypeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: {exc}") from exc
    return model.eval(), payload
