"""Errors and counters shared by every driver: one vocabulary for "the bus said nothing" and "the bytes were bad"."""

from __future__ import annotations

import termios
from collections import Counter
from dataclasses import dataclass, field

# What a serial port that has gone away raises: OSError (pyserial's SerialException is one) from read and write, and
# termios.error (not an OSError) from the tcflush/tcsetattr calls behind reset_input_buffer and the port settings.
PORT_ERRORS = (OSError, termios.error)


class DriverError(RuntimeError):
    """A device or bus could not be opened, read or written. The message names the bus (port or channel)."""


class BusTimeout(DriverError):
    """No (complete, valid) reply within the bounded timeout. `silent_ids` names the devices that did not answer."""

    def __init__(self, bus: str, silent_ids: list[int] | tuple[int, ...], detail: str = ""):
        self.bus = bus
        self.silent_ids = tuple(silent_ids)
        ids = ", ".join(str(i) for i in self.silent_ids) or "none"
        super().__init__(f"{bus}: no reply from ID(s) {ids}" + (f" ({detail})" if detail else ""))


class DeviceFault(DriverError):
    """A device answered but reports a fault (error flags, e-stop). `flags` names what it reported."""

    def __init__(self, bus: str, device_id: int, flags: list[str] | tuple[str, ...]):
        self.bus = bus
        self.device_id = device_id
        self.flags = tuple(flags)
        super().__init__(f"{bus}: ID {device_id} reports {', '.join(self.flags)}")


@dataclass
class LinkStats:
    """What a parser or bus has seen: good packets, rejected ones by reason, timeouts, retries.

    Rejections are counted, never raised out of the parser: a corrupted byte stream costs a packet, not the loop.
    """

    packets: int = 0
    rejected: Counter = field(default_factory=Counter)  # reason -> count ("checksum", "length", "foreign", ...)
    timeouts: int = 0
    retries: int = 0
    host_stalls: int = 0  # sends the host held, reads it was late for by more than a slice (not the device's)
    late_replies: int = 0  # replies that came after their request's deadline, taken before the next request

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())
