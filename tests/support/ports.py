"""Waiting on a serial port in tests without sleeping."""

import select


def wait_readable(serial_port, timeout_s: float = 5.0) -> None:
    """Until the emulator has answered (it writes a request's replies at once; the harvest's read then waits in the
    kernel for whatever of them is still being handed over), however slow a busy machine runs its thread."""
    assert select.select([serial_port.fileno()], [], [], timeout_s)[0], "the delayed replies did not come"
