"""`bruce-run`: run BRUCE's controller on a backend (`mock` by default is headless and needs no robot).

The controller (--controller: the ONNX policy, the model-based walking teacher or the standing controller)
follows a velocity command: --cmd VX,VY,WZ holds one, --scenario PATH plays a scenario file of timed segments
(see configs/scenarios/); with neither it is asked to stand still. --estimator picks where the base state the
controller sees comes from. --gap makes the mock play "the real robot" (a reality-gap profile, configs/gaps/).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
from pathlib import Path

from runtime.loop.exit import NOTHING_ENABLED, ExitCode, StopFlag, StopRequested

# Everything else is imported inside the functions: `main` takes SIGINT/SIGTERM over first, so that a signal while
# numpy, MuJoCo or onnxruntime load ends the run with one line and exit code 0, never a traceback.


def positive_seconds(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a duration > 0 s, got {text}")
    return value


def seed(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text}")
    return value


def constant_command(text: str):
    """--cmd VX,VY,WZ: one velocity command, within COMMAND_LIMITS."""
    from runtime.control.commands import COMMAND_AXES, CommandSchedule

    try:
        values = [float(part) for part in text.split(",")]
    except ValueError:
        values = []
    if len(values) != len(COMMAND_AXES) or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected VX,VY,WZ (three numbers: m/s, m/s, rad/s), got {text!r}")
    try:
        return CommandSchedule.constant(*values)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def join_option_values(argv: list[str], options: tuple[str, ...] = ("--cmd",)) -> list[str]:
    """`--cmd -0.3,0,0` as `--cmd=-0.3,0,0`: argparse would take a value that starts with a minus for an option."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in options and i + 1 < len(argv) and re.match(r"-[\d.]", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def default_rerun_sink() -> str:
    """A viewer only where one can be shown: headless machines (robots, CI) log nothing by default."""
    return "spawn" if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") else "off"


def build_parser() -> argparse.ArgumentParser:
    from bruce_hw.backends import BACKENDS
    from bruce_hw.config import DEFAULT_CONFIG
    from runtime.control.commands import COMMAND_LIMITS, COMMAND_UNITS
    from runtime.control.controllers import CONTROLLERS
    from runtime.estimation.estimators import ESTIMATORS
    from runtime.telemetry import SINK_HELP
    from runtime.transfer.registry import scheme_help

    p = argparse.ArgumentParser(prog="bruce-run", description=__doc__, epilog=EXIT_CODES_HELP)
    p.add_argument("--backend", choices=BACKENDS, default="mock",
                   help="mock: MuJoCo simulation; echo: kinematic mirror; hw: the robot's buses")
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key path, e.g. buses.bear.port=/dev/ttyUSB3 "
                        "(repeatable)")
    p.add_argument("--duration", type=positive_seconds, default=None, metavar="S",
                   help="seconds of control to run (default: the scenario's length with --scenario, else until "
                        "Ctrl-C)")
    p.add_argument("--realtime", action="store_true",
                   help="pace the loop to the wall clock (default for the mock: as fast as possible, but paced "
                        "with --rerun web)")
    choices, schemes = scheme_help()
    p.add_argument("--transfer", choices=choices, default=None,
                   help=f"{schemes} (runtime/transfer/; the model: transfer.reference_model) (default: "
                        "transfer.scheme in the config, shipped direct)")
    p.add_argument("--controller", choices=CONTROLLERS, default="policy",
                   help="policy: the ONNX walking policy (--policy); teacher: the model-based walking controller; "
                        "standing: the standing controller (default: %(default)s)")
    p.add_argument("--policy", type=Path, default=None, metavar="PATH",
                   help="ONNX walking policy (obs -> action) for --controller policy; default: policy.model in "
                        "the config, else the standing controller")
    p.add_argument("--policy-spec", type=Path, default=None, metavar="SPEC",
                   help="the policy's observation/action spec: a YAML path or a shipped name (table1, legged_gym; "
                        "docs/byo_policy.md); default: policy.spec in the config, else the policy's sidecar's, else "
                        "table1")
    p.add_argument("--estimator", choices=ESTIMATORS, default=None,
                   help="the base state the controller sees: truth: the simulator's (mock only); kinematic: IMU + "
                        "leg kinematics + contacts (default: truth on the mock, kinematic otherwise)")
    limits = ", ".join(f"{axis} [{low:g}, {high:g}] {unit}" for (axis, (low, high)), unit
                       in zip(COMMAND_LIMITS.items(), COMMAND_UNITS, strict=True))
    commands = p.add_mutually_exclusive_group()
    commands.add_argument("--cmd", type=constant_command, default=None, metavar="VX,VY,WZ",
                          help=f"hold one velocity command (base heading frame; {limits}; the policy was "
                               "trained on vx [-0.5, 0.8], vy [-0.2, 0.2]), ramped up from 0 (default: stand still)")
    commands.add_argument("--scenario", type=Path, default=None, metavar="PATH",
                          help="play a scenario YAML of timed velocity commands, e.g. "
                               "configs/scenarios/walk_then_turn.yaml (the command is 0 after its end)")
    p.add_argument("--gap", default=None, metavar="PROFILE",
                   help="mock only: a reality-gap profile, so the mock plays the real robot: a name in configs/gaps/ "
                        "(none, mild, default, harsh) or a YAML path (default: none)")
    p.add_argument("--gap-seed", type=seed, default=None, metavar="N",
                   help="seed of the profile's sensor noise (default: the profile's `seed`)")
    p.add_argument("--pinn", type=Path, default=None, metavar="PATH",
                   help="ONNX PINN of the transfer schemes; default: pinn.model in the config")
    p.add_argument("--rerun", default=None, metavar="SINK",
                   help=SINK_HELP + " (default: spawn with a display, off when headless)")
    p.add_argument("--stats", type=Path, default=None, metavar="PATH",
                   help="write a JSON summary here on every exit path")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="log every tick (q, qd, tau, IMU, contacts, command, targets, ...) into a new directory, "
                        "for `bruce-eval replay --log DIR` (docs/replay.md)")
    p.add_argument("--record-max-s", type=positive_seconds, default=None, metavar="S",
                   help="stop recording after S s of ticks; the run goes on (default: 3600)")
    return p


