"""ROBOTIS Protocol 2.0 without I/O: instructions and error numbers, CRC-16, byte stuffing, packets (`encode_packet`,
`encode_status`, `PacketParser`), and the decoding of the status error byte and of the X-series Hardware Error Status.
The emulator (`drivers/emulators/dynamixel.py`) speaks through it; the driver (`drivers/dynamixel.py`) leaves the
wire to ROBOTIS' dynamixel-sdk."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from drivers.errors import LinkStats
from drivers.framing import skip_to_header

# -- protocol constants (ROBOTIS Protocol 2.0) ------------------------------------------------------------------
HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
MAX_PACKET_LENGTH = 1024          # LEN field bound, as the SDK's RXPACKET_MAX_LEN

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REG_WRITE = 0x04
INST_ACTION = 0x05
INST_FACTORY_RESET = 0x06
INST_REBOOT = 0x08
INST_CLEAR = 0x10
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83
INST_BULK_READ = 0x92
INST_BULK_WRITE = 0x93

# Status packet error byte: bit 7 = Alert (see Hardware Error Status), low 7 bits = an error number.
ERROR_ALERT = 0x80
ERROR_NAMES = {1: "result fail", 2: "instruction error", 3: "crc error", 4: "data range error",
               5: "data length error", 6: "data limit error", 7: "access error"}
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(1, 8)

# Hardware Error Status (address 70) bits, X-series.
HARDWARE_ERROR_BITS = {"input_voltage": 0, "overheating": 2, "motor_encoder": 3, "electrical_shock": 4,
                       "overload": 5}


# -- CRC, stuffing, packets ------------------------------------------------------------------------------------
def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """ROBOTIS CRC-16: polynomial 0x8005, initial value 0, not reflected (CRC-16/BUYPASS)."""
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Byte stuffing of instruction + parameters: FD is inserted after every FF FF FD, so that the header pattern
    never appears inside a packet."""
    out = bytearray()
    for i, byte in enumerate(body):
        out.append(byte)
        if byte == 0xFD and i >= 2 and body[i - 2] == 0xFF and body[i - 1] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def _is_stuffing(buf: bytes | bytearray, i: int) -> bool:
    """True when buf[i] is a stuffing byte: an FD right after FF FF FD in the stuffed stream."""
    return i >= 3 and buf[i] == 0xFD and buf[i - 3:i] == b"\xff\xff\xfd"


def unstuff(body: bytes | bytearray) -> bytes:
    """Inverse of `stuff` (on the stuffed stream, the FD that follows FF FF FD is always a stuffing byte)."""
    return bytes(b for i, b in enumerate(body) if not _is_stuffing(body, i))


