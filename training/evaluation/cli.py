"""`bruce-eval`: evaluate learned dynamics models (`dynamics`, `dynamics_eval.py`), rehearse their sim-to-real
transfer (`transfer`, `transfer_eval.py`), run a walking controller on the command grid (`walking`,
`walking_eval.py`), set walking policies side by side under reality gaps (`policies`, `policy_table.py`) and
replay a recorded run against the simulator and the PINN (`replay`, `replay.py`).

The parser lives here, apart from both, so that `bruce-eval transfer` (onnxruntime and MuJoCo only) runs on the base
install: torch is imported only by the `dynamics` command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from training.evaluation import policy_table, replay, transfer_eval, walking_eval

DYNAMICS_HELP = "Held-out NMSE (one-step and open-loop K-step) and per-step compute of dynamics models."


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bruce-eval", description="Evaluate learned dynamics models "
                                     "(dynamics), rehearse their sim-to-real transfer (transfer), walk the "
                                     "command grid (walking).")
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("dynamics", help="held-out NMSE and per-step compute of dynamics models",
                            description=DYNAMICS_HELP)
    p.add_argument("--data", type=Path, required=True, help="dataset .npz (bruce-collect)")
    p.add_argument("--model", action="append", required=True, metavar="NAME=CKPT[,CKPT...]",
                   help="a model name and its checkpoints (several: mean ± std); repeatable")
    p.add_argument("--out", type=Path, required=True, help="directory for the JSON, Markdown and PNG outputs")
    p.add_argument("--k", default="10,100,1000", help="open-loop horizons (default: %(default)s)")
    p.add_argument("--starts", type=int, default=100, help="open-loop start points (default: %(default)s)")
    p.add_argument("--start-seed", type=int, default=None,
                   help="draw the start points at random with this seed (default: evenly spaced)")
    p.add_argument("--warmup", type=int, default=200, help="teacher-forced warm-up steps W (default: %(default)s)")
    p.add_argument("--chunk", type=int, default=1000,
                   help="one-step: transitions per teacher-forced chunk (default: %(default)s)")
    p.add_argument("--onnx", action="append", default=[], metavar="NAME=FILE",
                   help="the ONNX export of a model's first checkpoint, for the onnxruntime timing and parity "
                        "(default: exported by the kind's exporter)")
    p.add_argument("--no-onnx", action="store_true", help="skip the onnxruntime timing")
    p.add_argument("--timing-calls", type=int, default=2000,
                   help="timed calls per contender, 0 to skip timing (default: %(default)s)")
    p.add_argument("--train-fraction", type=float, default=0.8, help="the split (default: %(default)s)")
    p.add_argument("--config", default=None, help="robot config the data must match (default: BRUCE's)")
    transfer_eval.add_parser(commands)
    walking_eval.add_parser(commands)
    policy_table.add_parser(commands)
    replay.add_parser(commands)
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
        return replay.run_replay(args, argv)
    from training.evaluation.dynamics_eval import main_dynamics  # torch

    return main_dynamics(args, argv)


if __name__ == "__main__":
    raise SystemExit(main())
