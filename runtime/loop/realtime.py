"""Ask the OS for what a 1 kHz loop needs, say plainly what was granted, and give it back afterwards.

SCHED_FIFO (priority 50, as ros2_control's default; below the kernel's IRQ threads), affinity to one CPU
(the last allowed one, leaving the others to the telemetry thread and the OS), and mlockall so page faults
cannot stall a tick. Each request may be refused (no CAP_SYS_NICE / rtprio limit, a container, memlock
limit); the run continues and the report says what is missing. Without PREEMPT_RT expect tens of µs of
jitter whatever is granted.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import queue
import threading
import weakref
from dataclasses import dataclass, field

FIFO_PRIORITY = 50
_MCL_CURRENT, _MCL_FUTURE = 1, 2
# A thread beside the loop runs this many real-time priority steps below the loop: below its I/O threads and the
# loop, above whatever a computer runs at normal priority and lower real-time ones (the emulated devices' 40 here).
BESIDE_PRIORITY_STEPS = 5
# While a grant holds: (the loop's CPU, the CPUs the process had before, the loop's SCHED_FIFO priority or None), for
# the threads started beside the loop.
_loop_cpu: tuple[int, list[int], int | None] | None = None
_beside: weakref.WeakSet[threading.Thread] = weakref.WeakSet()


@dataclass
class RealtimeGrant:
    scheduler: str = "SCHED_OTHER"
    cpu: int | None = None
    memory_locked: bool = False
    refused: list[str] = field(default_factory=list)
    helpers: str | None = None  # the process's other threads, once put above the loop (runtime.loop.run)
    _restore: list = field(default_factory=list, repr=False)

    def text(self) -> str:
        got = [self.scheduler, f"CPU {self.cpu}" if self.cpu is not None else "any CPU",
               "memory locked" if self.memory_locked else "memory not locked"]
        line = "realtime: " + ", ".join(got) + (f"; {self.helpers}" if self.helpers else "")
        if self.refused:
            line += " (refused: " + "; ".join(self.refused) + ")"
        return line

    def to_json(self) -> dict:
        return {"scheduler": self.scheduler, "cpu": self.cpu, "memory_locked": self.memory_locked,
                "helpers": self.helpers, "refused": list(self.refused)}

    def release(self) -> None:
        """Undo what was granted (the calling thread's scheduler and affinity, the memory lock)."""
        global _loop_cpu
        _loop_cpu = None
        while self._restore:
            try:
                self._restore.pop()()
            except OSError:
                pass


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def request_realtime(priority: int = FIFO_PRIORITY, cpu: int | None = None, lock_memory: bool = True) -> RealtimeGrant:
    """Apply to the calling thread (Linux scheduling is per thread): start other threads before this."""
    grant = RealtimeGrant()
    if hasattr(os, "sched_setscheduler"):
        try:
            previous = (os.sched_getscheduler(0), os.sched_getparam(0))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            grant.scheduler = f"SCHED_FIFO {priority}"
            grant._restore.append(lambda: os.sched_setscheduler(0, previous[0], previous[1]))
        except OSError as exc:
            grant.refused.append(f"SCHED_FIFO: {exc.strerror} (needs CAP_SYS_NICE or an rtprio limit; in Docker "
                                 "--cap-add=sys_nice)")
    else:
        grant.refused.append("SCHED_FIFO: not available on this OS")
    if hasattr(os, "sched_setaffinity"):
        allowed = sorted(os.sched_getaffinity(0))
        target = allowed[-1] if cpu is None else cpu
        try:
            os.sched_setaffinity(0, {target})
            grant.cpu = target
            global _loop_cpu
            _loop_cpu = (target, allowed, priority if grant.scheduler.startswith("SCHED_FIFO") else None)
            grant._restore.append(lambda: os.sched_setaffinity(0, allowed))
        except OSError as exc:
            grant.refused.append(f"affinity to CPU {target}: {exc.strerror}")
    if lock_memory:
        try:
            libc = _libc()
            if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
                grant.memory_locked = True
                grant._restore.append(libc.munlockall)
            else:
                grant.refused.append(f"mlockall: {os.strerror(ctypes.get_errno())} (raise `ulimit -l` or "
                                     "CAP_IPC_LOCK)")
        except OSError as exc:
            grant.refused.append(f"mlockall: {exc}")
    return grant


def start_beside_the_loop(name: str, target, *args) -> threading.Thread:
    """Start a thread that computes beside the loop (the nominal controller's with a policy lag): on the CPUs the
    process may use but the loop's, `BESIDE_PRIORITY_STEPS` real-time priorities below the loop (at normal priority
    where the loop has none), however late it is started (a thread started by the loop's thread inherits its
    SCHED_FIFO and its one CPU); `helper_threads` leaves it out, so it is never put above the loop. Real-time, because
    the GIL does not inherit priority: a thread that holds it and is preempted by lesser work keeps every thread of
    the process waiting, the loop's too (docs/timing.md, "The policy beside the loop")."""

    def run() -> None:
        held = _loop_cpu
        if held is not None and hasattr(os, "sched_setscheduler"):
            cpu, allowed, priority = held
            try:
                os.sched_setaffinity(0, [c for c in allowed if c != cpu] or allowed)
                if priority is None:
                    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                else:
                    os.sched_setscheduler(0, os.SCHED_FIFO,
                                          os.sched_param(max(1, priority - BESIDE_PRIORITY_STEPS)))
            except OSError:  # keeps what it inherited; the loop's grant is reported on its own
                pass
        target(*args)

    thread = threading.Thread(target=run, name=name, daemon=True)
    _beside.add(thread)
    thread.start()
    return thread


class QueueWorker:
    """A thread fed through a queue (the nominal controller's, the nominal twin's): `start` (once; again after
    `close`), `put` an item, `close` (the worker's `work(queue)` returns when it takes None; joined). `beside`: started
    beside the loop (`start_beside_the_loop`); else a plain thread, which the loop's real-time grant treats as one of
    its helpers (`helper_threads`: its CPU, one priority above it)."""

    def __init__(self, name: str, work, beside: bool = True):
        self.name, self._work, self.beside = name, work, beside
        self._inputs: queue.SimpleQueue = queue.SimpleQueue()
        self.thread: threading.Thread | None = None

    def start(self) -> None:
        if self.thread is None:
            self._inputs = queue.SimpleQueue()  # a fresh one: nothing of a closed worker's is left in it
            if self.beside:
                self.thread = start_beside_the_loop(self.name, self._work, self._inputs)
            else:
                self.thread = threading.Thread(target=self._work, args=(self._inputs,), name=self.name, daemon=True)
                self.thread.start()

    def put(self, item) -> None:
        self._inputs.put(item)

    def close(self) -> None:
        if self.thread is not None:
            self._inputs.put(None)
            self.thread.join(timeout=2.0)
            self.thread = None


def helper_threads() -> list[threading.Thread]:
    """The process's other threads that serve the loop's I/O (bus threads, telemetry, the log relay): all but the
    calling thread and those started beside the loop."""
    me = threading.current_thread()
    return [t for t in threading.enumerate() if t is not me and t not in _beside]
