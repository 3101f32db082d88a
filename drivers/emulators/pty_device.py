"""A serial device on a pseudo-terminal: the host opens `path` with pyserial (or a vendor SDK) as if it were a
USB-serial adapter, and the emulator reads and writes the other end.

Bytes from the host arrive in a thread and go to `on_bytes(data)`; the emulator answers with `send(data)`.
"""

from __future__ import annotations

import os
import select
import threading
import tty
from collections.abc import Callable


class PtyDevice:
    def __init__(self, name: str, on_bytes: Callable[[bytes], None]):
        self.name = name
        self._on_bytes = on_bytes
        self._master, slave = os.openpty()
        # Raw mode on both ends: no echo, no line discipline, no CR/LF translation; bytes pass unchanged.
        tty.setraw(self._master)
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        # Keep the slave open so the pty survives the host closing and reopening the port.
        self._slave = slave
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        self._thread = threading.Thread(target=self._serve, name=f"pty-{name}", daemon=True)

    def start(self) -> PtyDevice:
        self._thread.start()
        return self

    def send(self, data: bytes) -> None:
        """Bytes from the device to the host."""
        if self._stop.is_set():
            return
        with self._write_lock:
            view = memoryview(data)
            while view:
                try:
                    n = os.write(self._master, view)
                except BlockingIOError:
                    select.select([], [self._master], [], 0.01)
                    continue
                except OSError:
                    return  # closed while sending
                view = view[n:]

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except OSError:
                return
            if data:
                self._on_bytes(data)

    def close(self) -> None:
        if self._stop.is_set():
            return  # closed already: the fd numbers may belong to someone else by now
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyDevice:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
