"""Cost per call of the two walking controllers, measured in one run on the same states: the model-based teacher
(`runtime.walking.teacher.WalkingTeacher`: kinematics, DCM footstep, IK, feed-forward) and the distilled ONNX
policy (`runtime.control.policy.PolicyController`: observation + onnxruntime), each called as the 1 kHz loop calls its
nominal controller at 100 Hz.

States come from a teacher walk in the mock at 0.4 m/s; each controller is then called on them in interleaved
blocks (one pinned core, the garbage collector off), so both see the same machine load.

    python bench/bench_walking_controllers.py [--policy PATH] [--seconds 6] [--blocks 5]
"""

from __future__ import annotations

import argparse
import gc
import os
import time
from pathlib import Path

import numpy as np

from bruce_hw.config import load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import CommandSchedule
from runtime.control.inference import OnnxPolicy
from runtime.control.policy import PolicyController
from runtime.loop.run import run_session
from runtime.observation.builder import ObservationBuilder
from runtime.walking.teacher import WalkingTeacher


class Recorder:
    """A teacher that keeps every (state, base, command) it is called with."""

    def __init__(self, config):
        self.teacher = WalkingTeacher(config)
        self.calls = []

    def reset(self, q):
        self.teacher.reset(q)

    def __call__(self, state, base, command):
        self.calls.append((state, base, np.array(command)))
        return self.teacher(state, base, command)


def time_calls(controller, calls) -> np.ndarray:
    controller.reset(calls[0][0].joints.q)
    out = np.empty(len(calls))
    clock = time.perf_counter_ns
    for i, (state, base, command) in enumerate(calls):
        t0 = clock()
        controller(state, base, command)
        out[i] = clock() - t0
    return out / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=Path, default=None, help="ONNX policy (default: the config's policy.model)")
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--blocks", type=int, default=5)
    args = parser.parse_args()
    config = load_config()
    policy_path = args.policy or config.models.policy
    if policy_path is None:
        raise SystemExit("bench: no policy given and policy.model is null in the config")
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
    recorder = Recorder(config)
    backend = MujocoBackend(config)
    run_session(backend, config, duration=args.seconds, realtime=False, controller=recorder,
                estimator="truth", commands=CommandSchedule.constant(0.4, 0.0, 0.0))
    calls = recorder.calls
    teacher = WalkingTeacher(config)
    onnx = OnnxPolicy(policy_path, ObservationBuilder(config).size, config.n_joints)
    onnx.warmup()
    student = PolicyController(config, onnx)
    samples = {"teacher": [], "onnx policy": []}
    gc.collect()
    gc.disable()
    try:
        for _ in range(args.blocks):
            samples["teacher"].append(time_calls(teacher, calls))
            samples["onnx policy"].append(time_calls(student, calls))
    finally:
        gc.enable()
    print(f"walking controllers, {len(calls)} calls x {args.blocks} blocks on the states of a {args.seconds:g} s "
          f"teacher walk at 0.4 m/s (policy {policy_path}):")
    p50 = {}
    for name, blocks in samples.items():
        us = np.concatenate(blocks)
        p50[name] = float(np.percentile(us, 50))
        print(f"  {name:12s} per call: p50 {p50[name]:7.1f} us  p99 {np.percentile(us, 99):7.1f} us  "
              f"max {us.max():8.1f} us")
    print(f"  teacher / onnx policy (p50): {p50['teacher'] / p50['onnx policy']:.1f}x")


if __name__ == "__main__":
    main()
