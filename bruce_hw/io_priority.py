"""The hw backend's I/O threads (the legs' bus thread, the sense-board reader, the arms) scheduled above the loop.

Once runtime.realtime has given the loop thread SCHED_FIFO on one CPU, an I/O thread left at SCHED_OTHER can be
starved: on another CPU by any real-time process there (the emulators under `bruce-emulate --realtime`, a driver's
IRQ thread), on the loop's CPU by the loop's spin before each deadline. A starved reader that holds the GIL stalls
the loop too (priority inversion). So each I/O thread is put on the loop's CPU(s) one FIFO priority step above it:
it preempts the loop when its data arrives, does its few tens of microseconds of parsing and blocks again; the
loop's spin yields the GIL on every turn (runtime.pacing). A loop without SCHED_FIFO leaves them as they are.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger("bruce_hw.io_priority")


def above_the_caller(threads: list[threading.Thread]) -> int | None:
    """Give `threads` the calling thread's CPU affinity and its SCHED_FIFO priority + 1; the priority given, or
    None when the caller is not SCHED_FIFO or the OS refused (the threads keep their scheduling then)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:  # 0: the calling thread (Linux schedules threads)
            return None
        priority = os.sched_getparam(0).sched_priority + 1
        cpus = os.sched_getaffinity(0)
    except (AttributeError, OSError):  # not Linux
        return None
    for thread in threads:
        tid = thread.native_id
        if tid is None or not thread.is_alive():
            continue
        try:
            os.sched_setaffinity(tid, cpus)
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            log.warning("thread %s keeps its scheduling: %s", thread.name, exc.strerror)
            return None
    return priority
