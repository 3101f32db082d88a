"""`bruce-eval replay --log DIR`: a recorded run (`bruce-run --record DIR`, runtime/recorder.py) against the nominal
simulator and the PINN: the paper's Fig. 6 comparison for that run (docs/replay.md).

1. Closed loop: the nominal mock (no gap, Eq. 8 alone) runs the log's controller on the log's own command sequence
   (`LoggedCommands`) for as many ticks, from the pose the run started from, through the runtime's loop, and is
   recorded in the same format (DIR/simulation). Per-joint RMSE of q and qd between the log and the simulation, tick
   by tick, and its split into a constant offset and the rest (bruce-eval transfer's metrics).
2. One step along the log: from each logged (q, qd) under the torque written, what the PINN (its LSTM state carried
   along the log, as on the robot) and the nominal MuJoCo model (`runtime.transfer.reference_models.NominalReference`,
   as the live gap monitor runs it; it needs the base state, which only a simulator's log has) predict for the next
   tick, against the next logged sample: per-joint RMSE.
3. The live gap monitor's residual, where the run had a reference model and logged it.

Output: DIR/replay.json (every figure), DIR/replay.md (the tables), DIR/fig6_replay.png.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bruce_hw.config import ConfigError, RobotConfig
from bruce_hw.types import GroundTruth
from runtime.recorder import LOG_FORMAT, LOG_VERSION, META_FILE, RunRecorder, describe_run, file_sha256
from runtime.robot_config import load_config
from training.evaluation.report import json_safe
from training.evaluation.transfer_metrics import joint_rmse, offset_and_shape

SIMULATION_DIR = "simulation"
FIGURE = "fig6_replay.png"
WINDOW_S = 1.0          # the traces' window, as the paper's Fig. 6 (bruce-eval transfer shows 10 to 11 s)
WINDOW_START_S = 10.0


class LogError(ValueError):
    """A log that cannot be read or replayed; the message names the file and the problem."""


# -- the log -------------------------------------------------------------------------------------------------
@dataclass
class RunLog:
    path: Path
    meta: dict
    rows: np.ndarray        # [T, row_width] float64 (a read-only memory map of rows.f64)
    torn_bytes: int = 0     # a last, partial row (a crash in the middle of a write), left out

    def has(self, name: str) -> bool:
        return any(c["name"] == name for c in self.meta["columns"])

    def column(self, name: str) -> np.ndarray:
        """[T, width], or [T] for a one-wide column."""
        for c in self.meta["columns"]:
            if c["name"] == name:
                part = self.rows[:, c["offset"]:c["offset"] + c["width"]]
                return part[:, 0] if c["width"] == 1 else part
        raise LogError(f"{self.path}: the log has no column {name!r}")

    @property
    def joints(self) -> tuple[str, ...]:
        return tuple(self.meta["joints"])

    @property
    def t(self) -> np.ndarray:
        return self.column("t")

    @property
    def tick(self) -> np.ndarray:
        return self.column("tick").astype(np.int64)

    def __len__(self) -> int:
        return len(self.rows)


REQUIRED_META = ("format", "version", "rows_file", "dtype", "joints", "loop_hz", "columns", "row_width")


def load_log(path: str | Path) -> RunLog:
    """A log directory written by `bruce-run --record`; LogError naming the file for a missing or corrupt one.
    A trailing partial row (the process died while writing) is left out and counted in `torn_bytes`."""
    path = Path(path)
    meta_path = path / META_FILE
    if not path.is_dir():
        raise LogError(f"{path}: log directory not found (bruce-run --record writes one)")
    if not meta_path.is_file():
        raise LogError(f"{meta_path}: not found: {path} is not a bruce-run log")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LogError(f"{meta_path}: not readable as JSON: {exc}") from None
    if not isinstance(meta, dict):
        raise LogError(f"{meta_path}: expected a JSON object, got {type(meta).__name__}")
    missing = [key for key in REQUIRED_META if key not in meta]
    if missing:
        raise LogError(f"{meta_path}: missing {', '.join(missing)}")
    if meta["format"] != LOG_FORMAT or meta["version"] != LOG_VERSION:
        raise LogError(f"{meta_path}: format {meta['format']!r} version {meta['version']!r}, expected "
                       f"{LOG_FORMAT!r} version {LOG_VERSION}")
    if meta["columns"] is None:
        ended = meta.get("ended") or {}
        raise LogError(f"{meta_path}: the run ended before its loop started, no rows "
                       f"({ended.get('error') or ended.get('stop_cause') or 'no cause recorded'})")
    width = meta["row_width"]
    if not isinstance(width, int) or width < 1 or sum(c["width"] for c in meta["columns"]) != width:
        raise LogError(f"{meta_path}: row_width {width!r} is not the sum of the columns' widths")
    rows_path = path / str(meta["rows_file"])
    if not rows_path.is_file():
        raise LogError(f"{rows_path}: not found")
    dtype = np.dtype(meta["dtype"])
    size = rows_path.stat().st_size
    count, torn = divmod(size, dtype.itemsize * width)
    if count == 0:
        raise LogError(f"{rows_path}: no complete row ({size} bytes, a row is {dtype.itemsize * width})")
    rows = np.memmap(rows_path, dtype=dtype, mode="r", shape=(count, width))
    log = RunLog(path=path, meta=meta, rows=rows, torn_bytes=torn)
    ticks = log.tick
    if np.any(np.diff(ticks) <= 0) or not np.all(np.isfinite(log.t)):
        raise LogError(f"{rows_path}: ticks not increasing or times not finite: not a {meta['row_width']}-wide "
                       "float64 row file")
    return log


class LoggedCommands:
    """A log's command sequence as a command schedule: `at(t)` is the command in force at the last logged tick
    read at or before t (to within half a tick), the first one before it."""

    def __init__(self, t: np.ndarray, command: np.ndarray, dt: float):
        self.t, self.command, self.half_tick = np.asarray(t), np.asarray(command), 0.5 * dt
        self.name = "the logged commands"
        self.duration = float(self.t[-1])

    def at(self, t: float) -> np.ndarray:
        i = int(np.searchsorted(self.t, t + self.half_tick, side="right")) - 1
        return self.command[max(i, 0)].copy()


# -- 1. closed loop --------------------------------------------------------------------------------------------
@dataclass
class Traces:
    """Two runs' joint traces on the ticks both reached (the form bruce-eval transfer's metrics take)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray


