"""BRUCE's sense board (Raspberry Pi Pico, BRUCE-OP v0.0.5/v0.0.7 firmware) on USB serial: IMU and foot contacts.

The wire protocol (firmware `Library/BRUCE_SENSE/pico/pico.ino`, host `Manager.py`) without I/O: `encode_command`,
`encode_packet`, `check_packet`, `SenseParser`; and `SenseBoard`, a daemon thread that keeps the newest sample, with
the official start-up checks bounded in time. A packet carries what the hw backend's IMU sample wants (rad/s, m/s^2
specific force, IMU frame): no conversion is made. The board gives no orientation (the backend's attitude filter
adds it), the spec gives no IMU -> body rotation (the official estimator treats IMU axes as body axes), and it has
no e-stop input: BRUCE's wireless stop is wired to the BEARs, so an e-stop reaches the stack through their error
byte. Timestamps are the host's `time.monotonic()` when a packet's bytes were read (the board sends no time).
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from drivers.errors import PORT_ERRORS, BusTimeout, DriverError, LinkStats

HEADER = 0xFF
TRAILER = 0xFE
PACKET_LEN = 29
PACKET_REST_LEN = PACKET_LEN - 2  # the length byte: bytes after it
COMMAND_LEN = 5
COMMAND_REST_LEN = COMMAND_LEN - 2
CONTACT_MARK = 0x80        # bit 7 of the contact byte is always set
BIAS_REPORT_FLAGS = 0xFF   # contact byte of a calibration bias report
MAX_COOLING_SPEED = 10
FIRMWARE_GRAVITY = 9.80665  # m/s^2 per g in the firmware's accelerometer scale (ISM330DHCX.h)
_FLOATS = struct.Struct("<6f")
_HEADER_AND_LENGTH = bytes((HEADER, PACKET_REST_LEN))


class PicoMode(IntEnum):
    IDLE = 0
    NOMINAL = 1
    RESET = 2
    CALIBRATE = 3

    @classmethod
    def parse(cls, mode: PicoMode | int | str) -> PicoMode:
        if isinstance(mode, str):
            name = {"calibration": "calibrate", "stream": "nominal"}.get(mode.lower(), mode.lower())
            try:
                return cls[name.upper()]
            except KeyError:
                raise ValueError(f"unknown sense-board mode {mode!r} (idle, nominal, reset, calibrate)") from None
        return cls(mode)


def checksum(body: bytes | bytearray | memoryview) -> int:
    """NOT of the low byte of the sum: what both directions use over the bytes between header and checksum."""
    return ~sum(body) & 0xFF


# -- host -> board ---------------------------------------------------------------------------------------------
def encode_command(mode: PicoMode | int | str, cooling_speed: int = 0) -> bytes:
    """The 5-byte command ``0xFF | 3 | cooling_speed << 2 | mode | NOT(3 + that byte) & 0xFF | 0xFE`` (mode 0 idle,
    1 nominal (stream), 2 reset IMU (then idle), 3 calibrate; cooling 0..10); raises ValueError for a mode or
    cooling speed the firmware does not define. The firmware reads commands only once per second in NOMINAL mode
    (every ~10 ms in IDLE), the last valid command in its buffer wins, and the rest of the buffer is discarded."""
    mode = PicoMode.parse(mode)
    if not (isinstance(cooling_speed, int | np.integer) and 0 <= cooling_speed <= MAX_COOLING_SPEED):
        raise ValueError(f"cooling_speed must be an integer 0..{MAX_COOLING_SPEED}, got {cooling_speed!r}")
    byte = (int(cooling_speed) << 2) | int(mode)
    return bytes((HEADER, COMMAND_REST_LEN, byte, checksum((COMMAND_REST_LEN, byte)), TRAILER))


def decode_command(packet: bytes) -> tuple[PicoMode, int] | None:
    """(mode, cooling_speed) of one 5-byte command, or None when the firmware would ignore it."""
    if (len(packet) != COMMAND_LEN or packet[0] != HEADER or packet[1] != COMMAND_REST_LEN
            or packet[3] != checksum(packet[1:3]) or packet[4] != TRAILER):
        return None
    return PicoMode(packet[2] & 3), (packet[2] >> 2) & 15


# -- board -> host ---------------------------------------------------------------------------------------------
def contact_byte(contact) -> int:
    """The packet's contact byte for four booleans in FOOT_CONTACT_NAMES order."""
    flags = CONTACT_MARK
    for bit, c in enumerate(contact):
        if c:
            flags |= 1 << bit
    return flags


