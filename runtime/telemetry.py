"""Rerun telemetry for the 1 kHz loop: a cheap write into shared memory on the control thread; batching and all
rerun I/O in a separate process, so rerun never holds the control process's GIL.

Why a process: a consumer *thread* in the control process held the GIL for ~1.5 ms per batch (pyarrow and rerun
calls), and the control thread stalled mid-tick waiting for it (tick work p99 330 -> 510-640 µs at 1 kHz, more
late ticks; a shorter `sys.setswitchinterval` did not help). A child process has its own interpreter and GIL.

Shared memory: one block, a file in /dev/shm (the temp dir where there is none) mapped by both processes and
unlinked as soon as the child has mapped it, so nothing is left behind however either process ends (no
multiprocessing resource tracker, no names to clean up). It holds three single-producer, single-consumer rings,
each with one slot more than its capacity (the slot the writer may be filling), and two counter blocks, each
part on its own cache lines:
    rows    float64 [capacity + 1, 2 + 7 * n_joints + 3]: tick, time, q, qd, q_hat (NaN when None), qd_hat, a,
            tau_star, tau, period_us, work_us, safety_code
    poses   float64 [max(8, capacity // pose_decimation) + 1, 2 + 7 * nbody]: tick, time, xpos, xquat (w, x, y, z)
    events  EVENT_CAPACITY + 1 fixed-size slots: tick, time, level, UTF-8 text (cut at EVENT_TEXT_BYTES bytes)
    counters written only by the parent (rows/poses/events written, rows rejected), and only by the child
            (rows/poses read, sent, overwritten before they were read, lost in a failed send)
`append` writes row n into slot n % (capacity + 1) (element and slice stores into a view made once per slot,
cheaper than one np.concatenate, which builds temporary arrays) and then stores n + 1 in the rows-written counter:
~1.5-2 µs in a paced loop, no allocation, no lock, never blocks. The child keeps its own read position; rows the
writer lapped before they were read are counted as dropped (drop-oldest: the newest `capacity` rows survive), and
after copying a range it re-reads the counter and drops the rows whose slots the writer may have started to
overwrite during the copy (seqlock style), so a torn row is never sent. Memory-order assumption: the row's stores
become visible to the other process before the counter's store, and the child's loads of the counter and of the
rows are not reordered; x86-64 (TSO) guarantees both, and aligned 8-byte stores are atomic. On a weakly ordered
CPU (aarch64) a row could in rare cases be read before all of it is visible: wrong telemetry, never a wrong
command. A row that does not fit the layout (an array that does not broadcast to n_joints values) is rejected in
`append`, counted in `dropped` and reported once in `error`/stderr; it never raises into the loop.

The child is a fresh interpreter started with subprocess (fork + exec, as multiprocessing's 'spawn': forking a
process with threads is unsafe; not multiprocessing itself, whose spawn re-imports the caller's __main__ and so
re-runs scripts without a main guard). It talks to the parent over a socketpair (multiprocessing Connection): the
parent sends the layout, sink and static geometry (a MuJoCo model cannot be pickled; its body names and geom
arrays are extracted in the parent, the child does not even import mujoco), the child answers ready (with the
serve URL) or failed, so `start()` raises TelemetryError naming the sink as before. It ignores
SIGINT/SIGTERM/SIGHUP (Ctrl-C goes to the whole process group; the parent handles it, then calls close()), keeps
off the last allowed CPU (where `runtime.realtime` pins the loop) when there are others, drains the rings every
`batch_period_s` (50 ms, so they stay small) and sends what it drained every `chunk_s` (FILE_CHUNK_S = 2 s to a
file, LIVE_CHUNK_S = 0.2 s to a viewer) columnar on its own `RecordingStream`, indexed by a `tick` sequence and a
`time` duration timeline only (no `log_time`/`log_tick`, on purpose). close() sends stop; the child
drains what is left, flushes and disconnects (a save= .rrd gets its footer), reports done and exits; the parent
waits up to CLOSE_TIMEOUT_S and kills it only if it hangs. If the parent dies without close() (SIGKILL), the child
sees the socket's EOF (or its parent pid change), sends what it has, flushes and exits; an atexit hook still
closes cleanly when the parent leaves without close(). Costs: start() takes ~0.5 s (a new interpreter importing
rerun and pyarrow; ~1 s on a cold disk cache) once, before the loop; close() ~0.15 s. Measured
(bench/bench_telemetry.py, 20 s real-time mock sessions with the PINN): tick work p99 with telemetry on within
noise of off (310-365 vs 312-322 µs; the consumer thread gave 618-644 µs on the same machine). Memory: rerun's
buffers live in the child, so `mlockall(MCL_FUTURE)` in the control process (runtime.realtime, after start()) no
longer locks them; the parent only maps the rings (a few MB). `dropped` etc. are read live from the child's
counters.

Size and memory, for runs that last all day. Besides the values, rerun stores a row id and the index columns for
every row of every entity, writes each chunk (one entity's rows of one send) as an Arrow message with its own
schema (~2 kB in the file), and for a file's footer keeps a manifest entry per chunk in memory until the file is
closed. Sending 34 entities at 1 kHz and the poses every 50 ms made ~900 chunks/s: the telemetry process grew
~75 MB/min (the manifest) and the file ~140 MB/min. Hence: rows go out in chunks of `chunk_s` (~13 chunks/s to a
file); the joints are one entity each (12 entities per row instead of 34); the safety code and the drop count go
out only where they change; poses at POSE_HZ (~30 Hz: the loop calls append_pose every `pose_decimation` =
ceil(loop_hz / POSE_HZ) ticks) and the base trajectory as one segment per chunk. Scalars stay float64: rerun
rejects other types for them (`rerun rrd verify`). A save= recording starts a new part when the current one
reaches `max_mb` (DEFAULT_MAX_MB, 1000 MB): PATH, then PATH-stem.001.rrd, .002, ... Each part gets its footer
when the next begins and carries the blueprint and the static data, so it opens on its own (or all together: one
recording id); the manifest goes with each part, so memory stays bounded however long the run. The size is read
after a flush before each chunk, so a part ends at most one chunk and its footer past max_mb. `keep=N` deletes
all but the newest N parts (disk <= N * max_mb); parts of an earlier recording at the same PATH are deleted at
start, as PATH itself is overwritten. serve keeps at most `buffer_mb` (DEFAULT_BUFFER_MB, 256 MB) of history for
viewers that connect late (rerun's default is 1 GiB). Measured figures and the commands: docs/telemetry.md.

Why one `send_record_batch` per batch instead of one `send_columns` per entity: both send the same Arrow chunks,
but `send_columns` costs ~50 µs of Python per call in rerun 0.41 (12 row entities and 11 bodies per chunk). The
record batch
carries the same field types and `rerun:*` metadata (copied from a chunk rerun itself builds with
`Chunk.from_columns`, plus `rerun:entity_path` per field), and rerun splits it into one chunk per entity. Rare
data (events, the trajectory segment) goes through `send_columns`.

Entity layout (Scalars with several series per row):
    joints/<joint>            [q, q_hat, a, qd, qd_hat, tau_star, tau] every tick; q_hat/qd_hat are NaN in rows
                              without a PINN estimate
    loop/period_us, loop/work_us   every tick
    safety/state (the int code), telemetry/dropped (running count at send time): the rows where either changes,
                              the row before (so the plot steps), and each chunk's first and last rows
    safety/events             TextLog
    world                     ViewCoordinates RIGHT_HAND_Z_UP (static); world/floor: the model's plane as a flat box
    world/robot/<body>        static geoms of the body in its own frame + a Transform3D per pose row (world frame)
    world/base_trajectory     LineStrips3D, one segment per chunk of pose rows; the 3-D view shows all of the past
A default blueprint (tabs: robot + loop, positions, velocities, torques; each per-joint plot shows its quantity's
series of joints/<joint> through a SeriesLines.visible_series override, the others stay in its legend) is sent
at start and with each new part. Without a model there is no 3-D view and append_pose does nothing.

Sinks (`--rerun`): spawn | connect[=ADDR] | serve[=PORT][,buffer_mb=MB] | save=PATH[,max_mb=MB][,keep=N] | off; a
trailing `,key=value` is an option (a comma otherwise stays in the path), max_mb=0 writes one file. ADDR is
host:port or a full rerun+http(s)://host:port/proxy URL (default rerun+http://127.0.0.1:9876/proxy); start() fails
at once when nothing listens there. `sent_rows` counts rows handed to rerun; a viewer that goes away mid-run loses
them unseen.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import math
import mmap
import os
import pickle
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

import numpy as np

if TYPE_CHECKING:
    import mujoco
    import pyarrow as pa

    from bruce_hw.config import RobotConfig

DEFAULT_MAX_MB = 1000.0     # save=: a new part starts when the current file reaches this size
DEFAULT_BUFFER_MB = 256     # serve: history the gRPC server keeps for viewers that connect late
SINK_HELP = ("where telemetry goes: spawn (a local viewer), connect[=HOST:PORT|URL] (a running viewer), "
             "serve[=PORT][,buffer_mb=MB] (a gRPC server a laptop viewer attaches to; keeps the newest MB for late "
             f"viewers, default {DEFAULT_BUFFER_MB}), save=PATH[,max_mb=MB][,keep=N] (an .rrd file; continues in "
             f"PATH-stem.001.rrd, .002, ... each time the file reaches MB, default {DEFAULT_MAX_MB:g}, 0: one file; "
             "keep=N: only the newest N files stay on disk), off")
SINK_KINDS = ("spawn", "connect", "serve", "save", "off")
ACCEPTED = ("expected one of spawn, connect, connect=HOST:PORT|URL, serve[=PORT][,buffer_mb=MB], "
            "save=PATH[,max_mb=MB][,keep=N], off")
SINK_OPTIONS = {"save": ("max_mb", "keep"), "serve": ("buffer_mb",)}
OPTION_ITEM = re.compile(r"[A-Za-z_]\w*=")  # a trailing ",key=value" is an option, not part of a path
DEFAULT_GRPC_PORT = 9876
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"  # where rerun connects without ADDR
VIEWER_PROBE_TIMEOUT_S = 2.0
EVENT_CAPACITY = 256
EVENT_TEXT_BYTES = 240
EVENT_LEVEL_BYTES = 16
POSE_HZ = 30.0              # 3-D poses (and the base trajectory's points): display rate, not loop rate
FILE_CHUNK_S = 2.0          # save=: each entity's rows go out in chunks of this many seconds
LIVE_CHUNK_S = 0.2          # spawn/connect/serve: the viewer's latency (rerun's own batching default)
GRPC_FLUSH_TIMEOUT_S = 5.0  # close() waits at most this long for an unreachable viewer; a file is always flushed
START_TIMEOUT_S = 60.0      # a new interpreter importing rerun (~1 s), plus up to ~10 s for a spawned viewer
CLOSE_TIMEOUT_S = 30.0      # a child stuck in rerun (blocked channel) is killed after this long
EXIT_TIMEOUT_S = 5.0        # after its last message, for the child's interpreter to exit
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
LOOP_SERIES = {"loop/period_us": "period", "loop/work_us": "work"}  # every row
STEP_SERIES = {"safety/state": "safety code", "telemetry/dropped": "dropped rows"}  # rows where they change
FLOOR_HALF_SIZE_M = 2.0  # MuJoCo planes of size 0 are infinite; show this much of them
TRAJECTORY_RADIUS_M = 0.003

# Counter blocks (int64, one cache line each). Written by the parent only:
ROWS_WRITTEN, POSES_WRITTEN, EVENTS_WRITTEN, ROWS_REJECTED = range(4)
# Written by the child only:
ROWS_READ, ROWS_SENT, ROWS_OVERRUN, ROWS_FAILED, POSES_READ, POSES_SENT, POSES_OVERRUN, POSES_FAILED = range(8)
COUNTERS = 8
EVENT_DTYPE = np.dtype([("tick", "<i8"), ("time", "<f8"), ("level", f"S{EVENT_LEVEL_BYTES}"),
                        ("text", f"S{EVENT_TEXT_BYTES}")])
ROW_BLOCKS = 7  # q, qd, q_hat, qd_hat, a, tau_star, tau
CHILD_BOOT = ("import json, sys; sys.path[:0] = json.loads(sys.argv[2]); "
              f"from {__name__} import _child_main; _child_main(int(sys.argv[1]))")


class TelemetryError(RuntimeError):
    """Telemetry could not be started; the message names the sink."""


@dataclass(frozen=True)
class RerunSink:
    kind: str
    target: str | None = None  # connect: ADDR (None: rerun's default); serve: PORT (None: 9876); save: PATH
    max_mb: float | None = None   # save: rotation size (None: DEFAULT_MAX_MB; 0: one file)
    keep: int | None = None       # save: parts kept on disk (None: all)
    buffer_mb: int | None = None  # serve: the server's history (None: DEFAULT_BUFFER_MB)

    def __str__(self) -> str:
        text = self.kind if self.target is None else f"{self.kind}={self.target}"
        for key in ("max_mb", "keep", "buffer_mb"):
            value = getattr(self, key)
            if value is not None:
                text += f",{key}={value:g}"
        return text


def parse_sink(text: str) -> RerunSink:
    """`spawn`, `connect`, `connect=ADDR`, `serve[=PORT][,buffer_mb=MB]`, `save=PATH[,max_mb=MB][,keep=N]` or
    `off`; ValueError (one line naming the value or option) otherwise."""
    parts = text.strip().split(",")
    n = len(parts)
    while n > 1 and OPTION_ITEM.match(parts[n - 1]):
        n -= 1
    kind, sep, target = ",".join(parts[:n]).partition("=")
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
    options: dict[str, float | int] = {}
    for item in parts[n:]:
        key, _, value = item.partition("=")
        allowed = SINK_OPTIONS.get(kind, ())
        if key not in allowed:
            takes = f"{kind} takes " + (", ".join(f"{k}=" for k in allowed) if allowed else "no options")
            raise ValueError(f"rerun sink {text!r}: unknown option {key!r} ({takes}): {ACCEPTED}")
        if key in options:
            raise ValueError(f"rerun sink {text!r}: option {key} given twice")
        options[key] = _sink_option(text, key, value)
    if options.get("keep") is not None and options.get("max_mb") == 0:
        raise ValueError(f"rerun sink {text!r}: keep= needs rotation, but max_mb=0 writes one file")
    return RerunSink(kind, target if sep else None, **options)


def _sink_option(text: str, key: str, value: str) -> float | int:
    """One option's value, checked; ValueError naming the option otherwise."""
    wants = {"max_mb": "a number of megabytes >= 0 (0: one file, never rotated)",
             "keep": "an integer >= 1 (how many of the newest parts stay on disk)",
             "buffer_mb": "an integer number of megabytes >= 1"}[key]
    try:
        number = float(value) if key == "max_mb" else int(value)
    except ValueError:
        number = None
    if number is None or not math.isfinite(number) or number < (0 if key == "max_mb" else 1):
        raise ValueError(f"rerun sink {text!r}: {key} must be {wants}, got {value!r}")
    return number


