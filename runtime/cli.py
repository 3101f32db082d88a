"""`bruce-run`: run BRUCE's controller on a backend (`mock` by default is headless and needs no robot)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from bruce_hw.backend import BACKENDS, BackendError, make_backend
from bruce_hw.config import DEFAULT_CONFIG, ConfigError, load_config
from runtime.inference import ModelError
from runtime.mixing import TRANSFERS
from runtime.run import run_session


def positive_seconds(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a duration > 0 s, got {text}")
    return value


def default_rerun_sink() -> str:
    """A viewer only where one can be shown: headless machines (robots, CI) log nothing by default."""
    return "spawn" if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else "off"


def build_parser() -> argparse.ArgumentParser:
    from runtime.telemetry import SINK_HELP

    p = argparse.ArgumentParser(prog="bruce-run", description=__doc__)
    p.add_argument("--backend", choices=BACKENDS, default="mock",
                   help="mock: MuJoCo simulation; echo: kinematic mirror; hw: the robot's buses")
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key path, e.g. buses.bear.port=/dev/ttyUSB3 "
                        "(repeatable)")
    p.add_argument("--duration", type=positive_seconds, default=None, metavar="S",
                   help="seconds of control to run (default: until Ctrl-C)")
    p.add_argument("--realtime", action="store_true",
                   help="pace the loop to the wall clock (default for the mock: as fast as possible)")
    p.add_argument("--transfer", choices=TRANSFERS, default="direct",
                   help="direct: Eq. 8 torques alone; pinn: Eq. 9, tracking the PINN's prediction (default: direct)")
    p.add_argument("--policy", type=Path, default=None, metavar="PATH",
                   help="ONNX walking policy (obs -> action); default: policy.model in the config, else the "
                        "standing controller")
    p.add_argument("--pinn", type=Path, default=None, metavar="PATH",
                   help="ONNX PINN for --transfer pinn; default: pinn.model in the config")
    p.add_argument("--rerun", default=None, metavar="SINK",
                   help=SINK_HELP + " (default: spawn with a display, off when headless)")
    p.add_argument("--stats", type=Path, default=None, metavar="PATH",
                   help="write a JSON summary here on every exit path")
    return p


def main(argv: list[str] | None = None) -> int:
    from runtime.telemetry import TelemetryError, parse_sink

    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        sink = parse_sink(args.rerun or default_rerun_sink())
    except ValueError as exc:
        parser.error(f"--rerun: {exc}")
    try:
        config = load_config(args.config, args.overrides)
        backend = make_backend(args.backend, config)
    except (ConfigError, BackendError) as exc:
        print(f"bruce-run: {exc}", file=sys.stderr)
        return 2
    realtime = args.realtime or args.backend == "hw"  # a robot is always paced
    try:
        summary = run_session(backend, config, duration=args.duration, realtime=realtime, stats_path=args.stats,
                              transfer=args.transfer, policy=args.policy, pinn=args.pinn,
                              rerun=None if sink.kind == "off" else sink)
    except (BackendError, ModelError, TelemetryError) as exc:
        print(f"bruce-run: {exc}", file=sys.stderr)
        return 1
    return 0 if summary.error is None else 1


if __name__ == "__main__":
    sys.exit(main())
