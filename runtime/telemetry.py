"""Rerun telemetry for the 1 kHz loop: a cheap append on the control thread, batching and I/O on a consumer thread.

The control thread only appends one tuple per tick to a bounded drop-oldest deque (no numpy, no locks, no rerun
calls); rows pushed out because the buffer was full are counted in `dropped`. A daemon consumer thread wakes every
`batch_period_s`, drains the buffers, stacks the rows into numpy columns and sends them, columnar, on the
Telemetry's own `RecordingStream` (never the global one), indexed by a `tick` sequence and a `time` duration
timeline only (no `log_time`/`log_tick`, on purpose). If rerun's channel fills up (slow viewer), it is the
consumer that blocks, and the loop's rows are dropped oldest first instead of stalling a tick.

Why one `send_record_batch` per batch instead of one `send_columns` per entity: both send the same Arrow chunks,
but `send_columns` costs ~50 µs of Python per call in rerun 0.41, so the 45 entities of a 50 ms batch took ~5 ms
of consumer time, all of it holding the GIL the control thread needs to start its next tick (measured: ~1.6 ms
per batch this way). The record batch carries the same field types and `rerun:*` metadata (copied from a chunk
rerun itself builds with `Chunk.from_columns`, plus `rerun:entity_path` per field), and rerun splits it into one
chunk per entity. Rare data (events, the trajectory segment) goes through `send_columns`.

Entity layout (one Scalars entity per quantity per joint, several series per row):
    joints/<joint>/position   [q, q_hat, a]        q_hat/qd_hat are NaN in rows without a PINN estimate
    joints/<joint>/velocity   [qd, qd_hat]
    joints/<joint>/torque     [tau_star, tau]
    loop/period_us, loop/work_us, safety/state (the int code), telemetry/dropped (running count at send time)
    safety/events             TextLog
    world                     ViewCoordinates RIGHT_HAND_Z_UP (static); world/floor: the model's plane as a flat box
    world/robot/<body>        static geoms of the body in its own frame + a Transform3D per pose row (world frame)
    world/base_trajectory     LineStrips3D, one segment per batch of pose rows; the 3-D view shows all of the past
A default blueprint (tabs: robot + loop, positions, velocities, torques) is sent once at start.

Sinks (`--rerun`): spawn | connect[=ADDR] | serve[=PORT] | save=PATH | off. ADDR is host:port or a full
rerun+http(s)://host:port/proxy URL (default rerun+http://127.0.0.1:9876/proxy); start() fails at once when
nothing listens there. `sent_rows` counts rows handed to rerun; a viewer that goes away mid-run loses them unseen.
"""

from __future__ import annotations

import atexit
import math
import os
import socket
import sys
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

import numpy as np

if TYPE_CHECKING:
    import mujoco
    import pyarrow as pa
    import rerun as rr

    from bruce_hw.config import RobotConfig

SINK_HELP = ("where telemetry goes: spawn (a local viewer), connect[=HOST:PORT|URL] (a running viewer), "
             "serve[=PORT] (a gRPC server a laptop viewer attaches to), save=PATH (an .rrd file), off")
SINK_KINDS = ("spawn", "connect", "serve", "save", "off")
ACCEPTED = "expected one of spawn, connect, connect=HOST:PORT|URL, serve, serve=PORT, save=PATH, off"
DEFAULT_GRPC_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"  # where rerun connects without ADDR
VIEWER_PROBE_TIMEOUT_S = 2.0
EVENT_CAPACITY = 256
GRPC_FLUSH_TIMEOUT_S = 5.0  # close() waits at most this long for an unreachable viewer; a file is always flushed
JOIN_TIMEOUT_S = 10.0       # a consumer stuck in rerun (blocked channel) is abandoned after this long
TEXT_LEVELS = {"critical": "CRITICAL", "error": "ERROR", "warn": "WARN", "warning": "WARN", "info": "INFO",
               "debug": "DEBUG", "trace": "TRACE"}
BLUE, ORANGE, GREEN, RED = (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40)
SERIES = {  # entity leaf -> (series names, colours), in the column order of each row
    "position": (["q", "q_hat", "a"], [BLUE, ORANGE, GREEN]),
    "velocity": (["qd", "qd_hat"], [BLUE, ORANGE]),
    "torque": (["tau_star", "tau"], [RED, BLUE]),
}
LOOP_SERIES = {"loop/period_us": "period", "loop/work_us": "work", "safety/state": "safety code",
               "telemetry/dropped": "dropped rows"}
