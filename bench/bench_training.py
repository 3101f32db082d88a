"""Paper-config training cost on this machine: seconds per epoch and the projected 1000-epoch total.

Times `training.dynamics.train.run_epoch` (the exact training step: TBPTT windows, Eq. 7, AdamW) with the paper's
model and training settings on 90 s of walking data (the paper's amount; collected here with the committed policy
unless --data is given), after one untimed warm-up epoch. Goal (issue #5): the full paper config (1000 epochs)
<= 30 min on 2 cores.

    python bench/bench_training.py [--data walk.npz] [--models pinn,lstm] [--epochs 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bruce_hw.config import load_config
from training.collect import CollectSettings, collect
from training.dataset import compute_stats, load_dataset, save_dataset, split_by_time
from training.dynamics.checkpoint import build_model
from training.dynamics.train import MODEL_PRESETS, Eq7Loss, TrainConfig, make_optimizer, run_epoch

TOTAL_GOAL_MIN = 30.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", help="dataset .npz (default: collect 90 s, seed 0)")
    parser.add_argument("--models", default="pinn,lstm", help="comma-separated kinds (pinn, lstm, olnn)")
    parser.add_argument("--epochs", type=int, default=3, help="timed epochs per model")
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads (the machine has 2 cores)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = load_config()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.data or save_dataset(Path(tmp) / "walk.npz", collect(config, CollectSettings(seconds=90.0,
                                                                                                  seed=0)))
        data = load_dataset(path, config)
    settings = TrainConfig()
    train_part, _ = split_by_time(data, settings.train_fraction)
    stats = compute_stats(train_part)
    print(f"training cost, paper settings (window {settings.window}, {settings.streams} streams, burn-in "
          f"{settings.burn_in}), {len(train_part)} training samples, torch {torch.__version__}, "
          f"{args.threads} thread(s)")
    for kind in args.models.split(","):
        torch.manual_seed(0)
        model = build_model(kind, MODEL_PRESETS["paper"][kind])
        model.fit_normalisation(stats)
        optimizer, _ = make_optimizer(model, settings)
        loss_fn = Eq7Loss(stats, settings.lambda_q, settings.lambda_qd)
        rng = np.random.default_rng(0)
        run_epoch(model, train_part, loss_fn, settings, rng, optimizer)  # warm-up
        seconds = []
        for _ in range(args.epochs):
            started = time.perf_counter()
            run_epoch(model, train_part, loss_fn, settings, rng, optimizer)
            seconds.append(time.perf_counter() - started)
        per_epoch = float(np.median(seconds))
        total_min = per_epoch * settings.epochs / 60
        verdict = "met" if total_min <= TOTAL_GOAL_MIN else "MISSED"
        print(f"  {kind:8s} {sum(p.numel() for p in model.parameters()):>8,} parameters: {per_epoch:6.2f} s/epoch "
              f"(min {min(seconds):.2f}, max {max(seconds):.2f}) -> {settings.epochs} epochs = {total_min:5.1f} min "
              f"(goal <= {TOTAL_GOAL_MIN:.0f} min: {verdict})")


if __name__ == "__main__":
    main()
