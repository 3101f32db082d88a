"""Koala BEAR packets: an encoder per instruction, value decoding, and `StatusParser`, which resynchronises on the
header and rejects what is not a status packet. Pure: no I/O.

Wire format (Dynamixel-1.0-like; Westwood's PyBEAR SDK and BRUCE-OP v0.0.7)::

    instruction   FF FF ID LEN INSTR params... CHK
    status reply  FF FF ID LEN ERROR data...   CHK

LEN = n_params + 2 (the bytes after it); CHK = ~(ID + LEN + INSTR/ERROR + params) & 0xFF. Register values are 4
bytes little-endian, float32 or uint32 by register. Writes (WRITE_STAT, WRITE_CFG, SAVE_CFG) get no reply.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from drivers.bear_registers import (
    BROADCAST_ID,
    HEADER,
    MAX_BULK_REGISTERS,
    MAX_DEVICE_ID,
    MAX_PARAMS,
    Instruction,
    Register,
    error_flags,
)
from drivers.errors import LinkStats
from drivers.framing import skip_to_header


# -- packets (pure: no I/O) -----------------------------------------------------------------------------------------
def checksum(body: bytes | bytearray) -> int:
    """~(sum of ID..last parameter) & 0xFF; the two header bytes are not included."""
    return ~sum(body) & 0xFF


def encode_frame(device_id: int, code: int, params: bytes = b"") -> bytes:
    """FF FF ID LEN code params CHK. `code` is the instruction (host) or the error byte (device)."""
    if not 0 <= device_id <= BROADCAST_ID:
        raise ValueError(f"BEAR ID {device_id} is out of range 0..{BROADCAST_ID}")
    if len(params) > MAX_PARAMS:
        raise ValueError(f"{len(params)} parameter bytes do not fit one BEAR packet (at most {MAX_PARAMS})")
    body = bytes((device_id, len(params) + 2, code)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


def encode_status(device_id: int, error: int, data: bytes = b"") -> bytes:
    """A device's reply packet (what the emulator sends)."""
    return encode_frame(device_id, error, data)


def _same_table(registers: Sequence[Register]) -> str:
    tables = {r.table for r in registers}
    if len(tables) > 1:
        raise ValueError("one packet reads or writes either config or status registers, not both")
    return tables.pop() if tables else "status"


def encode_ping(device_id: int) -> bytes:
    return encode_frame(device_id, Instruction.PING)


def encode_read(device_id: int, registers: Sequence[Register]) -> bytes:
    code = Instruction.READ_CFG if _same_table(registers) == "config" else Instruction.READ_STAT
    return encode_frame(device_id, code, bytes(r.address for r in registers))


def encode_write(device_id: int, values: Sequence[tuple[Register, int | float]]) -> bytes:
    code = Instruction.WRITE_CFG if _same_table([r for r, _ in values]) == "config" else Instruction.WRITE_STAT
    return encode_frame(device_id, code, b"".join(bytes((r.address,)) + r.encode(v) for r, v in values))


def encode_save_config(device_id: int) -> bytes:
    return encode_frame(device_id, Instruction.SAVE_CFG)


def encode_bulk(ids: Sequence[int], read_regs: Sequence[Register], write_regs: Sequence[Register] = (),
                values=None) -> bytes:
    """BULK_COMM (0x12) to the broadcast ID: params N, (n_read << 4 | n_write), read addresses, write addresses, then
    per motor its ID and 4 bytes per write register. `values[k][j]` is motor ids[k]'s value of write_regs[j],
    packed by type. Every listed motor answers one status packet (LEN = 4 n_read + 2) in request order, none if
    n_read = 0."""
    ids = [int(i) for i in ids]
    if not ids or len(set(ids)) != len(ids) or not all(0 <= i <= MAX_DEVICE_ID for i in ids):
        raise ValueError(f"BULK_COMM needs distinct device IDs in 0..{MAX_DEVICE_ID}, got {ids}")
    for regs in (read_regs, write_regs):
        if len(regs) > MAX_BULK_REGISTERS:
            raise ValueError(f"BULK_COMM takes at most {MAX_BULK_REGISTERS} read and {MAX_BULK_REGISTERS} write "
                             "registers")
        if any(r.table != "status" for r in regs):
            raise ValueError("BULK_COMM reaches status registers only")
    if any(not r.writable for r in write_regs):
        raise ValueError(f"read-only registers cannot be written: {[r.name for r in write_regs if not r.writable]}")
    rows = [] if not write_regs else list(values if values is not None else ())
    if len(rows) != (len(ids) if write_regs else 0):
        raise ValueError(f"BULK_COMM needs one row of {len(write_regs)} values per ID ({len(ids)} IDs)")
    flat: list[int | float] = []
    for device_id, row in zip(ids, rows, strict=False):
        row = list(row)
        if len(row) != len(write_regs):
            raise ValueError(f"ID {device_id}: {len(row)} values for {len(write_regs)} write registers")
        flat.append(device_id)
        flat.extend(r.check(v) for r, v in zip(write_regs, row, strict=True))
    if not write_regs:
        flat = list(ids)
    per_motor = "B" + "".join(r.fmt for r in write_regs)
    params = (bytes((len(ids), len(read_regs) << 4 | len(write_regs)))
              + bytes(r.address for r in read_regs) + bytes(r.address for r in write_regs)
              + struct.pack("<" + per_motor * len(ids), *flat))
    return encode_frame(BROADCAST_ID, Instruction.BULK_COMM, params)


