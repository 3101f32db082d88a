"""`bruce-eval policies`: walking policies side by side under reality gaps.

    bruce-eval policies --policy distilled=configs/robots/policies/bruce_walk.onnx --policy rl=runs/rl/policy.onnx \\
        --gap default,harsh --out eval/policies [--executor ray --ray-address auto]

runs each policy's rehearsal with direct transfer (`bruce-eval transfer`'s runs, every policy's on one executor,
cached under OUT/runs so an interrupted table resumes), or reads rehearsals already run (`--run NAME=DIR`, a
`bruce-eval transfer --schemes direct --set policy.model=PATH --out DIR` output), and prints, per gap profile and
experiment, each policy's falls over the gap seeds and its velocity tracking error: |mean velocity − command| after
the first 2 s, the worst axis (m/s or rad/s), averaged over the seeds. With --policy, OUT/policies.md holds it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from training.executor import ExecutorError, add_executor_arguments, make_executor

EXPERIMENTS = ("tracking", "circle", "reverse", "turn")


def policy_rows(report: dict) -> dict[tuple[str, str], dict]:
    """(profile, experiment) -> {"falls", "seeds", "tracking_error"} of the direct-transfer runs of one report."""
    profiles = report.get("profiles") or {report["meta"]["gap_name"]: report}
    rows = {}
    for profile, body in profiles.items():
        for experiment in EXPERIMENTS:
            if experiment not in body:
                continue
            runs = body[experiment]["direct"]["per_seed"]
            errors = [max(run["velocity_error"]) for run in runs]
            rows[profile, experiment] = {"falls": sum(bool(run["fell"]) for run in runs), "seeds": len(runs),
                                         "tracking_error": float(np.mean(errors))}
    return rows


def table(runs: dict[str, dict]) -> str:
    names = list(runs)
    rows = {name: policy_rows(report) for name, report in runs.items()}
    keys = [k for k in rows[names[0]] if all(k in rows[n] for n in names)]
    lines = ["| profile | experiment | " + " | ".join(f"{n} falls | {n} tracking error" for n in names) + " |",
             "|---|---|" + "---|---|" * len(names)]
    for key in keys:
        cells = [f"{rows[n][key]['falls']}/{rows[n][key]['seeds']} | {rows[n][key]['tracking_error']:.3f}"
                 for n in names]
        lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
    totals = [f"{sum(rows[n][k]['falls'] for k in keys)}/{sum(rows[n][k]['seeds'] for k in keys)} | "
              f"{np.mean([rows[n][k]['tracking_error'] for k in keys]):.3f}" for n in names]
    lines.append("| all | all | " + " | ".join(totals) + " |")
    return "\n".join(lines)


def add_parser(commands: argparse._SubParsersAction) -> None:
    p = commands.add_parser("policies", help="walking policies side by side under reality gaps",
                            description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="append", default=[], metavar="NAME=DIR",
                   help="a policy's name and its `bruce-eval transfer` output directory; repeatable")
    p.add_argument("--policy", action="append", default=[], metavar="NAME=ONNX",
                   help="a policy's name and file, rehearsed here; repeatable (needs --out)")
    p.add_argument("--gap", default="default,harsh", help="profiles for --policy (default: %(default)s)")
    p.add_argument("--experiments", default=",".join(EXPERIMENTS), help="for --policy (default: %(default)s)")
    p.add_argument("--seeds", default="0,1,2", help="gap seeds for --policy (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=20.0, help="per run, for --policy (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="with --policy: the runs' cache and policies.md")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="parallel runs with --executor local (default: CPU count)")
    add_executor_arguments(p)


def rehearse(args: argparse.Namespace) -> dict[str, dict]:
    """Each --policy's direct-transfer rehearsal, all on one executor: name -> {"profiles": {profile: report}}."""
    from training.evaluation.transfer_eval import (
        TransferError,
        evaluate,
        execute,
        plan_suite,
        settings_from_args,
        shipped_files,
    )

    settings = {}
    for item in args.policy:
        name, sep, path = item.partition("=")
        if not sep or not name:
            raise TransferError(f"--policy {item!r}: expected NAME=ONNX")
        if not Path(path).is_file():
            raise TransferError(f"--policy {name}: {path}: policy file not found")
        if name in settings:
            raise TransferError(f"--policy {name}: given twice")
        transfer_args = argparse.Namespace(
            gap=args.gap, suite=None, seeds=args.seeds, seconds=args.seconds, controller="policy",
            estimator="kinematic", experiments=args.experiments, latencies_ms="", gain_scales="", sweep_seeds="",
            lookahead="off", schemes="direct", overrides=[f"policy.model={Path(path).resolve()}"], jobs=args.jobs,
            config=None)
        settings[name] = settings_from_args(transfer_args)
    specs = [spec for one in settings.values() for spec in plan_suite(one)]
    with make_executor(args, args.jobs, ship=shipped_files(specs)) as executor:
        results = execute(specs, args.out, executor)
    return {name: {"profiles": {p.gap_name: evaluate(p, results)[0] for p in one.per_profile()}}
            for name, one in settings.items()}


def run_policies(args: argparse.Namespace) -> int:
    from bruce_hw.config import ConfigError
    from bruce_hw.reality_gap import GapError
    from training.evaluation.transfer_eval import TransferError

    if bool(args.run) == bool(args.policy):
        print("bruce-eval: policies: give --run NAME=DIR (rehearsals already run) or --policy NAME=ONNX "
              "(rehearsed here), not both", file=sys.stderr)
        return 2
    if args.policy:
        if args.out is None:
            print("bruce-eval: policies --policy: --out DIR is needed (the runs' cache and policies.md)",
                  file=sys.stderr)
            return 2
        try:
            runs = rehearse(args)
        except (TransferError, GapError, ConfigError, ExecutorError) as exc:
            print(f"bruce-eval: {exc}", file=sys.stderr)
            return 2
        text = table(runs)
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "policies.md").write_text(text + "\n")
        print(text)
        return 0
    runs = {}
    for item in args.run:
        name, sep, directory = item.partition("=")
        path = Path(directory) / "transfer.json"
        if not sep or not name:
            print(f"bruce-eval: --run {item!r}: expected NAME=DIR", file=sys.stderr)
            return 2
        if not path.is_file():
            print(f"bruce-eval: {path}: not found (run bruce-eval transfer --out {directory} first)", file=sys.stderr)
            return 2
        runs[name] = json.loads(path.read_text())
    print(table(runs))
    return 0