def part_path(path: str | Path, part: int) -> Path:
    """The file of part `part` of a rotated save=PATH recording: PATH itself, then PATH-stem.001.rrd, ..."""
    path = Path(path)
    return path if part == 0 else path.with_name(f"{path.stem}.{part:03d}{path.suffix}")


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


def _xyzw(wxyz: np.ndarray) -> np.ndarray:
    return wxyz[..., [1, 2, 3, 0]]  # MuJoCo quaternions are (w, x, y, z); rerun's are (x, y, z, w)


def _utf8(text: str, limit: int) -> bytes:
    """`text` as UTF-8, cut to at most `limit` bytes on a character boundary."""
    data = text.encode("utf-8", "replace")
    return data if len(data) <= limit else data[:limit].decode("utf-8", "ignore").encode()


def _geometry(model: mujoco.MjModel) -> dict:
    """What the child needs of the model, picklable: body names and the displayable geoms' arrays."""
    import mujoco

    geom = mujoco.mjtGeom
    kinds = {int(geom.mjGEOM_PLANE): "plane", int(geom.mjGEOM_BOX): "box", int(geom.mjGEOM_SPHERE): "sphere",
             int(geom.mjGEOM_ELLIPSOID): "ellipsoid", int(geom.mjGEOM_CAPSULE): "capsule",
             int(geom.mjGEOM_CYLINDER): "cylinder"}
    geoms = [(kinds[int(model.geom_type[g])], int(model.geom_bodyid[g]), np.array(model.geom_size[g]),
              np.array(model.geom_pos[g]), np.array(model.geom_quat[g]), np.array(model.geom_rgba[g]))
             for g in range(model.ngeom) if int(model.geom_type[g]) in kinds]
    return {"names": [model.body(b).name or f"body{b}" for b in range(model.nbody)], "geoms": geoms}


