"""Per-step compute of the learned dynamics models at batch 1 (`bruce-eval dynamics`, docs/dynamics.md): torch eager
and onnxruntime, timed interleaved on one pinned core with the GC off, and their rollout parity."""

from __future__ import annotations

import gc
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from runtime.loop.recorder import file_sha256
from training.dynamics.checkpoint import MODEL_KINDS
from training.dynamics.export import rollout_parity
from training.evaluation.dynamics_eval import EvalData, EvalError, LoadedModel

PARITY_STEPS = 200
PINN_SIGNATURE = (("q", "qd", "tau", "h", "c"), ("q_next", "qd_next", "h_next", "c_next"))


class TorchTick:
    """One model call at batch 1 with the state carried, under inference_mode (no_grad for a model whose step
    needs autograd, recorded in `mode`)."""

    def __init__(self, model: nn.Module, q: np.ndarray, qd: np.ndarray, tau: np.ndarray):
        self.model = model
        self.inputs = tuple(torch.from_numpy(v.astype(np.float32)[None]) for v in (q, qd, tau))
        self.state = model.initial_state(1)
        self.mode = "inference_mode"
        try:
            self()
        except RuntimeError:
            self.mode, self.state = "no_grad", model.initial_state(1)
            self()

    def __call__(self) -> None:
        with torch.inference_mode() if self.mode == "inference_mode" else torch.no_grad():
            self.state = tuple(self.model(*self.inputs, *self.state)[2:])


class BoundOnnxTick:
    """One `run_with_iobinding` on fixed float32 buffers; every input X with an output X_next is recurrent state,
    ping-ponged between two bindings like `runtime.control.inference.OnnxPinn`."""

    def __init__(self, path: Path, q: np.ndarray, qd: np.ndarray, tau: np.ndarray):
        import onnxruntime as ort

        from runtime.control.inference import open_session

        self.session = open_session(path, "dynamics")
        given = {"q": q, "qd": qd, "tau": tau}
        inputs = {t.name: t for t in self.session.get_inputs()}
        outputs = {t.name: t for t in self.session.get_outputs()}
        missing = [name for name in given if name not in inputs]
        if missing:
            raise EvalError(f"ONNX model {path}: no input {missing[0]!r} (inputs: {sorted(inputs)})")
        buffers = {}
        for name, value in given.items():
            buffers[name] = np.ascontiguousarray(np.broadcast_to(value.astype(np.float32), inputs[name].shape))
        self.state_names = [name for name in inputs if name not in given and f"{name}_next" in outputs]
        extra = [name for name in inputs if name not in given and name not in self.state_names]
        if extra:
            raise EvalError(f"ONNX model {path}: input {extra[0]!r} is neither q/qd/tau nor a state with an "
                            f"output {extra[0] + '_next'!r}")
        pairs = {name: (np.zeros(inputs[name].shape, np.float32), np.zeros(inputs[name].shape, np.float32))
                 for name in self.state_names}
        plain_outputs = {name: np.zeros(t.shape, np.float32) for name, t in outputs.items()
                         if not (name.endswith("_next") and name[:-5] in pairs)}
        self._ios = []
        for turn in (0, 1):
            io = self.session.io_binding()
            for name, array in buffers.items():
                io.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(array))
            for name, (a, b) in pairs.items():
                io.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy((a, b)[turn]))
                io.bind_ortvalue_output(f"{name}_next", ort.OrtValue.ortvalue_from_numpy((a, b)[1 - turn]))
            for name, array in plain_outputs.items():
                io.bind_ortvalue_output(name, ort.OrtValue.ortvalue_from_numpy(array))
            self._ios.append(io)
        self._keep = (buffers, pairs, plain_outputs)  # the bindings share this memory
        self._turn = 0

    def __call__(self) -> None:
        self.session.run_with_iobinding(self._ios[self._turn])
        self._turn = 1 - self._turn


