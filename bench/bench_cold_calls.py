"""What the tick's costliest calls cost on warm caches and after time has passed: the machine's share of the tick's
CPU time, apart from the loop's own work.

The policy's tick (every 10th) is the paced loop's p99 (docs/results/timing.md, "The loop's own cost on the hw
path"): its observation and network cost several times on the tick what they cost called back to back. This
bench calls each of them on one thread, pinned to one CPU, with something between two calls:

- `back to back`: nothing (warm caches: the calls' own work);
- `sleep 0.9 ms`, `sleep 9 ms`: the thread sleeps, as the loop between two ticks and between two policy ticks;
- `spin 9 ms`: the thread keeps its CPU, busy on nothing that touches memory; where this costs as much as the
  9-ms sleep, what cools the caches is time passing, not the thread's idling: the CPU's caches shared with work
  the guest does not see (a hypervisor's other guests on the same core or its SMT sibling);
- `ticks 9 x`: nine ticks' worth of the control thread's other work (the estimator, Eq. 8) back to back, no
  time between (the loop's own eviction).

CPU time a call is the thread's own clock (`time.thread_time_ns`), which a hypervisor's steal does not advance.

    python bench/bench_cold_calls.py [--calls 200] [--cpu 1] [--set policy.model=policies/bruce_walk_rl.onnx]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from bruce_hw import load_config, make_backend
from bruce_hw.types import JointCommand
from runtime.control.controllers import build_controller
from runtime.control.mixing import eq8_torque
from runtime.estimation.kinematic import KinematicEstimator

BETWEEN = ("back to back", "sleep 0.9 ms", "sleep 9 ms", "spin 9 ms", "ticks 9 x")


def spin(seconds: float) -> None:
    until = time.perf_counter() + seconds
    while time.perf_counter() < until:
        pass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=200, help="calls of each function after each kind of pause")
    parser.add_argument("--cpu", type=int, default=None, help="pin the thread to this CPU")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    config = load_config(overrides=args.overrides)
    backend = make_backend("mock", config)  # a standing robot's reading for the calls' inputs
    backend.configure()
    backend.activate()
    state = backend.read()
    controller, name = build_controller(config, None)
    estimator = KinematicEstimator(config)
    estimator.reset(state)
    estimator.update(state)
    base = estimator.estimate()
    command = np.array((0.4, 0.0, 0.0))
    controller(state, base, command)
    builder, network = controller.builder, controller.policy
    obs = controller.obs
    a = np.array(config.standing_pose, float)
    calls = {
        "policy network (OnnxPolicy)": lambda: network(obs),
        "observation (ObservationBuilder.build)": lambda: builder.build(command, state, base, a, a),
        "estimator (KinematicEstimator.update)": lambda: estimator.update(state),
    }

    def other_ticks() -> None:
        for _ in range(9):
            estimator.update(state)
            eq8_torque(a, state.joints.q, state.joints.qd, config.eq8)

    pause = {"back to back": lambda: None, "sleep 0.9 ms": lambda: time.sleep(0.0009),
             "sleep 9 ms": lambda: time.sleep(0.009), "spin 9 ms": lambda: spin(0.009), "ticks 9 x": other_ticks}
    clock = time.thread_time_ns
    print(f"{name}; CPU a call, p50 / p90 µs (the thread's clock), {args.calls} calls each"
          + (f", pinned to CPU {args.cpu}" if args.cpu is not None else ""))
    print(f"{'call':42s}" + "".join(f"{kind:>16s}" for kind in BETWEEN))
    for label, call in calls.items():
        for _ in range(50):
            call()
        row = []
        for kind in BETWEEN:
            wait, spent = pause[kind], []
            for _ in range(args.calls):
                wait()
                c0 = clock()
                call()
                spent.append((clock() - c0) / 1e3)
            row.append(f"{np.percentile(spent, 50):7.0f} / {np.percentile(spent, 90):4.0f}")
        print(f"{label:42s}" + "".join(f"{cell:>16s}" for cell in row))
    backend.write(JointCommand(tau_ff=np.zeros(len(config.joints))))
    backend.shutdown()


if __name__ == "__main__":
    main()
