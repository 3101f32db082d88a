"""How `bruce-emulate --realtime` shares its CPUs: the devices at real-time priority, the physics in a child process at
normal priority, which the kernel's tty workers preempt (ftrace of the hw runs that ended on a whole-bus silence: with
the physics real-time, a tty worker preempted halfway through a BEAR pty's buffer waited 5-10 ms behind it;
docs/results/timing.md)."""

from __future__ import annotations

import os

import pytest

from bruce_hw.emulation.physics_process import PHYSICS_NICE
from bruce_hw.emulation.plant import PHYSICS_THREAD_NAME
from bruce_hw.emulation.process import EmulatorProcess
from runtime.emulate_cli import EMULATOR_PRIORITY, OPERATOR_PRIORITY


def _children(pid: int) -> list[int]:
    found = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/children") as f:
            found += [int(word) for word in f.read().split()]
    return found


def _threads(pid: int) -> list[tuple[str, int | None]]:
    """Per thread of `pid`: its OS name and SCHED_FIFO priority (None for any other policy)."""
    found = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                name = f.read().strip()
            fifo = os.sched_getscheduler(int(tid)) == os.SCHED_FIFO
            found.append((name, os.sched_getparam(int(tid)).sched_priority if fifo else None))
        except OSError:  # the thread ended meanwhile
            continue
    return found


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling")
def test_realtime_emulator_runs_its_devices_real_time_and_its_physics_apart_at_normal_priority():
    with EmulatorProcess("--realtime") as emulator:
        if any("SCHED_FIFO refused" in line for line in emulator.output):
            pytest.skip("this machine refuses SCHED_FIFO: --realtime runs at normal priority")
        emulator.send("place")  # the physics answers the operator
        devices = _threads(emulator.proc.pid)
        children = _children(emulator.proc.pid)
        physics = [(name, priority, os.getpriority(os.PRIO_PROCESS, child)) for child in children
                   for name, priority in _threads(child) if name == PHYSICS_THREAD_NAME]
    assert physics == [(PHYSICS_THREAD_NAME, None, PHYSICS_NICE)], (children, physics)
    assert all(name != PHYSICS_THREAD_NAME for name, _ in devices), devices
    # The BEAR, Dynamixel and sense-board ptys, the board's firmware and its sender, the bridge to the physics at the
    # devices' priority; the operator's threads (main, events, stdin) one step below.
    priorities = [priority for _, priority in devices]
    assert priorities.count(EMULATOR_PRIORITY) >= 6, devices
    assert priorities.count(OPERATOR_PRIORITY) >= 1, devices