def encode_packet(accel, gyro, contact=(False,) * 4, *, bias_report: bool = False) -> bytes:
    """The 29-byte packet, 1 kHz, only in NOMINAL mode: ``0xFF | 27 | accel x,y,z float32 LE | gyro x,y,z float32 LE
    | contacts | checksum | 0xFE`` (values rounded to float32, as the board sends them). accel is the specific force
    (+g on the up axis at rest: the firmware's calibration subtracts g from z), gyro bias-corrected by the board.
    contacts: 0x80 | bits 0..3 in FOOT_CONTACT_NAMES order (1 = contact); 0xFF marks a calibration bias report.
    checksum = NOT(sum of bytes 1..26) & 0xFF."""
    flags = BIAS_REPORT_FLAGS if bias_report else contact_byte(contact)
    body = bytearray((PACKET_REST_LEN,))
    body += _FLOATS.pack(*(float(v) for v in accel), *(float(v) for v in gyro))
    body.append(flags)
    return bytes((HEADER, *body, checksum(body), TRAILER))


# Read-only contact arrays for each of the 16 contact patterns, shared by every sample.
_CONTACTS = tuple(np.array([(bits >> k) & 1 for k in range(4)], dtype=bool) for bits in range(16))
for _a in _CONTACTS:
    _a.flags.writeable = False


@dataclass(frozen=True, slots=True, eq=False)
class SenseSample:
    """One decoded packet. Arrays are read-only (shared with whoever holds the sample)."""

    accel: np.ndarray    # (3,) m/s^2, specific force, IMU frame
    gyro: np.ndarray     # (3,) rad/s, IMU frame
    contact: np.ndarray  # (4,) bool, FOOT_CONTACT_NAMES order
    bias_report: bool = False  # a calibration bias report: accel/gyro carry the biases, contact is meaningless


def check_packet(packet: bytes | bytearray | memoryview) -> str | None:
    """Why a 29-byte window is not a valid packet (a reject reason), or None when it is one."""
    if len(packet) != PACKET_LEN:
        return "truncated" if len(packet) < PACKET_LEN else "length"
    if packet[0] != HEADER:
        return "garbage"
    if packet[1] != PACKET_REST_LEN:
        return "length"
    if packet[PACKET_LEN - 1] != TRAILER:
        # A header inside the window means the packet was cut short and the next one began.
        return "truncated" if bytes(packet).find(_HEADER_AND_LENGTH, 1) >= 0 else "trailer"
    if packet[PACKET_LEN - 2] != checksum(packet[1:PACKET_LEN - 2]):
        return "checksum"
    flags = packet[PACKET_LEN - 3]
    if flags != BIAS_REPORT_FLAGS and flags & 0xF0 != CONTACT_MARK:
        return "flags"
    return None


def decode_packet(packet: bytes | bytearray | memoryview, offset: int = 0) -> SenseSample:
    """Decode a packet that `check_packet` accepted (no checks here)."""
    values = np.array(_FLOATS.unpack_from(packet, offset + 2))
    values.flags.writeable = False
    flags = packet[offset + PACKET_LEN - 3]
    bias = flags == BIAS_REPORT_FLAGS
    return SenseSample(accel=values[:3], gyro=values[3:], contact=_CONTACTS[0 if bias else flags & 0x0F],
                       bias_report=bias)


