"""Resynchronisation on a packet header, shared by the byte-stream parsers (BEAR, Dynamixel; driver and emulator)."""

from __future__ import annotations

from drivers.errors import LinkStats


def seek_header(buf: bytearray, header: bytes, stats: LinkStats, pos: int = 0) -> tuple[int, bool]:
    """Where the bytes of `buf` from `pos` on resume: at the first `header` (True), the bytes before it counted once
    as "garbage"; without a header (False), past all but a tail that may be its start, the rest counted as garbage.
    For a parser that walks its buffer by offset and drops what it has read once, at the end."""
    start = buf.find(header, pos)
    if start < 0:
        keep = next((k for k in range(len(header) - 1, 0, -1) if buf.endswith(header[:k])), 0)
        keep = min(keep, len(buf) - pos)
        if len(buf) - pos > keep:
            stats.reject("garbage")
        return len(buf) - keep, False
    if start > pos:
        stats.reject("garbage")
    return start, True


def skip_to_header(buf: bytearray, header: bytes, stats: LinkStats) -> bool:
    """Drop the bytes before the first `header` in `buf`, counted once as "garbage". Without a header, keep only a
    tail that may be its start. True when `buf` now starts with a header."""
    pos, found = seek_header(buf, header, stats)
    del buf[:pos]
    return found
