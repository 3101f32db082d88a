"""`bruce-eval dynamics`: held-out accuracy and per-step cost of the learned dynamics models (issue #5, §IV-B).

Every model has the shared interface: `n_joints`, `dt`, `initial_state(batch) -> tuple` (empty when stateless) and
`forward(q, qd, tau, *state) -> (q_next, qd_next, *state_next)` on float32 [B, n_joints]. On the test split of a
dataset (`split_by_time`, as the trainer splits it), cut into runs that cross no episode boundary
(`training.episodes`): one-step NMSE on increments, open-loop K-step NMSE from the same start points after the same
teacher-forced warm-up, a bounded-rollout check, and per-step compute at batch 1 in torch and onnxruntime with
their parity. The definitions and the outputs (`dynamics_eval.json`, `.md`, Fig. 4 and Fig. 5 as PNG):
docs/dynamics.md ("Evaluation protocol"). The parser is `training.evaluation.cli`'s.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from bruce_hw.config import ConfigError, RobotConfig
from runtime.recorder import file_sha256
from training.dataset import DatasetError, load_dataset, split_by_time
from training.dynamics.checkpoint import MODEL_KINDS, CheckpointError, load_model_checkpoint
from training.dynamics.export import rollout_parity
from training.episodes import episode_runs, run_indices
from training.evaluation.report import BOUND_FACTOR, bar_k, json_safe, markdown_table, plot_fig4, plot_fig5

PARITY_STEPS = 200
ONE_STEP_BATCH = 4096  # stateless models: transitions per forward call
PROVENANCE = ("format_version", "config_hash", "seed", "seconds", "created")  # dataset metadata copied to the JSON
PINN_SIGNATURE = (("q", "qd", "tau", "h", "c"), ("q_next", "qd_next", "h_next", "c_next"))


class EvalError(ValueError):
    """Inputs the evaluation cannot use: a data file, a checkpoint or an option, named in the message."""


# -- data ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalData:
    """The recorded arrays (float64, config joint order) and the test split's runs."""

    path: Path
    sha256: str
    q: np.ndarray        # [T, n] rad
    qd: np.ndarray       # [T, n] rad/s
    tau: np.ndarray      # [T, n] N m
    episode: np.ndarray  # [T] int
    dt: float
    test_start: int
    runs: tuple[tuple[int, int], ...]  # test-split runs [start, stop) inside one episode
    metadata: dict

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]


def load_eval_data(path: str | Path, config: RobotConfig, train_fraction: float = 0.8) -> EvalData:
    """Read a dataset with `training.dataset.load_dataset` (its checks against the robot config) and take its test
    part with `split_by_time`, so the evaluator and the trainer split by construction alike."""
    path = Path(path)
    dataset = load_dataset(path, config)
    _, test = split_by_time(dataset, train_fraction)
    test_start, total = test.span[0], len(dataset)
    return EvalData(path=path, sha256=file_sha256(path), q=dataset.q, qd=dataset.qd, tau=dataset.tau,
                    episode=dataset.episode, dt=dataset.dt, test_start=test_start,
                    runs=episode_runs(dataset.episode, test_start, total), metadata=dict(dataset.metadata))


