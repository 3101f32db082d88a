"""`bruce-eval replay --log DIR`: a recorded run (`bruce-run --record DIR`, runtime/loop/recorder.py) against the
nominal simulator and the PINN: the paper's Fig. 6 comparison for that run (docs/replay.md).

The sub-command's parser and the command: it resolves the config and the models the log names, runs the analysis
(`training.evaluation.replay`) and writes DIR/replay.json (every figure), DIR/replay.md (the tables) and
DIR/fig6_replay.png (`training.evaluation.replay_report`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bruce_hw.config import ConfigError, RobotConfig
from runtime.loop.recorder import META_FILE, file_sha256
from runtime.robot_config import load_config
from training.evaluation.replay import (
    LogError,
    RunLog,
    closed_loop_figures,
    gap_monitor_figures,
    load_log,
    nominal_one_step,
    one_step_figures,
    pinn_one_step,
    simulate,
)
from training.evaluation.replay_report import markdown, plot
from training.evaluation.report import json_safe

SIMULATION_DIR = "simulation"
FIGURE = "fig6_replay.png"


def add_parser(commands) -> argparse.ArgumentParser:
    p = commands.add_parser("replay", help="a recorded run (bruce-run --record) against the simulator and the PINN",
                            description=__doc__.split("\n\n")[0])
    p.add_argument("--log", type=Path, required=True, help="the log directory (bruce-run --record DIR)")
    p.add_argument("--out", type=Path, default=None,
                   help="directory for replay.json, replay.md, fig6_replay.png and the simulation's log "
                        "(default: LOG_replay beside the log)")
    p.add_argument("--config", default=None,
                   help="robot config (default: the log's, with the log's --set overrides)")
    p.add_argument("--policy", type=Path, default=None, help="ONNX policy (default: the log's)")
    p.add_argument("--pinn", type=Path, default=None,
                   help="ONNX PINN for the one-step predictions (default: the log's, else pinn.model)")
    p.add_argument("--joint", default="0", help="the joint of the traces: a name or an index (default: 0)")
    p.add_argument("--window", default=None, metavar="START,END",
                   help="seconds of the traces (default: 10 to 11 s, or the last second of a shorter log)")
    return p


def _config_of(log: RunLog, args) -> tuple[RobotConfig, list[str]]:
    recorded = log.meta.get("config") or {}
    overrides = list(recorded.get("overrides") or [])
    path = args.config or recorded.get("path")
    if path is None:
        raise LogError(f"{log.path / META_FILE}: no config recorded: pass --config")
    notes = []
    spec = log.meta.get("policy_spec")  # given to the run by --policy-spec: the same spec for the simulation
    if spec and not any(o.startswith("policy.spec=") for o in overrides):
        if not Path(spec["path"]).is_file():
            raise LogError(f"{spec['path']}: the log's policy spec file not found")
        overrides.append(f"policy.spec={spec['path']}")
    if args.config is None and recorded.get("sha256") and Path(path).is_file() and \
            file_sha256(path) != recorded["sha256"]:
        notes.append(f"the config {path} changed since the recording (SHA-256 differs)")
    config = load_config(path, overrides)
    if tuple(config.joints) != log.joints:
        raise LogError(f"{log.path / META_FILE}: joints {', '.join(log.joints)} differ from the config's "
                       f"({config.path}: {', '.join(config.joints)})")
    if config.loop_hz != log.meta["loop_hz"]:
        raise LogError(f"{log.path / META_FILE}: loop_hz {log.meta['loop_hz']} differs from the config's "
                       f"{config.loop_hz} ({config.path})")
    return config, notes


def _model_path(given: Path | None, recorded: dict | None, fallback: Path | None, what: str,
                notes: list[str]) -> Path | None:
    """The model file to use: `given`, else the log's (which must still exist), else `fallback`."""
    if given is not None:
        if not given.is_file():
            raise LogError(f"{given}: {what} file not found")
        return given
    if recorded:
        path = Path(recorded["path"])
        if not path.is_file():
            raise LogError(f"{path}: the log's {what} file not found (pass --{what} PATH)")
        if recorded.get("sha256") and file_sha256(path) != recorded["sha256"]:
            notes.append(f"the {what} {path} changed since the recording (SHA-256 differs)")
        return path
    return fallback


