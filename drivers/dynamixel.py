"""BRUCE's arms: six Dynamixel X-series servos (IDs 11-16), Protocol 2.0 at 2 Mbaud, through ROBOTIS' dynamixel-sdk.

Two parts:

* The Protocol 2.0 wire format without I/O (`crc16`, `stuff`/`unstuff`, `encode_packet`, `PacketParser`), error-byte
  and Hardware Error Status decoding, and the joint <-> servo unit conversions. The emulator
  (`drivers/emulators/dynamixel.py`) speaks through this part; the driver itself leaves the wire to the SDK.
* `DynamixelArms`, the driver: the SDK's PortHandler and PacketHandler(2.0), a GroupSyncRead of present position and
  velocity and a GroupSyncWrite of goal position, per tick; the Bus Watchdog set up so that a killed host or an
  unplugged bus stops the arms (docs/safety.md). Choices where BRUCE-OP v0.0.7's `run_dxl` and the SDK are silent
  are noted at the code that makes them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.errors import PORT_ERRORS, BusTimeout, DeviceFault, DriverError, LinkStats
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

# -- X-series control table addresses used by the driver ----------------------------------------------------------
ADDR_DRIVE_MODE = 10
ADDR_OPERATING_MODE = 11
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_POSITION_D_GAIN = 80
ADDR_POSITION_I_GAIN = 82
ADDR_POSITION_P_GAIN = 84
ADDR_BUS_WATCHDOG = 98
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
ADDR_PRESENT_INPUT_VOLTAGE = 144  # 0.1 V per count, 2 bytes
ADDR_PRESENT_TEMPERATURE = 146    # deg C, 1 byte
ADDR_INDIRECT_READ = 178          # Indirect Address 6 (168 + 2 * 5)
ADDR_INDIRECT_DATA_READ = 229     # Indirect Data 6 (224 + 5)
READ_BLOCK_LENGTH = 8             # present position (4) then present velocity (4)
OPERATING_MODE_POSITION = 3
BUS_WATCHDOG_UNIT_S = 0.02        # seconds per count of Bus Watchdog (the 50 Hz arm loop sends a packet every 20 ms)
BUS_WATCHDOG_MAX = 127            # counts (2.54 s)
BUS_WATCHDOG_ERROR = -1           # Bus Watchdog reads -1 (0xFF) after it stopped the servo

# -- X-series units -----------------------------------------------------------------------------------------------
POSITION_UNIT = 2.0 * math.pi / 4096.0         # rad per count
VELOCITY_UNIT = 0.229 * 2.0 * math.pi / 60.0   # rad/s per count (0.229 rpm)
CENTER_COUNTS = 2048                           # servo angle pi = joint 0 (servo angle = sign * q + pi)
POSITION_COUNTS_MAX = 4095                     # position mode range 0..4095


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


def counts_to_joint(counts: np.ndarray, signs: np.ndarray) -> np.ndarray:
    return signs * (np.asarray(counts, dtype=np.float64) - CENTER_COUNTS) * POSITION_UNIT


def joint_to_counts(q: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """Goal position counts of joint angles, rounded and clipped to the position-mode range."""
    counts = np.rint(CENTER_COUNTS + signs * np.asarray(q, dtype=np.float64) / POSITION_UNIT)
    return np.clip(counts, 0, POSITION_COUNTS_MAX).astype(np.int64)


def velocity_counts_to_joint(counts: np.ndarray, signs: np.ndarray) -> np.ndarray:
    return signs * np.asarray(counts, dtype=np.float64) * VELOCITY_UNIT


def joint_velocity_to_counts(qd: np.ndarray, signs: np.ndarray) -> np.ndarray:
    return np.rint(signs * np.asarray(qd, dtype=np.float64) / VELOCITY_UNIT).astype(np.int64)


def decode_read_block(data: bytes) -> tuple[int, int]:
    """The 8-byte indirect block -> (present position, present velocity) as signed counts."""
    if len(data) != READ_BLOCK_LENGTH:
        raise ValueError(f"read block of {len(data)} bytes, expected {READ_BLOCK_LENGTH}")
    return (int.from_bytes(data[0:4], "little", signed=True), int.from_bytes(data[4:8], "little", signed=True))


def watchdog_counts(watchdog_s: float) -> int:
    """Bus Watchdog register value for `watchdog_s` seconds: 0 for 0 (off), else round(watchdog_s / 20 ms), which
    must be 1..127 (0.02..2.54 s): ValueError otherwise."""
    seconds = float(watchdog_s)
    if seconds == 0.0:
        return 0
    counts = round(seconds / BUS_WATCHDOG_UNIT_S) if math.isfinite(seconds) else -1
    if not 1 <= counts <= BUS_WATCHDOG_MAX:
        raise ValueError(f"watchdog_s: {watchdog_s!r} s is not a Dynamixel Bus Watchdog setting; expected 0 (off) or "
                         f"{BUS_WATCHDOG_UNIT_S:g}..{BUS_WATCHDOG_MAX * BUS_WATCHDOG_UNIT_S:g} s "
                         f"(1..{BUS_WATCHDOG_MAX} units of {BUS_WATCHDOG_UNIT_S * 1000:g} ms)")
    return counts


def indirect_read_map() -> bytes:
    """The 16 bytes written at Indirect Address 6..13: the byte addresses of present position, then velocity (BRUCE's
    indirect block), so that Indirect Data 6..13 (229..236) are one 8-byte GroupSyncRead."""
    addresses = [ADDR_PRESENT_POSITION + i for i in range(4)] + [ADDR_PRESENT_VELOCITY + i for i in range(4)]
    return b"".join(a.to_bytes(2, "little") for a in addresses)


# -- SDK glue ----------------------------------------------------------------------------------------------------
_PORT_CLASS: type | None = None
READ_SLICE_S = 0.0005  # the longest one poll of the port blocks (see DynamixelArms.open)


def _bounded_port_class() -> type:
    """The SDK's PortHandler with the latency term of its packet timeout configurable: wire time + 2 x latency + 2 ms
    (the SDK hard-codes 16 ms; BRUCE sets the FTDI latency timer to 1 ms, and the default 2 ms makes a sync read give
    up about 6.6 ms after its request)."""
    global _PORT_CLASS
    if _PORT_CLASS is None:
        from dynamixel_sdk import PortHandler

        class BoundedPortHandler(PortHandler):
            def __init__(self, port_name: str, latency_ms: float):
                super().__init__(port_name)
                self.latency_ms = latency_ms

            def setPacketTimeout(self, packet_length):  # noqa: N802 (SDK name)
                self.packet_start_time = self.getCurrentTime()
                self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * self.latency_ms + 2.0

        _PORT_CLASS = BoundedPortHandler
    return _PORT_CLASS


def collect_status(port: Any, ids: Sequence[int], length: int, stats: LinkStats,
                   guard_s: float = 0.1) -> tuple[dict[int, bytes], dict[int, int]]:
    """After a SYNC_READ request: the status packets of `ids`, read with the port's `readPort` until all have come
    or the SDK's packet timeout (`isPacketTimeout`, and `guard_s` in any case) has passed.

    The bytes go through `PacketParser` rather than the SDK's rxPacket: after a cut-short reply the SDK's parser
    swallows the start of the next servo's reply, which would then be reported silent; this one resynchronises.
    Returns ({id: data}, {id: error byte}) for the IDs that answered with `length` bytes and no error number; a
    packet with an error number is kept in the second dict only. Foreign packets, duplicates and wrong lengths are
    counted in `stats` (as the parser counts garbage, CRC failures and truncation) and skipped.
    """
    parser = PacketParser(stats)
    wanted = set(ids)
    data: dict[int, bytes] = {}
    errors: dict[int, int] = {}
    deadline = time.monotonic() + guard_s
    while len(data) < len(wanted):
        chunk = port.readPort(4096)
        if not chunk:
            if port.isPacketTimeout() or time.monotonic() > deadline:
                parser.discard()
                break
            time.sleep(0.0001)  # let the device (or the emulator's thread) run
            continue
        for packet in parser.feed(bytes(chunk)):
            if not packet.is_status or packet.id not in wanted or packet.id in data or not packet.params:
                stats.reject("foreign")  # includes an adapter echoing our own request
            elif packet.error & 0x7F:
                stats.reject("status_error")
                errors[packet.id] = packet.error
            elif len(packet.data) != length:
                stats.reject("length")
            else:
                data[packet.id] = packet.data
                errors[packet.id] = packet.error
    return data, errors


# -- the driver --------------------------------------------------------------------------------------------------
class DynamixelArms:
    """BRUCE's six arm servos on one Protocol 2.0 bus, in joint units and in the order of `ids` (and `names`).

    Typical use::

        arms = DynamixelArms.open("/dev/ttyUSB1", 2_000_000, ids)       # ping all, set up with torque off
        arms.hold(pose)                                                 # torque on, goal = pose
        q, qd = arms.read()                                             # one GroupSyncRead
        arms.write_positions(q_goal)                                    # one GroupSyncWrite
        arms.close()                                                    # torque off, port closed

    Every transaction is bounded by the SDK's packet timeout; silence raises `BusTimeout` naming the silent IDs, a
    servo's error raises `DeviceFault` with named flags. `stats` counts packets, rejections, timeouts and retries.
    """

    def __init__(self, port: str, baud: int, ids: Sequence[int], *,
                 signs: Sequence[float] | None = None, names: Sequence[str] | None = None,
                 lower: Sequence[float] | None = None, upper: Sequence[float] | None = None,
                 hold_pose: Sequence[float] | None = None, latency_ms: float = 2.0, retries: int = 1,
                 position_p_gain: int = 800, torque_off_on_close: bool = True, watchdog_s: float = 0.0):
        self.port_name = port
        self.baud = int(baud)
        self.ids = tuple(int(i) for i in ids)
        n = len(self.ids)
        if n == 0 or len(set(self.ids)) != n or not all(0 <= i <= MAX_ID for i in self.ids):
            raise ValueError(f"ids must be unique servo IDs in 0..{MAX_ID}, got {self.ids}")
        if signs is None:
            signs = (1.0,) * n
        self.signs = self._vector(signs, "signs")
        self.names = tuple(names) if names is not None else tuple(f"dxl{i}" for i in self.ids)
        self.lower = self._vector(lower, "lower") if lower is not None else None
        self.upper = self._vector(upper, "upper") if upper is not None else None
        self.hold_pose = self._vector(hold_pose, "hold_pose") if hold_pose is not None else None
        self.latency_ms = float(latency_ms)
        self.retries = int(retries)
        self.position_p_gain = int(position_p_gain)
        self.torque_off_on_close = torque_off_on_close
        self.watchdog_s = float(watchdog_s)
        self.watchdog_counts = watchdog_counts(watchdog_s)   # Bus Watchdog value set up (0: not configured)
        self.bus = f"dynamixel {port}"
        self.stats = LinkStats()
        self.models: dict[int, int] = {}
        self.faults: dict[int, tuple[str, ...]] = {}
        self.torque_enabled = False
        self._torque_touched = False       # some servo may have torque on: close() turns it off
        self._torque_failed: tuple[int, ...] = ()   # IDs whose last torque enable / off failed
        self._watchdog_touched = False     # Bus Watchdog was written: close() writes 0
        self.stamp = 0.0                   # time.monotonic() of the last good read
        self._port: Any = None
        self._ph: Any = None
        self._sync_read: Any = None
        self._sync_write: Any = None

    def _vector(self, values: Sequence[float], what: str) -> np.ndarray:
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        if array.shape != (len(self.ids),):
            raise ValueError(f"{what}: expected {len(self.ids)} values (one per ID {self.ids}), got {array.shape[0]}")
        return array

    # -- life cycle ------------------------------------------------------------------------------------------
    @classmethod
    def open(cls, port: str, baud: int, ids: Sequence[int], **options) -> DynamixelArms:
        """Open the port, ping every servo (BusTimeout names the missing ones) and set them up, torque disabled."""
        arms = cls(port, baud, ids, **options)
        arms.connect()
        try:
            arms.ping()
            arms.setup()
        except BaseException:
            arms.close()
            raise
        return arms

    @classmethod
    def from_config(cls, config: Any, port: str | None = None, **options) -> DynamixelArms:
        """`open` with `buses.dynamixel` (watchdog_s included, unless given) and `arms` of a
        `bruce_hw.config.RobotConfig`."""
        bus, arms = config.buses.dynamixel, config.arms
        options.setdefault("watchdog_s", getattr(bus, "watchdog_s", 0.0))
        return cls.open(port or bus.port, bus.baud, bus.ids, names=arms.names, lower=arms.lower, upper=arms.upper,
                        hold_pose=arms.hold_pose, signs=arms.servo_signs, **options)

    def connect(self) -> None:
        """Open the serial port (no traffic)."""
        try:
            from dynamixel_sdk import GroupSyncRead, GroupSyncWrite, PacketHandler
        except ImportError as exc:
            raise DriverError(f"{self.bus}: the dynamixel-sdk package is not installed ({exc})") from exc

        port = _bounded_port_class()(self.port_name, self.latency_ms)
        try:
            opened = port.openPort() and port.setBaudRate(self.baud)
        except Exception as exc:  # serial.SerialException, OSError
            raise DriverError(f"{self.bus}: cannot open at {self.baud} baud: {exc}") from exc
        if not opened:
            raise DriverError(f"{self.bus}: cannot open at {self.baud} baud (unsupported rate?)")
        # The SDK opens its pyserial port with timeout 0 and polls it in a loop until a reply or its packet timeout
        # (up to 2 x latency + 2 ms): a busy loop that holds the GIL and the CPU. A read slice makes each poll block
        # in select instead; the packet timeout still bounds the whole wait.
        port.ser.timeout = READ_SLICE_S
        self._port, self._ph = port, PacketHandler(2.0)
        self._sync_read = GroupSyncRead(port, self._ph, ADDR_INDIRECT_DATA_READ, READ_BLOCK_LENGTH)
        self._sync_write = GroupSyncWrite(port, self._ph, ADDR_GOAL_POSITION, 4)
        for dxl_id in self.ids:
            self._sync_read.addParam(dxl_id)
            self._sync_write.addParam(dxl_id, [0, 0, 0, 0])

    def close(self) -> None:
        """Torque off (if it was ever on and `torque_off_on_close`, as BRUCE-OP's run_dxl does on exit), then Bus
        Watchdog 0 on the servos known to be torque-off (if setup wrote it), then the port closed. Best effort: errors
        are swallowed."""
        if self._port is None:
            return
        try:
            off: list[int] = list(self.ids)     # the servos known to be torque-off
            if self._torque_touched:
                off = []
                if self.torque_off_on_close:
                    try:
                        self.disable_torque()
                    except DriverError:
                        pass  # closing anyway: the bus may be the reason we are closing
                    off = [i for i in self.ids if i not in self._torque_failed]
            if self._watchdog_touched and off:
                # Never leave a servo with torque on and no watchdog: only the torque-off ones are cleared.
                try:
                    self.clear_watchdog(off)
                except DriverError:
                    pass
        finally:
            try:
                self._port.closePort()
            except Exception:
                pass
            self._port = None

    def __enter__(self) -> DynamixelArms:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._port is not None

    def _require_open(self) -> None:
        if self._port is None:
            raise DriverError(f"{self.bus}: not open")

    # -- single transactions (set-up, diagnostics) ---------------------------------------------------------
    def _transact(self, what: str, dxl_id: int, call, *args) -> tuple[Any, int]:
        """One request/status exchange with retries; returns (value, error byte) or raises BusTimeout."""
        from dynamixel_sdk import COMM_SUCCESS

        self._require_open()
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retries += 1
            try:
                out = call(self._port, dxl_id, *args)
            except PORT_ERRORS as exc:  # serial.SerialException included: the adapter went away
                raise DriverError(f"{self.bus}: {what} (ID {dxl_id}): {exc}") from exc
            finally:
                self._port.is_using = False
            value, result, error = out if len(out) == 3 else (None, *out)
            if result == COMM_SUCCESS:
                self.stats.packets += 1
                return value, error
            self.stats.timeouts += 1
        raise BusTimeout(self.bus, [dxl_id], what)

    def _checked(self, what: str, dxl_id: int, call, *args, alert_ok: bool = False) -> Any:
        """`_transact`, with a protocol error number, or the Alert bit (then Hardware Error Status is read for the
        flags' names), raised as `DeviceFault`."""
        value, error = self._transact(what, dxl_id, call, *args)
        if error & 0x7F or (error & ERROR_ALERT and not alert_ok):
            self._raise_error(dxl_id, error)
        return value

    def _raise_error(self, dxl_id: int, error: int) -> None:
        flags = [f for f in decode_status_error(error) if f != "alert"]
        if error & ERROR_ALERT:
            hardware = self.read_hardware_error(dxl_id)
            flags += decode_hardware_error(hardware) or ["alert"]
        self.faults[dxl_id] = tuple(flags)
        raise DeviceFault(self.bus, dxl_id, flags)

    def read_hardware_error(self, dxl_id: int) -> int:
        """Hardware Error Status (70) of one servo (the raw bits; see `decode_hardware_error`)."""
        value, _ = self._transact("read hardware error status", dxl_id, self._ph.read1ByteTxRx, ADDR_HARDWARE_ERROR)
        return int(value)

    def ping(self) -> dict[int, int]:
        """Model number of every servo; BusTimeout names all that did not answer."""
        missing = []
        for dxl_id in self.ids:
            try:
                model, error = self._transact("ping", dxl_id, self._ph.ping)
            except BusTimeout:
                missing.append(dxl_id)
                continue
            self.models[dxl_id] = int(model)
        if missing:
            raise BusTimeout(self.bus, missing, "ping")
        return dict(self.models)

    def setup(self) -> None:
        """Torque off, then drive mode 0, position mode, position PID gains and the indirect read block. The servos'
        own position limits (EEPROM 48/52) are left at their defaults: `goal_counts` clips instead."""
        block = list(indirect_read_map())
        for dxl_id in self.ids:
            self._checked("torque off", dxl_id, self._ph.write1ByteTxRx, ADDR_TORQUE_ENABLE, 0)
            self._checked("drive mode", dxl_id, self._ph.write1ByteTxRx, ADDR_DRIVE_MODE, 0)
            self._checked("operating mode", dxl_id, self._ph.write1ByteTxRx, ADDR_OPERATING_MODE,
                          OPERATING_MODE_POSITION)
            self._checked("position P gain", dxl_id, self._ph.write2ByteTxRx, ADDR_POSITION_P_GAIN,
                          self.position_p_gain)
            self._checked("position I gain", dxl_id, self._ph.write2ByteTxRx, ADDR_POSITION_I_GAIN, 0)
            self._checked("position D gain", dxl_id, self._ph.write2ByteTxRx, ADDR_POSITION_D_GAIN, 0)
            self._checked("indirect addresses", dxl_id, self._ph.writeTxRx, ADDR_INDIRECT_READ, len(block), block)
        self.torque_enabled = False
        if self.watchdog_counts:
            self.configure_watchdog()

    # -- Bus Watchdog ------------------------------------------------------------------------------------------
    def _write_watchdog(self, dxl_id: int, value: int, alert_ok: bool = False) -> None:
        try:
            self._checked(f"write Bus Watchdog (98) = {value}", dxl_id, self._ph.write1ByteTxRx, ADDR_BUS_WATCHDOG,
                          value & 0xFF, alert_ok=alert_ok)
        except DeviceFault as exc:
            flags = (*exc.flags, f"on write of Bus Watchdog (98) = {value}")
            self.faults[dxl_id] = flags
            raise DeviceFault(self.bus, dxl_id, flags) from exc

    def configure_watchdog(self) -> None:
        """Bus Watchdog = `watchdog_counts` on every servo: 0 first (clears a Bus Watchdog Error, e.g. one a killed
        previous run left), then the value, then read back: DeviceFault naming the servo and the register if it
        reads back otherwise. `setup()` calls it when `watchdog_s` > 0; it may be called again (torque on or off) to
        re-arm the watchdog after an error."""
        self._watchdog_touched = True
        for dxl_id in self.ids:
            self._write_watchdog(dxl_id, 0)
            if self.watchdog_counts:
                self._write_watchdog(dxl_id, self.watchdog_counts)
        for dxl_id, value in self.read_watchdog().items():
            if value != self.watchdog_counts:
                flags = (f"Bus Watchdog (98) reads back {value}, expected {self.watchdog_counts}",)
                self.faults[dxl_id] = flags
                raise DeviceFault(self.bus, dxl_id, flags)

    def read_watchdog(self) -> dict[int, int]:
        """Bus Watchdog (98) of every servo, {ID: value} as a signed byte: 0 off, 1..127 armed (units of
        `BUS_WATCHDOG_UNIT_S`), -1 (`BUS_WATCHDOG_ERROR`) the watchdog stopped that servo."""
        values = {}
        for dxl_id in self.ids:
            raw = int(self._checked("read Bus Watchdog (98)", dxl_id, self._ph.read1ByteTxRx, ADDR_BUS_WATCHDOG,
                                    alert_ok=True))
            values[dxl_id] = raw - 256 if raw & 0x80 else raw
        return values

    def clear_watchdog(self, ids: Sequence[int] | None = None) -> None:
        """Bus Watchdog 0 on `ids` (default: every servo): the watchdog off and a Bus Watchdog Error cleared. Every
        servo is tried (a hardware error alert does not stop it), then the first failure is raised."""
        failures: list[DriverError] = []
        for dxl_id in self.ids if ids is None else ids:
            try:
                self._write_watchdog(int(dxl_id), 0, alert_ok=True)
            except DriverError as exc:
                failures.append(exc)
        if failures:
            raise failures[0]

    def _set_torque(self, on: bool) -> None:
        """Every servo is tried, then the first failure is raised. Turning torque off succeeds on a servo that
        reports a hardware error (its write is still carried out)."""
        failures: list[DriverError] = []
        failed_ids: list[int] = []
        self._torque_touched |= on
        for dxl_id in self.ids:
            try:
                self._checked("torque enable" if on else "torque off", dxl_id, self._ph.write1ByteTxRx,
                              ADDR_TORQUE_ENABLE, int(on), alert_ok=not on)
            except DriverError as exc:
                failures.append(exc)
                failed_ids.append(dxl_id)
        self._torque_failed = tuple(failed_ids)
        self.torque_enabled = on and not failures
        if failures:
            silent = [i for exc in failures if isinstance(exc, BusTimeout) for i in exc.silent_ids]
            raise BusTimeout(self.bus, silent, "torque enable") if len(silent) == len(failures) else failures[0]

    def enable_torque(self) -> None:
        self._set_torque(True)

    def disable_torque(self) -> None:
        self._set_torque(False)

    # -- per tick ----------------------------------------------------------------------------------------------
    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """One GroupSyncRead: joint positions (rad) and velocities (rad/s) in `ids` order."""
        from dynamixel_sdk import COMM_SUCCESS

        self._require_open()
        try:
            result = self._sync_read.txPacket()
            if result != COMM_SUCCESS:
                raise DriverError(f"{self.bus}: sync read request not sent ({self._ph.getTxRxResult(result)})")
            data, errors = collect_status(self._port, self.ids, READ_BLOCK_LENGTH, self.stats)
        except PORT_ERRORS as exc:
            raise DriverError(f"{self.bus}: sync read: {exc}") from exc
        finally:
            self._port.is_using = False
        silent = [i for i in self.ids if i not in data]
        if silent:
            self.stats.timeouts += 1
            protocol_errors = {i: ", ".join(decode_status_error(errors[i])) for i in silent if i in errors}
            detail = "sync read of present position/velocity"
            if protocol_errors:
                detail += "; answered with " + "; ".join(f"ID {i}: {e}" for i, e in protocol_errors.items())
            raise BusTimeout(self.bus, silent, detail)
        alert = [i for i in self.ids if errors[i] & ERROR_ALERT]
        if alert:
            self._raise_error(alert[0], errors[alert[0]])
        blocks = [decode_read_block(data[i]) for i in self.ids]
        counts = np.array(blocks, dtype=np.int64).reshape(len(self.ids), 2)
        self.stamp = time.monotonic()
        return counts_to_joint(counts[:, 0], self.signs), velocity_counts_to_joint(counts[:, 1], self.signs)

    def goal_counts(self, q: Sequence[float]) -> np.ndarray:
        """Goal position counts for joint angles: clipped to the joint limits, then to 0..4095."""
        q = self._vector(q, "q")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{self.bus}: non-finite arm goal {q}")
        if self.lower is not None and self.upper is not None:
            q = np.clip(q, self.lower, self.upper)
        return joint_to_counts(q, self.signs)

    def write_positions(self, q: Sequence[float]) -> None:
        """One GroupSyncWrite of goal position (no status packets come back)."""
        from dynamixel_sdk import COMM_SUCCESS

        self._require_open()
        for dxl_id, count in zip(self.ids, self.goal_counts(q), strict=True):
            self._sync_write.changeParam(dxl_id, list(int(count).to_bytes(4, "little", signed=True)))
        try:
            result = self._sync_write.txPacket()
        except PORT_ERRORS as exc:
            raise DriverError(f"{self.bus}: sync write of goal position: {exc}") from exc
        finally:
            self._port.is_using = False
        if result != COMM_SUCCESS:
            raise DriverError(f"{self.bus}: sync write of goal position failed ({self._ph.getTxRxResult(result)})")

    def cycle(self, q_goal: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The per-tick I/O in one call: write the goals (if any), then read positions and velocities."""
        if q_goal is not None:
            self.write_positions(q_goal)
        return self.read()

    def hold(self, pose: Sequence[float] | None = None, ramp_s: float = 0.0, rate_hz: float = 50.0) -> None:
        """Hold the arms at `pose` (default: the configured hold pose): torque on, goal = pose. With `ramp_s` > 0 the
        goal moves linearly from the measured pose over that time (blocking, at `rate_hz`), as BRUCE-OP does."""
        if pose is None:
            if self.hold_pose is None:
                raise ValueError(f"{self.bus}: no pose given and no hold_pose configured")
            pose = self.hold_pose
        target = self._vector(pose, "pose")
        start = self.read()[0] if ramp_s > 0 else target
        if ramp_s > 0:
            # Goal = measured pose before torque goes on, so that enabling torque does not jump.
            self.write_positions(start)
        if not self.torque_enabled:
            self.enable_torque()
        steps = max(1, int(round(ramp_s * rate_hz)))
        for k in range(1, steps + 1):
            self.write_positions(start + (target - start) * (k / steps))
            if k < steps:
                time.sleep(1.0 / rate_hz)
