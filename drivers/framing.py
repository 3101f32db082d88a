"""Resynchronisation on a packet header, shared by the byte-stream parsers (BEAR, Dynamixel; driver and emulator)."""

from __future__ import annotations

from drivers.errors import LinkStats


def skip_to_header(buf: bytearray, header: bytes, stats: LinkStats) -> bool:
    """Drop the bytes before the first `header` in `buf`, counted once as "garbage". Without a header, keep only a
    tail that may be its start. True when `buf` now starts with a header."""
    start = buf.find(header)
    if start < 0:
        keep = next((k for k in range(len(header) - 1, 0, -1) if buf.endswith(header[:k])), 0)
        if len(buf) > keep:
            stats.reject("garbage")
            del buf[:len(buf) - keep]
        return False
    if start:
        stats.reject("garbage")
        del buf[:start]
    return True
