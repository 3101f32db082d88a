"""`bruce-eval dynamics`'s evaluation: held-out accuracy of the learned dynamics models (issue #5, §IV-B).

Every model has the shared interface: `n_joints`, `dt`, `initial_state(batch) -> tuple` (empty when stateless) and
`forward(q, qd, tau, *state) -> (q_next, qd_next, *state_next)` on float32 [B, n_joints]. On the test split of a
dataset (`split_by_time`, as the trainer splits it), cut into runs that cross no episode boundary
(`training.episodes`): one-step NMSE on increments, open-loop K-step NMSE from the same start points after the same
teacher-forced warm-up, and a bounded-rollout check. The definitions: docs/dynamics.md ("Evaluation protocol").
The per-step compute is measured in `training.evaluation.dynamics_timing`, the command (its parser, the JSON, Markdown
and figures it writes) is `training.evaluation.dynamics_cli`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from bruce_hw.config import RobotConfig
from runtime.loop.recorder import file_sha256
from training.dataset import load_dataset, split_by_time
from training.dynamics.checkpoint import load_model_checkpoint
from training.episodes import episode_runs, run_indices
from training.evaluation.report import BOUND_FACTOR

ONE_STEP_BATCH = 4096  # stateless models: transitions per forward call


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