def aligned(robot: RunLog, simulation: RunLog) -> tuple[Traces, Traces]:
    """The robot's rows and the simulation's rows of the same ticks (a tick the robot's log dropped is left out)."""
    sim_row = np.full(int(max(robot.tick.max(), simulation.tick.max())) + 1, -1)
    sim_row[simulation.tick] = np.arange(len(simulation))
    rows = sim_row[robot.tick]
    both = rows >= 0
    r, s = np.flatnonzero(both), rows[both]
    t = robot.t[r]
    return (Traces(t, robot.column("q")[r], robot.column("qd")[r], robot.column("tau")[r]),
            Traces(t, simulation.column("q")[s], simulation.column("qd")[s], simulation.column("tau")[s]))


def simulate(log: RunLog, config: RobotConfig, out: Path, policy: Path | None) -> RunLog:
    """The nominal simulator, closed loop, on the log's commands and controller, recorded into `out`."""
    from bruce_hw.mock import MujocoBackend
    from runtime.run import run_session

    meta = log.meta
    controller = meta.get("controller") or "policy"
    initial_q = meta.get("initial_q")
    start = np.asarray(initial_q if initial_q is not None else log.column("q")[0], dtype=float)
    if start.shape != (config.n_joints,):
        raise LogError(f"{log.path / META_FILE}: initial_q has {start.size} values, the config {config.n_joints}")
    estimator = meta.get("estimator") or "truth"
    commands = LoggedCommands(log.t, log.column("command"), config.dt)
    ticks = int(log.tick[-1]) + 1
    if out.exists():  # an earlier replay's simulation: this replay's output replaces it
        shutil.rmtree(out)
    recorder = RunRecorder(out, config, describe_run(config, backend="mock", controller=controller, policy=policy,
                                                     transfer="direct", pinn=None, estimator=estimator,
                                                     overrides=list(meta.get("config", {}).get("overrides", [])),
                                                     commands=commands),
                           max_s=ticks / config.loop_hz + 1.0)
    try:
        summary = run_session(MujocoBackend(config, initial_q=start), config, duration=ticks / config.loop_hz,
                              realtime=False, transfer="direct", policy=policy,
                              controller_kind=controller,
                              estimator=estimator, commands=commands, observers=[recorder])
    finally:
        recorder.close()
    simulation = load_log(out)
    simulation.meta["fell"] = bool(summary.truth is not None and summary.truth.fell)
    return simulation