# -- metric building blocks ----------------------------------------------------------------------------------
def nmse_per_joint(pred: np.ndarray, true: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Mean squared error over every axis but the last, divided by `variance` [n]: [n]."""
    err = np.asarray(pred, np.float64) - np.asarray(true, np.float64)
    return np.mean(err.reshape(-1, err.shape[-1]) ** 2, axis=0) / variance


def checked_variance(values: np.ndarray, what: str) -> np.ndarray:
    """Per-joint variance (ddof 0) of [N, n] values; a joint that never changes cannot normalise an error."""
    variance = np.var(values, axis=0)
    flat = np.flatnonzero(~(variance > 0))
    if flat.size:
        raise EvalError(f"the test split's {what} has zero variance at joint {int(flat[0])}; NMSE is undefined")
    return variance


def select_start_points(runs: Sequence[tuple[int, int]], warmup: int, horizon: int, count: int,
                        seed: int | None = None) -> np.ndarray:
    """`count` start points (sorted), evenly spaced over the eligible ones, or drawn without replacement with
    `seed`; fewer when fewer are eligible. None eligible is an EvalError."""
    eligible = run_indices(runs, before=warmup, after=horizon)
    if eligible.size == 0:
        longest = max((b - a for a, b in runs), default=0)
        raise EvalError(f"no start point fits a warm-up of {warmup} and a {horizon}-step rollout inside one run of "
                        f"the test split (longest run: {longest} samples); lower --warmup or --k")
    if count <= 0:
        raise EvalError(f"--starts: expected a count > 0, got {count}")
    if count >= eligible.size:
        return eligible.copy()
    if seed is None:
        picks = np.round(np.linspace(0, eligible.size - 1, count)).astype(np.int64)
    else:
        picks = np.sort(np.random.default_rng(seed).choice(eligible.size, size=count, replace=False))
    return eligible[picks]


# -- models ----------------------------------------------------------------------------------------------------
@dataclass
class LoadedModel:
    kind: str
    path: Path
    model: nn.Module
    trained_on: dict | None  # the checkpoint's "data" provenance (path, sha256, split), when it has one


def load_checkpoint(path: str | Path) -> LoadedModel:
    """A `training.dynamics.checkpoint` file -> its float32 model in eval mode, its kind and its training-data
    record."""
    model, payload = load_model_checkpoint(path)
    trained_on = payload.get("data") if isinstance(payload.get("data"), dict) else None
    return LoadedModel(payload["kind"], Path(path), model.float().eval(), trained_on)


def check_model_fits(loaded: LoadedModel, data: EvalData) -> None:
    model = loaded.model
    if getattr(model, "n_joints", None) != data.n_joints:
        raise EvalError(f"checkpoint {loaded.path}: model has n_joints={getattr(model, 'n_joints', None)}, "
                        f"data file {data.path} has {data.n_joints} joints")
    if not math.isclose(float(getattr(model, "dt", float("nan"))), data.dt, rel_tol=1e-6):
        raise EvalError(f"checkpoint {loaded.path}: model dt={getattr(model, 'dt', None)} s, data file {data.path} "
                        f"has dt={data.dt} s")


def is_stateless(model: nn.Module) -> bool:
    return len(model.initial_state(1)) == 0


# -- predictions -----------------------------------------------------------------------------------------------
def _rows(array: torch.Tensor, index: np.ndarray) -> torch.Tensor:
    return array[torch.from_numpy(np.ascontiguousarray(index, np.int64))]


def _tensors(data: EvalData) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return tuple(torch.from_numpy(a.astype(np.float32)) for a in (data.q, data.qd, data.tau))


def teacher_forced_warmup(model: nn.Module, arrays: Sequence[torch.Tensor], first: np.ndarray,
                          warmup: int) -> tuple[torch.Tensor, ...]:
    """The state after feeding the recorded samples first-warmup .. first-1 from a zero state."""
    state = model.initial_state(len(first))
    if not state:
        return state
    q, qd, tau = arrays
    for back in range(warmup, 0, -1):
        index = first - back
        state = tuple(model(_rows(q, index), _rows(qd, index), _rows(tau, index), *state)[2:])
    return state


@torch.no_grad()
def one_step_predictions(model: nn.Module, data: EvalData, transitions: np.ndarray, warmup: int,
                         chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """(q_hat[t+1], qd_hat[t+1]) for each scored transition t (docs/dynamics.md), float64 [N, n] each."""
    arrays = _tensors(data)
    q, qd, tau = arrays
    if is_stateless(model):
        outs = [model(_rows(q, part), _rows(qd, part), _rows(tau, part))
                for part in np.array_split(transitions, max(1, math.ceil(len(transitions) / ONE_STEP_BATCH)))]
        return (torch.cat([o[0] for o in outs]).double().numpy(), torch.cat([o[1] for o in outs]).double().numpy())
    # Chunks of consecutive scored transitions (never across a run: scored transitions are consecutive within
    # a run), all advanced together as one batch; finished chunks repeat their last row, masked out below.
    breaks = np.flatnonzero(np.diff(transitions) != 1) + 1
    chunks = [piece for run in np.split(transitions, breaks) for piece in np.array_split(
        run, max(1, math.ceil(len(run) / chunk)))]
    first = np.array([c[0] for c in chunks])
    lengths = np.array([len(c) for c in chunks])
    state = teacher_forced_warmup(model, arrays, first, warmup)
    q_pred = np.empty((lengths.max(), len(chunks), data.n_joints))
    qd_pred = np.empty_like(q_pred)
    for i in range(lengths.max()):
        index = first + np.minimum(i, lengths - 1)
        q_next, qd_next, *state = model(_rows(q, index), _rows(qd, index), _rows(tau, index), *state)
        q_pred[i], qd_pred[i] = q_next.double().numpy(), qd_next.double().numpy()
    take = [(i, b) for b, n in enumerate(lengths) for i in range(n)]
    steps, batch = np.array(take).T
    return q_pred[steps, batch], qd_pred[steps, batch]


@torch.no_grad()
def open_loop_rollout(model: nn.Module, data: EvalData, starts: np.ndarray, warmup: int,
                      horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Predicted (q, qd) at s+1 .. s+horizon for every start s: float64 [horizon, N, n] each."""
    arrays = _tensors(data)
    q, qd, tau = arrays
    state = teacher_forced_warmup(model, arrays, starts, warmup)
    q_hat, qd_hat = _rows(q, starts), _rows(qd, starts)
    q_pred = np.empty((horizon, len(starts), data.n_joints))
    qd_pred = np.empty_like(q_pred)
    for k in range(horizon):
        q_hat, qd_hat, *state = model(q_hat, qd_hat, _rows(tau, starts + k), *state)
        q_pred[k], qd_pred[k] = q_hat.double().numpy(), qd_hat.double().numpy()
    return q_pred, qd_pred


def rollout_truth(values: np.ndarray, starts: np.ndarray, horizon: int) -> np.ndarray:
    """values[s + k] for k = 1 .. horizon: [horizon, N, n]."""
    return values[starts[None, :] + np.arange(1, horizon + 1)[:, None]]


# -- one checkpoint ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Protocol:
    """What every model is evaluated on: identical for all of them."""

    ks: tuple[int, ...]
    warmup: int
    starts: np.ndarray
    transitions: np.ndarray
    chunk: int


def _nmse_entry(q_nmse: np.ndarray, qd_nmse: np.ndarray) -> dict:
    return {"q": float(np.mean(q_nmse)), "qd": float(np.mean(qd_nmse)),
            "q_per_joint": q_nmse.tolist(), "qd_per_joint": qd_nmse.tolist()}


def bounded_check(q_pred: np.ndarray, qd_pred: np.ndarray, data: EvalData) -> dict:
    """Whether the rollouts stay finite and within BOUND_FACTOR x the test split's range about its centre."""
    test = slice(data.test_start, None)
    ratios = []
    for pred, values in ((q_pred, data.q[test]), (qd_pred, data.qd[test])):
        lo, hi = values.min(axis=0), values.max(axis=0)
        half = np.maximum((hi - lo) / 2, 1e-12)
        with np.errstate(invalid="ignore"):
            ratios.append(float(np.max(np.abs(pred - (hi + lo) / 2) / half)))
    finite = bool(np.isfinite(q_pred).all() and np.isfinite(qd_pred).all())
    worst = max(ratios) if finite else float("inf")
    return {"finite": finite, "within_bound": finite and worst <= BOUND_FACTOR, "bound_factor": BOUND_FACTOR,
            "max_range_ratio": worst, "q_max_range_ratio": ratios[0], "qd_max_range_ratio": ratios[1]}


def evaluate_model(model: nn.Module, data: EvalData, protocol: Protocol) -> tuple[dict, dict]:
    """All accuracy numbers of one model, and the traces of its first rollout (for Fig. 4)."""
    test = slice(data.test_start, None)
    valid = run_indices(data.runs)
    q_inc_var = checked_variance(data.q[valid + 1] - data.q[valid], "q increments")
    qd_inc_var = checked_variance(data.qd[valid + 1] - data.qd[valid], "qd increments")
    q_var, qd_var = checked_variance(data.q[test], "q"), checked_variance(data.qd[test], "qd")

    t = protocol.transitions
    q_next, qd_next = one_step_predictions(model, data, t, protocol.warmup, protocol.chunk)
    with np.errstate(over="ignore", invalid="ignore"):  # a diverged model's NMSE is reported as non-finite
        one_step = _nmse_entry(nmse_per_joint(q_next - data.q[t], data.q[t + 1] - data.q[t], q_inc_var),
                               nmse_per_joint(qd_next - data.qd[t], data.qd[t + 1] - data.qd[t], qd_inc_var))

    horizon = max(protocol.ks)
    q_pred, qd_pred = open_loop_rollout(model, data, protocol.starts, protocol.warmup, horizon)
    q_true, qd_true = rollout_truth(data.q, protocol.starts, horizon), rollout_truth(data.qd, protocol.starts, horizon)
    with np.errstate(over="ignore", invalid="ignore"):
        k_step = {str(k): _nmse_entry(nmse_per_joint(q_pred[:k], q_true[:k], q_var),
                                      nmse_per_joint(qd_pred[:k], qd_true[:k], qd_var)) for k in protocol.ks}
    result = {"one_step": one_step, "k_step": k_step, "bounded": bounded_check(q_pred, qd_pred, data)}
    traces = {"q": q_pred[:, 0], "qd": qd_pred[:, 0]}
    return result, traces


def metric_table(result: dict) -> dict[str, float]:
    """The flat metrics summarised across checkpoints: one_step_q, one_step_qd, k<K>_q, k<K>_qd."""
    flat = {"one_step_q": result["one_step"]["q"], "one_step_qd": result["one_step"]["qd"]}
    for k, entry in result["k_step"].items():
        flat[f"k{k}_q"], flat[f"k{k}_qd"] = entry["q"], entry["qd"]
    return flat


def summarise(results: Sequence[dict]) -> dict:
    tables = [metric_table(r) for r in results]
    summary = {}
    for key in tables[0]:
        values = np.array([t[key] for t in tables])
        with np.errstate(invalid="ignore", over="ignore"):  # a diverged checkpoint makes the summary non-finite
            summary[key] = {"mean": float(np.mean(values)),
                            "std": float(np.std(values, ddof=1)) if len(values) > 1 else None, "n": len(values),
                            "non_finite": int(np.sum(~np.isfinite(values)))}
    return summary


# -- timing ----------------------------------------------------------------------------------------------------
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
    ping-ponged between two bindings like `runtime.inference.OnnxPinn`."""

    def __init__(self, path: Path, q: np.ndarray, qd: np.ndarray, tau: np.ndarray):
        import onnxruntime as ort

        from runtime.inference import open_session

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

    from runtime.inference import OnnxPinn, session_options

    session = ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"])
    names = (tuple(t.name for t in session.get_inputs()), tuple(t.name for t in session.get_outputs()))
    if names == PINN_SIGNATURE:
        pinn = OnnxPinn(path, n_joints)
        pinn.warmup(10)
        return (lambda: pinn.step(q, qd, tau)), "runtime.inference.OnnxPinn.step"
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


# -- CLI -------------------------------------------------------------------------------------------------------
def parse_named_paths(items: Sequence[str], option: str) -> dict[str, list[Path]]:
    named: dict[str, list[Path]] = {}
    for item in items:
        name, sep, paths = item.partition("=")
        if not sep or not name or not paths:
            raise EvalError(f"{option}: expected NAME=PATH[,PATH...], got {item!r}")
        if name in named:
            raise EvalError(f"{option}: name {name!r} given twice")
        named[name] = [Path(p) for p in paths.split(",") if p]
    return named


def parse_ks(text: str) -> tuple[int, ...]:
    try:
        ks = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        ks = []
    if not ks or ks[0] < 1:
        raise EvalError(f"--k: expected horizons >= 1 separated by commas, got {text!r}")
    return tuple(ks)


def run_dynamics(args: argparse.Namespace, argv: Sequence[str]) -> int:
    from bruce_hw.config import DEFAULT_CONFIG
    from runtime.robot_config import load_config

    if not 0.0 < args.train_fraction < 1.0:
        raise EvalError(f"--train-fraction: expected a fraction in (0, 1), got {args.train_fraction}")
    config = load_config(args.config or DEFAULT_CONFIG)
    data = load_eval_data(args.data, config, args.train_fraction)
    ks = parse_ks(args.k)
    if args.warmup < 0 or args.chunk < 1:
        raise EvalError(f"--warmup must be >= 0 and --chunk >= 1, got {args.warmup} and {args.chunk}")
    starts = select_start_points(data.runs, args.warmup, max(ks), args.starts, args.start_seed)
    transitions = run_indices(data.runs, before=args.warmup)
    if transitions.size == 0:
        raise EvalError(f"no one-step transition of the test split has {args.warmup} warm-up steps in its run")
    protocol = Protocol(ks, args.warmup, starts, transitions, args.chunk)
    checkpoints = parse_named_paths(args.model, "--model")
    onnx_given = parse_named_paths(args.onnx, "--onnx")
    unknown = sorted(set(onnx_given) - set(checkpoints))
    if unknown:
        raise EvalError(f"--onnx: {unknown[0]!r} is not a --model name ({sorted(checkpoints)})")

    models: dict[str, dict] = {}
    traces: dict[str, dict] = {}
    first_models: dict[str, LoadedModel] = {}
    for name, paths in checkpoints.items():
        results = []
        for path in paths:
            loaded = load_checkpoint(path)
            check_model_fits(loaded, data)
            begin = time.perf_counter()
            result, trace = evaluate_model(loaded.model, data, protocol)
            trained_sha = (loaded.trained_on or {}).get("sha256")
            result = {"checkpoint": str(path), "kind": loaded.kind,
                      "parameters": sum(p.numel() for p in loaded.model.parameters()),
                      "trained_on": loaded.trained_on,
                      "trained_on_this_file": None if trained_sha is None else trained_sha == data.sha256,
                      **result, "eval_s": time.perf_counter() - begin}
            if trained_sha is not None and trained_sha != data.sha256:
                print(f"bruce-eval: warning: {path} was trained on another data file (sha256 {trained_sha[:12]}…), "
                      f"its test split here may overlap what it trained on", file=sys.stderr)
            results.append(result)
            first_models.setdefault(name, loaded)
            traces.setdefault(name, trace)
            k_mid = bar_k(ks)
            print(f"bruce-eval: {name} {path}: one-step NMSE q {result['one_step']['q']:.3g} qd "
                  f"{result['one_step']['qd']:.3g}; K={k_mid} q {result['k_step'][str(k_mid)]['q']:.3g} qd "
                  f"{result['k_step'][str(k_mid)]['qd']:.3g}; bounded {result['bounded']['within_bound']} "
                  f"({result['eval_s']:.1f} s)", file=sys.stderr)
        models[name] = {"kind": results[0]["kind"], "checkpoints": [str(p) for p in paths],
                        "summary": summarise(results), "bounded": all(r["bounded"]["within_bound"] for r in results),
                        "per_checkpoint": results}

    compute: dict[str, dict] = {}
    if args.timing_calls > 0:
        with tempfile.TemporaryDirectory(prefix="bruce-eval-") as tmp:
            onnx_files: dict[str, Path | None] = {}
            for name, loaded in first_models.items():
                if args.no_onnx:
                    onnx_files[name] = None
                elif name in onnx_given:
                    onnx_files[name] = onnx_given[name][0]
                else:
                    onnx_files[name] = export_for_timing(loaded, Path(tmp))
            exported = frozenset(n for n, f in onnx_files.items() if f is not None and n not in onnx_given)
            compute = measure_compute(first_models, onnx_files, data, int(starts[0]), args.timing_calls, exported)

    import onnxruntime

    selection = "evenly spaced" if args.start_seed is None else f"random, seed {args.start_seed}"
    report = {
        "command": "bruce-eval " + " ".join(argv),
        "data": {"path": str(data.path), "sha256": data.sha256, "samples": int(data.q.shape[0]), "dt": data.dt,
                 "n_joints": data.n_joints, "joints": list(config.joints),
                 "metadata": {k: data.metadata[k] for k in PROVENANCE if k in data.metadata},
                 "test_split": {"train_fraction": args.train_fraction, "start": data.test_start,
                                "stop": int(data.q.shape[0]), "runs": [list(r) for r in data.runs]}},
        "protocol": {"k": list(ks), "warmup": args.warmup, "starts": int(starts.size),
                     "start_selection": selection,
                     "start_points": starts.tolist(), "one_step_transitions": int(transitions.size),
                     "one_step_chunk": args.chunk, "k_step_error": "every step 1..K",
                     "nmse": "per joint: mean squared error / variance (ddof 0) of the ground truth on the test split; "
                             "averaged over joints. One-step on increments x[t+1]-x[t]."},
        "models": models,
        "compute": compute,
        "environment": {"python": platform.python_version(), "torch": torch.__version__,
                        "onnxruntime": onnxruntime.__version__, "numpy": np.__version__,
                        "machine": platform.machine(), "cpus": os.cpu_count()},
    }
    report = json_safe(report)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "dynamics_eval.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "dynamics_eval.md").write_text(markdown_table(report))
    plot_fig4(args.out / "fig4_joint0_rollout.png", data, int(starts[0]), traces, config.joints[0])
    plot_fig5(args.out / "fig5_nmse_runtime.png", report)
    print(markdown_table(report))
    print(f"bruce-eval: wrote {args.out}/dynamics_eval.json, dynamics_eval.md, fig4_joint0_rollout.png, "
          f"fig5_nmse_runtime.png")
    return 0


def main_dynamics(args: argparse.Namespace, argv: Sequence[str]) -> int:
    """`bruce-eval dynamics` (the parser is `training.evaluation.cli`'s, which loads torch only for this command)."""
    # One intra-op thread: the rollouts are long chains of small batched calls, where a second thread only adds
    # synchronisation (measured ~10-50x slower on the shared 2-core VM); the timing is per-thread anyway.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return run_dynamics(args, argv)
    except (EvalError, DatasetError, CheckpointError, ConfigError) as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 1
    finally:
        torch.set_num_threads(threads)
