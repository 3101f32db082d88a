"""`bruce-eval policies`: walking policies side by side under reality gaps, from `bruce-eval transfer` outputs.

Each policy's rehearsal is run first with direct transfer, e.g.

    bruce-eval transfer --gap default,harsh --experiments tracking,circle,reverse,turn --seeds 0,1,2 \\
        --latencies-ms '' --gain-scales '' --schemes direct --set policy.model=PATH --out eval/NAME

then `bruce-eval policies --run distilled=eval/distilled --run rl=eval/rl` prints, per gap profile and experiment,
each policy's falls over the gap seeds and its velocity tracking error: |mean velocity − command| after the first
2 s, the worst axis (m/s or rad/s), averaged over the seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

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
    p.add_argument("--run", action="append", required=True, metavar="NAME=DIR",
                   help="a policy's name and its `bruce-eval transfer` output directory; repeatable")


def run_policies(args: argparse.Namespace) -> int:
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