def closed_loop_figures(robot: RunLog, simulation: RunLog) -> dict:
    """Per-joint RMSE of q and qd between the log and the simulation over every tick both have, mean over joints
    as `joint_rmse` (bruce-eval transfer's figure), and the q error's offset / shape split."""
    a, b = aligned(robot, simulation)
    per_q, per_qd = joint_rmse(a, b, skip_s=-1.0), joint_rmse(a, b, skip_s=-1.0, what="qd")
    offset, shape = offset_and_shape(a, b, skip_s=-1.0)
    names = robot.joints
    return {"ticks": len(a.t), "joint_rmse": float(np.mean(per_q)), "joint_velocity_rmse": float(np.mean(per_qd)),
            "joint_rmse_per_joint": dict(zip(names, per_q.tolist(), strict=True)),
            "joint_velocity_rmse_per_joint": dict(zip(names, per_qd.tolist(), strict=True)),
            "offset_per_joint": dict(zip(names, offset.tolist(), strict=True)),
            "shape_per_joint": dict(zip(names, shape.tolist(), strict=True)),
            "simulation_fell": simulation.meta.get("fell")}


# -- 2. one step along the log ---------------------------------------------------------------------------------
def transitions(log: RunLog) -> np.ndarray:
    """Rows i whose next row is the next tick (a dropped row breaks the chain)."""
    return np.flatnonzero(np.diff(log.tick) == 1)


def pinn_one_step(log: RunLog, pinn_path: Path) -> np.ndarray:
    """[T, 2, n]: row i + 1's (q, qd) as the PINN predicts it from row i under the torque written (NaN where row
    i + 1 is not the next tick); the LSTM state is carried along consecutive ticks and reset at a break."""
    from runtime.inference import OnnxPinn

    q, qd, tau = log.column("q"), log.column("qd"), log.column("tau")
    pinn = OnnxPinn(pinn_path, q.shape[1])
    out = np.full((len(log), 2, q.shape[1]), np.nan)
    following = np.zeros(len(log), dtype=bool)
    following[transitions(log)] = True
    for i in range(len(log) - 1):
        if not following[i]:
            pinn.reset()
            continue
        out[i + 1, 0], out[i + 1, 1] = pinn.step(q[i], qd[i], tau[i])
    return out


def nominal_one_step(log: RunLog, config: RobotConfig) -> np.ndarray:
    """As `pinn_one_step`, for the nominal MuJoCo model set to the logged base state (simulator logs only)."""
    from runtime.transfer.reference_models import NominalReference

    q, qd, tau = log.column("q"), log.column("qd"), log.column("tau")
    base = [log.column(name) for name in ("base_pos", "base_quat", "base_linvel", "base_angvel")]
    row = [0]

    def base_state() -> GroundTruth:
        i = row[0]
        return GroundTruth(sim_time=float(log.t[i]), base_pos=base[0][i], base_quat=base[1][i],
                           base_linvel=base[2][i], base_angvel=base[3][i])

    reference = NominalReference(config, base_state)
    out = np.full((len(log), 2, q.shape[1]), np.nan)
    for i in transitions(log):
        row[0] = i
        out[i + 1, 0], out[i + 1, 1] = reference.step(np.array(q[i]), np.array(qd[i]), tau[i])
    return out


def one_step_figures(log: RunLog, predicted: np.ndarray) -> dict:
    """Per-joint RMSE of the predictions against the logged next samples."""
    valid = np.all(np.isfinite(predicted[:, 0]), axis=1)
    names = log.joints
    if not valid.any():
        return {"transitions": 0}
    error_q = predicted[valid, 0] - log.column("q")[valid]
    error_qd = predicted[valid, 1] - log.column("qd")[valid]
    rms_q, rms_qd = np.sqrt(np.mean(error_q ** 2, axis=0)), np.sqrt(np.mean(error_qd ** 2, axis=0))
    return {"transitions": int(valid.sum()), "rmse_q": float(np.mean(rms_q)), "rmse_qd": float(np.mean(rms_qd)),
            "rmse_q_per_joint": dict(zip(names, rms_q.tolist(), strict=True)),
            "rmse_qd_per_joint": dict(zip(names, rms_qd.tolist(), strict=True))}


