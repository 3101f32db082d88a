"""The telemetry process: reads the rings and sends them to rerun in chunks (entity layout and blueprint below;
why a process, chunk sizes and file rotation: docs/telemetry.md#design).

Entities: joints/<joint> [q, q_hat, a, qd, qd_hat, tau_star, tau] every tick (q_hat/qd_hat NaN without a model);
gap/<joint> [qd residual, q residual, qd window RMS] with a gap monitor; loop/period_us, loop/work_us; safety/state
and telemetry/dropped where they change; safety/events (TextLog); world/robot/<body> (static geoms + a pose per
pose row) and world/base_trajectory with a MuJoCo model.
"""

from __future__ import annotations

import contextlib
import math
import mmap
import os
import pickle
import signal
import sys
import time
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

import numpy as np

from runtime.telemetry.ring import (
    EVENTS_WRITTEN,
    GAP_BLOCKS,
    POSES_FAILED,
    POSES_OVERRUN,
    POSES_READ,
    POSES_SENT,
    POSES_WRITTEN,
    ROW_BLOCKS,
    ROWS_FAILED,
    ROWS_OVERRUN,
    ROWS_READ,
    ROWS_REJECTED,
    ROWS_SENT,
    ROWS_WRITTEN,
    Layout,
    RingReader,
)
from runtime.telemetry.sink import (
    TelemetryError,
    part_path,
    web_origins,
    web_viewer_link,
)

if TYPE_CHECKING:
    import pyarrow as pa

GRPC_FLUSH_TIMEOUT_S = 5.0  # close() waits at most this long for an unreachable viewer; a file is always flushed
TEXT_LEVELS = {"critical": "CRITICAL", "error": "ERROR", "warn": "WARN", "warning": "WARN", "info": "INFO",
               "debug": "DEBUG", "trace": "TRACE"}
BLUE, ORANGE, GREEN, RED = (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40)
# One entity per joint, joints/<joint>, with these series in this order; ROW_ORDER picks them from the row blocks
# (q, qd, q_hat, qd_hat, a, tau_star, tau). One entity instead of three (position, velocity, torque) because
# rerun stores a row id and the index columns per entity and row: at 1 kHz that overhead outweighed the values.
JOINT_SERIES = ("q", "q_hat", "a", "qd", "qd_hat", "tau_star", "tau")
JOINT_COLOURS = (BLUE, ORANGE, GREEN, BLUE, ORANGE, RED, BLUE)
ROW_ORDER = (0, 2, 4, 1, 3, 5, 6)
QUANTITIES = {  # the blueprint's per-joint plots: which of JOINT_SERIES each shows (SeriesLines.visible_series)
    "position": [name in ("q", "q_hat", "a") for name in JOINT_SERIES],
    "velocity": [name in ("qd", "qd_hat") for name in JOINT_SERIES],
    "torque": [name in ("tau_star", "tau") for name in JOINT_SERIES],
}
TAB_NAMES = {"position": "positions", "velocity": "velocities", "torque": "torques"}
LOOP_SERIES = {"loop/period_us": "period", "loop/work_us": "work"}  # every row
STEP_SERIES = {"safety/state": "safety code", "telemetry/dropped": "dropped rows"}  # rows where they change
LIVE_WINDOW_S = 10.0  # live sinks: the plots show this many trailing seconds (a browser redraws every frame)
FLOOR_HALF_SIZE_M = 2.0  # MuJoCo planes of size 0 are infinite; show this much of them
TRAJECTORY_RADIUS_M = 0.003

# With a gap monitor (a transfer scheme with a reference model) each row carries three more blocks, sent as one
# entity per joint, gap/<joint>: the one-step residuals (measured minus predicted a tick earlier) and the
# monitor's short-window RMS of the velocity residual (runtime.transfer.gap_monitor).
GAP_SERIES = ("qd residual", "q residual", "qd window RMS")
GAP_COLOURS = (BLUE, GREEN, RED)
def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    return wxyz[..., [1, 2, 3, 0]]  # MuJoCo quaternions are (w, x, y, z); rerun's are (x, y, z, w)


# -- the telemetry process ---------------------------------------------------------------------------------
def picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")