def _window(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        start, end = (float(v) for v in text.split(","))
    except ValueError:
        raise LogError(f"--window: expected START,END in seconds, got {text!r}") from None
    if not end > start:
        raise LogError(f"--window: END must exceed START, got {text!r}")
    return start, end


def _joint(text: str, joints: tuple[str, ...]) -> int:
    if text in joints:
        return joints.index(text)
    if text.isdigit() and int(text) < len(joints):
        return int(text)
    raise LogError(f"--joint: {text!r} is neither a joint ({', '.join(joints)}) nor an index 0..{len(joints) - 1}")


def replay(args, argv: list[str]) -> dict:
    """The whole replay; writes the outputs and returns the report."""
    from training.dataset import config_hash

    log = load_log(args.log)
    config, notes = _config_of(log, args)
    joint, window = _joint(args.joint, log.joints), _window(args.window)
    meta = log.meta
    controller = meta.get("controller") or "policy"
    policy = _model_path(args.policy, meta.get("policy"), None, "policy", notes) if controller == "policy" else None
    pinn = _model_path(args.pinn, meta.get("pinn"), config.models.pinn, "pinn", notes)
    out = args.out or (log.path.parent / f"{log.path.name}_replay")
    out.mkdir(parents=True, exist_ok=True)
    if log.torn_bytes:
        notes.append(f"the rows file ends in a partial row ({log.torn_bytes} bytes, left out): the run was cut off")
    if meta.get("rows_dropped"):
        notes.append(f"{meta['rows_dropped']} rows were dropped while recording (the disk was behind)")
    simulation = simulate(log, config, out / SIMULATION_DIR, policy)
    predicted, one_step = {}, {}
    if pinn is None:
        one_step["pinn"] = {"unavailable": "no PINN: pass --pinn PATH or set pinn.model"}
    else:
        predicted["pinn"] = pinn_one_step(log, pinn)
        one_step["pinn"] = {"model": str(pinn), **one_step_figures(log, predicted["pinn"])}
    if log.has("base_pos"):
        predicted["nominal"] = nominal_one_step(log, config)
        one_step["nominal"] = one_step_figures(log, predicted["nominal"])
    else:
        one_step["nominal"] = {"unavailable": "the log has no base state (a robot measures none), which the nominal "
                                              "model needs; the closed loop and the PINN compare instead"}
    report = {
        "meta": {"command": "bruce-eval " + " ".join(argv), "log_path": str(log.path),
                 "log": {key: meta.get(key) for key in ("backend", "controller", "policy", "transfer", "pinn",
                                                        "estimator", "gap", "commands", "started_utc",
                                                        "rows_written", "rows_dropped", "recording_stopped",
                                                        "ended", "config")},
                 "config": str(config.path), "config_hash": config_hash(config), "pinn": str(pinn) if pinn else None,
                 "policy": str(policy) if policy else None, "simulation_log": str(out / SIMULATION_DIR),
                 "simulation_start": "the log's initial_q" if meta.get("initial_q") is not None
                 else "the log's first joint angles",
                 "joint": log.joints[joint], "window_s": list(window) if window else None, "notes": notes},
        "closed_loop": closed_loop_figures(log, simulation),
        "one_step": one_step,
        "gap_monitor": gap_monitor_figures(log),
    }
    (out / "replay.json").write_text(json.dumps(json_safe(report), indent=2) + "\n")
    (out / "replay.md").write_text(markdown(report))
    try:
        plot(out / FIGURE, log, simulation, predicted, report, joint, window)
        report["figure"] = str(out / FIGURE)
    except ModuleNotFoundError as exc:  # matplotlib comes with the `train` extra; the numbers do not need it
        report["figure"] = f"no figure ({exc.name} is not installed: pip install -e '.[train]')"
    report["out"] = str(out)
    return report


def run_replay(args, argv: list[str]) -> int:
    from runtime.control.inference import ModelError

    try:
        report = replay(args, argv)
    except (LogError, ConfigError, ModelError) as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 2
    print((Path(report["out"]) / "replay.md").read_text())
    print(f"bruce-eval: wrote {report['out']}/replay.json, replay.md, {report['figure']}")
    return 0