# -- 3. the live gap monitor -----------------------------------------------------------------------------------
def gap_monitor_figures(log: RunLog) -> dict | None:
    """RMS of the residual the live gap monitor logged (None: the run had no reference model)."""
    if not log.has("gap_qd"):
        return None
    gap_q, gap_qd = log.column("gap_q"), log.column("gap_qd")
    scored = np.all(np.isfinite(gap_qd), axis=1)
    if not scored.any():
        return {"samples": 0}
    rms_q = np.sqrt(np.mean(gap_q[scored] ** 2, axis=0))
    rms_qd = np.sqrt(np.mean(gap_qd[scored] ** 2, axis=0))
    names = log.joints
    return {"samples": int(scored.sum()), "model": log.meta.get("reference_model"),
            "rms_q": float(np.mean(rms_q)), "rms_qd": float(np.mean(rms_qd)),
            "rms_q_per_joint": dict(zip(names, rms_q.tolist(), strict=True)),
            "rms_qd_per_joint": dict(zip(names, rms_qd.tolist(), strict=True))}


# -- the report ---------------------------------------------------------------------------------------------------
def forward_velocity(log: RunLog) -> np.ndarray | None:
    """The base's forward velocity in its heading frame (simulator logs: from the truth), every 10th row."""
    if not log.has("base_linvel"):
        return None
    from runtime.observers import heading_velocity

    quat, linvel, angvel = log.column("base_quat"), log.column("base_linvel"), log.column("base_angvel")
    return np.array([heading_velocity(GroundTruth(0.0, np.zeros(3), quat[i], linvel[i], angvel[i]))[0]
                     for i in range(0, len(log), 10)])


def window_of(t: np.ndarray, window: tuple[float, float] | None) -> np.ndarray:
    """The rows shown in the traces: `window` (s), else 1 s from 10 s (the paper's), or the last second."""
    if window is None:
        start = min(WINDOW_START_S, max(0.0, float(t[-1]) - WINDOW_S))
        window = (start, start + WINDOW_S)
    return (t >= window[0]) & (t < window[1])


