"""What a real-time loop that is behind does to a serial port's bytes, with and without the pacer's breath.

The kernel moves a serial port's bytes from the writer to the reader in a worker at normal priority (the tty's
`flush_to_ldisc`, for a USB adapter's replies as for a pseudo-terminal's requests), and the scheduler often wakes it
on the writer's CPU. A SCHED_FIFO loop on that CPU that runs its ticks back to back keeps it off the CPU until the
loop sleeps or another CPU takes it over. Traced on the hw path (docs/results/timing.md): a request waited 7.1 ms so,
and every BEAR looked silent. `runtime.loop.pacing.Pacer` sleeps `breath_s` after a period without a sleep, and, where
the loop calls `breathe` halfway through a tick, inside a tick that has gone `mid_tick_s` without one; this bench
measures the request's delivery with the three threads of the hw path apart and nothing else:

- the loop: the real `Pacer` (1 kHz) on CPU 1 at SCHED_FIFO 50, whose ticks spin for `--heavy-ms` (more than a
  period: behind, as on a slowed virtual CPU) for 10 ticks, then 0.3 ms for 20 ticks, over and over;
- the bus thread: a process on CPU 1 at SCHED_FIFO 51 writing an 8-byte stamp into a pseudo-terminal every 1 ms;
- the device: a process on CPU 0 at SCHED_FIFO 40 reading the other side, noting how late each stamp came.

Per setting (no breath; `breath_s` 50 µs, the default, between ticks; and inside them too), alternated `--rounds`
times: the delivery delay p50 / p99 / max and the stamps later than 1 ms and than 3 ms (a bulk cycle's reply
timeout). Root (SCHED_FIFO) and two CPUs.

    python bench/bench_worker_behind_loop.py [--seconds 5] [--rounds 3] [--heavy-ms 1.3]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import struct
import time
import tty

import numpy as np

from runtime.loop.pacing import Pacer

LOOP_CPU, DEVICE_CPU = 1, 0
LATE_S = 0.003  # a bulk cycle's reply timeout (safety.bear_reply_timeout_s)


def _realtime(cpu: int, priority: int) -> None:
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))


def _spin(ns: int) -> None:
    end = time.monotonic_ns() + ns
    while time.monotonic_ns() < end:
        pass


def _loop(seconds: float, heavy_ms: float, breath_s: float, inside: bool, out) -> None:
    _realtime(LOOP_CPU, 50)
    pacer = Pacer(0.001, breath_s=breath_s)
    pacer.start()
    end, tick = time.monotonic() + seconds, 0
    while time.monotonic() < end:
        pacer.wait()
        work = round(1e6 * (heavy_ms if tick % 30 < 10 else 0.3))
        if inside:  # as runtime/loop/run.py after its costliest section
            _spin(work // 2)
            pacer.breathe()
            work -= work // 2
        _spin(work)
        tick += 1
    out.put({"ticks": tick, "late": pacer.late_ticks, "breaths": pacer.breaths})


def _writer(path: str, seconds: float) -> None:
    _realtime(LOOP_CPU, 51)
    fd = os.open(path, os.O_WRONLY | os.O_NOCTTY)
    end = time.monotonic() + seconds
    due = time.monotonic()
    while (now := time.monotonic()) < end:
        os.write(fd, struct.pack("<q", time.monotonic_ns()))
        due += 0.001
        time.sleep(max(0.0, due - now))
    os.close(fd)


def _device(master: int, seconds: float, out) -> None:
    _realtime(DEVICE_CPU, 40)
    delays, data = [], b""
    end = time.monotonic() + seconds + 0.2
    os.set_blocking(master, False)
    while time.monotonic() < end:
        try:
            data += os.read(master, 4096)
        except BlockingIOError:
            time.sleep(0.0001)
            continue
        now = time.monotonic_ns()
        while len(data) >= 8:
            (sent,), data = struct.unpack("<q", data[:8]), data[8:]
            delays.append(now - sent)
    out.put(delays)


def measure(seconds: float, heavy_ms: float, breath_s: float, inside: bool) -> dict:
    ctx = mp.get_context("fork")
    master, slave = os.openpty()
    tty.setraw(slave)  # bytes as written: no echo, no line editing, no newline translation
    path = os.ttyname(slave)
    loop_out, device_out = ctx.Queue(), ctx.Queue()
    device = ctx.Process(target=_device, args=(master, seconds, device_out))
    device.start()
    time.sleep(0.1)
    procs = [ctx.Process(target=_loop, args=(seconds, heavy_ms, breath_s, inside, loop_out)),
             ctx.Process(target=_writer, args=(path, seconds))]
    for proc in procs:
        proc.start()
    loop = loop_out.get()
    delays = np.array(device_out.get(), dtype=np.float64) / 1e9
    for proc in (*procs, device):
        proc.join()
    os.close(master)
    os.close(slave)
    return {**loop, "stamps": delays.size, "p50_ms": 1e3 * np.percentile(delays, 50),
            "p99_ms": 1e3 * np.percentile(delays, 99), "max_ms": 1e3 * delays.max(),
            "over_1ms": int(np.sum(delays > 0.001)), "over_3ms": int(np.sum(delays > LATE_S))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--heavy-ms", type=float, default=1.3, help="CPU time of a behind tick (more than 1 ms)")
    args = parser.parse_args()
    if os.cpu_count() < 2:
        raise SystemExit("bench_worker_behind_loop: needs two CPUs")
    default_breath = Pacer(0.001).breath_ns / 1e9
    print(f"loop ticks of {args.heavy_ms} ms x 10, then 0.3 ms x 20, on CPU {LOOP_CPU}; {args.seconds:g} s a run")
    for round_ in range(1, args.rounds + 1):
        for breath, inside in ((0.0, False), (default_breath, False), (default_breath, True)):
            r = measure(args.seconds, args.heavy_ms, breath, inside)
            where = "none" if not breath else f"{1e6 * breath:.0f} µs " + ("inside ticks too" if inside else
                                                                          "between ticks")
            print(f"  round {round_}, breath {where}: delivery p50 {r['p50_ms']:.2f} / p99 "
                  f"{r['p99_ms']:.2f} / max {r['max_ms']:.2f} ms; of {r['stamps']}, {r['over_1ms']} later than 1 ms, "
                  f"{r['over_3ms']} than {1e3 * LATE_S:g} ms; loop {r['ticks']} ticks, {r['late']} late, "
                  f"{r['breaths']} breaths",
                  flush=True)


if __name__ == "__main__":
    main()
