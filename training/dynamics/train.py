"""`bruce-train`: train a dynamics model (the PINN or a baseline) on a `bruce-collect` dataset, the paper's way.

    bruce-train --data data/walk.npz --model pinn [--preset paper|small] [--seed 0] [--epochs E]
                --out runs/pinn_s0.pt [--resume] [--resample] [--ignore-extra]

Contiguous 80/20 split by time, statistics from the training part only; Eq. 7 with each term divided by the
training spread of its one-step increment (`Eq7Loss`), teacher-forced; truncated BPTT on windows inside episodes,
the LSTM state carried from window to window of a stream, the first `burn_in` steps after a fresh state not
counted; AdamW lr 1e-2, weight decay 1e-2, x0.4 every 150 epochs, 1000 epochs, gradient norm clipped at 1.
Checkpoints every `checkpoint_every` epochs: --resume continues an interrupted run with the same result.
`--model analytic` is identified by least squares instead. Details: docs/dynamics.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from bruce_hw.config import ConfigError, load_config
from runtime.loop.recorder import file_sha256
from training.dataset import (
    Dataset,
    DatasetError,
    DatasetStats,
    compute_stats,
    split_by_time,
    windows,
)
from training.dynamics.checkpoint import CheckpointError, build_model, read_checkpoint, save_checkpoint
from training.dynamics.pinn import PinnStep, joint_stop_range
from training.external_data import load_training_data


@dataclass(frozen=True)
class TrainConfig:
    epochs: int = 1000
    lr: float = 1e-2
    weight_decay: float = 1e-2
    lr_step_epochs: int = 150
    lr_gamma: float = 0.4
    window: int = 100        # transitions per TBPTT window
    streams: int = 64        # windows per batch (parallel streams)
    burn_in: int = 50        # uncounted steps after a fresh (zero) LSTM state
    lambda_q: float = 1.0
    lambda_qd: float = 1.0
    grad_clip: float = 1.0   # gradient norm: an LSTM at lr 1e-2 otherwise takes occasional destructive steps
    train_fraction: float = 0.8
    checkpoint_every: int = 25
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("epochs", "lr_step_epochs", "window", "streams", "checkpoint_every"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value > 0):
                raise ValueError(f"TrainConfig.{name}: expected an integer > 0, got {value!r}")
        if not (isinstance(self.burn_in, int) and 0 <= self.burn_in < self.window):
            raise ValueError(f"TrainConfig.burn_in: expected an integer in [0, window={self.window}), "
                             f"got {self.burn_in!r}")
        for name in ("lr", "weight_decay", "lr_gamma", "grad_clip", "lambda_q", "lambda_qd"):
            if not (getattr(self, name) >= 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"TrainConfig.{name}: expected a finite value >= 0, got {getattr(self, name)!r}")
        if not 0 < self.train_fraction < 1:
            raise ValueError(f"TrainConfig.train_fraction: expected a value in (0, 1), got {self.train_fraction!r}")


# Presets: "paper" is the default (the paper's sizes and schedule); "small" keeps tests and smoke runs fast.
MODEL_PRESETS: dict[str, dict[str, dict]] = {
    "paper": {"pinn": {}, "lstm": {}, "olnn": {}, "analytic": {}},
    "small": {"pinn": {"resnet_widths": (16, 55), "lstm_hidden": 16, "lstm_layers": 1},
              "lstm": {"lstm_hidden": 16, "lstm_layers": 1},
              "olnn": {}, "analytic": {}},
}
TRAIN_PRESETS: dict[str, dict] = {
    "paper": {},
    "small": {"epochs": 4, "window": 20, "streams": 8, "burn_in": 5, "lr_step_epochs": 2, "checkpoint_every": 2},
}


class Eq7Loss:
    """Eq. 7 with each term divided by the training spread of its one-step increment (`DatasetStats` q_inc_std,
    qd_inc_std), per joint; lambda_q and lambda_qd weigh the terms."""

    def __init__(self, stats: DatasetStats, lambda_q: float, lambda_qd: float):
        self.q_weight = torch.as_tensor(lambda_q / stats.q_inc_std ** 2, dtype=torch.float32)
        self.qd_weight = torch.as_tensor(lambda_qd / stats.qd_inc_std ** 2, dtype=torch.float32)

    def per_sample(self, q_hat, qd_hat, q_true, qd_true) -> torch.Tensor:
        """[..., n] predictions and targets -> [...] loss per transition (mean over joints)."""
        return ((q_hat - q_true) ** 2 * self.q_weight + (qd_hat - qd_true) ** 2 * self.qd_weight).mean(-1)


def _window_predictions(model: nn.Module, q, qd, tau, state: tuple) -> tuple[torch.Tensor, torch.Tensor, tuple]:
    """Teacher-forced one-step predictions for inputs [W, B, n]: a window call for recurrent models, one flat batch
    of independent transitions for stateless ones."""
    if state:
        q_hat, qd_hat, *state = model(q, qd, tau, *state)
        return q_hat, qd_hat, tuple(state)
    shape = q.shape
    q_hat, qd_hat = model(q.reshape(-1, shape[-1]), qd.reshape(-1, shape[-1]), tau.reshape(-1, shape[-1]))[:2]
    return q_hat.reshape(shape), qd_hat.reshape(shape), ()


def run_epoch(model: nn.Module, train: Dataset, loss_fn: Eq7Loss, config: TrainConfig, rng: np.random.Generator,
              optimizer: torch.optim.Optimizer | None) -> float:
    """One pass over the training part; returns the mean counted loss. Without an optimizer: evaluation only."""
    cut = windows(train, config.window, offset=int(rng.integers(config.window)))
    if len(cut) == 0:
        raise ValueError(f"no window of {config.window} transitions fits in an episode of the training data")
    index, fresh = cut.streams(min(config.streams, len(cut)))
    state = model.initial_state(index.shape[1])
    total, count = 0.0, 0
    for step in range(index.shape[0]):
        batch = {k: torch.from_numpy(v).transpose(0, 1) for k, v in cut.gather(train, index[step], np.float32).items()}
        q, qd, tau = batch["q"], batch["qd"], batch["tau"]  # [W + 1, B, n], time first
        starts = torch.from_numpy(fresh[step])
        mask = torch.ones(config.window, len(starts))
        mask[:config.burn_in, starts] = 0.0
        state = tuple(torch.where(starts[None, :, None], 0.0, s.detach()) for s in state)
        with torch.set_grad_enabled(optimizer is not None):
            q_hat, qd_hat, state = _window_predictions(model, q[:-1], qd[:-1], tau[:-1], state)
            per_sample = loss_fn.per_sample(q_hat, qd_hat, q[1:], qd[1:])
            loss = (per_sample * mask).sum() / mask.sum()
        if optimizer is not None:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if config.grad_clip > 0:
                nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimizer.step()
        total += float((per_sample.detach() * mask).sum())
        count += int(mask.sum())
    return total / count


def make_optimizer(model: nn.Module, config: TrainConfig):
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=config.lr_step_epochs, gamma=config.lr_gamma)
    return optimizer, scheduler


def train(data_path: str | Path, kind: str, out: str | Path, *, model_config: dict | None = None,
          train_config: TrainConfig | None = None, robot_config=None, resume: bool = False,
          progress: bool = True, command: str | None = None, resample: bool = False,
          ignore_extra: bool = False) -> dict:
    """Train a `kind` model on `data_path` and write the checkpoint `out`; returns the final checkpoint dict.
    `command` (the bruce-train line) is recorded in the checkpoint so an export can say how to regenerate it.
    `data_path` may be another simulator's trajectory (docs/byo_data.md), converted in memory; `resample` and
    `ignore_extra` are bruce-import-data's options for it."""
    config = train_config or TrainConfig()
    robot_config = robot_config or load_config()
    data = load_training_data(data_path, robot_config, resample=resample, ignore_extra=ignore_extra,
                              say=lambda line: print(f"bruce-train: {line}"))
    train_part, _ = split_by_time(data, config.train_fraction)
    stats = compute_stats(train_part)
    out = Path(out)
    provenance = {"path": str(data_path), "sha256": file_sha256(data_path),
                  "config_hash": data.metadata.get("config_hash"), "train_fraction": config.train_fraction,
                  "train_samples": len(train_part), "collect_command": data.metadata.get("command")}

    if kind == "analytic":  # no gradient training: least squares on the same training part
        return _identify_analytic(train_part, stats, robot_config, out, provenance, config, command)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = build_model(kind, model_config)
        model.fit_normalisation(stats)
        if isinstance(model, PinnStep):  # the stop is the PINN's stated physics; the baselines are as published
            model.set_joint_stop(*joint_stop_range(robot_config, train_part.q))
        optimizer, scheduler = make_optimizer(model, config)
        rng = np.random.default_rng(config.seed)
        start_epoch, history = 0, []
        if resume and out.is_file():
            previous = read_checkpoint(out)
            if previous.get("train", {}).get("config") != dataclasses.asdict(config) or previous["kind"] != kind:
                raise ValueError(f"--resume: {out} was trained with other settings; resume needs the same ones")
            if previous["data"]["sha256"] != provenance["sha256"]:
                raise ValueError(f"--resume: {out} was trained on other data ({previous['data']['path']})")
            if previous["train"]["epoch"] >= config.epochs:  # finished already: nothing to resume
                return {key: previous[key] for key in ("stats", "data", "train")}
            model.load_state_dict(previous["state_dict"])
            optimizer.load_state_dict(previous["resume"]["optimizer"])
            scheduler.load_state_dict(previous["resume"]["scheduler"])
            torch.set_rng_state(previous["resume"]["torch_rng"])
            rng.bit_generator.state = previous["resume"]["numpy_rng"]
            start_epoch, history = previous["train"]["epoch"], list(previous["train"]["history"])

        def checkpoint(epoch: int, final: bool) -> dict:
            extra = {"stats": stats.to_json(), "data": provenance,
                     "train": {"config": dataclasses.asdict(config), "epoch": epoch, "history": history,
                               "command": command}}
            if not final:
                extra["resume"] = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                                   "torch_rng": torch.get_rng_state(), "numpy_rng": rng.bit_generator.state}
            save_checkpoint(out, model, **extra)
            return extra

        model.train()
        bar = tqdm(range(start_epoch, config.epochs), initial=start_epoch, total=config.epochs, unit="epoch",
                   desc=f"train {kind}", disable=not progress, file=sys.stderr)
        for epoch in bar:
            started = time.perf_counter()
            loss = run_epoch(model, train_part, Eq7Loss(stats, config.lambda_q, config.lambda_qd), config, rng,
                             optimizer)
            scheduler.step()
            if not math.isfinite(loss):
                raise FloatingPointError(f"train {kind}: the loss became {loss} in epoch {epoch + 1}")
            history.append({"epoch": epoch + 1, "loss": loss, "lr": scheduler.get_last_lr()[0],
                            "seconds": time.perf_counter() - started})
            bar.set_postfix(loss=f"{loss:.4g}")
            if (epoch + 1) % config.checkpoint_every == 0 and epoch + 1 < config.epochs:
                checkpoint(epoch + 1, final=False)
        model.eval()
        return checkpoint(config.epochs, final=True)