def plot(path: Path, robot: RunLog, simulation: RunLog, predicted: dict[str, np.ndarray], report: dict,
         joint: int, window: tuple[float, float] | None) -> None:
    """Fig. 6 for a recorded run: joint `joint`'s angle, velocity and torque and its phase portrait, robot against
    the simulation (and the one-step predictions), the per-joint RMSE, the one-step velocity residual."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    name = robot.joints[joint]
    a, b = aligned(robot, simulation)
    shown = window_of(a.t, window)
    fig, axes = plt.subplots(2, 4, figsize=(20, 8))
    runs = (("robot (log)", "k", a), ("simulator (closed loop)", "tab:blue", b))
    colours = {"pinn": "tab:red", "nominal": "tab:green"}
    one_step_rows = window_of(robot.t, window)
    for label, colour, run in runs:
        kw = {"color": colour, "label": label, "lw": 0.9}
        axes[0, 0].plot(run.t[shown], run.q[shown, joint], **kw)
        axes[0, 1].plot(run.t[shown], run.qd[shown, joint], **kw)
        axes[0, 2].plot(run.t[shown], run.tau[shown, joint], **kw)
        axes[0, 3].plot(run.q[shown, joint], run.qd[shown, joint], **kw)
    for model, values in predicted.items():
        kw = {"color": colours[model], "lw": 0.7, "ls": "--", "label": f"{model}, one step along the log"}
        axes[0, 0].plot(robot.t[one_step_rows], values[one_step_rows, 0, joint], **kw)
        axes[0, 1].plot(robot.t[one_step_rows], values[one_step_rows, 1, joint], **kw)
    titles = (f"{name} angle (rad)", f"{name} velocity (rad/s)", f"{name} torque written (N m)",
              f"{name} phase portrait (rad, rad/s)")
    for ax, title in zip(axes[0], titles, strict=True):
        ax.set_title(title)
        ax.legend(fontsize=7)
    x = np.arange(len(robot.joints))
    closed = report["closed_loop"]
    axes[1, 0].bar(x, list(closed["joint_rmse_per_joint"].values()), color="tab:blue")
    axes[1, 0].set_title(f"joint RMSE, robot vs simulator (rad); mean {closed['joint_rmse']:.4g}")
    bars = {model: report["one_step"][model] for model in predicted if report["one_step"][model].get("transitions")}
    gap = report.get("gap_monitor")
    if gap and gap.get("samples"):
        bars["live gap monitor"] = {"rmse_qd_per_joint": gap["rms_qd_per_joint"]}
    width = 0.8 / max(len(bars), 1)
    for i, (label, entry) in enumerate(bars.items()):
        axes[1, 1].bar(x + (i - (len(bars) - 1) / 2) * width, list(entry["rmse_qd_per_joint"].values()), width,
                       color=colours.get(label, "tab:purple"), label=label)
    axes[1, 1].set_title("one-step velocity RMSE along the log (rad/s)")
    axes[1, 1].legend(fontsize=7)
    for ax in axes[1, :2]:
        ax.set_xticks(x, robot.joints, rotation=60, fontsize=7)
    for model, values in predicted.items():
        axes[1, 2].plot(robot.t[one_step_rows], robot.column("qd")[one_step_rows, joint]
                        - values[one_step_rows, 1, joint], color=colours[model], lw=0.7, label=model)
    if robot.has("gap_qd"):
        axes[1, 2].plot(robot.t[one_step_rows], robot.column("gap_qd")[one_step_rows, joint], color="tab:purple",
                        lw=0.7, label=f"live gap monitor ({robot.meta.get('reference_model')})")
    axes[1, 2].set_title(f"{name} one-step velocity residual, measured - predicted (rad/s)")
    axes[1, 2].legend(fontsize=7)
    speed_robot, speed_sim = forward_velocity(robot), forward_velocity(simulation)
    if speed_robot is not None and speed_sim is not None:
        axes[1, 3].plot(robot.t[::10], speed_robot, color="k", lw=0.9, label="robot (log, simulator truth)")
        axes[1, 3].plot(simulation.t[::10], speed_sim, color="tab:blue", lw=0.9, label="simulator (closed loop)")
        axes[1, 3].set_title("forward velocity (m/s)")
    else:
        axes[1, 3].set_title("velocity command vx (m/s) (no base velocity in a robot's log)")
    axes[1, 3].plot(robot.t, robot.column("command")[:, 0], color="0.5", lw=0.8, ls=":", label="command vx")
    axes[1, 3].legend(fontsize=7)
    fig.suptitle(f"{robot.path}: robot log against the nominal simulator and the PINN")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _fmt(value) -> str:
    return "—" if value is None else f"{value:.4g}"


def _ended(ended: dict | None) -> str:
    ended = ended or {}
    cause = ended.get("error") or ended.get("stop_cause") or ended.get("note") or "not recorded (no close)"
    return cause + (f" (exit code {ended['exit_code']})" if ended.get("exit_code") is not None else "")


def markdown(report: dict) -> str:
    meta, closed, one_step, gap = report["meta"], report["closed_loop"], report["one_step"], report["gap_monitor"]
    log = meta["log"]
    lines = [f"# Replay of {meta['log_path']}", "",
             f"{log['backend']} backend, {log['controller']}, transfer {log['transfer']}, "
             f"gap {log['gap']['profile'] if log['gap'] else 'none (no profile)'}; {closed['ticks']} ticks compared "
             f"({log['rows_written']} rows, {log['rows_dropped']} dropped); the run ended: {_ended(log['ended'])}",
             "",
             "| joint | RMSE q vs simulator (rad) | offset (rad) | RMSE qd vs simulator (rad/s) | "
             "one-step qd RMSE PINN (rad/s) | one-step qd RMSE nominal (rad/s) | live gap monitor qd RMS (rad/s) |",
             "|---|---|---|---|---|---|---|"]
    for name in closed["joint_rmse_per_joint"]:
        cells = [closed["joint_rmse_per_joint"][name], closed["offset_per_joint"][name],
                 closed["joint_velocity_rmse_per_joint"][name],
                 one_step["pinn"].get("rmse_qd_per_joint", {}).get(name),
                 one_step["nominal"].get("rmse_qd_per_joint", {}).get(name),
                 (gap or {}).get("rms_qd_per_joint", {}).get(name)]
        lines.append(f"| {name} | " + " | ".join(_fmt(c) for c in cells) + " |")
    lines.append(f"| **mean** | **{_fmt(closed['joint_rmse'])}** | | **{_fmt(closed['joint_velocity_rmse'])}** | "
                 f"{_fmt(one_step['pinn'].get('rmse_qd'))} | {_fmt(one_step['nominal'].get('rmse_qd'))} | "
                 f"{_fmt((gap or {}).get('rms_qd'))} |")
    notes = [f"- {key}: {value}" for key, value in one_step.items() if "unavailable" in value]
    notes += [f"- {note}" for note in meta["notes"]]
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


# -- the command ----------------------------------------------------------------------------------------------------
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
    from runtime.inference import ModelError

    try:
        report = replay(args, argv)
    except (LogError, ConfigError, ModelError) as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 2
    print((Path(report["out"]) / "replay.md").read_text())
    print(f"bruce-eval: wrote {report['out']}/replay.json, replay.md, {report['figure']}")
    return 0
