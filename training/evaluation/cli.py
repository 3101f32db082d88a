"""`bruce-eval`: evaluate learned dynamics models (`dynamics`, `dynamics_cli.py`), rehearse their sim-to-real
transfer (`transfer`, `transfer_eval.py`), run a walking controller on the command grid (`walking`,
`walking_eval.py`), set walking policies side by side under reality gaps (`policies`, `policy_table.py`) and
replay a recorded run against the simulator and the PINN (`replay`, `replay_cli.py`).

Each command adds its sub-parser (`add_parser`) and runs from its own module; this one only dispatches. None of them
imports torch at import time, so that `bruce-eval transfer` (onnxruntime and MuJoCo only) runs on the base install:
torch is imported only by the `dynamics` command.
"""

from __future__ import annotations

import argparse
import sys

from training.evaluation import dynamics_cli, policy_table, replay_cli, transfer_eval, walking_eval


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bruce-eval", description="Evaluate learned dynamics models "
                                     "(dynamics), rehearse their sim-to-real transfer (transfer), walk the "
                                     "command grid (walking).")
    commands = parser.add_subparsers(dest="command", required=True)
    dynamics_cli.add_parser(commands)
    transfer_eval.add_parser(commands)
    walking_eval.add_parser(commands)
    policy_table.add_parser(commands)
    replay_cli.add_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.command == "transfer":
        return transfer_eval.run_transfer(args, argv)
    if args.command == "walking":
        return walking_eval.run_walking(args)
    if args.command == "policies":
        return policy_table.run_policies(args)
    if args.command == "replay":
        return replay_cli.run_replay(args, argv)
    return dynamics_cli.main_dynamics(args, argv)  # imports torch


if __name__ == "__main__":
    raise SystemExit(main())