def decode_values(registers: Sequence[Register], data: bytes) -> list[int | float]:
    """Typed values of a reply's data, one per register in order."""
    if len(data) != 4 * len(registers):
        raise ValueError(f"{len(data)} data bytes for {len(registers)} registers")
    return list(struct.unpack("<" + "".join(r.fmt for r in registers), data))


def reply_length(n_registers: int) -> int:
    """LEN of a reply carrying n register values."""
    return 4 * n_registers + 2


@dataclass(frozen=True)
class StatusPacket:
    id: int
    error: int
    data: bytes

    @property
    def flags(self) -> tuple[str, ...]:
        return error_flags(self.error)


class StatusParser:
    """Finds status packets in a byte stream: skips garbage up to the next FF FF header, rejects (and counts in
    `stats`) bad lengths, bad checksums, instruction packets and unexpected IDs, and keeps an incomplete packet until
    more bytes come. Never raises on any input; holds at most one frame's worth of bytes.

    After a bad checksum it drops one byte only, not the claimed frame: a real packet may start inside it. A frame
    whose checksum matches but which holds the start of an expected reply (FF FF, ID, LEN, error byte) is taken for a
    cut reply completed by the next one and dropped up to that start.
    """

    def __init__(self, stats: LinkStats | None = None):
        self.stats = stats if stats is not None else LinkStats()
        self._buffer = bytearray()
        self._length: int | None = None
        self._ids: frozenset[int] | None = None

    def expect(self, length: int | None = None, ids: Iterable[int] | None = None) -> None:
        """Accept only replies of this LEN and from these IDs (None: any). Gating on LEN means a false header in
        garbage cannot make the parser wait for up to 255 bytes that will never come."""
        self._length = length
        self._ids = None if ids is None else frozenset(ids)

    @property
    def pending(self) -> int:
        """Bytes held back: an incomplete packet (or a lone trailing 0xFF)."""
        return len(self._buffer)

    def clear(self) -> int:
        dropped = len(self._buffer)
        self._buffer.clear()
        return dropped

    def _reply_start_inside(self, buf: bytearray, total: int) -> int | None:
        """Where, inside the frame buf[:total], the bytes read as the start of an expected reply: FF FF, an expected
        ID, the expected LEN, an error byte with bit 7 (those present in the buffer). FF FF alone is not enough: a
        float32 value holds it (present_iq 4.28 A is ff ff 88 40), and a motor at rest sends it every cycle."""
        start = 2
        while (inner := buf.find(HEADER, start, total)) != -1:
            tail = buf[inner + 2:inner + 5]
            ok = len(tail) == 3
            if ok:
                device_id, length, error = tail
                ok = (device_id not in (0xFF, BROADCAST_ID) and error & 0x80
                      and (self._ids is None or device_id in self._ids)
                      and (length == self._length if self._length is not None else length >= 2))
            if ok:
                return inner
            start = inner + 1
        return None

    def feed(self, data: bytes | bytearray) -> list[StatusPacket]:
        buf = self._buffer
        buf += data
        found: list[StatusPacket] = []
        while True:
            if not skip_to_header(buf, HEADER, self.stats):
                return found
            if len(buf) < 5:
                return found
            device_id, length, error = buf[2], buf[3], buf[4]
            reason = None
            if device_id == 0xFF:  # FF FF FF: the header starts one byte later
                reason = "garbage"
            elif device_id == BROADCAST_ID or not error & 0x80:  # an instruction packet, not a reply
                reason = "foreign"
            elif length < 2 or (self._length is not None and length != self._length):
                reason = "length"
            if reason:
                self.stats.reject(reason)
                del buf[:1]
                continue
            total = 4 + length
            if len(buf) < total:
                return found
            if checksum(buf[2:total - 1]) != buf[total - 1]:
                self.stats.reject("checksum")
                del buf[:1]
                continue
            inner = self._reply_start_inside(buf, total)
            if inner is not None:
                # A reply's start inside the frame: a reply cut short and completed by the next one's bytes, whose
                # 8-bit checksum matched by chance (1 in 256), which would hand the loop a made-up sample.
                # Resynchronise there.
                self.stats.reject("truncated")
                del buf[:inner]
                continue
            packet = StatusPacket(device_id, error, bytes(buf[5:total - 1]))
            del buf[:total]
            if self._ids is not None and device_id not in self._ids:
                self.stats.reject("foreign")
                continue
            self.stats.packets += 1
            found.append(packet)
