"""`bruce-eval replay`'s analysis: a recorded run (`bruce-run --record DIR`, runtime/loop/recorder.py, read by
`load_log`) against the nominal simulator and the PINN, the numbers of the paper's Fig. 6 comparison for that run
(docs/replay.md). The command is `training.evaluation.replay_cli`, the figure and the tables `replay_report`.

1. Closed loop: the nominal mock (no gap, Eq. 8 alone) runs the log's controller on the log's own command sequence
   (`LoggedCommands`) for as many ticks, from the pose the run started from, through the runtime's loop, and is
   recorded in the same format (DIR/simulation). Per-joint RMSE of q and qd between the log and the simulation, tick
   by tick, and its split into a constant offset and the rest (bruce-eval transfer's metrics).
2. One step along the log: from each logged (q, qd) under the torque written, what the PINN (its LSTM state carried
   along the log, as on the robot) and the nominal MuJoCo model (`runtime.transfer.reference_models.NominalReference`,
   as the live gap monitor runs it; it needs the base state, which only a simulator's log has) predict for the next
   tick, against the next logged sample: per-joint RMSE.
3. The live gap monitor's residual, where the run had a reference model and logged it.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import GroundTruth
from runtime.loop.recorder import LOG_FORMAT, LOG_VERSION, META_FILE, RunRecorder, describe_run
from training.evaluation.transfer_metrics import joint_rmse, offset_and_shape

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
    from runtime.loop.run import run_session

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
    from runtime.control.inference import OnnxPinn

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


# -- for the report ------------------------------------------------------------------------------------------------
def forward_velocity(log: RunLog) -> np.ndarray | None:
    """The base's forward velocity in its heading frame (simulator logs: from the truth), every 10th row."""
    if not log.has("base_linvel"):
        return None
    from runtime.loop.observers import heading_velocity

    quat, linvel, angvel = log.column("base_quat"), log.column("base_linvel"), log.column("base_angvel")
    return np.array([heading_velocity(GroundTruth(0.0, np.zeros(3), quat[i], linvel[i], angvel[i]))[0]
                     for i in range(0, len(log), 10)])


def window_of(t: np.ndarray, window: tuple[float, float] | None) -> np.ndarray:
    """The rows shown in the traces: `window` (s), else 1 s from 10 s (the paper's), or the last second."""
    if window is None:
        start = min(WINDOW_START_S, max(0.0, float(t[-1]) - WINDOW_S))
        window = (start, start + WINDOW_S)
    return (t >= window[0]) & (t < window[1])
