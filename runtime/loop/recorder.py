"""`bruce-run --record DIR`: the run's own log, one row per tick at the loop rate, for replaying the run against the
simulator and the PINN (`bruce-eval replay`; the format, column by column: docs/replay.md).

A log is a directory: `meta.json` (the format, every column with its unit and width, the joints in config order,
the config, models, backend, transfer scheme, gap profile and command source of the run, and at close how many
rows were written or dropped and how the run ended) and `rows.f64`, fixed-width little-endian float64 rows appended
in whole blocks (`np.fromfile(path, "<f8").reshape(-1, row_width)`).

The control thread never waits on the disk: `on_tick` copies the tick into the next row of a preallocated block;
a full block goes to the writer thread through a queue and the next block of a small preallocated pool is taken.
When none is free (the disk is behind by the whole pool), rows are dropped and counted, never waited for (the `tick`
column shows where). The writer thread appends each block and syncs it to the disk, so a crash of the process
loses at most the blocks it had not written yet (a second's worth each). After `max_s` seconds of ticks the
recording stops with one warning line and the run goes on; `close` (called on every exit path: the CLI's
`finally`) writes the last, partial block and the final meta.json.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import queue
import threading
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from bruce_hw.backend import Backend
from bruce_hw.config import RobotConfig
from bruce_hw.types import FOOT_CONTACT_NAMES
from runtime.loop.observers import TickObserver, TickView

log = logging.getLogger("runtime.loop.recorder")

LOG_FORMAT = "bruce-run-log"
LOG_VERSION = 1
META_FILE = "meta.json"
ROWS_FILE = "rows.f64"
ROW_DTYPE = "<f8"
BLOCK_ROWS = 1000          # rows per block: 1 s at 1 kHz, what a crash can lose at most per unwritten block
POOL_BLOCKS = 8            # blocks in the pool: the writer may fall this many seconds behind before rows drop
DEFAULT_MAX_S = 3600.0     # an hour of ticks (~4 GB at 1 kHz); recording stops after it, the run goes on
WRITE_CHUNK = 1 << 16      # bytes per write call: the writer thread runs above the loop on a real-time run
                           # (bruce_hw.io_priority), so it gives the GIL back between pieces of a block


class RecordError(ValueError):
    """A log that cannot be recorded as asked (the message names the path)."""


@dataclass(frozen=True)
class Column:
    name: str
    width: int
    unit: str
    what: str


def log_columns(config: RobotConfig, reference: bool, truth: bool) -> tuple[Column, ...]:
    """The row's columns in order: always the tick, the measured state, IMU, contacts, command, targets and
    torques; with a transfer scheme that has a reference model, its state and the gap monitor's residual; on a
    simulator, its base state (ground truth)."""
    n = config.n_joints
    columns = [
        Column("tick", 1, "1", "loop tick since activation"),
        Column("t", 1, "s", "backend clock at this tick's read, since the loop started (simulated time on the mock)"),
        Column("q", n, "rad", "joint angles read"),
        Column("qd", n, "rad/s", "joint velocities read"),
        Column("tau_measured", n, "N m", "joint torques the drives report (motor current x torque constant)"),
        Column("joint_age", 1, "s", "age of the joint reading at this tick (clock - its stamp)"),
        Column("imu_gyro", 3, "rad/s", "angular velocity, IMU frame"),
        Column("imu_accel", 3, "m/s^2", "specific force, IMU frame (+g up at rest)"),
        Column("imu_quat", 4, "1", "orientation (w, x, y, z) IMU -> world; NaN where the IMU gives none"),
        Column("imu_age", 1, "s", "age of the IMU reading at this tick"),
        Column("contacts", len(FOOT_CONTACT_NAMES), "0/1", "foot contact switches, " + ", ".join(FOOT_CONTACT_NAMES)),
        Column("estop", 1, "0/1", "emergency-stop input asserted"),
        Column("command", 3, "m/s, m/s, rad/s", "velocity command in force (vx, vy, yaw rate; heading frame)"),
        Column("a", n, "rad", "controller targets in force (the policy's a_t)"),
        Column("tau_star", n, "N m", "Eq. 8 on the targets"),
        Column("tau", n, "N m", "torque written (the safety stage's output)"),
        Column("safety_state", 1, "code", "safety stage: 0 soft start, 1 running, 2 damping"),
    ]
    if reference:
        columns += [
            Column("q_hat", n, "rad", "the transfer scheme's reference angles (NaN where it made none)"),
            Column("qd_hat", n, "rad/s", "the transfer scheme's reference velocities"),
            Column("gap_q", n, "rad", "gap monitor: q read minus the reference model's one-step prediction of it "
                   "(NaN on ticks it scored nothing)"),
            Column("gap_qd", n, "rad/s", "gap monitor: the same for qd"),
        ]
    if truth:
        columns += [
            Column("base_pos", 3, "m", "simulator truth: base position, world"),
            Column("base_quat", 4, "1", "simulator truth: base orientation (w, x, y, z), base -> world"),
            Column("base_linvel", 3, "m/s", "simulator truth: base linear velocity, world"),
            Column("base_angvel", 3, "rad/s", "simulator truth: base angular velocity, base frame"),
        ]
    return tuple(columns)


def column_layout(columns: tuple[Column, ...]) -> list[dict]:
    """meta.json's `columns`: each column's name, first index in the row, width, unit and meaning."""
    out, offset = [], 0
    for c in columns:
        out.append({"name": c.name, "offset": offset, "width": c.width, "unit": c.unit, "what": c.what})
        offset += c.width
    return out


REPOSITORY = Path(__file__).resolve().parents[2]


def portable_path(path: str | Path) -> str:
    """A path as a record names it for another machine: relative to this repository when it lies inside it (a
    checkout anywhere else has the same file there), else as given."""
    resolved = Path(path).resolve()
    return resolved.relative_to(REPOSITORY).as_posix() if resolved.is_relative_to(REPOSITORY) else str(path)


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, read in blocks (logs, datasets, checkpoints and models are recorded by it)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def file_record(path: str | Path | None) -> dict | None:
    """A model or input file as the log records it: its path and SHA-256 (None when there is none)."""
    if path is None:
        return None
    path = Path(path)
    return {"path": str(path.resolve()), "sha256": file_sha256(path) if path.is_file() else None}


def utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def describe_run(config: RobotConfig, *, backend: str, controller: str, policy: Path | None, transfer: str,
                 pinn: Path | None, estimator: str | None, overrides: list[str], gap=None, commands=None,
                 scenario: Path | None = None) -> dict:
    """What a log records about its run, for a replay to repeat it: the config file (path, SHA-256, overrides),
    the controller and its policy file, the transfer scheme and its PINN, the estimator, the gap profile the mock
    played (with its seed) and where the commands came from."""
    from runtime.transfer.stage import settings_for  # the transfer stage loads MuJoCo: only when a run is described

    policy_path = (policy or config.models.policy) if controller == "policy" else None
    reference_model = settings_for(config).reference_model if transfer != "direct" else None
    uses_pinn = reference_model == "pinn"
    return {
        "config": {**file_record(config.path), "overrides": list(overrides), "mjcf": file_record(config.mjcf)},
        "backend": backend,
        "controller": controller if controller != "policy" or policy_path is not None else "standing",
        "policy": file_record(policy_path),
        "policy_spec": file_record(config.models.policy_spec) if policy_path is not None else None,
        "transfer": transfer,
        "reference_model": reference_model,
        "pinn": file_record((pinn or config.models.pinn) if uses_pinn else None),
        "estimator": estimator or ("truth" if backend == "mock" else "kinematic"),
        "gap": None if gap is None else {"profile": str(gap.source), "seed": gap.seed},
        "commands": ({"source": "scenario", **file_record(scenario)} if scenario is not None else
                     {"source": "cmd", "name": commands.name} if commands is not None else {"source": "none"}),
    }


class RunRecorder(TickObserver):
    """The log of a run at `path` (a new or empty directory), as a tick observer of `runtime.loop.run.run_session`.
    `run` is `describe_run`'s record of the run; `max_s` bounds the recording (the run goes on after it)."""

    def __init__(self, path: str | Path, config: RobotConfig, run: dict, max_s: float = DEFAULT_MAX_S,
                 block_rows: int = BLOCK_ROWS, pool_blocks: int = POOL_BLOCKS):
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise RecordError(f"--record {self.path}: exists and is not an empty directory (a log is never "
                              "overwritten: choose a new path)")
        if not max_s > 0:
            raise RecordError(f"--record-max-s: expected seconds > 0, got {max_s}")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path / ROWS_FILE, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        except OSError as exc:
            raise RecordError(f"--record {self.path}: cannot create the log: {exc.strerror}") from None
        self.reference = run.get("transfer", "direct") != "direct"  # every scheme but direct has a reference model
        self.max_rows = max(1, round(max_s * config.loop_hz))
        self.block_rows, self.pool_blocks = block_rows, pool_blocks
        self.meta = {"format": LOG_FORMAT, "version": LOG_VERSION, "rows_file": ROWS_FILE, "dtype": ROW_DTYPE,
                     "joints": list(config.joints), "loop_hz": config.loop_hz, "dt": config.dt,
                     "started_utc": utc_now(), "max_s": max_s, "block_rows": block_rows, **run,
                     "columns": None, "row_width": None, "initial_q": None, "rows_written": 0, "rows_dropped": 0,
                     "recording_stopped": None, "ended": None, "closed_utc": None, "write_error": None}
        self.ticks_seen = 0        # rows recorded + rows dropped
        self.rows_dropped = 0
        self.rows_written = 0      # by the writer thread
        self.stopped: str | None = None
        self._ended: dict | None = None
        self._blocks: list[np.ndarray] = []
        self._block: np.ndarray | None = None
        self._block_index = -1
        self._fill = 0
        self._gap_samples = 0
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._free: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        self._write_meta()  # a log that ends before its loop still says so
        self._writer = threading.Thread(target=self._write_blocks, name="run-recorder", daemon=True)
        self._writer.start()

    # -- control thread ------------------------------------------------------------------------------------
    def on_start(self, backend: Backend, config: RobotConfig) -> None:
        """Lay out the row (the simulator's truth where the backend has one) and allocate the pool: before the
        first tick, so that no tick allocates."""
        truth = backend.ground_truth() is not None
        columns = log_columns(config, self.reference, truth)
        layout = column_layout(columns)
        width = sum(c.width for c in columns)
        self._slices = {c["name"]: slice(c["offset"], c["offset"] + c["width"]) for c in layout}
        self._truth = truth
        self._blocks = [np.full((self.block_rows, width), np.nan) for _ in range(self.pool_blocks)]
        for index in range(1, self.pool_blocks):
            self._free.put(index)
        self._block_index, self._block, self._fill = 0, self._blocks[0], 0
        initial_q = getattr(backend, "initial_q", None)  # where the mock placed the legs (a robot: its own pose)
        self._jobs.put(("meta", {"columns": layout, "row_width": width,
                                 "initial_q": None if initial_q is None else [float(v) for v in initial_q]}))

    def on_tick(self, view: TickView) -> None:
        if self.stopped is not None or not self._blocks:
            return None
        if self.ticks_seen == self.max_rows:
            self.stopped = (f"recording stopped after {self.max_rows} rows ({self.meta['max_s']:g} s, "
                            "--record-max-s); the run went on")
            log.warning("recorder: %s: %s", self.path, self.stopped)
            return None
        self.ticks_seen += 1
        if self._block is None and not self._take_block():
            self.rows_dropped += 1
            return None
        row = self._block[self._fill]
        s = self._slices
        robot = view.robot
        joints, imu = robot.joints, robot.imu
        row[0], row[1] = view.tick, view.now - view.clock0
        row[s["q"]], row[s["qd"]], row[s["tau_measured"]] = joints.q, joints.qd, joints.tau
        row[s["joint_age"]] = view.now - joints.stamp
        row[s["imu_gyro"]], row[s["imu_accel"]] = imu.gyro, imu.accel
        row[s["imu_quat"]] = np.nan if imu.orientation is None else imu.orientation
        row[s["imu_age"]] = view.now - imu.stamp
        row[s["contacts"]], row[s["estop"]] = robot.contacts.contact, robot.estop
        row[s["command"]], row[s["a"]], row[s["tau_star"]], row[s["tau"]] = (view.command, view.a, view.tau_star,
                                                                             view.tau)
        row[s["safety_state"]] = np.nan if view.safety is None else int(view.safety.state)
        if self.reference:
            scheme, gap = view.scheme, view.gap
            row[s["q_hat"]] = np.nan if scheme is None or scheme.q_hat is None else scheme.q_hat
            row[s["qd_hat"]] = np.nan if scheme is None or scheme.qd_hat is None else scheme.qd_hat
            fresh = gap is not None and gap.samples != self._gap_samples  # the monitor scored this tick
            row[s["gap_q"]] = gap.last.q if fresh else np.nan
            row[s["gap_qd"]] = gap.last.qd if fresh else np.nan
            if gap is not None:
                self._gap_samples = gap.samples
        if self._truth:
            truth = view.truth
            row[s["base_pos"]], row[s["base_quat"]] = truth.base_pos, truth.base_quat
            row[s["base_linvel"]], row[s["base_angvel"]] = truth.base_linvel, truth.base_angvel
        self._fill += 1
        if self._fill == self.block_rows:
            self._hand_over()
        return None

    def _hand_over(self) -> None:
        """The current block (its filled rows) to the writer; the next block is taken when the next row needs it."""
        self._jobs.put(("rows", self._block_index, self._fill))
        self._block, self._block_index, self._fill = None, -1, 0

    def _take_block(self) -> bool:
        try:
            self._block_index = self._free.get_nowait()
        except queue.Empty:
            if not self.rows_dropped:
                log.warning("recorder: %s: the disk is behind by %d blocks: dropping rows (counted in meta.json)",
                            self.path, self.pool_blocks)
            return False
        self._block = self._blocks[self._block_index]
        return True

    def on_end(self, summary) -> None:
        self._ended = {"stop_cause": summary.stop_cause, "exit_code": int(summary.exit_code),
                       "fault_class": summary.fault_class}

    # -- close (any thread, after the loop) ------------------------------------------------------------------
    def close(self, error: BaseException | str | None = None) -> dict:
        """Write the last rows and the final meta.json; `error` is what ended the run when the loop raised (its
        observers' `on_end` is not called then). Idempotent. Returns the final meta."""
        if self._closed:
            return self.meta
        self._closed = True
        if self._block is not None and self._fill:
            self._hand_over()
        self._jobs.put(None)
        self._writer.join()
        os.close(self._fd)
        ended = self._ended
        if error is not None:
            text = error if isinstance(error, str) else f"{type(error).__name__}: {error}"
            ended = {**(ended or {}), "error": text}
        self.meta.update(rows_written=self.rows_written, rows_dropped=self.rows_dropped,
                         recording_stopped=self.stopped, closed_utc=utc_now(),
                         ended=ended or {"stop_cause": None, "note": "the loop did not end normally (no summary)"})
        self._write_meta()
        return self.meta

    # -- writer thread -------------------------------------------------------------------------------------------
    def _write_blocks(self) -> None:
        """Append each block handed over, sync it, give the block back; blocks on the queue, never polls."""
        while True:
            job = self._jobs.get()
            if job is None:
                return
            if job[0] == "meta":
                self.meta.update(job[1])
                self._write_meta()
                continue
            _, index, rows = job
            if self.meta["write_error"] is None:
                try:
                    data = memoryview(self._blocks[index][:rows]).cast("B")
                    for start in range(0, len(data), WRITE_CHUNK):
                        piece = data[start:start + WRITE_CHUNK]
                        while piece:
                            piece = piece[os.write(self._fd, piece):]
                    os.fsync(self._fd)
                    self.rows_written += rows
                except OSError as exc:  # disk full, device gone: the run goes on, the log says where it ends
                    self.meta["write_error"] = f"{self.path / ROWS_FILE}: {exc.strerror} after {self.rows_written} rows"
                    log.warning("recorder: %s", self.meta["write_error"])
            self._free.put(index)  # every column of a row is written each tick: no clearing

    def _write_meta(self) -> None:
        """meta.json, replaced atomically: a reader sees the old or the new one, never half of one."""
        target = self.path / META_FILE
        temporary = target.with_suffix(".json.tmp")
        try:
            temporary.write_text(json.dumps(self.meta, indent=1) + "\n")
            os.replace(temporary, target)
        except OSError as exc:
            self.meta["write_error"] = f"{target}: {exc.strerror}"
            log.warning("recorder: %s", self.meta["write_error"])