FLOOR_HALF_SIZE_M = 2.0  # MuJoCo planes of size 0 are infinite; show this much of them
TRAJECTORY_RADIUS_M = 0.003


class TelemetryError(RuntimeError):
    """Telemetry could not be started; the message names the sink."""


@dataclass(frozen=True)
class RerunSink:
    kind: str
    target: str | None = None  # connect: ADDR (None: rerun's default); serve: PORT (None: 9876); save: PATH

    def __str__(self) -> str:
        return self.kind if self.target is None else f"{self.kind}={self.target}"


def parse_sink(text: str) -> RerunSink:
    """`spawn`, `connect`, `connect=ADDR`, `serve`, `serve=PORT`, `save=PATH` or `off`; ValueError otherwise."""
    kind, sep, target = text.strip().partition("=")
    if kind not in SINK_KINDS:
        raise ValueError(f"unknown rerun sink {text!r}: {ACCEPTED}")
    if kind in ("spawn", "off") and sep:
        raise ValueError(f"rerun sink {text!r} takes no value: {ACCEPTED}")
    if sep and not target:
        raise ValueError(f"rerun sink {text!r} has nothing after '=': {ACCEPTED}")
    if kind == "save" and not sep:
        raise ValueError(f"rerun sink {text!r} needs a file, save=PATH: {ACCEPTED}")
    if kind == "serve" and sep and not (target.isdigit() and 0 < int(target) < 65536):
        raise ValueError(f"rerun sink {text!r}: the port must be an integer in 1..65535: {ACCEPTED}")
    return RerunSink(kind, target if sep else None)


def grpc_url(addr: str | None) -> str | None:
    """A connect ADDR as rerun wants it: host:port -> rerun+http://host:port/proxy; URLs pass unchanged."""
    if addr is None or "://" in addr:
        return addr
    return f"rerun+http://{addr}/proxy"


def _probe_viewer(sink: RerunSink, url: str) -> None:
    """Fail fast, naming the address, when nothing listens where a viewer should be."""
    parts = urlsplit(url)
    if parts.hostname is None or parts.port is None:
        return  # let rerun judge URLs it may complete itself
    try:
        socket.create_connection((parts.hostname, parts.port), timeout=VIEWER_PROBE_TIMEOUT_S).close()
    except OSError as exc:
        raise TelemetryError(f"rerun sink {sink}: no viewer reachable at {parts.hostname}:{parts.port} ({exc}); "
                             "start one there with `rerun`, or use --rerun serve / --rerun save=PATH") from exc


def make_telemetry(config: RobotConfig, sink: RerunSink, model: mujoco.MjModel | None = None,
                   **kwargs) -> Telemetry | None:
    """A Telemetry for `sink` (not started), or None when the sink is `off`."""
    return None if sink.kind == "off" else Telemetry(config, sink, model=model, **kwargs)


def _drain(buffer: deque) -> list:
    """Everything in `buffer`, oldest first; popleft is atomic, so the control thread can keep appending."""
    items = []
    try:
        while True:
            items.append(buffer.popleft())
    except IndexError:
        return items


def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    return wxyz[..., [1, 2, 3, 0]]  # MuJoCo quaternions are (w, x, y, z); rerun's are (x, y, z, w)


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
        return self._pa.ListArray.from_arrays(offsets, self._pa.array(values.ravel()), type=self.components[0].type)

    def vector_lists(self, values: np.ndarray, list_type) -> pa.Array:
        """(n, m) float32 -> n rows of one m-vector, typed as `list_type` (list<fixed_size_list<float32, m>>)."""
        pa = self._pa
        vectors = pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), type=list_type.value_type)
        return pa.ListArray.from_arrays(pa.array(np.arange(len(values) + 1, dtype=np.int32)), vectors, type=list_type)

    def batch(self, columns: list) -> pa.RecordBatch:
        return self._pa.RecordBatch.from_arrays(columns, schema=self.schema)


def _time_columns(rr, ticks, times) -> list:
    return [rr.TimeColumn("tick", sequence=np.asarray(ticks, dtype=np.int64)),
            rr.TimeColumn("time", duration=np.asarray(times, dtype=np.float64))]