EXIT_CODES_HELP = "exit codes: " + ", ".join(f"{int(c)} {c.name.lower().replace('_', ' ')}" for c in ExitCode)


def main(argv: list[str] | None = None) -> int:
    """bruce-run; the exit code is a runtime.loop.exit.ExitCode."""
    stop = StopFlag().install()
    try:
        return _main(argv, stop)
    except StopRequested as exc:
        print(f"bruce-run: {exc} {NOTHING_ENABLED}", file=sys.stderr)
        return ExitCode.OK
    finally:
        stop.restore()


def _main(argv: list[str] | None, stop: StopFlag) -> int:
    from dataclasses import replace

    from bruce_hw.backend import BackendError
    from bruce_hw.backends import make_backend
    from bruce_hw.config import ConfigError
    from bruce_hw.reality_gap import GapError, load_gap
    from runtime.control.commands import CommandSchedule
    from runtime.control.inference import ModelError
    from runtime.control.policy_spec import policy_spec_for, spec_file, trained_commands
    from runtime.loop.recorder import RecordError
    from runtime.loop.run import RunSummary, exit_code_of, run_session, stats_path_error, write_stats
    from runtime.robot_config import load_config
    from runtime.telemetry import TelemetryError, parse_sink
    from runtime.transfer.stage import settings_for

    parser = build_parser()
    args = parser.parse_args(join_option_values(sys.argv[1:] if argv is None else list(argv)))
    if args.policy is not None and args.controller != "policy":
        parser.error(f"--policy is for --controller policy, not {args.controller}")
    if args.policy_spec is not None and args.controller != "policy":
        parser.error(f"--policy-spec is for --controller policy, not {args.controller}")
    if args.record_max_s is not None and args.record is None:
        parser.error("--record-max-s is for --record DIR")
    if args.backend != "mock":
        for flag, value in (("--gap", args.gap), ("--gap-seed", args.gap_seed)):
            if value is not None:
                parser.error(f"{flag} is for --backend mock (a simulated robot), not {args.backend}")
    # Each line names its part itself ("safety: ...", "hw backend: ...", "gap: ..."): no logger name before it.
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        sink = parse_sink(args.rerun or default_rerun_sink())
    except ValueError as exc:
        parser.error(f"--rerun: {exc}")

    def refused(code: ExitCode, text: str, error: str | None) -> int:
        """The end of a run that never reached its session: one line, and the stats."""
        print(f"bruce-run: {text}", file=sys.stderr)
        summary = RunSummary(backend=args.backend, transfer=args.transfer or "direct", error=error)
        summary.end(code, text)
        write_stats(summary, args.stats)
        return code

    if args.stats is not None:
        problem = stats_path_error(args.stats)
        if problem is not None:
            args.stats = None  # where nothing can be written, nothing is
            return refused(ExitCode.BAD_INPUT, problem, None)
    try:
        stop.arm()  # a signal from here on (or one that came while the modules loaded) stops start-up at once
        config = load_config(args.config, args.overrides)
        transfer_settings = settings_for(config)
        if args.policy_spec is not None:
            config = replace(config, models=replace(config.models, policy_spec=spec_file(args.policy_spec)))
        policy_path = args.policy or config.models.policy
        if args.controller == "policy" and policy_path is not None:
            policy_spec_for(config, policy_path)  # a bad spec is one line here, before the session starts
        commands = CommandSchedule.from_yaml(args.scenario) if args.scenario is not None else args.cmd
        if args.controller == "policy" and policy_path is not None and commands is not None:
            # A policy walks what it was trained on; outside that nobody knows what it does (docs/usage.md).
            ranges = trained_commands(policy_path)
            outside = commands.outside(ranges) if ranges else None
            if outside is not None:
                given = f"--scenario {args.scenario}" if args.scenario is not None else "--cmd"
                raise ConfigError(f"{given}: {outside}, the range the policy {policy_path} was trained on (its "
                                  "sidecar's commands): refused, since what it does there was never tried")
        transfer = args.transfer or transfer_settings.scheme
        if args.pinn is not None and (transfer == "direct" or transfer_settings.reference_model != "pinn"):
            raise ConfigError(f"--pinn {args.pinn}: transfer {transfer} on reference model "
                              f"{transfer_settings.reference_model} uses no PINN (pick one with --transfer eq9, shadow "
                              "or observer)")
        options = {}
        if args.gap is not None or args.gap_seed is not None:
            gap = load_gap(args.gap or "none", config.joints)
            options["gap"] = gap if args.gap_seed is None else replace(gap, seed=args.gap_seed)
            print(f"bruce-run: reality gap {gap.source} (seed {options['gap'].seed})", flush=True)
        backend = make_backend(args.backend, config, **options)
    except (ConfigError, GapError, BackendError) as exc:
        # a missing device file is an input too: the port setting
        return refused(ExitCode.BAD_INPUT, str(exc), f"{type(exc).__name__}: {exc}")
    except StopRequested as exc:
        return refused(ExitCode.OK, f"{exc} {NOTHING_ENABLED}", None)
    # A robot is always paced; so is a run watched in a browser, which would otherwise be over before the page opens.
    realtime = args.realtime or args.backend == "hw" or sink.kind == "web"
    duration = args.duration
    if duration is None and args.scenario is not None:
        duration = commands.duration
    recorder = failure = None
    try:
        if args.record is not None:
            recorder = _recorder(args, config, transfer, options.get("gap"), commands)
        summary = run_session(backend, config, duration=duration, realtime=realtime, stats_path=args.stats,
                              transfer=transfer, policy=args.policy, pinn=args.pinn,
                              rerun=None if sink.kind == "off" else sink, controller_kind=args.controller,
                              estimator=args.estimator, commands=commands, stop=stop,
                              observers=[recorder] if recorder is not None else [])
    except RecordError as exc:
        return refused(ExitCode.BAD_INPUT, str(exc), f"{type(exc).__name__}: {exc}")
    except (BackendError, ModelError, TelemetryError, ValueError) as exc:  # the session's summary has named it
        failure = exc
        return exit_code_of(exc)
    finally:  # every exit path, Ctrl-C and safety trips included, closes the log
        if recorder is not None:
            recorder.close(failure or sys.exc_info()[1])  # the latter: an error that propagates
    return summary.exit_code


def _recorder(args, config, transfer: str, gap, commands):
    """`--record DIR`: the run's log (runtime.loop.recorder); RecordError for a path that cannot take one."""
    from runtime.loop.recorder import DEFAULT_MAX_S, RunRecorder, describe_run

    run = describe_run(config, backend=args.backend, controller=args.controller, policy=args.policy,
                       transfer=transfer, pinn=args.pinn, estimator=args.estimator, overrides=args.overrides,
                       gap=gap, commands=commands, scenario=args.scenario)
    return RunRecorder(args.record, config, run, max_s=args.record_max_s or DEFAULT_MAX_S)


if __name__ == "__main__":
    sys.exit(main())