def onnx_tick(path: Path, n_joints: int, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> tuple[Callable, str]:
    """The runtime's `OnnxPinn.step` where the file has the PINN signature, else a `BoundOnnxTick`."""
    import onnxruntime as ort

    from runtime.control.inference import OnnxPinn, session_options

    session = ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"])
    names = (tuple(t.name for t in session.get_inputs()), tuple(t.name for t in session.get_outputs()))
    if names == PINN_SIGNATURE:
        pinn = OnnxPinn(path, n_joints)
        pinn.warmup(10)
        return (lambda: pinn.step(q, qd, tau)), "runtime.control.inference.OnnxPinn.step"
    return BoundOnnxTick(path, q, qd, tau), "run_with_iobinding (bound buffers)"


def timed_calls(step: Callable[[], Any], calls: int) -> np.ndarray:
    out = np.empty(calls)
    clock = time.perf_counter_ns
    for i in range(calls):
        begin = clock()
        step()
        out[i] = clock() - begin
    return out / 1e3


def time_contenders(contenders: dict[str, Callable[[], Any]], calls: int, blocks: int = 4) -> dict[str, dict]:
    """p50/p99/max µs per contender, interleaved in `blocks` on one pinned core with the GC off; affinity, thread
    count and GC state are restored afterwards."""
    samples: dict[str, list[np.ndarray]] = {name: [] for name in contenders}
    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    threads = torch.get_num_threads()
    gc_was_enabled = gc.isenabled()
    try:
        if affinity:
            os.sched_setaffinity(0, {max(affinity)})
        torch.set_num_threads(1)
        gc.collect()
        gc.disable()
        for step in contenders.values():
            timed_calls(step, min(calls, 200))
        per_block = max(1, calls // blocks)
        for _ in range(blocks):
            for name, step in contenders.items():
                samples[name].append(timed_calls(step, per_block))
    finally:
        if gc_was_enabled:
            gc.enable()
        torch.set_num_threads(threads)
        if affinity:
            os.sched_setaffinity(0, affinity)
    stats = {}
    for name, parts in samples.items():
        s = np.concatenate(parts)
        stats[name] = {"p50_us": float(np.median(s)), "p99_us": float(np.percentile(s, 99)),
                       "max_us": float(s.max()), "calls": int(s.size)}
    return stats


def export_for_timing(loaded: LoadedModel, directory: Path) -> Path | None:
    exporter = MODEL_KINDS[loaded.kind].onnx_exporter()
    if exporter is None:
        return None
    return Path(exporter(loaded.model, directory / f"{loaded.kind}_{loaded.path.stem}.onnx"))


def measure_compute(models: dict[str, LoadedModel], onnx_files: dict[str, Path | None], data: EvalData,
                    sample: int, calls: int, exported: frozenset[str] = frozenset()) -> dict[str, dict]:
    """Per-step compute per model name (docs/dynamics.md); `exported` names the models whose ONNX file was
    exported for this run (a temporary file: only its hash is kept)."""
    q, qd, tau = data.q[sample], data.qd[sample], data.tau[sample]
    contenders, modes, paths = {}, {}, {}
    for name, loaded in models.items():
        tick = TorchTick(loaded.model, q, qd, tau)
        contenders[(name, "torch")] = tick
        modes[name] = tick.mode
        if onnx_files.get(name) is not None:
            step, paths[name] = onnx_tick(onnx_files[name], data.n_joints, q, qd, tau)
            contenders[(name, "ort")] = step
    stats = time_contenders(contenders, calls)
    compute = {}
    for name, loaded in models.items():
        entry = {"checkpoint": str(loaded.path), "batch": 1, "torch": {**stats[(name, "torch")],
                                                                       "mode": modes[name], "threads": 1}}
        if (name, "ort") in stats:
            onnx_path = onnx_files[name]
            steps = min(PARITY_STEPS, data.q.shape[0] - sample)
            entry["ort"] = {**stats[(name, "ort")], "call": paths[name],
                            "file": "(exported for this run)" if name in exported else str(onnx_path),
                            "sha256": file_sha256(onnx_path),
                            "parity_max_abs": rollout_parity(loaded.model, onnx_path, [
                                x[sample:sample + steps] for x in (data.q, data.qd, data.tau)]),
                            "parity_steps": steps}
        compute[name] = entry
    return compute
