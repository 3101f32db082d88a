"""The process's other Python threads (the hw backend's bus thread, sense-board reader and arms, the log relay)
scheduled one real-time step above the loop, on its CPU (docs/timing.md, "Scheduling").

Once runtime.loop.realtime has given the loop thread SCHED_FIFO on one CPU, a thread left at SCHED_OTHER can be starved
(by a real-time process on another CPU, any busy process, or the loop's spin), and a starved thread that holds the
GIL stalls the loop too (priority inversion). So every Python thread goes on the loop's CPU(s) one FIFO priority
step above it: an I/O thread preempts the loop when its data arrives, parses for a few tens of microseconds and
blocks again; the loop's spin yields the GIL on every turn (runtime.loop.pacing). Threads without the GIL (onnxruntime's
pool, the telemetry child process) are not touched; a loop without SCHED_FIFO leaves them as they are. Such a
thread must block rather than poll: a poller above the loop starves it and burns the CPU's real-time budget.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable

log = logging.getLogger("bruce_hw.io_priority")


def above_the_caller(threads: list[threading.Thread]) -> tuple[int | None, Callable[[], None]]:
    """Give `threads` the calling thread's CPU affinity and its SCHED_FIFO priority + 1. Returns the priority given
    (None when the caller is not SCHED_FIFO or the OS refused; the threads keep their scheduling then) and a function
    that gives every changed thread its scheduling back (those still alive)."""
    changed: list[tuple[int, int, os.sched_param, set[int]]] = []

    def restore() -> None:
        for tid, policy, param, cpus in changed:
            try:
                os.sched_setscheduler(tid, policy, param)
                os.sched_setaffinity(tid, cpus)
            except OSError:  # the thread has ended
                pass

    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:  # 0: the calling thread (Linux schedules threads)
            return None, restore
        priority = os.sched_getparam(0).sched_priority + 1
        cpus = os.sched_getaffinity(0)
    except (AttributeError, OSError):  # not Linux
        return None, restore
    for thread in threads:
        tid = thread.native_id
        if tid is None or not thread.is_alive():
            continue
        try:
            saved = (tid, os.sched_getscheduler(tid), os.sched_getparam(tid), os.sched_getaffinity(tid))
            os.sched_setaffinity(tid, cpus)
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            changed.append(saved)
        except OSError as exc:
            log.warning("realtime: thread %s keeps its scheduling: %s", thread.name, exc.strerror)
            restore()
            return None, restore
    return priority, restore
