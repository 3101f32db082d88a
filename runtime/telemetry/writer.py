"""The control thread's side of telemetry: `Telemetry.append` copies a tick into a shared-memory ring (never blocks,
no allocation, drops counted); a child process (`runtime.telemetry.sender`) does all rerun I/O, so rerun never holds
the control process's GIL. Design and measurements: docs/telemetry.md.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import math
import mmap
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Self

import numpy as np

from runtime.telemetry.ring import (
    EVENT_CAPACITY,
    EVENT_LEVEL_BYTES,
    EVENT_TEXT_BYTES,
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
    shm_dir,
    utf8,
)
from runtime.telemetry.sink import (
    DEFAULT_BUFFER_MB,
    DEFAULT_GRPC_PORT,
    DEFAULT_MAX_MB,
    DEFAULT_VIEWER_URL,
    WEB_BUFFER_MB,
    WEB_ROW_HZ,
    RerunSink,
    TelemetryError,
    check_port_free,
    grpc_url,
    part_path,
    probe_viewer,
    viewer_host,
)

if TYPE_CHECKING:
    import mujoco

    from bruce_hw.config import RobotConfig

POSE_HZ = 30.0              # 3-D poses (and the base trajectory's points): display rate, not loop rate
FILE_CHUNK_S = 2.0          # save=: each entity's rows go out in chunks of this many seconds
LIVE_CHUNK_S = 0.2          # spawn/connect/serve/web: the viewer's latency (rerun's own batching default)
START_TIMEOUT_S = 60.0      # a new interpreter importing rerun (~1 s), plus up to ~10 s for a spawned viewer
CLOSE_TIMEOUT_S = 30.0      # a child stuck in rerun (blocked channel) is killed after this long
EXIT_TIMEOUT_S = 5.0        # after its last message, for the child's interpreter to exit
CHILD_BOOT = ("import json, sys; sys.path[:0] = json.loads(sys.argv[2]); "
              "from runtime.telemetry.sender import child_main; child_main(int(sys.argv[1]))")


def make_telemetry(config: RobotConfig, sink: RerunSink, model: mujoco.MjModel | None = None,
                   **kwargs) -> Telemetry | None:
    """A Telemetry for `sink` (not started), or None when the sink is `off`."""
    return None if sink.kind == "off" else Telemetry(config, sink, model=model, **kwargs)


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



class Telemetry:
    def __init__(self, config: RobotConfig, sink: RerunSink, *, model: mujoco.MjModel | None = None,
                 capacity: int = 4096, batch_period_s: float = 0.05, chunk_s: float | None = None,
                 pose_decimation: int | None = None, recording_name: str = "bruce-run", gap: bool = False):
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
        # web: a browser's viewer gets one row per this many ticks (loop timing: each interval's maximum)
        row_hz = (sink.row_hz or WEB_ROW_HZ) if sink.kind == "web" else config.loop_hz
        self.row_decimation = max(1, round(config.loop_hz / row_hz))
        self.recording_name = recording_name
        self.gap = gap  # rows carry the gap monitor's residuals (append's `gap`), sent under gap/<joint>
        self.joints = tuple(config.joints)
        self.url: str | None = None  # serve: the URL the gRPC server reported; web: the page to open
        self._error: BaseException | None = None
        self._geometry = None if model is None else _geometry(model)
        self._pose_capacity = max(8, capacity // pose_decimation)
        nbody = 0 if self._geometry is None else len(self._geometry["names"])
        self._layout = Layout(len(self.joints), capacity, nbody, self._pose_capacity, gap)
        # Private memory until start() copies it into the shared block: rows appended before start() go along.
        self._memory: bytearray | mmap.mmap = bytearray(self._layout.size)
        self._bind(self._memory)
        n_joints, self._row_slot_count, self._pose_slot_count = len(self.joints), capacity + 1, self._pose_capacity + 1
        self._nan_row = np.full(n_joints, np.nan)
        blocks = ROW_BLOCKS + (GAP_BLOCKS if gap else 0)
        self._row_blocks = tuple(slice(2 + k * n_joints, 2 + (k + 1) * n_joints) for k in range(blocks))
        self._n_rows = self._n_poses = self._n_events = 0
        self._rejected_rows = self._rejected_poses = 0
        self._final: tuple[int, int, int, int] | None = None  # sent/dropped rows, sent/dropped poses after close
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._started = self._closed = False
        self._ready = False  # the child opened the sink

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
               work_us: float, safety_code: int, gap=None) -> None:
        """One tick (arrays in config.joints order): copied into the shared ring, then the counter is bumped.
        `gap`: (qd residual, q residual, qd window RMS) of the gap monitor this tick, or None (no residual this
        tick: NaN); ignored unless the telemetry was made with gap=True."""
        n = self._n_rows
        slot = self._row_slots[n % self._row_slot_count]
        b0, b1, b2, b3, b4, b5, b6 = self._row_blocks[:ROW_BLOCKS]
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
            if self.gap:
                for block, values in zip(self._row_blocks[ROW_BLOCKS:], gap or (nan, nan, nan), strict=True):
                    slot[block] = values
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
        self._event_ring[n % (EVENT_CAPACITY + 1)] = (tick, time_s, utf8(str(level), EVENT_LEVEL_BYTES),
                                                utf8(str(text), EVENT_TEXT_BYTES))
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
        elif self.sink.kind == "web":
            print(f"telemetry: rerun web viewer on port {self.sink.web_port}, its gRPC stream on port "
                  f"{self.sink.server_port} (all interfaces); open in a browser: {self.url}  (on this machine "
                  "127.0.0.1 works as the host in both places; ,host=NAME picks another)", flush=True)

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
        if self.sink.kind == "save" and self._ready:
            print(f"telemetry: {self.saved_text()}", flush=True)

    def saved_text(self) -> str:
        """Where a save= recording went: the file, and its continuation parts when it was rotated."""
        path = Path(self.sink.target).expanduser().absolute()
        parts = 1
        while part_path(path, parts).exists():
            parts += 1
        more = f" and {parts - 1} continuation part(s) {part_path(path, 1).name} .. " \
               f"{part_path(path, parts - 1).name}" if parts > 1 else ""
        return f"rerun recording saved to {path}{more} (view: bruce-view {path}, in a browser: add --web)"

    def __enter__(self) -> Self:
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
            probe_viewer(self.sink, url or DEFAULT_VIEWER_URL)  # rerun would wait 5 s, then drop everything
            return url
        if kind == "serve":
            port = self.sink.server_port  # rerun only logs a failed bind; find out here, with a clear error
            check_port_free(port, "the gRPC server", f"rerun sink {self.sink}")
            return str(port)
        if kind == "web":
            check_port_free(self.sink.server_port, "the gRPC server", f"rerun sink {self.sink}")
            check_port_free(self.sink.web_port, "the web viewer", f"rerun sink {self.sink}")
            return self.sink.host or viewer_host()  # the host in the link to open
        if kind == "spawn":
            headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
            if sys.platform.startswith("linux") and headless:
                raise TelemetryError(f"rerun sink {self.sink}: no display (DISPLAY and WAYLAND_DISPLAY unset) for a "
                                     "viewer; on a headless machine use --rerun serve or --rerun save=PATH")
            return None
        raise TelemetryError(f"rerun sink {self.sink}: unknown kind {kind!r}")

    def _spawn(self, target: str | None) -> None:
        layout = self._layout
        fd, path = tempfile.mkstemp(prefix="bruce-telemetry-", dir=shm_dir())
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
                "gap": self.gap,
                "target": target, "sink": str(self.sink), "recording_name": self.recording_name,
                "batch_period_s": self.batch_period_s, "chunk_s": self.chunk_s, "parent": os.getpid(),
                "row_decimation": self.row_decimation,
                "max_mb": DEFAULT_MAX_MB if self.sink.max_mb is None else self.sink.max_mb, "keep": self.sink.keep,
                "buffer_mb": self.sink.buffer_mb or (WEB_BUFFER_MB if self.sink.kind == "web" else DEFAULT_BUFFER_MB),
                **({"web_port": self.sink.web_port, "grpc_port": self.sink.server_port}
                   if self.sink.kind == "web" else {})})
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
        self._ready = True

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