def _identify_analytic(train_part: Dataset, stats: DatasetStats, robot_config, out: Path, provenance: dict,
                       config: TrainConfig, command: str | None) -> dict:
    """The analytic baseline: identified by least squares (deterministic; the seed only draws the states of its
    positive-definiteness check), saved as a checkpoint like the trained models."""
    from training.dynamics.analytic import AnalyticConfig, identify_dataset

    model = identify_dataset(train_part, AnalyticConfig.from_robot_config(robot_config), seed=config.seed)
    extra = {"stats": stats.to_json(), "data": provenance,
             "train": {"config": dataclasses.asdict(config), "epoch": 0, "history": [], "command": command},
             "identification": model.identification.as_dict()}
    save_checkpoint(out, model, **extra)
    return extra


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bruce-train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="dataset .npz (bruce-collect, bruce-import-data), or another "
                        "simulator's .csv/.npz trajectory, converted in memory (docs/byo_data.md)")
    parser.add_argument("--model", required=True, choices=("pinn", "lstm", "olnn", "analytic"),
                        help="analytic: identified by least squares, not trained (epochs do not apply)")
    parser.add_argument("--preset", choices=sorted(TRAIN_PRESETS), default="paper")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--epochs", type=int, help="override the preset's epochs")
    parser.add_argument("--config", help="robot config (default configs/robots/bruce.yaml)")
    parser.add_argument("--out", required=True, help="checkpoint to write (.pt)")
    parser.add_argument("--resume", action="store_true", help="continue the interrupted run in --out")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--resample", action="store_true",
                        help="an external trajectory at another rate: resample it to rates.loop_hz")
    parser.add_argument("--ignore-extra", action="store_true",
                        help="an external trajectory: drop its joints that the config lacks")
    args = parser.parse_args(argv)
    settings = {**TRAIN_PRESETS[args.preset], "seed": args.seed}
    if args.epochs is not None:
        settings["epochs"] = args.epochs
    try:
        result = train(args.data, args.model, args.out, model_config=MODEL_PRESETS[args.preset][args.model],
                       train_config=TrainConfig(**settings), robot_config=load_config(args.config) if args.config
                       else None, resume=args.resume, progress=not args.no_progress, resample=args.resample,
                       ignore_extra=args.ignore_extra,
                       command=shlex.join(["bruce-train", *(sys.argv[1:] if argv is None else argv)]))
    except (DatasetError, CheckpointError, ConfigError) as exc:
        print(f"bruce-train: error: {exc}", file=sys.stderr)
        return 2
    history = result["train"]["history"]
    if not history:
        print(f"bruce-train: analytic identified: {json.dumps(result['identification'])} -> {args.out}")
        return 0
    print(f"bruce-train: {args.model} ({args.preset}), {len(history)} epochs, final loss {history[-1]['loss']:.4g}, "
          f"{np.mean([h['seconds'] for h in history]):.2f} s/epoch -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
