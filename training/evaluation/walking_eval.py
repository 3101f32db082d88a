"""`bruce-eval walking`: a walking controller on the command grid of the walking acceptance (nominal mock, Eq. 8).

Each grid point is a 20-s run from standing at a constant command, through the runtime's own loop with the
simulator's base state; a point passes when the robot does not fall and its mean velocity after the first 2 s is
within 0.1 (m/s, rad/s) of the command on every axis. DIR/walking.json holds every run's figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, load_config, resolve_config_path
from training.executor import ExecutorError, add_executor_arguments, job_files, make_executor

# vx in {-0.5, -0.3, 0, 0.4, 0.8} x yaw rate in {-0.5, 0, 0.5}, and vy +-0.2 standing: 17 points.
GRID = [(vx, 0.0, wz) for vx in (-0.5, -0.3, 0.0, 0.4, 0.8) for wz in (-0.5, 0.0, 0.5)] + \
    [(0.0, -0.2, 0.0), (0.0, 0.2, 0.0)]
TRACKING_LIMIT = 0.1  # m/s and rad/s, per axis


def walk_point(config_path: str, overrides: list[str], controller: str, command: tuple[float, float, float],
               seconds: float) -> dict:
    """One grid point: fell, the tracking error per axis, and whether it passes."""
    from bruce_hw.mock import MujocoBackend
    from runtime.control.commands import CommandSchedule
    from runtime.loop.run import run_session

    config = load_config(config_path, overrides)
    summary = run_session(MujocoBackend(config), config, duration=seconds, realtime=False,
                          controller_kind=controller, commands=CommandSchedule.constant(*command))
    truth = summary.truth
    error = {axis: float(value) for axis, value in truth.tracking_error.items()}
    return {"command": list(command), "fell": bool(truth.fell), "stop_cause": summary.stop_cause,
            "tracking_error": error,
            "passes": (not truth.fell and summary.stop_cause == "duration reached"
                       and max(error.values()) <= TRACKING_LIMIT)}


def add_parser(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("walking", help="a walking controller on the 17-point command grid",
                            description=__doc__)
    p.add_argument("--out", type=Path, required=True, help="directory for walking.json")
    p.add_argument("--policy", type=Path, default=None, help="ONNX policy (default: the config's policy.model)")
    p.add_argument("--controller", choices=("policy", "teacher"), default="policy")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--config", default=DEFAULT_CONFIG)
    p.add_argument("--jobs", type=int, default=2, help="parallel runs with --executor local (default: %(default)s)")
    add_executor_arguments(p)


def run_walking(args: argparse.Namespace) -> int:
    overrides = [f"policy.model={args.policy.resolve()}"] if args.policy else []
    if args.policy and not args.policy.is_file():
        print(f"bruce-eval: {args.policy}: policy file not found", file=sys.stderr)
        return 2
    from runtime.robot_config import load_config as load_checked  # the runtime's sections too (transfer)

    try:
        load_checked(args.config, overrides)
    except ConfigError as exc:
        print(f"bruce-eval: {exc}", file=sys.stderr)
        return 2
    config_path = resolve_config_path(args.config)
    try:
        with make_executor(args, args.jobs, ship=job_files(config_path, overrides)) as ex:
            config, shipped = ex.shipped_config(config_path, overrides)
            calls = [(config, shipped, args.controller, cmd, args.seconds) for cmd in GRID]
            points: list[dict] = [{}] * len(calls)
            for index, point in ex.map(walk_point, calls):
                points[index] = point
    except ExecutorError as exc:
        print(f"bruce-eval: {exc}", file=sys.stderr)
        return 2
    passed = sum(p["passes"] for p in points)
    falls = sum(p["fell"] for p in points)
    worst = max(max(p["tracking_error"].values()) for p in points)
    report = {"policy": str(args.policy) if args.policy else "config policy.model", "controller": args.controller,
              "seconds": args.seconds, "passed": passed, "points": len(points), "falls": falls,
              "worst_tracking_error": worst, "grid": points}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "walking.json").write_text(json.dumps(report, indent=2) + "\n")
    for p in points:
        e = p["tracking_error"]
        print(f"  cmd {p['command']}: {'FELL' if p['fell'] else 'walked'}, error vx {e['vx']:.3f} vy {e['vy']:.3f} "
              f"wz {e['wz']:.3f}{'' if p['passes'] else '  <- fails'}")
    print(f"bruce-eval: {passed}/{len(points)} grid points pass ({falls} falls, worst tracking error {worst:.3f}); "
          f"wrote {args.out / 'walking.json'}")
    return 0
