"""Koala BEAR packets: an encoder per instruction, value decoding, and `StatusParser`, which resynchronises on the
header and rejects what is not a status packet. Pure: no I/O.

Wire format (Dynamixel-1.0-like; Westwood's PyBEAR SDK and BRUCE-OP v0.0.7)::

    instruction   FF FF ID LEN INSTR params... CHK
    status reply  FF FF ID LEN ERROR data...   CHK

LEN = n_params + 2 (the bytes after it); CHK = ~(ID + LEN + INSTR/ERROR + params) & 0xFF. Register values are 4
bytes little-endian, float32 or uint32 by register. Writes (WRITE_STAT, WRITE_CFG, SAVE_CFG) get no reply.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from drivers.bear_registers import (
    BROADCAST_ID,
    FLOAT32_MAX,
    HEADER,
    MAX_BULK_REGISTERS,
    MAX_DEVICE_ID,
    MAX_PARAMS,
    RATED_LIMITS,
    Instruction,
    Register,
    error_flags,
)
from drivers.errors import LinkStats
from drivers.framing import seek_header


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


class BulkLayout:
    """One BULK_COMM's shape, the IDs with the read and write registers, validated once; `encode(values)` packs a
    request of that shape. The bus thread sends the same shape every cycle (`bulk_layout` keeps them): its checks and
    packing formats are built once, not every millisecond.

    BULK_COMM (0x12) goes to the broadcast ID: params N, (n_read << 4 | n_write), read addresses, write addresses,
    then per motor its ID and 4 bytes per write register. Every listed motor answers one status packet (LEN = 4 n_read
    + 2) in request order, none if n_read = 0."""

    def __init__(self, ids: Sequence[int], read_regs: Sequence[Register], write_regs: Sequence[Register] = ()):
        ids = tuple(int(i) for i in ids)
        if not ids or len(set(ids)) != len(ids) or not all(0 <= i <= MAX_DEVICE_ID for i in ids):
            raise ValueError(f"BULK_COMM needs distinct device IDs in 0..{MAX_DEVICE_ID}, got {list(ids)}")
        for regs in (read_regs, write_regs):
            if len(regs) > MAX_BULK_REGISTERS:
                raise ValueError(f"BULK_COMM takes at most {MAX_BULK_REGISTERS} read and {MAX_BULK_REGISTERS} write "
                                 "registers")
            if any(r.table != "status" for r in regs):
                raise ValueError("BULK_COMM reaches status registers only")
        if any(not r.writable for r in write_regs):
            raise ValueError(f"read-only registers cannot be written: {[r.name for r in write_regs if not r.writable]}")
        self.ids, self.reads, self.writes = ids, tuple(read_regs), tuple(write_regs)
        self.read_names = tuple(r.name for r in read_regs)
        self.unpack_reply = struct.Struct("<" + "".join(r.fmt for r in read_regs)).unpack  # one reply's data
        self._head = (bytes((len(ids), len(read_regs) << 4 | len(write_regs)))
                      + bytes(r.address for r in read_regs) + bytes(r.address for r in write_regs))
        self._pack = struct.Struct("<" + ("B" + "".join(r.fmt for r in write_regs)) * len(ids)).pack
        # Each f32 goal's bound, beyond which `Register.check` refuses it (the rated current, else float32's range):
        # values within every bound are packed as they are; any other goes through `check`, which names the problem.
        self._bounds = (tuple(RATED_LIMITS.get(r.name, FLOAT32_MAX) for r in write_regs) * len(ids)
                        if write_regs and all(r.kind == "f32" for r in write_regs) else None)
        self._ids_placed: list[int | float] = [0] * (len(ids) * (len(write_regs) + 1))  # ID, then its values
        self._ids_placed[::len(write_regs) + 1] = ids

    def encode(self, values=None) -> bytes:
        """The request; `values[k][j]` is motor ids[k]'s value of write_regs[j] (rows, or an array of them)."""
        if not self.writes:
            return encode_frame(BROADCAST_ID, Instruction.BULK_COMM, self._head + bytes(self.ids))
        return encode_frame(BROADCAST_ID, Instruction.BULK_COMM, self._head + self._pack(*self._flat(values)))

    def _flat(self, values) -> list[int | float]:
        """ID, its values, for each motor; every value checked."""
        if self._bounds is not None and values is not None:
            table = np.asarray(values)
            if table.dtype.kind in "fiub" and table.shape == (len(self.ids), len(self.writes)):
                goals = table.ravel().tolist()
                if all(-bound <= value <= bound for value, bound in zip(goals, self._bounds, strict=True)):
                    flat = self._ids_placed.copy()  # NaN is within no bound: it takes the path below
                    step = len(self.writes) + 1
                    for j in range(step - 1):
                        flat[1 + j::step] = goals[j::step - 1]
                    return flat
        flat = []
        rows = list(values if values is not None else ())
        if len(rows) != len(self.ids):
            raise ValueError(f"BULK_COMM needs one row of {len(self.writes)} values per ID ({len(self.ids)} IDs)")
        for device_id, row in zip(self.ids, rows, strict=True):
            row = list(row)
            if len(row) != len(self.writes):
                raise ValueError(f"ID {device_id}: {len(row)} values for {len(self.writes)} write registers")
            flat.append(device_id)
            flat.extend(r.check(v) for r, v in zip(self.writes, row, strict=True))
        return flat