class _Layout:
    """Where each ring and counter block lies in the shared block (each part starts on a 64-byte line). A ring
    has one slot more than its capacity: the slot the writer may be filling, so `capacity` rows stay readable."""

    def __init__(self, n_joints: int, capacity: int, nbody: int, pose_capacity: int):
        self.row_width = 2 + ROW_BLOCKS * n_joints + 3
        self.pose_width = 2 + 7 * nbody
        self.parts = []
        offset = 0
        for name, dtype, shape in (("ctrl", np.int64, (COUNTERS,)), ("stats", np.int64, (COUNTERS,)),
                                   ("rows", np.float64, (capacity + 1, self.row_width)),
                                   ("poses", np.float64, (pose_capacity + 1, self.pose_width)),
                                   ("events", EVENT_DTYPE, (EVENT_CAPACITY + 1,))):
            dtype = np.dtype(dtype)
            self.parts.append((name, dtype, shape, offset))
            offset += -(-dtype.itemsize * math.prod(shape) // 64) * 64
        self.size = offset

    def views(self, buffer) -> dict[str, np.ndarray]:
        return {name: np.frombuffer(buffer, dtype, count=math.prod(shape), offset=offset).reshape(shape)
                for name, dtype, shape, offset in self.parts}


def _shm_dir() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()


def _picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


class Telemetry:
    def __init__(self, config: RobotConfig, sink: RerunSink, *, model: mujoco.MjModel | None = None,
                 capacity: int = 4096, batch_period_s: float = 0.05, chunk_s: float | None = None,
                 pose_decimation: int | None = None, recording_name: str = "bruce-run"):
        if sink.kind == "off":
            raise ValueError("Telemetry needs a sink other than 'off' (make_telemetry returns None for it)")
        if pose_decimation is None:
            pose_decimation = max(1, math.ceil(config.loop_hz / POSE_HZ))
        if chunk_s is None:
            chunk_s = FILE_CHUNK_S if sink.kind == "save" else LIVE_CHUNK_S
        if capacity < 1 or pose_decimation < 1 or not batch_period_s > 0 or not chunk_s >= 0:
            raise ValueError("capacity and pose_decimation must be >= 1, batch_period_s > 0 and chunk_s >= 0")
        self.config = config
        self.sink = sink
        self.model = model
        self.capacity = capacity
        self.batch_period_s = batch_period_s
        self.chunk_s = chunk_s
        self.pose_decimation = pose_decimation  # the loop calls append_pose every this many ticks
        self.recording_name = recording_name
        self.joints = tuple(config.joints)
        self.url: str | None = None  # serve: the URL the gRPC server reported
        self._error: BaseException | None = None
        self._geometry = None if model is None else _geometry(model)
        self._pose_capacity = max(8, capacity // pose_decimation)
        nbody = 0 if self._geometry is None else len(self._geometry["names"])
        self._layout = _Layout(len(self.joints), capacity, nbody, self._pose_capacity)
        # Private memory until start() copies it into the shared block: rows appended before start() go along.
        self._memory: bytearray | mmap.mmap = bytearray(self._layout.size)
        self._bind(self._memory)
        n_joints, self._row_slot_count, self._pose_slot_count = len(self.joints), capacity + 1, self._pose_capacity + 1
        self._nan_row = np.full(n_joints, np.nan)
        self._row_blocks = tuple(slice(2 + k * n_joints, 2 + (k + 1) * n_joints) for k in range(ROW_BLOCKS))
        self._n_rows = self._n_poses = self._n_events = 0
        self._rejected_rows = self._rejected_poses = 0
        self._final: tuple[int, int, int, int] | None = None  # sent/dropped rows, sent/dropped poses after close
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._started = self._closed = False

    def _bind(self, buffer) -> None:
        views = self._layout.views(buffer)
        self._ctrl, self._stats = views["ctrl"], views["stats"]
        self._event_ring = views["events"]
        # One view per slot, made once: indexing a list is cheaper than making a view per call.
        self._row_slots = list(views["rows"])
        nbody = self._layout.pose_width // 7
        self._pose_slots = [(slot[:2], slot[2:2 + 3 * nbody].reshape(nbody, 3), slot[2 + 3 * nbody:].reshape(nbody, 4))
                            for slot in views["poses"]]

    # -- counters, live from the child until close() -------------------------------------------------------
    @property
    def sent_rows(self) -> int:
        return self._final[0] if self._final else int(self._stats[ROWS_SENT])

    def _dropped_live(self, written: int, rejected: int, read: int, overrun: int, failed: int, capacity: int) -> int:
        """Rejected here, overwritten before the child read them, lost in a failed send, or already lapped."""
        stats = self._stats
        unread = written - int(stats[read])
        return rejected + int(stats[overrun]) + int(stats[failed]) + max(0, unread - capacity)

    @property
    def dropped(self) -> int:
        """Joint rows that never reached rerun: overwritten in a full ring, rejected, or lost in a failed send."""
        if self._final:
            return self._final[1]
        return self._dropped_live(self._n_rows, self._rejected_rows, ROWS_READ, ROWS_OVERRUN, ROWS_FAILED,
                                  self.capacity)

    @property
    def sent_poses(self) -> int:
        return self._final[2] if self._final else int(self._stats[POSES_SENT])

    @property
    def dropped_poses(self) -> int:
        if self._final:
            return self._final[3]
        return self._dropped_live(self._n_poses, self._rejected_poses, POSES_READ, POSES_OVERRUN, POSES_FAILED,
                                  self._pose_capacity)

    @property
    def error(self) -> BaseException | None:
        """The first failure: a rejected row here, or one the telemetry process reported (sending, flushing)."""
        self._receive(0.0)
        return self._error

    # -- control thread ------------------------------------------------------------------------------------
    def append(self, tick: int, time_s: float, q, qd, q_hat, qd_hat, a, tau_star, tau, period_us: float,
               work_us: float, safety_code: int) -> None:
        """One tick (arrays in config.joints order): copied into the shared ring, then the counter is bumped."""
        n = self._n_rows
        slot = self._row_slots[n % self._row_slot_count]
        b0, b1, b2, b3, b4, b5, b6 = self._row_blocks
        nan = self._nan_row
        try:  # element and slice stores: cheaper than one concatenate (no temporary arrays), measured cold
            slot[0] = tick
            slot[1] = time_s
            slot[b0] = q
            slot[b1] = qd
            slot[b2] = nan if q_hat is None else q_hat
            slot[b3] = nan if qd_hat is None else qd_hat
            slot[b4] = a
            slot[b5] = tau_star
            slot[b6] = tau
            slot[-3] = period_us
            slot[-2] = work_us
            slot[-1] = safety_code
        except (ValueError, TypeError) as exc:  # a half-written slot is harmless: the child reads rows < n only,
            self._reject_row(exc)               # and the row this slot held is already out of its readable range
            return
        self._n_rows = n = n + 1
        self._ctrl[ROWS_WRITTEN] = n  # after the row: the child reads rows below this count only

    def append_pose(self, tick: int, time_s: float, xpos, xquat) -> None:
        """Every body's world pose, (nbody, 3) and (nbody, 4; w, x, y, z), for the 3-D view (no model: ignored)."""
        if self._geometry is None:
            return
        n = self._n_poses
        index, positions, quaternions = self._pose_slots[n % self._pose_slot_count]
        try:
            index[0] = tick
            index[1] = time_s
            positions[...] = xpos
            quaternions[...] = xquat
        except (ValueError, TypeError) as exc:
            self._rejected_poses += 1
            self._note_error(exc, "append_pose: poses that do not match the model's bodies are rejected; they "
                                  "count as dropped")
            return
        self._n_poses = n = n + 1
        self._ctrl[POSES_WRITTEN] = n

    def event(self, tick: int, time_s: float, text: str, level: str = "warn") -> None:
        """A line for safety/events (rare); the text is cut at EVENT_TEXT_BYTES bytes of UTF-8."""
        n = self._n_events
        self._event_ring[n % (EVENT_CAPACITY + 1)] = (tick, time_s, _utf8(str(level), EVENT_LEVEL_BYTES),
                                                _utf8(str(text), EVENT_TEXT_BYTES))
        self._n_events = n = n + 1
        self._ctrl[EVENTS_WRITTEN] = n

    def _reject_row(self, exc: BaseException) -> None:
        self._rejected_rows += 1
        self._ctrl[ROWS_REJECTED] = self._rejected_rows
        self._note_error(exc, f"append: rows that do not fit {len(self.joints)} joints are rejected; they count "
                              "as dropped, later rows are still sent")

    def _note_error(self, exc: BaseException, what: str) -> None:
        if self._error is None:
            self._error = exc
            print(f"telemetry: rerun sink {self.sink}: {what} ({type(exc).__name__}: {exc})", file=sys.stderr,
                  flush=True)

    # -- lifecycle -----------------------------------------------------------------------------------------
    def start(self) -> None:
        """Check the sink, start the telemetry process and wait until it has opened the sink and sent the
        blueprint and static data; TelemetryError on failure."""
        if self._started or self._closed:
            raise TelemetryError(f"rerun sink {self.sink}: telemetry was already started or closed")
        self._started = True
        target = self._check_sink()
        try:
            self._spawn(target)
        except TelemetryError:
            self._end_child(kill=True)
            raise
        except Exception as exc:
            self._end_child(kill=True)
            raise TelemetryError(f"rerun sink {self.sink}: {type(exc).__name__}: {exc}") from exc
        atexit.register(self.close)  # a process leaving without close() still gets a complete file
        if self.sink.kind == "serve":
            port = self.sink.target or DEFAULT_GRPC_PORT
            print(f"telemetry: rerun gRPC server on port {port} (all interfaces); view it from another machine with"
                  f": rerun rerun+http://{socket.gethostname()}:{port}/proxy  (locally: rerun {self.url})", flush=True)

    def close(self) -> None:
        """Stop the telemetry process after it has sent everything buffered, flushed and disconnected (waits up
        to CLOSE_TIMEOUT_S, then kills it). Idempotent; rows never sent count as dropped afterwards."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self._end_child(kill=False)
        sent_rows, sent_poses = int(self._stats[ROWS_SENT]), int(self._stats[POSES_SENT])
        self._final = (sent_rows, self._n_rows + self._rejected_rows - sent_rows,
                       sent_poses, self._n_poses + self._rejected_poses - sent_poses)

    def __enter__(self) -> Telemetry:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _check_sink(self) -> str | None:
        """What can be checked here, with a clear error, before a process is started; the child's sink target."""
        kind, target = self.sink.kind, self.sink.target
        if kind == "save":
            path = Path(target).expanduser().absolute()
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                stale = re.compile(re.escape(path.stem) + r"\.\d{3,}" + re.escape(path.suffix))
                for old in path.parent.iterdir():  # later parts of an earlier recording at PATH, as PATH itself
                    if stale.fullmatch(old.name) and old.is_file():  # is overwritten
                        old.unlink()
            except OSError as exc:
                raise TelemetryError(f"rerun sink {self.sink}: cannot create {path.parent}: {exc}") from exc
            return str(path)
        if kind == "connect":
            url = grpc_url(target)
            _probe_viewer(self.sink, url or DEFAULT_VIEWER_URL)  # rerun would wait 5 s, then drop everything
            return url
        if kind == "serve":
            port = int(target) if target else DEFAULT_GRPC_PORT
            with socket.socket() as probe:  # rerun only logs a failed bind; find out here, with a clear error
                try:
                    probe.bind(("0.0.0.0", port))
                except OSError as exc:
                    raise TelemetryError(f"rerun sink {self.sink}: cannot listen on port {port}: {exc}") from exc
            return str(port)
        if kind == "spawn":
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
            if sys.platform.startswith("linux") and headless:
                raise TelemetryError(f"rerun sink {self.sink}: no display (DISPLAY and WAYLAND_DISPLAY unset) for a "
                                     "viewer; on a headless machine use --rerun serve or --rerun save=PATH")
            return None
        raise TelemetryError(f"rerun sink {self.sink}: unknown kind {kind!r}")

    def _spawn(self, target: str | None) -> None:
        layout = self._layout
        fd, path = tempfile.mkstemp(prefix="bruce-telemetry-", dir=_shm_dir())
        try:
            try:
                os.ftruncate(fd, layout.size)
                shared = mmap.mmap(fd, layout.size)
            finally:
                os.close(fd)
            shared[:] = self._memory  # what was appended before start()
            self._memory = shared
            self._bind(shared)
            ours, theirs = socket.socketpair()
            with theirs:
                self._proc = subprocess.Popen(
                    [sys.executable, "-c", CHILD_BOOT, str(theirs.fileno()), json.dumps(sys.path)],
                    pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
            self._conn = Connection(ours.detach())
            self._conn.send({
                "path": path, "size": layout.size, "joints": self.joints, "capacity": self.capacity,
                "pose_capacity": self._pose_capacity, "geometry": self._geometry, "kind": self.sink.kind,
                "target": target, "sink": str(self.sink), "recording_name": self.recording_name,
                "batch_period_s": self.batch_period_s, "chunk_s": self.chunk_s, "parent": os.getpid(),
                "max_mb": DEFAULT_MAX_MB if self.sink.max_mb is None else self.sink.max_mb, "keep": self.sink.keep,
                "buffer_mb": DEFAULT_BUFFER_MB if self.sink.buffer_mb is None else self.sink.buffer_mb})
            reply = self._receive(START_TIMEOUT_S, until=("ready", "failed"))
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)  # the child has mapped it (or failed): nothing named is left behind
        if reply is None:
            code = self._proc.poll()
            raise TelemetryError(f"rerun sink {self.sink}: the telemetry process " + (
                f"did not get ready within {START_TIMEOUT_S:.0f} s" if code is None else
                f"exited with code {code} before it was ready (see its output above)"))
        if reply[0] == "failed":
            raise TelemetryError(reply[1])
        self.url = reply[1]

    def _receive(self, timeout: float, until: tuple[str, ...] = ()):
        """Handle the child's messages for up to `timeout` s; the first whose kind is in `until`, else None
        (also at EOF)."""
        conn = self._conn
        deadline = time.monotonic() + timeout
        while conn is not None:
            try:
                if not conn.poll(max(0.0, deadline - time.monotonic())):
                    return None
                message = conn.recv()
            except (EOFError, OSError):
                return None
            if message[0] == "error" and self._error is None:
                self._error = message[1]  # the child printed it already
            if message[0] in until:
                return message
        return None

    def _end_child(self, kill: bool) -> None:
        proc, conn = self._proc, self._conn
        if proc is None:
            return
        try:
            if not kill:
                with contextlib.suppress(OSError):
                    conn.send(("stop",))
                if self._receive(CLOSE_TIMEOUT_S, until=("done",)) is None and proc.poll() is None:
                    self._note_error(TimeoutError(f"no answer within {CLOSE_TIMEOUT_S:.0f} s"),
                                     "the telemetry process did not finish; killed, unsent rows count as dropped")
                    kill = True
            if kill:
                proc.kill()
            try:
                proc.wait(EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        finally:  # also on a second Ctrl-C: the child sees EOF, then sends what it has and flushes by itself
            self._proc = self._conn = None
            conn.close()


# -- the telemetry process ---------------------------------------------------------------------------------
def _child_main(fd: int) -> None:
    """Entry point of the telemetry process (see CHILD_BOOT): serve one Telemetry until stop or EOF."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)  # the parent decides when to stop; its death shows as EOF
    conn = Connection(fd)
    spec = conn.recv()
    if hasattr(os, "sched_getaffinity"):
        allowed = sorted(os.sched_getaffinity(0))
        if len(allowed) > 1:
            os.sched_setaffinity(0, allowed[:-1])  # runtime.realtime pins the loop to the last one
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


class _RingReader:
    """The consumer side of one shared ring: rows of `ring` (capacity + 1 slots), the count of rows written
    in `written[index]`; row i lies in slot i % (capacity + 1)."""

    def __init__(self, ring: np.ndarray, written: np.ndarray, index: int):
        self.ring, self.written, self.index = ring, written, index
        self.slots = len(ring)
        self.capacity = self.slots - 1
        self.read = 0

    def take(self) -> tuple[np.ndarray, int]:
        """A copy of the rows written since the last take, oldest first, and how many were lost: lapped by
        the writer before they were read, or possibly being overwritten while they were copied."""
        capacity, start = self.capacity, self.read
        end = int(self.written[self.index])
        lapped = max(0, end - start - capacity)
        start += lapped
        rows = self.ring[np.arange(start, end) % self.slots]
        # Row i's slot is rewritten from the moment the writer starts row i + slots, i.e. once its count
        # reaches i + slots = i + capacity + 1: rows below after - capacity may be torn.
        after = int(self.written[self.index])
        torn = min(max(0, after - capacity - start), end - start)
        self.read = end
        return rows[torn:], lapped + torn


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
        views = _Layout(len(self.joints), spec["capacity"], nbody, spec["pose_capacity"]).views(self.memory)
        self.ctrl, self.stats = views["ctrl"], views["stats"]
        self.rows = _RingReader(views["rows"], self.ctrl, ROWS_WRITTEN)
        self.poses = _RingReader(views["poses"], self.ctrl, POSES_WRITTEN)
        self.events = _RingReader(views["events"], self.ctrl, EVENTS_WRITTEN)

        import rerun as rr

        self.recording = rr.RecordingStream(spec["recording_name"])
        self._open_sink()
        self.blueprint = _BlueprintSender(self._blueprint(), spec["recording_name"])
        self.blueprint.send(self.recording)
        self._log_static(rr)
        scalars = rr.Scalars.columns(scalars=[0.0])
        self.row_columns = _EntityColumns(rr, scalars, [f"joints/{name}" for name in self.joints] + list(LOOP_SERIES))
        self.step_columns = _EntityColumns(rr, scalars, list(STEP_SERIES))
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
        elif kind == "spawn":
            recording.spawn()  # may wait up to ~10 s for the viewer to come up
        else:
            raise TelemetryError(f"rerun sink {self.sink}: unknown kind {kind!r}")

    def _blueprint(self):
        import rerun as rr
        import rerun.blueprint as rrb

        def per_joint(quantity: str):
            visible = rr.SeriesLines(visible_series=QUANTITIES[quantity])
            views = [rrb.TimeSeriesView(origin=f"joints/{name}", name=f"{name} {quantity}",
                                        overrides={f"joints/{name}": visible}) for name in self.joints]
            return rrb.Grid(*views, grid_columns=max(1, math.ceil(len(views) / 2)), name=f"{quantity}s")

        loop = rrb.Vertical(
            rrb.TimeSeriesView(origin="loop", name="loop timing (µs)"),
            rrb.TimeSeriesView(origin="/", contents=["safety/state", "telemetry/dropped"], name="safety / drops"),
            rrb.TextLogView(origin="safety/events", name="safety events"),
        )
        overview = loop
        if self.geometry is not None:
            # All of the past is in range so the trajectory accumulates; transforms stay latest-at, geoms static.
            past = [rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                                         end=rrb.TimeRangeBoundary.cursor_relative()) for timeline in ("tick", "time")]
            overview = rrb.Horizontal(rrb.Spatial3DView(origin="world", name="robot", time_ranges=past), loop,
                                      column_shares=[3, 2])
        tabs = rrb.Tabs(rrb.Vertical(overview, name="robot"), per_joint("position"), per_joint("velocity"),
                        per_joint("torque"))
        return rrb.Blueprint(tabs, rrb.TimePanel(timeline="time"))

    def _log_static(self, rr) -> None:
        log = self.recording.log
        for name in self.joints:
            log(f"joints/{name}", rr.SeriesLines(names=JOINT_SERIES, colors=JOINT_COLOURS), static=True, strict=True)
        for path, label in (LOOP_SERIES | STEP_SERIES).items():
            log(path, rr.SeriesLines(names=[label]), static=True, strict=True)
        if self.geometry is not None:
            log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, strict=True)
            self._log_geometry(rr)

    def _log_geometry(self, rr) -> None:
        """Each body's primitives, static, in the body's frame; the per-pose transforms place the bodies."""
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
                w, x, y, z = wxyz
                pos = pos - size[1] * np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
            by_body.setdefault(body, {}).setdefault(kind, []).append((size, pos, quat, rgba))
        for body, by_kind in by_body.items():
            parts = []
            for kind, geoms in by_kind.items():
                sizes, centers, quats, colors = (np.array(column) for column in zip(*geoms, strict=True))
                common = dict(quaternions=quats, colors=colors, fill_mode="solid")
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
                self.conn.send(("error", _picklable(exc)))

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

    def _send_rows(self, rows: np.ndarray) -> None:
        n, n_joints = len(rows), len(self.joints)
        blocks = rows[:, 2:2 + ROW_BLOCKS * n_joints].reshape(n, ROW_BLOCKS, n_joints)
        per_joint = blocks[:, ROW_ORDER].transpose(0, 2, 1)  # (row, joint, series in JOINT_SERIES order)
        ticks = rows[:, 0].astype(np.int64)
        out = self.row_columns
        columns = out.index_arrays(ticks, rows[:, 1])
        columns += [out.scalar_lists(per_joint[:, j]) for j in range(n_joints)]
        columns += [out.scalar_lists(rows[:, k, None]) for k in (-3, -2)]  # period_us, work_us
        self.recording.send_record_batch(out.batch(columns))

        # The safety code and the drop count change rarely: a row where either changes, the row before it (so
        # the plot steps instead of ramping) and the chunk's first and last rows.
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
