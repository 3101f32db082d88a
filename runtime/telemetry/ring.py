"""The shared-memory block between the control process and the telemetry process: three single-producer,
single-consumer rings (rows, poses, events) and two counter blocks, each on its own cache lines. The design and its
memory-order assumption: docs/telemetry.md#design.
"""

from __future__ import annotations

import math
import os
import tempfile

import numpy as np

EVENT_CAPACITY = 256
EVENT_TEXT_BYTES = 240
EVENT_LEVEL_BYTES = 16
# Counter blocks (int64, one cache line each). Written by the parent only:
ROWS_WRITTEN, POSES_WRITTEN, EVENTS_WRITTEN, ROWS_REJECTED = range(4)
# Written by the child only:
ROWS_READ, ROWS_SENT, ROWS_OVERRUN, ROWS_FAILED, POSES_READ, POSES_SENT, POSES_OVERRUN, POSES_FAILED = range(8)
COUNTERS = 8
EVENT_DTYPE = np.dtype([("tick", "<i8"), ("time", "<f8"), ("level", f"S{EVENT_LEVEL_BYTES}"),
                        ("text", f"S{EVENT_TEXT_BYTES}")])
ROW_BLOCKS = 7  # q, qd, q_hat, qd_hat, a, tau_star, tau
GAP_BLOCKS = 3  # with a gap monitor: qd residual, q residual, qd window RMS (the sender's GAP_SERIES)
class Layout:
    """Where each ring and counter block lies in the shared block (each part starts on a 64-byte line). A ring
    has one slot more than its capacity: the slot the writer may be filling, so `capacity` rows stay readable."""

    def __init__(self, n_joints: int, capacity: int, nbody: int, pose_capacity: int, gap: bool = False):
        self.row_width = 2 + (ROW_BLOCKS + (GAP_BLOCKS if gap else 0)) * n_joints + 3
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


def shm_dir() -> str:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()


class RingReader:
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


def utf8(text: str, limit: int) -> bytes:
    """`text` as UTF-8, cut to at most `limit` bytes on a character boundary."""
    data = text.encode("utf-8", "replace")
    return data if len(data) <= limit else data[:limit].decode("utf-8", "ignore").encode()