def encode_packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One Protocol 2.0 packet: header, ID, LEN (after stuffing, CRC included), stuffed instruction + params, CRC
    over everything before it."""
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    head = HEADER + bytes([dxl_id & 0xFF, length & 0xFF, length >> 8]) + body
    return head + crc16(head).to_bytes(2, "little")


def encode_status(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    return encode_packet(dxl_id, INST_STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True, slots=True)
class Packet:
    """A packet found in a byte stream; `params` are unstuffed. For a status packet (instruction 0x55) the first
    parameter is the error byte: see `error` and `data`."""

    id: int
    instruction: int
    params: bytes

    @property
    def is_status(self) -> bool:
        return self.instruction == INST_STATUS

    @property
    def error(self) -> int:
        return self.params[0] if self.is_status and self.params else 0

    @property
    def data(self) -> bytes:
        return self.params[1:] if self.is_status else self.params


class PacketParser:
    """Finds Protocol 2.0 packets in a byte stream fed in arbitrary chunks.

    Garbage before a header, impossible lengths, CRC failures, cut-short packets and invalid IDs are counted in
    `stats` by reason ("garbage", "length", "crc", "truncated", "id") and skipped; nothing is raised. After a bad
    packet the search restarts one byte after its header, and a packet still arriving is given up as "truncated" as
    soon as a complete packet with a valid CRC shows up after its header, so a cut-short packet or a corrupted LEN
    cannot hide the packets that follow.
    """

    def __init__(self, stats: LinkStats | None = None, max_length: int = MAX_PACKET_LENGTH):
        self.stats = stats if stats is not None else LinkStats()
        self.max_length = max_length
        self._buf = bytearray()
        self._crc_failed_ids: list[int] = []

    @property
    def pending(self) -> int:
        """Bytes held back: the start of a packet still arriving (or a possible header prefix)."""
        return len(self._buf)

    def discard(self) -> None:
        """Drop a partial packet (the sender stopped mid-packet)."""
        if self._buf:
            self.stats.reject("truncated" if self._buf.startswith(HEADER) else "garbage")
            self._buf.clear()

    def take_crc_failures(self) -> list[int]:
        """IDs of the packets rejected for their CRC since the last call (a device answers those with a CRC error)."""
        ids, self._crc_failed_ids = self._crc_failed_ids, []
        return ids

    def _next_complete_packet(self, buf: bytearray) -> int:
        """Start of the first complete packet with a valid CRC after buf[0], or -1. Stuffing keeps the header
        pattern out of packet bodies, so a hit inside a packet still arriving is not a real packet's body."""
        j = buf.find(HEADER, 1)
        while j >= 0 and j + 7 <= len(buf):
            length = buf[j + 5] | (buf[j + 6] << 8)
            end = j + 7 + length
            if 3 <= length <= self.max_length and end <= len(buf) and \
                    crc16(memoryview(buf)[j:end - 2]) == buf[end - 2] | (buf[end - 1] << 8):
                return j
            j = buf.find(HEADER, j + 1)
        return -1

    def feed(self, data: bytes) -> list[Packet]:
        buf = self._buf
        buf.extend(data)
        found: list[Packet] = []
        while True:
            if not skip_to_header(buf, HEADER, self.stats):
                return found
            if len(buf) < 7:
                return found
            length = buf[5] | (buf[6] << 8)
            if length < 3 or length > self.max_length:  # at least instruction + CRC
                self.stats.reject("length")
                del buf[:1]
                continue
            if len(buf) < 7 + length:
                later = self._next_complete_packet(buf)
                if later < 0:
                    return found
                # A complete, valid packet after this header: this one was truncated (or its LEN corrupted).
                self.stats.reject("truncated")
                del buf[:later]
                continue
            end = 7 + length
            if crc16(memoryview(buf)[:end - 2]) != buf[end - 2] | (buf[end - 1] << 8):
                later = self._next_complete_packet(buf)
                if 0 < later < end:  # a good packet starts inside: this one was cut short, not garbled
                    self.stats.reject("truncated")
                    del buf[:later]
                    continue
                self.stats.reject("crc")
                self._crc_failed_ids.append(buf[4])
                del buf[:1]
                continue
            inner = buf.find(HEADER, 7, end - 2)
            if 0 <= inner <= end - 2 - len(HEADER):
                # A header inside the (stuffed) body: this packet was cut short and a later one's bytes completed
                # it, with a CRC that matches by chance (1 in 65536): the packet starts at that header.
                self.stats.reject("truncated")
                del buf[:inner]
                continue
            dxl_id, body = buf[4], unstuff(buf[7:end - 2])
            del buf[:end]
            if dxl_id > MAX_ID and dxl_id != BROADCAST_ID:
                self.stats.reject("id")
                continue
            self.stats.packets += 1
            found.append(Packet(dxl_id, body[0], bytes(body[1:])))


# -- decoding of errors and units ------------------------------------------------------------------------------
def decode_status_error(error: int) -> list[str]:
    """Named flags of a status packet's error byte (empty when 0)."""
    names = []
    number = error & 0x7F
    if number:
        names.append(ERROR_NAMES.get(number, f"error {number}"))
    if error & ERROR_ALERT:
        names.append("alert")
    return names


def decode_hardware_error(status: int) -> list[str]:
    """Named flags of Hardware Error Status (address 70); unknown bits as 'bit N'."""
    names = [name for name, bit in HARDWARE_ERROR_BITS.items() if status & (1 << bit)]
    known = sum(1 << bit for bit in HARDWARE_ERROR_BITS.values())
    names += [f"bit {bit}" for bit in range(8) if status & ~known & (1 << bit)]
    return names


def encode_hardware_error(flags: Sequence[str]) -> int:
    unknown = [f for f in flags if f not in HARDWARE_ERROR_BITS]
    if unknown:
        raise ValueError(f"unknown hardware error flag(s) {unknown}; expected {sorted(HARDWARE_ERROR_BITS)}")
    return sum(1 << HARDWARE_ERROR_BITS[f] for f in set(flags))
