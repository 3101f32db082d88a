"""Tick cost of every transfer scheme next to Eq. 9's, measured in one run (issue #20).

The inputs are a real walk: 2 s of the committed policy at 0.4 m/s on the `default` gap under direct transfer
(`training.evaluation.transfer_runs.run_one`), replayed tick by tick. Each scheme is driven exactly as the loop
drives it (`predict(a, q, qd, tau*, command)`, then `torque(tau*, q, qd)`); the timed part is those two calls,
split into the model work (`predict`, the loop's `pinn` section) and the mixing (`torque`). The schemes run
interleaved in blocks of one replay each, the garbage collector off, so a slow moment of a shared machine falls on
all of them alike.
Schemes on the nominal MuJoCo model (perfect-model controls, mock only) get the standing robot's base state.

Goal (issue #20): the recommended scheme's model work p50 <= 2x Eq. 9's.

    python bench/bench_transfer_schemes.py [--blocks 5] [--schemes direct,eq9,shadow,observer]
"""

from __future__ import annotations

import argparse
import gc
import time

import numpy as np

from bruce_hw.config import load_config
from bruce_hw.reality_gap import load_gap
from bruce_hw.robot_model import BruceModel
from runtime.transfer.registry import scheme_entry, scheme_names
from runtime.transfer.schemes import build_scheme

RATIO_GOAL = 2.0
COMMAND = (0.4, 0.0, 0.0)


def recorded_walk(seconds: float):
    """(a, q, qd, tau*) per tick of a direct-transfer walk on the default gap; a from Eq. 8 inverted."""
    from training.evaluation.transfer_runs import RunSpec, run_one

    config = load_config()
    record = run_one(RunSpec(experiment="tracking", command=COMMAND, seconds=seconds, mode="direct",
                             gap=load_gap("default")))
    kp, kd = config.eq8.kp, config.eq8.kd
    a = record.q + (record.tau + kd * record.qd) / kp
    return config, a, record.q, record.qd, record.tau


def time_scheme(scheme, a, q, qd, tau_star, command) -> tuple[np.ndarray, np.ndarray]:
    """ns per tick of predict and of torque over one replay."""
    n = len(q)
    predict_ns, torque_ns = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    perf = time.perf_counter_ns
    scheme.reset()
    for i in range(n):
        t0 = perf()
        scheme.predict(a[i], q[i], qd[i], tau_star[i], command)
        t1 = perf()
        scheme.torque(tau_star[i], q[i], qd[i])
        t2 = perf()
        predict_ns[i], torque_ns[i] = t1 - t0, t2 - t1
    return predict_ns, torque_ns


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--blocks", type=int, default=5, help="replays per scheme, interleaved (default: %(default)s)")
    parser.add_argument("--seconds", type=float, default=2.0, help="length of the replayed walk (default: %(default)s)")
    parser.add_argument("--schemes", default=None,
                        help="comma-separated schemes, SCHEME@nominal for the perfect-model control (default: every "
                             "scheme on the PINN, then every model-based one on the nominal model)")
    args = parser.parse_args(argv)

    config, a, q, qd, tau_star = recorded_walk(args.seconds)
    robot = BruceModel(config)
    standing = robot.new_data()
    robot.place_standing(standing)

    def standing_truth():  # the standing robot's base state, for the schemes on the nominal model
        return robot.ground_truth(standing)

    command = np.array(COMMAND)
    names = scheme_names(aliases=False)  # `pinn` is eq9
    modes = args.schemes.split(",") if args.schemes else [*names, *(f"{s}@nominal" for s in names
                                                                     if scheme_entry(s).uses_reference)]
    schemes = {}
    for mode in modes:
        name, _, model = mode.partition("@")
        overrides = [f"transfer.reference_model={model}"] if model else []
        schemes[mode] = build_scheme(load_config(overrides=overrides), name, base_state=standing_truth)
    times = {mode: ([], []) for mode in schemes}
    gc.collect()
    gc.disable()
    try:
        for block in range(args.blocks):
            order = list(schemes)[block % len(schemes):] + list(schemes)[:block % len(schemes)]
            for mode in order:
                predict_ns, torque_ns = time_scheme(schemes[mode], a, q, qd, tau_star, command)
                times[mode][0].append(predict_ns)
                times[mode][1].append(torque_ns)
    finally:
        gc.enable()

    def p(values, pct):
        return float(np.percentile(np.concatenate(values), pct)) / 1e3

    eq9 = next((m for m in schemes if m in ("eq9", *scheme_entry("eq9").aliases)), None)
    eq9_p50 = p(times[eq9][0], 50) if eq9 else None
    print(f"transfer scheme tick cost, {len(q)} ticks x {args.blocks} blocks of a 0.4 m/s walk on the default gap "
          "(µs; model work = predict, the loop's pinn section; mixing = torque)")
    print(f"{'scheme':<20} {'model p50':>10} {'model p99':>10} {'mixing p50':>11} {'total p50':>10} {'x Eq. 9':>8}")
    for mode, (predict_ns, torque_ns) in times.items():
        total = [pn + tn for pn, tn in zip(predict_ns, torque_ns, strict=True)]
        model_p50 = p(predict_ns, 50)
        ratio = f"{model_p50 / eq9_p50:8.2f}" if eq9_p50 else f"{'-':>8}"
        print(f"{mode:<20} {model_p50:10.1f} {p(predict_ns, 99):10.1f} {p(torque_ns, 50):11.1f} "
              f"{p(total, 50):10.1f} {ratio}")
    if eq9_p50:
        print(f"goal: the recommended scheme's model work p50 <= {RATIO_GOAL:g} x Eq. 9's "
              f"({RATIO_GOAL * eq9_p50:.1f} µs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
