"""One PINN step (the paper's network, random weights): torch eager vs onnxruntime, and ORT's call paths.

All measured in one run, interleaved in blocks, on one pinned core with the garbage collector off, each
carrying the LSTM state (h', c') into the next call with fixed (q, qd, tau) inputs (fed-back states of an
untrained model drift without bound over 10^5 calls; the cost of a call does not depend on the values):
- torch eager: `PinnStep` under `torch.inference_mode()`, one intra-op thread, tensors fed back as tensors;
- torch eager, numpy in/out: the same, called the way the runtime calls a PINN (float64 numpy in and out);
- runtime: `runtime.control.inference.OnnxPinn.step` exactly as the 1 kHz loop calls it (float64 in and out,
  IOBinding ping-pong, non-finite check);
- ORT call paths on the same session: `run(names, feeds)`, `run_with_iobinding(io)`,
  `run_with_iobinding(io, RunOptions)` and `run_with_ort_values`, to show why the runtime uses the second
  (bound rows repeat one call on fixed buffers).
Goals (issue #3): the runtime's ORT step p99 <= 100 µs and >= 10x faster than torch eager, compared like for
like: each side on its own buffers, and each side called as the runtime calls a PINN (numpy float64 in and out).

    python bench/bench_pinn_step.py [--calls 20000] [--blocks 4]
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from runtime.control.inference import OnnxPinn, session_options
from training.dynamics.export import export_pinn_onnx
from training.dynamics.pinn import PinnStep, make_random_pinn
from training.evaluation.dynamics_timing import timed_calls

P99_GOAL_US = 100.0
SPEEDUP_GOAL = 10.0


def random_pinn(seed: int = 0) -> PinnStep:
    model = make_random_pinn(seed=seed)
    with torch.no_grad():  # a non-zero head, so the LSTM's output is used like in a trained model
        model.head.weight.normal_(std=1e-3)
    return model.eval()


class TorchLoop:
    def __init__(self, model: PinnStep):
        self.model = model
        n = model.n_joints
        self.q, self.qd = torch.zeros(1, n), torch.zeros(1, n)
        self.tau = torch.full((1, n), 0.1)
        self.h, self.c = model.initial_state()

    def __call__(self) -> None:
        with torch.inference_mode():
            self.q_next, self.qd_next, self.h, self.c = self.model(self.q, self.qd, self.tau, self.h, self.c)


class TorchNumpyLoop(TorchLoop):
    """Torch eager called the way the runtime calls a PINN: float64 numpy arrays in and out."""

    def __init__(self, model: PinnStep):
        super().__init__(model)
        n = model.n_joints
        self.q_np, self.qd_np, self.tau_np = np.zeros(n), np.zeros(n), np.full(n, 0.1)

    def __call__(self) -> None:
        with torch.inference_mode():
            q, qd = (torch.from_numpy(v).float().unsqueeze(0) for v in (self.q_np, self.qd_np))
            tau = torch.from_numpy(self.tau_np).float().unsqueeze(0)
            q_next, qd_next, self.h, self.c = self.model(q, qd, tau, self.h, self.c)
            self.q_next, self.qd_next = q_next[0].double().numpy(), qd_next[0].double().numpy()


class RuntimeLoop:
    def __init__(self, path: Path, n: int):
        self.pinn = OnnxPinn(path, n)
        self.pinn.warmup()
        self.q, self.qd, self.tau = np.zeros(n), np.zeros(n), np.full(n, 0.1)

    def __call__(self) -> None:
        self.q_next, self.qd_next = self.pinn.step(self.q, self.qd, self.tau)


class CallPath:
    """The same session and feedback, through one of onnxruntime's Python call paths."""

    def __init__(self, path: Path, n: int, layers: int, hidden: int, kind: str):
        self.session = ort.InferenceSession(str(path), session_options(), providers=["CPUExecutionProvider"])
        self.kind = kind
        state = (layers, 1, hidden)
        self.feeds = {"q": np.zeros((1, n), np.float32), "qd": np.zeros((1, n), np.float32),
                      "tau": np.full((1, n), 0.1, np.float32), "h": np.zeros(state, np.float32),
                      "c": np.zeros(state, np.float32)}
        self.outputs = ["q_next", "qd_next", "h_next", "c_next"]
        self.run_options = ort.RunOptions()
        if kind.startswith("iobinding"):
            self.io = self.session.io_binding()
            self.out = {name: np.zeros_like(self.feeds[src]) for name, src in
                        zip(self.outputs, ("q", "qd", "h", "c"), strict=True)}
            for name, array in self.feeds.items():
                self.io.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(array))
            for name, array in self.out.items():
                self.io.bind_ortvalue_output(name, ort.OrtValue.ortvalue_from_numpy(array))
        if kind == "ort_values":
            self.values = {k: ort.OrtValue.ortvalue_from_numpy(v) for k, v in self.feeds.items()}

    def __call__(self) -> None:
        if self.kind == "run":
            _, _, h, c = self.session.run(self.outputs, self.feeds)
            self.feeds.update(h=h, c=c)
        elif self.kind == "iobinding":
            self.session.run_with_iobinding(self.io)
        elif self.kind == "iobinding+RunOptions":
            self.session.run_with_iobinding(self.io, self.run_options)
        else:
            self.session.run_with_ort_values(self.outputs, self.values)


