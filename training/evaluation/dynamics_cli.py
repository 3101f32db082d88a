"""`bruce-eval dynamics`: its sub-command's parser and the command, which evaluates every checkpoint
(`dynamics_eval`), times the first of each model (`dynamics_timing`) and writes `dynamics_eval.json`, `.md`, Fig. 4
and Fig. 5 as PNG (`report`). torch is imported only when the command runs, so that the parser builds on the base
install.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from training.evaluation.report import bar_k, json_safe, markdown_table, plot_fig4, plot_fig5

DYNAMICS_HELP = "Held-out NMSE (one-step and open-loop K-step) and per-step compute of dynamics models."
PROVENANCE = ("format_version", "config_hash", "seed", "seconds", "created")  # dataset metadata copied to the JSON


def add_parser(commands) -> argparse.ArgumentParser:
    p = commands.add_parser("dynamics", help="held-out NMSE and per-step compute of dynamics models",
                            description=DYNAMICS_HELP)
    p.add_argument("--data", type=Path, required=True, help="dataset .npz (bruce-collect)")
    p.add_argument("--model", action="append", required=True, metavar="NAME=CKPT[,CKPT...]",
                   help="a model name and its checkpoints (several: mean ± std); repeatable")
    p.add_argument("--out", type=Path, required=True, help="directory for the JSON, Markdown and PNG outputs")
    p.add_argument("--k", default="10,100,1000", help="open-loop horizons (default: %(default)s)")
    p.add_argument("--starts", type=int, default=100, help="open-loop start points (default: %(default)s)")
    p.add_argument("--start-seed", type=int, default=None,
                   help="draw the start points at random with this seed (default: evenly spaced)")
    p.add_argument("--warmup", type=int, default=200, help="teacher-forced warm-up steps W (default: %(default)s)")
    p.add_argument("--chunk", type=int, default=1000,
                   help="one-step: transitions per teacher-forced chunk (default: %(default)s)")
    p.add_argument("--onnx", action="append", default=[], metavar="NAME=FILE",
                   help="the ONNX export of a model's first checkpoint, for the onnxruntime timing and parity "
                        "(default: exported by the kind's exporter)")
    p.add_argument("--no-onnx", action="store_true", help="skip the onnxruntime timing")
    p.add_argument("--timing-calls", type=int, default=2000,
                   help="timed calls per contender, 0 to skip timing (default: %(default)s)")
    p.add_argument("--train-fraction", type=float, default=0.8, help="the split (default: %(default)s)")
    p.add_argument("--config", default=None, help="robot config the data must match (default: BRUCE's)")
    return p


def parse_named_paths(items: Sequence[str], option: str) -> dict[str, list[Path]]:
    from training.evaluation.dynamics_eval import EvalError

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
    from training.evaluation.dynamics_eval import EvalError

    try:
        ks = sorted({int(part) for part in text.split(",") if part.strip()})
    except ValueError:
        ks = []
    if not ks or ks[0] < 1:
        raise EvalError(f"--k: expected horizons >= 1 separated by commas, got {text!r}")
    return tuple(ks)


def run_dynamics(args: argparse.Namespace, argv: Sequence[str]) -> int:
    import torch

    from bruce_hw.config import DEFAULT_CONFIG
    from runtime.robot_config import load_config
    from training.episodes import run_indices
    from training.evaluation.dynamics_eval import (
        EvalError,
        LoadedModel,
        Protocol,
        check_model_fits,
        evaluate_model,
        load_checkpoint,
        load_eval_data,
        select_start_points,
        summarise,
    )
    from training.evaluation.dynamics_timing import export_for_timing, measure_compute

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
    """`bruce-eval dynamics` (loads torch)."""
    import torch

    from bruce_hw.config import ConfigError
    from training.dataset import DatasetError
    from training.dynamics.checkpoint import CheckpointError
    from training.evaluation.dynamics_eval import EvalError

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