def child_main(fd: int) -> None:
    """Entry point of the telemetry process (see CHILD_BOOT): serve one Telemetry until stop or EOF."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)  # the parent decides when to stop; its death shows as EOF
    conn = Connection(fd)
    spec = conn.recv()
    if hasattr(os, "sched_getaffinity"):
        allowed = sorted(os.sched_getaffinity(0))
        if len(allowed) > 1:
            os.sched_setaffinity(0, allowed[:-1])  # runtime.loop.realtime pins the loop to the last one
    sender = _Sender(spec, conn)
    try:
        sender.open()
    except Exception as exc:
        text = exc if isinstance(exc, TelemetryError) else f"rerun sink {spec['sink']}: {type(exc).__name__}: {exc}"
        text = str(text)
        with contextlib.suppress(OSError):
            conn.send(("failed", text))
        sender.disconnect()
        return
    with contextlib.suppress(OSError):
        conn.send(("ready", sender.url))
    orphaned = sender.run()
    if not orphaned:
        with contextlib.suppress(OSError):
            conn.send(("done",))


class _BlueprintSender:
    """Sends one blueprint to a recording, again for each new part. rerun's `send_blueprint` builds a new
    blueprint stream per call and never frees it (rerun 0.41: ~1 MB and two threads per call, so a leak per
    part); this keeps one blueprint stream and logs the blueprint into a fresh memory sink of it per send, which is
    what `send_blueprint` does inside. If those internals are not there (another rerun version), it falls back to
    `send_blueprint`."""

    def __init__(self, blueprint, application_id: str):
        self.blueprint, self.application_id = blueprint, application_id
        self.stream = None

    def send(self, recording) -> None:
        try:
            import rerun_bindings as bindings
            from rerun.recording_stream import RecordingStream

            if self.stream is None:
                self.stream = RecordingStream._from_native(bindings.new_blueprint(
                    application_id=self.application_id, make_default=False, make_thread_default=False,
                    default_enabled=True))
            memory = self.stream.memory_recording()
            self.stream.set_time("blueprint", sequence=0)
            self.blueprint._log_to_stream(self.stream)
            send = bindings.send_blueprint
        except (ImportError, AttributeError, TypeError):
            recording.send_blueprint(self.blueprint, make_active=True, make_default=True)
            return
        send(memory.storage, True, True, recording=recording.to_native())  # make_active, make_default


class _EntityColumns:
    """An Arrow schema of `tick`, `time` and the components of many entities, for one `send_record_batch`.

    Field types and `rerun:*` metadata come from a one-row chunk that rerun builds from `sample_columns` (what
    `send_columns` would send), with `rerun:entity_path` added per field; rerun splits the batch per entity.
    """

    def __init__(self, rr, sample_columns, entities: list[str]):
        import pyarrow as pa
        from rerun.chunk import Chunk

        sample = Chunk.from_columns("/sample", _time_columns(rr, [0], [0.0]), sample_columns).to_record_batch()
        index = [sample.schema.field(name) for name in ("tick", "time")]
        # Drop the sortedness claim: rerun checks the order itself.
        index = [f.with_metadata({k: v for k, v in f.metadata.items() if k != b"rerun:is_sorted"}) for f in index]
        self.components = [f for f in sample.schema if f.metadata.get(b"rerun:kind") == b"data"]
        fields = [f.with_name(f"/{path}:{f.name}")
                  .with_metadata({**f.metadata, b"rerun:entity_path": f"/{path}".encode()})
                  for path in entities for f in self.components]
        self.schema = pa.schema(index + fields)
        self._pa = pa

    def index_arrays(self, ticks, times) -> list:
        nanos = np.round(np.asarray(times, dtype=np.float64) * 1e9).astype(np.int64)
        return [self._pa.array(np.asarray(ticks, dtype=np.int64)),
                self._pa.array(nanos, type=self.schema.field("time").type)]

    def scalar_lists(self, values: np.ndarray) -> pa.Array:
        """(n, k) float64 -> n rows of k scalars."""
        n, k = values.shape
        offsets = self._pa.array(np.arange(0, n * k + 1, k, dtype=np.int32))
        return self._pa.ListArray.from_arrays(offsets, self._pa.array(np.ravel(values)),
                                              type=self.components[0].type)

    def vector_lists(self, values: np.ndarray, list_type) -> pa.Array:
        """(n, m) float32 -> n rows of one m-vector, typed as `list_type` (list<fixed_size_list<float32, m>>)."""
        pa = self._pa
        vectors = pa.FixedSizeListArray.from_arrays(pa.array(np.ravel(values)), type=list_type.value_type)
        return pa.ListArray.from_arrays(pa.array(np.arange(len(values) + 1, dtype=np.int32)), vectors, type=list_type)

    def batch(self, columns: list) -> pa.RecordBatch:
        return self._pa.RecordBatch.from_arrays(columns, schema=self.schema)


def decimated(rows: np.ndarray, every: int) -> np.ndarray:
    """One row per `every` ticks (the last of each interval of ticks // every) with the interval's largest
    period_us and work_us, so a single late tick still shows. An interval split between two sends gives a row in
    each."""
    if every <= 1 or not len(rows):
        return rows
    intervals = rows[:, 0].astype(np.int64) // every
    last = np.flatnonzero(np.r_[intervals[1:] != intervals[:-1], True])
    out = rows[last]
    out[:, -3:-1] = np.fmax.reduceat(rows[:, -3:-1], np.r_[0, last[:-1] + 1], axis=0)  # fmax: tick 0's NaN period
    return out


def _time_columns(rr, ticks, times) -> list:
    return [rr.TimeColumn("tick", sequence=np.asarray(ticks, dtype=np.int64)),
            rr.TimeColumn("time", duration=np.asarray(times, dtype=np.float64))]


class _Sender:
    """The telemetry process's side: reads the rings and sends them to rerun."""

    def __init__(self, spec: dict, conn: Connection):
        self.spec, self.conn = spec, conn
        self.sink = spec["sink"]
        self.joints = spec["joints"]
        self.geometry = spec["geometry"]
        self.url: str | None = None
        self.recording = None
        self.error_sent = False
        self.bodies: list[tuple[int, str]] = []  # (MuJoCo body id, name) of every body but the world
        self.base_body: int | None = None
        self.last_base: np.ndarray | None = None
        self.row_columns: _EntityColumns | None = None
        self.step_columns: _EntityColumns | None = None
        self.last_step: np.ndarray | None = None  # STEP_SERIES' values in the last row sent
        self.pose_columns: _EntityColumns | None = None
        self.gap_columns: _EntityColumns | None = None
        self.pending_rows: list[np.ndarray] = []   # drained from the rings, not yet sent (one chunk's worth)
        self.pending_poses: list[np.ndarray] = []
        self.part = 0                              # save=: the part being written (part_path)
        self.blueprint: _BlueprintSender | None = None
        self.max_bytes = spec["max_mb"] * 1e6 if spec["kind"] == "save" else 0.0

    # -- start-up ------------------------------------------------------------------------------------------
    def open(self) -> None:
        spec = self.spec
        fd = os.open(spec["path"], os.O_RDWR)
        try:
            self.memory = mmap.mmap(fd, spec["size"])
        finally:
            os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(spec["path"])
        nbody = 0 if self.geometry is None else len(self.geometry["names"])
        views = Layout(len(self.joints), spec["capacity"], nbody, spec["pose_capacity"],
                        spec["gap"]).views(self.memory)
        self.ctrl, self.stats = views["ctrl"], views["stats"]
        self.rows = RingReader(views["rows"], self.ctrl, ROWS_WRITTEN)
        self.poses = RingReader(views["poses"], self.ctrl, POSES_WRITTEN)
        self.events = RingReader(views["events"], self.ctrl, EVENTS_WRITTEN)

        import rerun as rr

        self.recording = rr.RecordingStream(spec["recording_name"])
        self._open_sink()
        self.blueprint = _BlueprintSender(self._blueprint(), spec["recording_name"])
        self.blueprint.send(self.recording)
        self._log_static(rr)
        scalars = rr.Scalars.columns(scalars=[0.0])
        self.row_columns = _EntityColumns(rr, scalars, [f"joints/{name}" for name in self.joints] + list(LOOP_SERIES))
        self.step_columns = _EntityColumns(rr, scalars, list(STEP_SERIES))
        if spec["gap"]:
            self.gap_columns = _EntityColumns(rr, scalars, [f"gap/{name}" for name in self.joints])
        if self.bodies:
            sample = rr.Transform3D.columns(translation=[[0.0, 0.0, 0.0]], quaternion=[[0.0, 0.0, 0.0, 1.0]])
            self.pose_columns = _EntityColumns(rr, sample, [f"world/robot/{name}" for _, name in self.bodies])

    def _open_sink(self) -> None:
        recording, kind, target = self.recording, self.spec["kind"], self.spec["target"]
        if kind == "save":
            recording.save(target)
        elif kind == "connect":
            recording.connect_grpc(target)
        elif kind == "serve":
            self.url = recording.serve_grpc(grpc_port=int(target),
                                            server_memory_limit=f"{self.spec['buffer_mb']}MB")
        elif kind == "web":
            import rerun as rr

            # Both servers listen on all interfaces. The page comes from web_port under whatever name the browser
            # used, so that origin must be allowed to read the stream (rerun allows localhost and rerun.io only).
            web_port, grpc_port = self.spec["web_port"], self.spec["grpc_port"]
            local = recording.serve_grpc(grpc_port=grpc_port, server_memory_limit=f"{self.spec['buffer_mb']}MB",
                                         cors_allow_origin=web_origins(web_port))
            rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=local)
            self.url = web_viewer_link(target, web_port, grpc_port)  # target: the host for the link
        elif kind == "spawn":
            recording.spawn()  # may wait up to ~10 s for the viewer to come up
        else:
            raise TelemetryError(f"rerun sink {self.sink}: unknown kind {kind!r}")

    def _blueprint(self):
        import rerun as rr
        import rerun.blueprint as rrb

        # Live, every plot shows the trailing LIVE_WINDOW_S: readable while it scrolls, and a browser redraws a
        # bounded number of points per frame however long the run. A recording shows all of it.
        window = {}
        if self.spec["kind"] != "save":
            window = {"time_ranges": [rrb.VisibleTimeRange(
                "time", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-LIVE_WINDOW_S),
                end=rrb.TimeRangeBoundary.cursor_relative())]}

        def per_joint(quantity: str):
            visible = rr.SeriesLines(visible_series=QUANTITIES[quantity])
            views = [rrb.TimeSeriesView(origin=f"joints/{name}", name=f"{name} {quantity}",
                                        overrides={f"joints/{name}": visible}, **window) for name in self.joints]
            return rrb.Grid(*views, grid_columns=max(1, math.ceil(len(views) / 2)), name=TAB_NAMES[quantity])

        loop = rrb.Vertical(
            rrb.TimeSeriesView(origin="loop", name="loop timing (µs)", **window),
            rrb.TimeSeriesView(origin="/", contents=["safety/state", "telemetry/dropped"], name="safety / drops",
                               **window),
            rrb.TextLogView(origin="safety/events", name="safety events"),
        )
        overview = loop
        if self.geometry is not None:
            # All of the past is in range so the trajectory accumulates; transforms stay latest-at, geoms static.
            past = [rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                                         end=rrb.TimeRangeBoundary.cursor_relative()) for timeline in ("tick", "time")]
            overview = rrb.Horizontal(rrb.Spatial3DView(origin="world", name="robot", time_ranges=past), loop,
                                      column_shares=[3, 2])
        tabs = [rrb.Vertical(overview, name="robot"), per_joint("position"), per_joint("torque"),
                per_joint("velocity")]
        if self.spec["gap"]:
            views = [rrb.TimeSeriesView(origin=f"gap/{name}", name=f"{name} gap (rad/s, rad)", **window)
                     for name in self.joints]
            tabs.append(rrb.Grid(*views, grid_columns=max(1, math.ceil(len(views) / 2)), name="gap"))
        # The side panels start collapsed (a click opens them): in a laptop's browser window the views need the room.
        return rrb.Blueprint(rrb.Tabs(*tabs), rrb.BlueprintPanel(state="collapsed"),
                             rrb.SelectionPanel(state="collapsed"), rrb.TimePanel(timeline="time", state="collapsed"))

    def _log_static(self, rr) -> None:
        log = self.recording.log
        for name in self.joints:
            log(f"joints/{name}", rr.SeriesLines(names=JOINT_SERIES, colors=JOINT_COLOURS), static=True, strict=True)
            if self.spec["gap"]:
                log(f"gap/{name}", rr.SeriesLines(names=GAP_SERIES, colors=GAP_COLOURS), static=True, strict=True)
        for path, label in (LOOP_SERIES | STEP_SERIES).items():
            log(path, rr.SeriesLines(names=[label]), static=True, strict=True)
        if self.geometry is not None:
            log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, strict=True)
            self._log_geometry(rr)

    def _log_geometry(self, rr) -> None:
        """Each body's primitives, static, in the body's frame; the per-pose transforms place the bodies."""
        from bruce_hw.quaternion import body_z_in_world  # here: the child process imports no bruce_hw otherwise

        names = self.geometry["names"]
        self.bodies = [(b, names[b]) for b in range(1, len(names))]  # body 0 is the world itself
        self.base_body = names.index("base") if "base" in names else None
        by_body: dict[int, dict[str, list]] = {}
        for kind, body, size, pos, wxyz, rgba in self.geometry["geoms"]:
            quat, rgba = _xyzw(wxyz), np.round(rgba * 255).astype(np.uint8)
            if kind == "plane":
                half = [s if s > 0 else FLOOR_HALF_SIZE_M for s in size[:2]]
                floor = rr.Boxes3D(half_sizes=[[half[0], half[1], 0.001]], centers=[pos - [0.0, 0.0, 0.001]],
                                   quaternions=[quat], colors=[rgba], fill_mode="solid")
                self.recording.log("world/floor", floor, static=True, strict=True)
                continue
            if body == 0:
                continue
            if kind == "capsule":
                # MuJoCo centres a capsule on its position; rerun starts one at its translation, along local +z.
                pos = pos - size[1] * np.array(body_z_in_world(wxyz))
            by_body.setdefault(body, {}).setdefault(kind, []).append((size, pos, quat, rgba))
        for body, by_kind in by_body.items():
            parts = []
            for kind, geoms in by_kind.items():
                sizes, centers, quats, colors = (np.array(column) for column in zip(*geoms, strict=True))
                common = {"quaternions": quats, "colors": colors, "fill_mode": "solid"}
                if kind == "box":
                    parts.append(rr.Boxes3D(half_sizes=sizes, centers=centers, **common))
                elif kind in ("sphere", "ellipsoid"):
                    half = np.repeat(sizes[:, :1], 3, axis=1) if kind == "sphere" else sizes
                    parts.append(rr.Ellipsoids3D(half_sizes=half, centers=centers, **common))
                elif kind == "capsule":
                    parts.append(rr.Capsules3D(lengths=2 * sizes[:, 1], radii=sizes[:, 0], translations=centers,
                                               **common))
                else:  # cylinder: centred in both, size = (radius, half-length)
                    parts.append(rr.Cylinders3D(lengths=2 * sizes[:, 1], radii=sizes[:, 0], centers=centers,
                                                **common))
            self.recording.log(f"world/robot/{names[body]}", *parts, static=True, strict=True)

    # -- running -------------------------------------------------------------------------------------------
    def run(self) -> bool:
        """Drain the rings every batch_period_s and send what was drained every chunk_s, until stop (False) or
        until the parent is gone (True); then send what is left, flush and disconnect."""
        conn, period, parent = self.conn, self.spec["batch_period_s"], self.spec["parent"]
        chunk_s = self.spec["chunk_s"]
        orphaned = False
        now = time.monotonic()
        deadline, send_at = now + period, now + chunk_s
        try:
            while True:
                try:
                    if conn.poll(max(0.0, deadline - time.monotonic())):
                        if conn.recv()[0] == "stop":
                            break
                        continue
                except (EOFError, OSError):
                    orphaned = True
                    break
                if os.getppid() != parent:
                    orphaned = True
                    break
                self.drain()
                now = time.monotonic()
                if now >= send_at:
                    self.send_pending()
                    send_at = max(send_at + chunk_s, now)
                deadline = max(deadline + period, now)
            self.drain()
            self.send_pending()
            self.recording.flush(timeout_sec=1e9 if self.spec["kind"] == "save" else GRPC_FLUSH_TIMEOUT_S)
        except Exception as exc:
            self.note_error(exc, "flushing at close failed; data not yet delivered may be lost")
        finally:
            self.disconnect()
        return orphaned

    def disconnect(self) -> None:
        recording, self.recording = self.recording, None
        if recording is not None:
            recording.disconnect()  # writes the .rrd footer, closes connections, stops a gRPC server

    def note_error(self, exc: BaseException, what: str) -> None:
        if not self.error_sent:
            self.error_sent = True
            print(f"telemetry: rerun sink {self.sink}: {what} ({type(exc).__name__}: {exc})", file=sys.stderr,
                  flush=True)
            with contextlib.suppress(OSError):
                self.conn.send(("error", picklable(exc)))

    def drain(self) -> None:
        """Copy what the rings hold into the pending lists (the rings stay small; rerun gets whole chunks);
        events, rare, go out at once."""
        import rerun as rr

        stats = self.stats
        rows, lost = self.rows.take()
        stats[ROWS_READ] = self.rows.read
        stats[ROWS_OVERRUN] += lost
        if len(rows):
            self.pending_rows.append(rows)
        poses, lost = self.poses.take()
        stats[POSES_READ] = self.poses.read
        stats[POSES_OVERRUN] += lost
        if len(poses):
            self.pending_poses.append(poses)
        events, _ = self.events.take()
        if len(events):
            try:
                self._send_events(rr, events)
            except Exception as exc:
                self.note_error(exc, f"sending {len(events)} events failed")

    def send_pending(self) -> None:
        """Send the drained rows and poses as one chunk per entity, in a new part if the file has reached max_mb
        (checked before sending, so no part is left without rows); a failure drops (and counts) them but never
        ends the process."""
        import rerun as rr

        if not (self.pending_rows or self.pending_poses):
            return
        if self.max_bytes and self._part_bytes() >= self.max_bytes:
            try:
                self._next_part(rr)
            except Exception as exc:
                self.note_error(exc, f"starting part {self.part} failed; the recording goes on in the last file")
                self.max_bytes = 0.0
        stats = self.stats
        rows = np.concatenate(self.pending_rows) if self.pending_rows else None
        poses = np.concatenate(self.pending_poses) if self.pending_poses else None
        self.pending_rows, self.pending_poses = [], []
        if rows is not None:
            try:
                self._send_rows(rows)
                stats[ROWS_SENT] += len(rows)
            except Exception as exc:
                stats[ROWS_FAILED] += len(rows)
                self.note_error(exc, f"sending {len(rows)} rows failed; they count as dropped, later batches "
                                     "are still tried")
        if poses is not None and self.pose_columns is not None:
            try:
                self._send_poses(rr, poses)
                stats[POSES_SENT] += len(poses)
            except Exception as exc:
                stats[POSES_FAILED] += len(poses)
                self.note_error(exc, f"sending {len(poses)} poses failed; later batches are still tried")

    def _part_bytes(self) -> int:
        """The current part's size on disk, after rerun has written what it has queued (a few ms once a chunk),
        so a part ends at most one chunk (and its footer) past max_mb."""
        self.recording.flush(timeout_sec=GRPC_FLUSH_TIMEOUT_S)
        try:
            return os.path.getsize(part_path(self.spec["target"], self.part))
        except OSError:
            return 0

    def _next_part(self, rr) -> None:
        """Continue the recording in the next part: the previous file gets its footer when its sink is
        replaced; each part carries the blueprint and static data, so it opens on its own."""
        self.part += 1
        path = part_path(self.spec["target"], self.part)
        self.recording.save(str(path))
        self.blueprint.send(self.recording)
        self._log_static(rr)
        keep = self.spec["keep"]
        if keep is not None and self.part >= keep:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(part_path(self.spec["target"], self.part - keep))
        print(f"telemetry: recording continues in {path}" + (f" (keeping the newest {keep} parts)" if keep else ""),
              file=sys.stderr, flush=True)

    def _send_rows(self, all_rows: np.ndarray) -> None:
        rows = decimated(all_rows, self.spec["row_decimation"])  # tick 0's period is NaN: it has no previous tick
        n, n_joints = len(rows), len(self.joints)
        blocks = rows[:, 2:2 + ROW_BLOCKS * n_joints].reshape(n, ROW_BLOCKS, n_joints)
        per_joint = blocks[:, ROW_ORDER].transpose(0, 2, 1)  # (row, joint, series in JOINT_SERIES order)
        ticks = rows[:, 0].astype(np.int64)
        out = self.row_columns
        columns = out.index_arrays(ticks, rows[:, 1])
        columns += [out.scalar_lists(per_joint[:, j]) for j in range(n_joints)]
        columns += [out.scalar_lists(rows[:, k, None]) for k in (-3, -2)]  # period_us, work_us
        self.recording.send_record_batch(out.batch(columns))
        if self.gap_columns is not None:
            start = 2 + ROW_BLOCKS * n_joints
            gap = rows[:, start:start + GAP_BLOCKS * n_joints].reshape(n, GAP_BLOCKS, n_joints).transpose(0, 2, 1)
            out = self.gap_columns
            columns = out.index_arrays(ticks, rows[:, 1])
            columns += [out.scalar_lists(gap[:, j]) for j in range(n_joints)]
            self.recording.send_record_batch(out.batch(columns))
        self._send_steps(all_rows)

    def _send_steps(self, rows: np.ndarray) -> None:
        """The safety code and the drop count change rarely: a row where either changes, the row before it (so
        the plot steps instead of ramping) and the chunk's first and last rows."""
        n, ticks = len(rows), rows[:, 0].astype(np.int64)
        stats = self.stats
        dropped = int(self.ctrl[ROWS_REJECTED] + stats[ROWS_OVERRUN] + stats[ROWS_FAILED])
        step = np.column_stack((rows[:, -1], np.full(n, float(dropped))))
        previous = step[:1] if self.last_step is None else self.last_step[None]
        changed = np.any(step != np.vstack((previous, step[:-1])), axis=1)
        keep = changed | np.roll(changed, -1)
        keep[[0, -1]] = True
        self.last_step = step[-1].copy()
        out = self.step_columns
        columns = out.index_arrays(ticks[keep], rows[keep, 1])
        columns += [out.scalar_lists(step[keep, k, None]) for k in range(len(STEP_SERIES))]
        self.recording.send_record_batch(out.batch(columns))

    def _send_poses(self, rr, poses: np.ndarray) -> None:
        n, nbody = len(poses), len(self.geometry["names"])
        ticks, times = poses[:, 0].astype(np.int64), poses[:, 1]
        positions = poses[:, 2:2 + 3 * nbody].reshape(n, nbody, 3).astype(np.float32)
        rotations = np.ascontiguousarray(_xyzw(poses[:, 2 + 3 * nbody:].reshape(n, nbody, 4).astype(np.float32)))
        out = self.pose_columns
        columns = out.index_arrays(ticks, times)
        for body, _ in self.bodies:
            for field in out.components:  # in the sample's order
                values = {"Transform3D:translation": positions, "Transform3D:quaternion": rotations}[field.name]
                columns.append(out.vector_lists(np.ascontiguousarray(values[:, body]), field.type))
        self.recording.send_record_batch(out.batch(columns))
        if self.base_body is not None:
            base = positions[:, self.base_body].astype(np.float64)
            segment = base if self.last_base is None else np.vstack((self.last_base, base))
            self.last_base = base[-1].copy()
            self.recording.send_columns(
                "world/base_trajectory", indexes=_time_columns(rr, ticks[-1:], times[-1:]),
                columns=rr.LineStrips3D.columns(strips=[segment], radii=[TRAJECTORY_RADIUS_M]), strict=True)

    def _send_events(self, rr, events: np.ndarray) -> None:
        texts = [text.decode("utf-8", "ignore") for text in events["text"]]
        levels = [level.decode("utf-8", "ignore") for level in events["level"]]
        levels = [TEXT_LEVELS.get(level.lower(), level.upper()) for level in levels]
        self.recording.send_columns("safety/events", indexes=_time_columns(rr, events["tick"], events["time"]),
                                    columns=rr.TextLog.columns(text=texts, level=levels), strict=True)

