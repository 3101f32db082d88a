"""Cost of rerun telemetry on the 1 kHz control thread, and its effect on a real-time mock run, in one run.

1. Control-thread cost: a loop paced to 1 kHz by `runtime.loop.pacing.Pacer` whose body makes fresh copies of five
   10-joint arrays (as the loop passes them) and, with telemetry on, calls `Telemetry.append` every tick and
   `append_pose` every `Telemetry.pose_decimation` ticks (~30 Hz, as the loop does; sink save= to a temporary
   .rrd, the MuJoCo mock's model, so the 3-D geometry and poses are sent too). Telemetry off is the same body
   without the calls (`mock.body_poses()` is called in both). Reported per tick: the telemetry
   calls alone, the whole body, and how late the ticks start. The loop runs on the last allowed CPU, as
   `bruce-run --realtime` does; the telemetry process keeps off that CPU by itself.
2. Real-time mock session: `runtime.loop.run.run_session` on the mock backend, paced to the wall clock, as
   `bench/bench_realtime_mock.py` runs it, with telemetry off and then on (save= to a temporary .rrd): late
   ticks (> 250 µs behind the deadline), tick work p99 and the loop's own telemetry section.

Goals: <= 5 µs per tick in telemetry on the control thread; late ticks <= 0.1 % and tick work p99 <= 300 µs
with telemetry on (issue #3; compare with the off run, which telemetry cannot improve).

    python bench/bench_telemetry.py [--ticks 20000] [--seconds 20] [--transfer pinn|direct]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import io
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bruce_hw import load_config, make_backend
from runtime.loop.pacing import Pacer
from runtime.telemetry import Telemetry, parse_sink

GOAL_US = 5.0
LATE_SHARE_GOAL = 0.001
WORK_P99_GOAL_US = 300.0


def paced_loop(config, mock, telemetry: Telemetry | None, ticks: int, pose_every: int) -> dict[str, np.ndarray]:
    """Per-tick µs: the telemetry calls, the whole body, and how late the tick started."""
    joints = np.linspace(-0.5, 0.5, config.n_joints)
    calls, bodies, late = (np.empty(ticks) for _ in range(3))
    clock = time.perf_counter_ns
    pacer = Pacer(config.dt)
    gc.collect()
    gc.disable()  # as in the loop: its allocations are acyclic
    try:
        pacer.start()
        for tick in range(ticks):
            behind = pacer.wait()
            t0 = clock()
            q, qd, a, tau_star, tau = (joints.copy() for _ in range(5))
            poses = mock.body_poses() if tick % pose_every == 0 else None
            t1 = clock()
            if telemetry is not None:
                telemetry.append(tick, tick * config.dt, q, qd, None, None, a, tau_star, tau, 1000.0, 60.0, 0)
                if poses is not None:
                    telemetry.append_pose(tick, tick * config.dt, *poses)
            t2 = clock()
            calls[tick], bodies[tick], late[tick] = (t2 - t1) / 1e3, (t2 - t0) / 1e3, behind / 1e3
    finally:
        gc.enable()
    return {"calls": calls, "bodies": bodies, "late": late, "pose": np.arange(ticks) % pose_every == 0}


def row(label: str, values: np.ndarray) -> str:
    return (f"  {label:34s} median {np.median(values):6.2f}  mean {values.mean():6.2f}  "
            f"p99 {np.percentile(values, 99):7.2f}  max {values.max():8.1f}")


def control_thread_cost(config, ticks: int, pose_every: int | None) -> None:
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    loop_cpu = allowed[-1] if len(allowed) > 1 else None
    mock = make_backend("mock", config)
    mock.configure()
    if loop_cpu is not None:
        os.sched_setaffinity(0, {loop_cpu})  # this thread only; the telemetry process starts from the full set
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "bench.rrd"
            telemetry = Telemetry(config, parse_sink(f"save={path}"), model=mock.model, pose_decimation=pose_every)
            pose_every = telemetry.pose_decimation
            off = paced_loop(config, mock, None, ticks, pose_every)
            if loop_cpu is not None:
                os.sched_setaffinity(0, set(allowed))
            started = time.perf_counter()
            telemetry.start()
            start_s = time.perf_counter() - started
            if loop_cpu is not None:
                os.sched_setaffinity(0, {loop_cpu})
            on = paced_loop(config, mock, telemetry, ticks, pose_every)
            closing = time.perf_counter()
            telemetry.close()
            close_s = time.perf_counter() - closing
            size_mb = path.stat().st_size / 1e6
    finally:
        if loop_cpu is not None:
            os.sched_setaffinity(0, set(allowed))

    print(f"1. telemetry on the control thread: {ticks} ticks paced to 1 kHz per measurement, loop on CPU "
          f"{loop_cpu}, telemetry process on the other allowed CPUs")
    print("per tick, µs")
    print(row("off: timer pair only", off["calls"]))
    print(row(f"on: append (+ append_pose /{pose_every})", on["calls"]))
    print(row("on: ticks with append only", on["calls"][~on["pose"]]))
    print(row("on: ticks with append + append_pose", on["calls"][on["pose"]]))
    print(row("off: loop body (5 array copies)", off["bodies"]))
    print(row("on: loop body + telemetry", on["bodies"]))
    print(row("off: tick start, late by", off["late"]))
    print(row("on: tick start, late by", on["late"]))
    print(f"  on - off, telemetry calls: median {np.median(on['calls']) - np.median(off['calls']):.2f} µs, "
          f"p99 {np.percentile(on['calls'], 99) - np.percentile(off['calls'], 99):.2f} µs")
    print(f"  ticks starting > 250 µs late: off {int(np.sum(off['late'] > 250))}, on {int(np.sum(on['late'] > 250))}")
    print(f"  rows sent {telemetry.sent_rows}, dropped {telemetry.dropped}; poses sent {telemetry.sent_poses}, "
          f"dropped {telemetry.dropped_poses}; error {telemetry.error!r}")
    print(f"  start() {start_s * 1e3:.0f} ms, close() {close_s * 1e3:.0f} ms, .rrd {size_mb:.1f} MB")
    mean_cost, p99_cost = on["calls"].mean(), np.percentile(on["calls"], 99)
    print(f"goal <= {GOAL_US:.0f} µs per tick in telemetry on the control thread (mean / p99 of the calls): "
          f"{'met' if mean_cost <= GOAL_US else 'NOT met'} ({mean_cost:.2f} / {p99_cost:.2f} µs)")


def realtime_session(config, seconds: float, transfer: str, sink) -> tuple[dict, float]:
    from runtime.loop.run import run_session

    pinn = None
    with tempfile.TemporaryDirectory() as tmp:
        if transfer == "pinn":
            import torch

            from training.dynamics.export import export_pinn_onnx
            from training.dynamics.pinn import make_random_pinn

            model = make_random_pinn(seed=0)
            with torch.no_grad():
                model.head.weight.normal_(std=1e-4)  # non-zero, small: the closed loop still stands
            pinn = export_pinn_onnx(model, Path(tmp) / "pinn.onnx")
        if sink == "save":
            sink = parse_sink(f"save={Path(tmp) / 'session.rrd'}")
        started = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            summary = run_session(make_backend("mock", config), config, duration=seconds, realtime=True,
                                  transfer=transfer, pinn=pinn, rerun=sink)
        wall = time.perf_counter() - started
    return {**summary.to_json(), "dropped": summary.telemetry_dropped}, wall


def realtime_figures(config, seconds: float, transfer: str) -> None:
    results = {}
    for label, sink in (("off", None), ("on", "save")):
        results[label], wall = realtime_session(config, seconds, transfer, sink)
        results[label]["wall"] = wall
    print(f"2. real-time mock session, {seconds:g} s each, transfer {transfer}, telemetry off vs on (save=):")
    for label, stats in results.items():
        tel = stats["sections_us"].get("telemetry")
        tel_text = f", telemetry section p50/p99 {tel['p50']:.1f}/{tel['p99']:.1f} µs" if tel and label == "on" \
            else ""
        print(f"  {label:3s}: late ticks {stats['late_ticks']} of {stats['ticks']} = "
              f"{100 * stats['late_share']:.3f} %, skipped {stats['skipped_ticks']}; tick work p50 "
              f"{stats['work_us']['p50']:.0f} / p99 {stats['work_us']['p99']:.0f} / max "
              f"{stats['work_us']['max']:.0f} µs{tel_text}; worst overruns µs "
              f"{[round(v) for v in stats['worst_overruns_us'][:3]]}"
              + (f"; rows dropped {stats['dropped']}; session {stats['wall']:.1f} s wall" if label == "on" else ""))
    on = results["on"]
    share, p99 = on["late_share"], on["work_us"]["p99"]
    print(f"goal with telemetry on: late ticks <= {100 * LATE_SHARE_GOAL:.1f} %: "
          f"{'met' if share <= LATE_SHARE_GOAL else 'MISSED'} ({100 * share:.3f} %); tick work p99 <= "
          f"{WORK_P99_GOAL_US:.0f} µs: {'met' if p99 <= WORK_P99_GOAL_US else 'MISSED'} ({p99:.0f} µs; off: "
          f"{results['off']['work_us']['p99']:.0f} µs)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=20_000, help="ticks per measurement of part 1 (1 s per 1000)")
    parser.add_argument("--pose-every", type=int, default=None,
                        help="ticks between append_pose calls (default: Telemetry's pose_decimation, ~30 Hz)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each real-time session of part 2")
    parser.add_argument("--transfer", choices=("pinn", "direct"), default="pinn",
                        help="the sessions' transfer, as bench_realtime_mock.py (default pinn)")
    args = parser.parse_args()
    config = load_config()
    control_thread_cost(config, args.ticks, args.pose_every)
    if args.seconds > 0:
        realtime_figures(config, args.seconds, args.transfer)


if __name__ == "__main__":
    main()
