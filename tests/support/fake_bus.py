"""A fake bus cycle for the legs' bus thread (bruce_hw.bus_thread), and a bounded wait for a condition, for the
bus thread's tests (bruce_hw/test_bus_thread.py) and the host witness's (bruce_hw/test_host_witness.py)."""

import threading
import time


class FakeBus:
    def __init__(self, cycle_s: float = 0.0, fail_at: int | None = None):
        self.cycle_s, self.fail_at = cycle_s, fail_at
        self.sent: list = []
        self.lock = threading.Lock()

    def cycle(self, command):
        with self.lock:
            if self.fail_at is not None and len(self.sent) >= self.fail_at:
                raise OSError("the adapter is gone")
            self.sent.append(command)
            n = len(self.sent)
        time.sleep(self.cycle_s)
        return ("reading", n, command)


def wait_for(predicate, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.001)
    return False