@functools.lru_cache(maxsize=256)
def _cached_layout(ids: tuple[int, ...], read_regs: tuple[Register, ...], write_regs: tuple[Register, ...]):
    return BulkLayout(ids, read_regs, write_regs)


def bulk_layout(ids: Sequence[int], read_regs: Sequence[Register], write_regs: Sequence[Register] = ()
                ) -> BulkLayout:
    """The layout of this shape, built once (a bus asks the same few shapes over and over: its cycle, the cycle with
    its monitoring reads, the retries to the IDs that did not answer)."""
    return _cached_layout(tuple(int(i) for i in ids), tuple(read_regs), tuple(write_regs))


def encode_bulk(ids: Sequence[int], read_regs: Sequence[Register], write_regs: Sequence[Register] = (),
                values=None) -> bytes:
    """A BULK_COMM request (`BulkLayout`): `values[k][j]` is motor ids[k]'s value of write_regs[j], packed by type."""
    return bulk_layout(ids, read_regs, write_regs).encode(values)


def decode_values(registers: Sequence[Register], data: bytes) -> list[int | float]:
    """Typed values of a reply's data, one per register in order."""
    if len(data) != 4 * len(registers):
        raise ValueError(f"{len(data)} data bytes for {len(registers)} registers")
    return list(struct.unpack("<" + "".join(r.fmt for r in registers), data))


def reply_length(n_registers: int) -> int:
    """LEN of a reply carrying n register values."""
    return 4 * n_registers + 2


class StatusPacket(NamedTuple):  # a tuple: ten are made every bus cycle; a frozen dataclass takes twice as long
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

    def _reply_start_inside(self, buf: bytearray, base: int, total: int) -> int | None:
        """Where, inside the frame buf[base:base + total], the bytes read as the start of an expected reply: FF FF,
        an expected ID, the expected LEN, an error byte with bit 7 (those present in the buffer). FF FF alone is not
        enough: a float32 value holds it (present_iq 4.28 A is ff ff 88 40), and a motor at rest sends it every
        cycle."""
        start = base + 2
        while (inner := buf.find(HEADER, start, base + total)) != -1:
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
        # Walks the buffer by offset and drops what it has read once, at the end: the bus thread feeds ten replies a
        # cycle, and a cut at each would move the rest of the buffer each time.
        buf = self._buffer
        buf += data
        found: list[StatusPacket] = []
        stats, want_length, want_ids = self.stats, self._length, self._ids
        pos = 0
        try:
            while True:
                pos, at_header = seek_header(buf, HEADER, stats, pos)
                if not at_header or len(buf) - pos < 5:
                    return found
                device_id, length, error = buf[pos + 2], buf[pos + 3], buf[pos + 4]
                reason = None
                if device_id == 0xFF:  # FF FF FF: the header starts one byte later
                    reason = "garbage"
                elif device_id == BROADCAST_ID or not error & 0x80:  # an instruction packet, not a reply
                    reason = "foreign"
                elif length < 2 or (want_length is not None and length != want_length):
                    reason = "length"
                if reason:
                    stats.reject(reason)
                    pos += 1
                    continue
                total = 4 + length
                if len(buf) - pos < total:
                    return found
                if checksum(buf[pos + 2:pos + total - 1]) != buf[pos + total - 1]:
                    stats.reject("checksum")
                    pos += 1
                    continue
                inner = self._reply_start_inside(buf, pos, total)
                if inner is not None:
                    # A reply's start inside the frame: a reply cut short and completed by the next one's bytes, whose
                    # 8-bit checksum matched by chance (1 in 256), which would hand the loop a made-up sample.
                    # Resynchronise there.
                    stats.reject("truncated")
                    pos = inner
                    continue
                packet = StatusPacket(device_id, error, bytes(buf[pos + 5:pos + total - 1]))
                pos += total
                if want_ids is not None and device_id not in want_ids:
                    stats.reject("foreign")
                    continue
                stats.packets += 1
                found.append(packet)
        finally:
            del buf[:pos]