class SenseParser:
    """Incremental parser of the board's byte stream. Never raises on bad bytes: it counts them in `stats`
    and resynchronises on the next header (a failed candidate costs one byte, so a real packet that starts
    inside a false one is still found). Unlike the official host, which flushes its input after one packet, it
    keeps every packet. Reject reasons: "garbage" (bytes outside any packet, counted once per run), "length",
    "trailer", "checksum", "flags" (a contact byte that is neither 0x80..0x8F nor 0xFF), "truncated" (the next
    header appears inside a packet, or the stream stalls mid-packet)."""

    def __init__(self, stats: LinkStats | None = None):
        self.stats = stats if stats is not None else LinkStats()
        self.skipped_bytes = 0
        self._buf = bytearray()
        self._in_bad_run = False  # garbage right after a rejection is part of that rejection, not a new one

    @property
    def pending(self) -> int:
        """Bytes of a packet begun but not yet complete."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray) -> list[SenseSample]:
        buf = self._buf
        buf += data
        out: list[SenseSample] = []
        i, n = 0, len(buf)
        while i < n:
            j = buf.find(HEADER, i)
            if j < 0:
                self._skip(n - i)
                i = n
                break
            if j > i:
                self._skip(j - i)
                i = j
            if n - i < 2:
                break  # wait for the length byte
            if buf[i + 1] != PACKET_REST_LEN:
                self._reject("length")
                i += 1
                continue
            if n - i < PACKET_LEN:
                break  # wait for the rest
            reason = check_packet(buf[i:i + PACKET_LEN])  # a copy: no export pins the buffer
            if reason is not None:
                self._reject(reason)
                i += 1
                continue
            out.append(decode_packet(buf, i))
            self.stats.packets += 1
            self._in_bad_run = False
            i += PACKET_LEN
        del buf[:i]
        return out

    def drop_partial(self) -> None:
        """The rest of a begun packet did not come (the stream stalled): drop it as truncated."""
        if self._buf:
            self._reject("truncated")
            self.skipped_bytes += len(self._buf)
            self._buf.clear()

    def _skip(self, count: int) -> None:
        self.skipped_bytes += count
        if not self._in_bad_run:
            self._reject("garbage")

    def _reject(self, reason: str) -> None:
        self.stats.reject(reason)
        self._in_bad_run = True


# -- the board over pyserial -----------------------------------------------------------------------------------
class SenseBoard:
    """The sense board on a serial port, read by a daemon thread that keeps the latest sample.

    Usage (the hw backend)::

        board = SenseBoard("/dev/ttyACM0")  # opens the port and starts the reader (DriverError naming the port)
        board.start()                      # NOMINAL + the official start-up IMU check, bounded in time
        imu, contacts = board.read()       # per tick, never blocks; stamps are host monotonic time
        board.age()                        # seconds since the last packet (inf before the first)
        board.close()                      # board to IDLE, thread stopped, port closed
    """

    def __init__(self, port: str, baud: int = 115200, *, read_timeout_s: float = 0.005, write_timeout_s: float = 0.1,
                 stall_s: float = 0.010, stats: LinkStats | None = None):
        self.port = port
        self.baud = baud
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self.stall_s = stall_s
        self.stats = stats if stats is not None else LinkStats()
        self.mode = PicoMode.IDLE    # last commanded
        self.cooling_speed = 0       # last commanded
        self.error: BaseException | None = None  # why the reader thread stopped, if it did
        self._parser = SenseParser(self.stats)
        self._serial = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        self._latest: tuple[SenseSample | None, float, int] = (None, -math.inf, 0)  # swapped whole: atomic read
        self._collector: list[SenseSample] | None = None
        self._bias_reports: deque[SenseSample] = deque(maxlen=8)
        self.open()

    # -- lifecycle
    def open(self) -> SenseBoard:
        """Open the port and start the reader thread (done by the constructor; again after `close()`)."""
        if self._serial is not None:
            return self
        import serial  # lazy: the stack imports without pyserial

        try:
            self._serial = serial.Serial(self.port, self.baud, timeout=self.read_timeout_s,
                                         write_timeout=self.write_timeout_s, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as e:
            raise DriverError(f"{self.port}: cannot open the sense board: {e}") from e
        self._parser = SenseParser(self.stats)  # no half packet left over from before a close
        self._stop.clear()
        self._thread = threading.Thread(target=self._read_loop, name=f"sense-reader-{self.port}", daemon=True)
        self._thread.start()
        return self

    @property
    def thread(self) -> threading.Thread | None:
        """The reader thread (the hw backend schedules it with its other I/O threads)."""
        return self._thread

    def close(self) -> None:
        """Board to IDLE (as the official shutdown does, best effort), reader stopped, port closed."""
        if self._serial is None:
            return
        try:
            self.set_mode(PicoMode.IDLE)
        except DriverError:
            pass
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        try:
            self._serial.close()
        except Exception:  # closing must not fail the shutdown path
            pass
        self._serial = None

    def __enter__(self) -> SenseBoard:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        """The reader thread is running (False after close or after the port failed; see `error`)."""
        return self._thread is not None and self._thread.is_alive()

    # -- commands
    def set_mode(self, mode: PicoMode | int | str, cooling_speed: int | None = None) -> None:
        """Send a mode (and cooling speed, default: unchanged). In NOMINAL mode the firmware takes up to 1 s to
        act on it. Sent once per change: the official host re-sends cooling at 1 Hz, but the firmware keeps its mode
        and cooling until told otherwise."""
        mode = PicoMode.parse(mode)
        cooling = self.cooling_speed if cooling_speed is None else cooling_speed
        packet = encode_command(mode, cooling)
        self._write(packet)
        self.cooling_speed = int(cooling)
        self.mode = mode

    def set_cooling(self, speed: int) -> None:
        """Cooling speed 0..10 (pump and fan; the firmware runs them only in NOMINAL mode)."""
        mode = PicoMode.IDLE if self.mode in (PicoMode.RESET, PicoMode.CALIBRATE) else self.mode
        self.set_mode(mode, speed)

    def _write(self, packet: bytes) -> None:
        if self._serial is None:
            raise DriverError(f"{self.port}: sense board is not open")
        with self._write_lock:
            try:
                self._serial.write(packet)
            except PORT_ERRORS as e:  # SerialTimeoutException is a SerialException, an OSError
                raise DriverError(f"{self.port}: cannot write to the sense board: {e}") from e

    # -- per tick
    def latest(self) -> tuple[SenseSample | None, float | None]:
        """(latest sample, its host monotonic stamp), or (None, None) before the first. Never blocks."""
        sample, stamp, _ = self._latest
        return (sample, stamp) if sample is not None else (None, None)

    @property
    def sample_count(self) -> int:
        """Samples received since open (bias reports excluded)."""
        return self._latest[2]

    def age(self, now: float | None = None) -> float:
        """Seconds since the latest sample arrived (inf before the first): a stopped stream makes it grow."""
        stamp = self._latest[1]
        return (time.monotonic() if now is None else now) - stamp

    def read(self) -> tuple[SenseSample, float]:
        """The latest sample and the monotonic time it arrived; stale data keep their old stamp (the safety stage's
        sensor-age check catches a stopped stream). Raises BusTimeout before the first."""
        sample, stamp, _ = self._latest
        if sample is None:
            raise BusTimeout(self.port, (), "no sense-board packet received yet")
        return sample, stamp

    def raise_if_stale(self, max_age_s: float, now: float | None = None) -> None:
        """BusTimeout naming the port when the newest packet is older than max_age_s."""
        age = self.age(now)
        if age > max_age_s:
            what = "no packet yet" if math.isinf(age) else f"last packet {1e3 * age:.1f} ms ago"
            raise BusTimeout(self.port, (), f"IMU stream stopped: {what} > {1e3 * max_age_s:.1f} ms")

    # -- start-up (as BRUCE-OP's `run_sense` does)
    def start(self, *, check_imu: bool = True, stream_timeout_s: float = 3.0, imu_samples: int = 500,
              max_accel_x_std: float = 1.0, imu_attempts: int = 3, sample_timeout_s: float = 5.0) -> None:
        """NOMINAL mode, wait for the stream, then the official IMU check (see `check_imu`)."""
        self.set_mode(PicoMode.NOMINAL)
        self.wait_for_stream(stream_timeout_s)
        if check_imu:
            self.check_imu(samples=imu_samples, max_accel_x_std=max_accel_x_std, attempts=imu_attempts,
                           sample_timeout_s=sample_timeout_s, stream_timeout_s=stream_timeout_s)

    def wait_for_stream(self, timeout_s: float = 3.0) -> None:
        """Until a new sample arrives; BusTimeout naming the port if none within timeout_s."""
        count = self.sample_count
        deadline = time.monotonic() + timeout_s
        while self.sample_count == count:
            if time.monotonic() > deadline:
                raise BusTimeout(self.port, (), f"no sense-board packet within {timeout_s:.1f} s of asking for "
                                                f"NOMINAL mode{self._reader_note()}")
            time.sleep(0.002)

    def check_imu(self, *, samples: int = 500, max_accel_x_std: float = 1.0, attempts: int = 3,
                  sample_timeout_s: float = 5.0, stream_timeout_s: float = 3.0) -> float:
        """The official start-up check, bounded: the robot must be still; the std-dev of accel x over `samples`
        packets must not exceed max_accel_x_std (m/s^2), else reset the IMU and retry, at most `attempts` checks.
        Returns the accepted std-dev; raises DriverError naming the port when every attempt failed."""
        std = math.nan
        for attempt in range(attempts):
            if attempt:
                self.stats.retries += 1
                self.reset_imu(stop_timeout_s=stream_timeout_s, stream_timeout_s=stream_timeout_s)
            batch = self.collect(samples, sample_timeout_s)
            if len(batch) < max(2, samples):
                raise BusTimeout(self.port, (), f"IMU check got {len(batch)} of {samples} samples in "
                                                f"{sample_timeout_s:.1f} s{self._reader_note()}")
            std = float(np.std([s.accel[0] for s in batch], ddof=1))  # statistics.stdev, as the official check
            if std <= max_accel_x_std:
                return std
        raise DriverError(f"{self.port}: IMU check failed {attempts} times: std-dev of accel x {std:.2f} m/s^2 > "
                          f"{max_accel_x_std} m/s^2 over {samples} samples (robot moving, or IMU faulty)")

    def reset_imu(self, *, stop_timeout_s: float = 3.0, stream_timeout_s: float = 3.0, quiet_s: float = 0.05) -> None:
        """RESET (the firmware re-configures the IMU and goes IDLE), wait for the stream to stop, then NOMINAL
        and wait for it to resume. Bounded; DriverError naming the port if the board does not follow. The official
        code sends RESET, sleeps 0.5 s and sends NOMINAL; since the firmware polls once a second in NOMINAL mode,
        both often land in the same poll and the reset is lost: waiting for the stream to stop avoids that."""
        self.set_mode(PicoMode.RESET)
        deadline = time.monotonic() + stop_timeout_s
        while self.age() < quiet_s:
            if time.monotonic() > deadline:
                raise DriverError(f"{self.port}: IMU reset not taken: the stream did not stop within "
                                  f"{stop_timeout_s:.1f} s")
            time.sleep(0.005)
        self.set_mode(PicoMode.NOMINAL)
        self.wait_for_stream(stream_timeout_s)

    def wait_for_contact(self, samples: int = 100, timeout_s: float = 10.0) -> None:
        """The official contact check: `samples` samples with any foot in contact (robot on the ground)."""
        deadline = time.monotonic() + timeout_s
        seen = checked = 0
        batch: list[SenseSample] = []
        self._collector = batch
        try:
            while seen < samples:
                if time.monotonic() > deadline:
                    raise DriverError(f"{self.port}: {seen} of {samples} samples with a foot contact within "
                                      f"{timeout_s:.1f} s (is the robot on the ground?)")
                time.sleep(0.005)
                end = len(batch)  # the reader only appends
                seen += sum(1 for s in batch[checked:end] if s.contact.any())
                checked = end
        finally:
            self._collector = None

    def collect(self, n: int, timeout_s: float) -> list[SenseSample]:
        """The next n samples (fewer if timeout_s passes first)."""
        batch: list[SenseSample] = []
        self._collector = batch
        deadline = time.monotonic() + timeout_s
        try:
            while len(batch) < n and time.monotonic() < deadline:
                time.sleep(0.002)
        finally:
            self._collector = None
        return batch[:n]

    # -- IMU bias calibration (the firmware's mode 3; the robot must lie still, z axis up)
    def calibrate_imu(self, *, store: bool = True, report_timeout_s: float = 5.0,
                      sampling_timeout_s: float = 30.0) -> tuple[SenseSample, SenseSample]:
        """The firmware's bias calibration: returns (old bias report, new bias report), each with `.gyro` and
        `.accel` holding the biases. With store=False the new bias is declined and the board keeps the old one.
        The board is IDLE afterwards (call `start()` again)."""
        self._bias_reports.clear()
        self.set_mode(PicoMode.CALIBRATE)
        old = self._wait_bias_report(report_timeout_s, "current bias")
        self.set_mode(PicoMode.CALIBRATE)  # confirmation: start sampling
        new = self._wait_bias_report(sampling_timeout_s, "new bias")
        self.set_mode(PicoMode.CALIBRATE if store else PicoMode.IDLE)
        self.mode = PicoMode.IDLE  # the firmware ends calibration in IDLE either way
        return old, new

    def _wait_bias_report(self, timeout_s: float, what: str) -> SenseSample:
        deadline = time.monotonic() + timeout_s
        while not self._bias_reports:
            if time.monotonic() > deadline:
                raise BusTimeout(self.port, (), f"no {what} report from the sense board within {timeout_s:.1f} s")
            time.sleep(0.005)
        return self._bias_reports.popleft()

    # -- reader thread
    def _reader_note(self) -> str:
        return f"; reader stopped: {self.error}" if self.error is not None else ""

    def _read_loop(self) -> None:
        ser = self._serial
        stalled = False
        try:
            while not self._stop.is_set():
                data = ser.read(ser.in_waiting or 1)  # bounded by read_timeout_s
                now = time.monotonic()
                if not data:
                    if self._parser.pending:
                        self._parser.drop_partial()
                    # stats.timeouts counts stalls: gaps longer than stall_s while NOMINAL was requested
                    if (not stalled and self.mode == PicoMode.NOMINAL and self._latest[0] is not None
                            and now - self._latest[1] > self.stall_s):
                        stalled = True
                        self.stats.timeouts += 1
                    continue
                for sample in self._parser.feed(data):
                    if sample.bias_report:
                        self._bias_reports.append(sample)
                        continue
                    self._latest = (sample, now, self._latest[2] + 1)
                    stalled = False
                    collector = self._collector
                    if collector is not None:
                        collector.append(sample)
        except Exception as e:  # port gone (unplugged, closed): the stream's age shows it
            if not self._stop.is_set():
                self.error = e