def summary(samples: np.ndarray) -> dict:
    return {"p50": float(np.median(samples)), "p99": float(np.percentile(samples, 99)), "max": float(samples.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=20_000, help="timed calls per block and contender")
    parser.add_argument("--blocks", type=int, default=4, help="interleaved blocks (host drift hits all alike)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cpu = sorted(os.sched_getaffinity(0))[-1]
    os.sched_setaffinity(0, {cpu})

    model = random_pinn()
    cfg = model.config
    with tempfile.TemporaryDirectory() as tmp:
        path = export_pinn_onnx(model, Path(tmp) / "pinn.onnx")
        contenders = {"torch eager": TorchLoop(model), "torch eager, numpy in/out": TorchNumpyLoop(model),
                      "runtime OnnxPinn.step": RuntimeLoop(path, cfg.n_joints)}
        for kind in ("run", "iobinding", "iobinding+RunOptions", "ort_values"):
            contenders[f"ort {kind}"] = CallPath(path, cfg.n_joints, cfg.lstm_layers, cfg.lstm_hidden, kind)
        samples: dict[str, list[np.ndarray]] = {name: [] for name in contenders}
        gc.collect()
        gc.disable()
        try:
            for name, step in contenders.items():  # warm-up
                timed_calls(step, 500 if name.startswith("torch") else 2000)
            for _ in range(args.blocks):
                for name, step in contenders.items():
                    calls = args.calls // 10 if name.startswith("torch") else args.calls  # torch is ~10x slower
                    samples[name].append(timed_calls(step, calls))
        finally:
            gc.enable()

    print(f"PINN step, paper size ({sum(p.numel() for p in model.parameters()):,} parameters, LSTM "
          f"{cfg.lstm_layers}x{cfg.lstm_hidden}), one core (CPU {cpu}), onnxruntime {ort.__version__}, "
          f"torch {torch.__version__}; {args.blocks} interleaved blocks")
    stats = {name: summary(np.concatenate(s)) for name, s in samples.items()}
    for name, s in stats.items():
        print(f"  {name:26s} p50 {s['p50']:8.1f} µs   p99 {s['p99']:8.1f} µs   max {s['max']:9.1f} µs")
    ours = stats["runtime OnnxPinn.step"]
    # Like for like: the module called on its own buffers (tensors fed back / bound OrtValues), and the module
    # called the way the runtime calls a PINN (float64 numpy in and out, with the conversions each side needs).
    pairs = (("torch eager", "ort iobinding", "the module on its own buffers"),
             ("torch eager, numpy in/out", "runtime OnnxPinn.step", "as the runtime calls it"))
    for torch_name, ort_name, what in pairs:
        speedup = stats[torch_name]["p50"] / stats[ort_name]["p50"]
        print(f"torch eager / onnxruntime, {what} ({torch_name} / {ort_name}, p50): {speedup:.1f}x "
              f"(goal >= {SPEEDUP_GOAL:.0f}x: {'met' if speedup >= SPEEDUP_GOAL else 'MISSED'})")
    mixed = stats["torch eager"]["p50"] / ours["p50"]
    print(f"  (mixed: torch eager on tensors / the runtime's numpy step: {mixed:.1f}x)")
    print(f"runtime ORT step p99: {ours['p99']:.1f} µs (goal <= {P99_GOAL_US:.0f} µs: "
          f"{'met' if ours['p99'] <= P99_GOAL_US else 'MISSED'})")
    base = stats["ort iobinding"]["p50"]
    for kind in ("run", "iobinding+RunOptions", "ort_values"):
        print(f"  ort {kind} costs {stats[f'ort {kind}']['p50'] - base:+.1f} µs over run_with_iobinding(io) (p50)")


if __name__ == "__main__":
    main()