class Telemetry:
    def __init__(self, config: RobotConfig, sink: RerunSink, *, model: mujoco.MjModel | None = None,
                 capacity: int = 4096, batch_period_s: float = 0.05, pose_decimation: int = 20,
                 recording_name: str = "bruce-run"):
        if sink.kind == "off":
            raise ValueError("Telemetry needs a sink other than 'off' (make_telemetry returns None for it)")
        if capacity < 1 or pose_decimation < 1 or not batch_period_s > 0:
            raise ValueError("capacity and pose_decimation must be >= 1 and batch_period_s > 0")
        self.config = config
        self.sink = sink
        self.model = model
        self.capacity = capacity
        self.batch_period_s = batch_period_s
        self.pose_decimation = pose_decimation
        self.recording_name = recording_name
        self.joints = tuple(config.joints)
        self.sent_rows = 0
        self.sent_poses = 0
        self.error: BaseException | None = None  # the first failure of the consumer (or of close's flush)
        self.url: str | None = None  # serve: the URL the gRPC server reported
        self._rows: deque = deque(maxlen=capacity)
        self._poses: deque = deque(maxlen=max(8, capacity // pose_decimation))
        self._events: deque = deque(maxlen=EVENT_CAPACITY)
        # Each counter has a single writer (control thread, or consumer), so `+=` needs no lock.
        self._overflow_rows = self._failed_rows = 0
        self._overflow_poses = self._failed_poses = 0
        self._nan_row = np.full(config.n_joints, np.nan)
        self._recording: rr.RecordingStream | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._started = self._closed = False
        self._bodies: list[tuple[int, str]] = []  # (MuJoCo body id, name) of every body but the world
        self._base_body: int | None = None
        self._last_base: np.ndarray | None = None
        self._row_columns: _EntityColumns | None = None
        self._pose_columns: _EntityColumns | None = None

    @property
    def dropped(self) -> int:
        """Joint rows that never reached rerun: pushed out of a full buffer, or lost in a failed send."""
        return self._overflow_rows + self._failed_rows

    @property
    def dropped_poses(self) -> int:
        return self._overflow_poses + self._failed_poses

    # -- control thread ------------------------------------------------------------------------------------
    def append(self, tick: int, time_s: float, q, qd, q_hat, qd_hat, a, tau_star, tau, period_us: float,
               work_us: float, safety_code: int) -> None:
        """One tick (arrays in config.joints order, not mutated afterwards): a tuple and a deque append."""
        rows = self._rows
        if len(rows) == self.capacity:  # the append below pushes the oldest row out
            self._overflow_rows += 1
        rows.append((tick, time_s, q, qd, q_hat, qd_hat, a, tau_star, tau, period_us, work_us, safety_code))

    def append_pose(self, tick: int, time_s: float, xpos, xquat) -> None:
        """Every body's world pose, (nbody, 3) and (nbody, 4; w, x, y, z), for the 3-D view."""
        poses = self._poses
        if len(poses) == poses.maxlen:
            self._overflow_poses += 1
        poses.append((tick, time_s, xpos, xquat))

    def event(self, tick: int, time_s: float, text: str, level: str = "warn") -> None:
        self._events.append((tick, time_s, text, level))

    # -- lifecycle -----------------------------------------------------------------------------------------
    def start(self) -> None:
        """Open the sink, send the blueprint and static data, start the consumer; TelemetryError on failure."""
        if self._started or self._closed:
            raise TelemetryError(f"rerun sink {self.sink}: telemetry was already started or closed")
        self._started = True
        import rerun as rr  # rerun-sdk loads only when telemetry is used

        try:
            self._recording = rr.RecordingStream(self.recording_name)
            self._open_sink()
            self._recording.send_blueprint(self._blueprint(), make_active=True, make_default=True)
            self._log_static(rr)
            self._prepare_columns(rr)
        except TelemetryError:
            raise
        except Exception as exc:
            raise TelemetryError(f"rerun sink {self.sink}: {type(exc).__name__}: {exc}") from exc
        atexit.register(self.close)  # a process leaving without close() still gets a complete file
        self._thread = threading.Thread(target=self._consume, name="telemetry", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the consumer, send everything still buffered, flush (blocking) and disconnect. Idempotent."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self._stop.set()
        thread, self._thread = self._thread, None
        recording = self._recording
        try:
            if thread is not None:
                thread.join(JOIN_TIMEOUT_S)
            if recording is None or self._row_columns is None or (thread is not None and thread.is_alive()):
                self._discard_pending()  # nothing to send with, or the consumer is stuck inside rerun
            else:
                self._send_pending()
            if recording is not None:
                recording.flush(timeout_sec=1e9 if self.sink.kind == "save" else GRPC_FLUSH_TIMEOUT_S)
        except Exception as exc:
            self._note_error(exc, "flushing at close failed; data not yet delivered may be lost")
        finally:  # also on a second Ctrl-C: the .rrd gets its footer whatever was sent
            self._recording = None
            if recording is not None:
                recording.disconnect()  # writes the .rrd footer, closes connections, stops a gRPC server

    def __enter__(self) -> Telemetry:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- start-up ------------------------------------------------------------------------------------------
    def _open_sink(self) -> None:
        recording, kind, target = self._recording, self.sink.kind, self.sink.target
        if kind == "save":
            path = Path(target).expanduser()
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise TelemetryError(f"rerun sink {self.sink}: cannot create {path.parent}: {exc}") from exc
            recording.save(path)
        elif kind == "connect":
            url = grpc_url(target)
            _probe_viewer(self.sink, url or DEFAULT_VIEWER_URL)  # rerun would wait 5 s, then drop everything
            recording.connect_grpc(url)
        elif kind == "serve":
            port = int(target) if target else DEFAULT_GRPC_PORT
            with socket.socket() as probe:  # rerun only logs a failed bind; find out here, with a clear error
                try:
                    probe.bind(("0.0.0.0", port))
                except OSError as exc:
                    raise TelemetryError(f"rerun sink {self.sink}: cannot listen on port {port}: {exc}") from exc
            self.url = recording.serve_grpc(grpc_port=port)
            print(f"telemetry: rerun gRPC server on port {port} (all interfaces); view it from another machine with"
                  f": rerun rerun+http://{socket.gethostname()}:{port}/proxy  (locally: rerun {self.url})", flush=True)
        elif kind == "spawn":
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
            if sys.platform.startswith("linux") and headless:
                raise TelemetryError(f"rerun sink {self.sink}: no display (DISPLAY and WAYLAND_DISPLAY unset) for a "
                                     "viewer; on a headless machine use --rerun serve or --rerun save=PATH")
            recording.spawn()  # may wait up to ~10 s for the viewer to come up
        else:
            raise TelemetryError(f"rerun sink {self.sink}: unknown kind {kind!r}")

    def _blueprint(self):
        import rerun.blueprint as rrb

        def per_joint(leaf: str):
            views = [rrb.TimeSeriesView(origin=f"joints/{name}/{leaf}", name=f"{name} {leaf}") for name in self.joints]
            return rrb.Grid(*views, grid_columns=max(1, math.ceil(len(views) / 2)), name=f"{leaf}s")

        loop = rrb.Vertical(
            rrb.TimeSeriesView(origin="loop", name="loop timing (µs)"),
            rrb.TimeSeriesView(origin="/", contents=["safety/state", "telemetry/dropped"], name="safety / drops"),
            rrb.TextLogView(origin="safety/events", name="safety events"),
        )
        overview = loop
        if self.model is not None:
            # All of the past is in range so the trajectory accumulates; transforms stay latest-at, geoms static.
            past = [rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                                         end=rrb.TimeRangeBoundary.cursor_relative()) for timeline in ("tick", "time")]
            overview = rrb.Horizontal(rrb.Spatial3DView(origin="world", name="robot", time_ranges=past), loop,
                                      column_shares=[3, 2])
        tabs = rrb.Tabs(rrb.Vertical(overview, name="robot"), per_joint("position"), per_joint("velocity"),
                        per_joint("torque"))
        return rrb.Blueprint(tabs, rrb.TimePanel(timeline="time"))

    def _log_static(self, rr) -> None:
        log = self._recording.log
        for name in self.joints:
            for leaf, (names, colours) in SERIES.items():
                log(f"joints/{name}/{leaf}", rr.SeriesLines(names=names, colors=colours), static=True, strict=True)
        for path, label in LOOP_SERIES.items():
            log(path, rr.SeriesLines(names=[label]), static=True, strict=True)
        if self.model is not None:
            log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, strict=True)
            self._log_geometry(rr, self.model)

    def _log_geometry(self, rr, model: mujoco.MjModel) -> None:
        """Each body's primitives, static, in the body's frame; the per-pose transforms place the bodies."""
        import mujoco

        geom = mujoco.mjtGeom
        names = [model.body(b).name or f"body{b}" for b in range(model.nbody)]
        self._bodies = [(b, names[b]) for b in range(1, model.nbody)]  # body 0 is the world itself
        self._base_body = names.index("base") if "base" in names else None
        by_body: dict[int, dict[int, list]] = {}
        for g in range(model.ngeom):
            kind, body = int(model.geom_type[g]), int(model.geom_bodyid[g])
            size, pos, quat = model.geom_size[g].copy(), model.geom_pos[g].copy(), _xyzw(model.geom_quat[g])
            rgba = np.round(model.geom_rgba[g] * 255).astype(np.uint8)
            if kind == geom.mjGEOM_PLANE:
                half = [s if s > 0 else FLOOR_HALF_SIZE_M for s in size[:2]]
                floor = rr.Boxes3D(half_sizes=[[half[0], half[1], 0.001]], centers=[pos - [0.0, 0.0, 0.001]],
                                   quaternions=[quat], colors=[rgba], fill_mode="solid")
                self._recording.log("world/floor", floor, static=True, strict=True)
                continue
            if body == 0 or kind not in (geom.mjGEOM_BOX, geom.mjGEOM_SPHERE, geom.mjGEOM_ELLIPSOID,
                                         geom.mjGEOM_CAPSULE, geom.mjGEOM_CYLINDER):
                continue
            if kind == geom.mjGEOM_CAPSULE:
                # MuJoCo centres a capsule on its position; rerun starts one at its translation, along local +z.
                w, x, y, z = model.geom_quat[g]
                pos = pos - size[1] * np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
            by_body.setdefault(body, {}).setdefault(kind, []).append((size, pos, quat, rgba))
        for body, by_kind in by_body.items():
            parts = []
            for kind, geoms in by_kind.items():
                sizes, centers, quats, colors = (np.array(column) for column in zip(*geoms, strict=True))
                common = dict(quaternions=quats, colors=colors, fill_mode="solid")
                if kind == geom.mjGEOM_BOX:
                    parts.append(rr.Boxes3D(half_sizes=sizes, centers=centers, **common))
                elif kind in (geom.mjGEOM_SPHERE, geom.mjGEOM_ELLIPSOID):
                    half = np.repeat(sizes[:, :1], 3, axis=1) if kind == geom.mjGEOM_SPHERE else sizes
                    parts.append(rr.Ellipsoids3D(half_sizes=half, centers=centers, **common))
                elif kind == geom.mjGEOM_CAPSULE:
                    parts.append(rr.Capsules3D(lengths=2 * sizes[:, 1], radii=sizes[:, 0], translations=centers,
                                               **common))
                else:  # cylinder: centred in both, size = (radius, half-length)
                    parts.append(rr.Cylinders3D(lengths=2 * sizes[:, 1], radii=sizes[:, 0], centers=centers,
                                                **common))
            self._recording.log(f"world/robot/{names[body]}", *parts, static=True, strict=True)

    def _prepare_columns(self, rr) -> None:
        row_entities = [f"joints/{name}/{leaf}" for name in self.joints for leaf in SERIES] + list(LOOP_SERIES)
        self._row_columns = _EntityColumns(rr, rr.Scalars.columns(scalars=[0.0]), row_entities)
        if self._bodies:
            sample = rr.Transform3D.columns(translation=[[0.0, 0.0, 0.0]], quaternion=[[0.0, 0.0, 0.0, 1.0]])
            self._pose_columns = _EntityColumns(rr, sample, [f"world/robot/{name}" for _, name in self._bodies])

    # -- consumer thread -----------------------------------------------------------------------------------
    def _consume(self) -> None:
        while not self._stop.wait(self.batch_period_s):
            self._send_pending()

    def _discard_pending(self) -> None:
        self._failed_rows += len(_drain(self._rows))
        self._failed_poses += len(_drain(self._poses))
        self._events.clear()

    def _send_pending(self) -> None:
        """Drain all buffers and send them; a failure drops (and counts) that batch but never ends the thread."""
        import rerun as rr

        rows, poses, events = _drain(self._rows), _drain(self._poses), _drain(self._events)
        if rows:
            try:
                self._send_rows(rows)
                self.sent_rows += len(rows)
            except Exception as exc:
                self._failed_rows += len(rows)
                self._note_error(exc, f"sending {len(rows)} rows failed; they count as dropped, later batches "
                                      "are still tried")
        if poses and self._pose_columns is not None:
            try:
                self._send_poses(rr, poses)
                self.sent_poses += len(poses)
            except Exception as exc:
                self._failed_poses += len(poses)
                self._note_error(exc, f"sending {len(poses)} poses failed; later batches are still tried")
        if events:
            try:
                self._send_events(rr, events)
            except Exception as exc:
                self._note_error(exc, f"sending {len(events)} events failed")

    def _note_error(self, exc: BaseException, what: str) -> None:
        if self.error is None:
            self.error = exc
            print(f"telemetry: rerun sink {self.sink}: {what} ({type(exc).__name__}: {exc})", file=sys.stderr,
                  flush=True)

    def _stack(self, column, what: str, fill_none: bool = False) -> np.ndarray:
        if fill_none:
            column = [self._nan_row if v is None else v for v in column]
        stacked = np.array(column, dtype=np.float64)
        if stacked.shape != (len(column), len(self.joints)):
            raise ValueError(f"{what}: expected rows of {len(self.joints)} values, got an array of {stacked.shape}")
        return stacked

    def _send_rows(self, rows: list) -> None:
        ticks, times, q, qd, q_hat, qd_hat, a, tau_star, tau, period, work, code = zip(*rows, strict=True)
        # (row, joint, series): joint j's slice [:, j] is the (n, k) column of its entity.
        position = np.stack((self._stack(q, "q"), self._stack(q_hat, "q_hat", True), self._stack(a, "a")), axis=-1)
        velocity = np.stack((self._stack(qd, "qd"), self._stack(qd_hat, "qd_hat", True)), axis=-1)
        torque = np.stack((self._stack(tau_star, "tau_star"), self._stack(tau, "tau")), axis=-1)
        out = self._row_columns
        columns = out.index_arrays(ticks, times)
        for j in range(len(self.joints)):
            columns += [out.scalar_lists(position[:, j]), out.scalar_lists(velocity[:, j]),
                        out.scalar_lists(torque[:, j])]
        for values in (period, work, code, (self.dropped,) * len(rows)):
            columns.append(out.scalar_lists(np.asarray(values, dtype=np.float64)[:, None]))
        self._recording.send_record_batch(out.batch(columns))

    def _send_poses(self, rr, poses: list) -> None:
        ticks, times, xpos, xquat = zip(*poses, strict=True)
        positions = np.array(xpos, dtype=np.float32)
        rotations = np.ascontiguousarray(_xyzw(np.array(xquat, dtype=np.float32)))
        out = self._pose_columns
        columns = out.index_arrays(ticks, times)
        for body, _ in self._bodies:
            for field in out.components:  # in the sample's order
                values = {"Transform3D:translation": positions, "Transform3D:quaternion": rotations}[field.name]
                columns.append(out.vector_lists(np.ascontiguousarray(values[:, body]), field.type))
        self._recording.send_record_batch(out.batch(columns))
        if self._base_body is not None:
            base = positions[:, self._base_body].astype(np.float64)
            segment = base if self._last_base is None else np.vstack((self._last_base, base))
            self._last_base = base[-1].copy()
            self._recording.send_columns(
                "world/base_trajectory", indexes=_time_columns(rr, ticks[-1:], times[-1:]),
                columns=rr.LineStrips3D.columns(strips=[segment], radii=[TRAJECTORY_RADIUS_M]), strict=True)

    def _send_events(self, rr, events: list) -> None:
        ticks, times, texts, levels = zip(*events, strict=True)
        levels = [TEXT_LEVELS.get(str(level).lower(), str(level).upper()) for level in levels]
        self._recording.send_columns("safety/events", indexes=_time_columns(rr, ticks, times),
                                     columns=rr.TextLog.columns(text=list(texts), level=levels), strict=True)
