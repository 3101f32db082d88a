"""The evaluation's report: strict JSON, the Markdown table, and the paper's Fig. 4 and Fig. 5 as PNG
(`bruce-eval dynamics`: training/evaluation/dynamics_eval.py and dynamics_timing.py compute what they show)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from training.evaluation.dynamics_eval import EvalData

BOUND_FACTOR = 10.0  # a rollout is bounded while it stays within this many times the data's range about its centre


def json_safe(value: Any) -> Any:
    """Non-finite floats -> None (strict JSON has no NaN/Infinity); numpy scalars and arrays -> Python."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _fmt(entry: dict) -> str:
    mean, std = entry["mean"], entry["std"]
    if mean is None or not math.isfinite(mean):
        return f"diverged ({entry['non_finite']}/{entry['n']})"
    return f"{mean:.3g}" + ("" if std is None else f" ± {std:.2g}")


def _fmt_time(stats: dict | None) -> str:
    return "—" if stats is None else f"{stats['p50_us']:.0f} / {stats['p99_us']:.0f}"


def markdown_table(report: dict) -> str:
    ks = report["protocol"]["k"]
    header = ["model", "n", "1-step q", "1-step q̇"] + [f"K={k} {x}" for k in ks for x in ("q", "q̇")]
    header += ["bounded", "torch µs p50/p99", "ORT µs p50/p99"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, entry in report["models"].items():
        summary = entry["summary"]
        row = [name, str(len(entry["checkpoints"])), _fmt(summary["one_step_q"]), _fmt(summary["one_step_qd"])]
        row += [_fmt(summary[f"k{k}_{x}"]) for k in ks for x in ("q", "qd")]
        row.append("yes" if entry["bounded"] else "**no**")
        compute = report["compute"].get(name, {})
        row += [_fmt_time(compute.get("torch")), _fmt_time(compute.get("ort"))]
        lines.append("| " + " | ".join(row) + " |")
    p = report["protocol"]
    notes = (f"NMSE per joint, averaged over {report['data']['n_joints']} joints, on the test split of "
             f"`{Path(report['data']['path']).name}` (sha256 {report['data']['sha256'][:12]}…, samples "
             f"[{report['data']['test_split']['start']}, {report['data']['samples']})). One-step: increments, "
             f"{p['one_step_transitions']} transitions; K-step: open loop from {p['starts']} start points, error at "
             f"every step 1..K; warm-up {p['warmup']} teacher-forced steps. mean ± std over checkpoints (ddof 1). "
             f"Bounded: the {max(ks)}-step rollouts stay finite and within {BOUND_FACTOR:g}x the data's range. "
             "Compute: batch 1, one thread, first checkpoint.")
    return "\n".join(lines) + "\n\n" + notes + "\n"


def bar_k(ks: Sequence[int]) -> int:
    return min(ks, key=lambda k: (abs(math.log(k / 100)), k))


def plot_fig4(path: Path, data: EvalData, start: int, traces: dict[str, dict], joint_name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(traces.values()))
    horizon = first["q"].shape[0]
    steps = np.arange(1, horizon + 1)
    t_ms = steps * data.dt * 1e3
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), sharex=True)
    for col, (key, unit) in enumerate((("q", "rad"), ("qd", "rad/s"))):
        truth = getattr(data, key)[start + steps, 0]
        axes[0, col].plot(t_ms, truth, color="black", lw=2, label="ground truth")
        # Traces are shown within 2 spans of the truth's range (a diverging model would flatten the rest); the
        # error panels below are not clipped.
        span = max(float(np.ptp(truth)), 1e-6)
        axes[0, col].set_ylim(truth.min() - 2 * span, truth.max() + 2 * span)
        for name, trace in traces.items():
            axes[0, col].plot(t_ms, trace[key][:, 0], lw=1.2, label=name)
            axes[1, col].plot(t_ms, trace[key][:, 0] - truth, lw=1.2, label=name)
        axes[0, col].set_ylabel(f"{'q' if key == 'q' else 'q̇'} [{unit}]")
        axes[1, col].set_ylabel(f"error [{unit}]")
        axes[1, col].set_xlabel("time after the start point [ms]")
        axes[1, col].axhline(0.0, color="black", lw=0.8)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"Joint 0 ({joint_name}): {horizon}-step open-loop rollout from test sample {start}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_fig5(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = bar_k(report["protocol"]["k"])
    names = list(report["models"])
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for ax, key, label in ((axes[0], "q", "position q"), (axes[1], "qd", "velocity q̇")):
        for i, name in enumerate(names):
            entry = report["models"][name]["summary"][f"k{k}_{key}"]
            mean, std = entry["mean"], entry["std"] or 0.0
            if mean is not None and math.isfinite(mean) and mean > 0:
                ax.bar(i, mean, yerr=std, capsize=4, color=f"C{i}")
            else:
                ax.text(i, 0.5, "diverged" if mean is None or not math.isfinite(mean) else "0",
                        transform=ax.get_xaxis_transform(), ha="center")
        ax.set_yscale("log")
        ax.set_xticks(x, names)
        ax.set_title(f"NMSE {label}, K = {k}")
    ax = axes[2]
    for offset, backend in ((-0.2, "torch"), (0.2, "ort")):
        p50 = [report["compute"].get(n, {}).get(backend, {}).get("p50_us", np.nan) for n in names]
        p99 = [report["compute"].get(n, {}).get(backend, {}).get("p99_us", np.nan) for n in names]
        err = [np.zeros(len(names)), np.nan_to_num(np.subtract(p99, p50))]
        ax.bar(x + offset, np.nan_to_num(p50), width=0.4, yerr=err, capsize=3,
               label=f"{'torch eager' if backend == 'torch' else 'onnxruntime'} (p50, whisker p99)")
    ax.axhline(1000.0, color="red", lw=1, label="1 kHz budget")
    ax.set_yscale("log")
    ax.set_xticks(x, names)
    ax.set_ylabel("µs per step, batch 1")
    ax.set_title("compute per step")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
