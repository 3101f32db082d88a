"""Byte-exact emulator of BRUCE's sense board (Pico firmware of BRUCE-OP v0.0.5/v0.0.7) on a pseudo-terminal.

`SenseBoardEmulator` runs the firmware's loop (`pico.ino`) on a thread: boots in IDLE (reads commands every
`idle_poll_s`), streams the 29-byte packet at `rate_hz` in NOMINAL (reading commands only every `command_poll_s`,
1 s on the board), RESET and CALIBRATE as the firmware does them, and the cooling pump and fan. A physics adapter
calls `set_measurement(accel=, gyro=, contacts=)` (thread-safe), or `tick()` per step in lockstep. Faults for tests:
`set_silent`, `corrupt_next(how)`, `inject_garbage`, `set_imu_glitch`, `set_reply_delay`. Packets are paced on
`time.monotonic()`, so on a loaded machine the rate is approximate.
"""

from __future__ import annotations

import fcntl
import math
import os
import struct
import termios
import threading
import time
from collections import deque

import numpy as np

from drivers.emulators.pty_device import PtyDevice
from drivers.emulators.reply_delay import ReplyDelay, wait_until
from drivers.sense_codec import (
    COMMAND_LEN,
    COMMAND_REST_LEN,
    FIRMWARE_GRAVITY,
    HEADER,
    TRAILER,
    PicoMode,
    checksum,
    encode_packet,
)

# The firmware's float32 scale factors (ISM330DHCX at 500 dps / 4 g; DEGREE_TO_RADIAN as the firmware spells it).
GYRO_SCALE = np.float32(17.5) * (np.float32(0.0174533) / np.float32(1000))       # rad/s per LSB
ACCEL_SCALE = np.float32(0.1220703125) * (np.float32(FIRMWARE_GRAVITY) / np.float32(1000))  # m/s^2 per LSB
CORRUPTIONS = ("checksum", "trailer", "length", "header", "flags", "truncate")
PUMP_MIN, PUMP_MAX = 30, 80
_MAX_CATCH_UP = 10        # periods sent at once after a stall (as a USB CDC link delivers a backlog); longer: dropped
# Lockstep: with no step for this long (a host that is starting up, or gone) the board streams on its own clock again,
# as the real one always does, so that the host's start-up check sees packets.
LOCKSTEP_IDLE_S = 0.01
_MAX_UNREAD = 2048        # bytes waiting in the host's input before packets are dropped (the board's USB FIFO fills)
_MAX_RX = 65536           # host bytes kept between command reads


class SenseBoardEmulator:
    def __init__(self, *, rate_hz: float = 1000.0, command_poll_s: float = 1.0, idle_poll_s: float = 0.01,
                 quantize: bool = True, calibration_samples: int = 10000, calibration_wait_s: float = 15.0,
                 mode: PicoMode | int = PicoMode.IDLE, name: str = "sense", seed: int = 0, lockstep: bool = False):
        """`lockstep`: while streaming, a packet goes out on each `tick()` (a lockstep physics step) instead of
        every 1/rate_hz s of the wall clock."""
        self.rate_hz = rate_hz
        self.lockstep = lockstep
        self._last_tick = -math.inf
        self.command_poll_s = command_poll_s
        self.idle_poll_s = idle_poll_s
        self.quantize = quantize
        self.calibration_samples = calibration_samples
        self.calibration_wait_s = calibration_wait_s
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._rng = np.random.default_rng(seed)
        # measured values (written by the physics adapter) and the board's own state
        self._accel = np.array([0.0, 0.0, FIRMWARE_GRAVITY])
        self._gyro = np.zeros(3)
        self._contact = np.zeros(4, dtype=bool)
        self._accel_offset = np.zeros(3)  # the chip's own offset, what calibration measures
        self._gyro_offset = np.zeros(3)
        self._accel_bias = np.zeros(3, dtype=np.float32)  # the board's stored ("EEPROM") bias
        self._gyro_bias = np.zeros(3, dtype=np.float32)
        self._mode = PicoMode(mode)
        self._cooling_speed = 0
        self._cooling_on = False
        # host bytes and fault injection
        self._rx = bytearray()
        self._silent = False
        self._corrupt: deque[str] = deque()
        self._garbage = bytearray()
        self._glitch_std = 0.0
        self._glitch_persistent = False
        # what happened, for tests and tools
        self.packets_sent = 0
        self.packets_dropped = 0
        self.commands: list[tuple[PicoMode, int]] = []  # every valid command the firmware read, in order
        self.commands_rejected = 0                       # 0xFF-led commands with a bad length/checksum/trailer
        # set_reply_delay: packets wait in `_outbox` (due time, bytes) for the sender thread, oldest first
        self.reply_delay = ReplyDelay()
        self._outbox: deque[tuple[float, bytes]] = deque()
        self._outbox_changed = threading.Condition()
        self._in_flight = 0       # packets handed to the sender and not yet written
        self._last_due = -math.inf
        self._pty = PtyDevice(name, self._on_bytes)
        self._peek_fd = os.open(self._pty.path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)  # host backlog probe
        self._thread = threading.Thread(target=self._firmware, name=f"emulator-{name}", daemon=True)
        self._sender = threading.Thread(target=self._send_delayed, name=f"emulator-{name}-sender", daemon=True)

    # -- lifecycle
    @property
    def path(self) -> str:
        """The device the host opens (like /dev/ttyACM0)."""
        return self._pty.path

    def start(self) -> SenseBoardEmulator:
        self._pty.start()
        self._thread.start()
        self._sender.start()
        return self

    def close(self) -> None:
        if self._stop.is_set():
            return  # closing twice must not close file descriptors that were reused meanwhile
        self._stop.set()
        with self._outbox_changed:
            self._outbox_changed.notify_all()
        for thread in (self._thread, self._sender):
            if thread.is_alive():
                thread.join(timeout=2.0)
        self._pty.close()
        try:
            os.close(self._peek_fd)
        except OSError:
            pass

    def __enter__(self) -> SenseBoardEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- the physics adapter's side
    def set_measurement(self, accel=None, gyro=None, contacts=None) -> None:
        """What the IMU and foot switches sense now: accel the specific force in m/s^2 in the IMU frame (+g up at
        rest), gyro rad/s, contacts in FOOT_CONTACT_NAMES order; None leaves a quantity unchanged."""
        with self._lock:
            if accel is not None:
                self._accel = np.array(accel, dtype=float).reshape(3)
            if gyro is not None:
                self._gyro = np.array(gyro, dtype=float).reshape(3)
            if contacts is not None:
                self._contact = np.array(contacts, dtype=bool).reshape(4)

    def measurement(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(accel, gyro, contacts) as last set (copies)."""
        with self._lock:
            return self._accel.copy(), self._gyro.copy(), self._contact.copy()

    def set_sensor_offset(self, accel=None, gyro=None) -> None:
        """The IMU chip's own offset (raw = true + offset), which the board's calibration measures."""
        with self._lock:
            if accel is not None:
                self._accel_offset = np.array(accel, dtype=float).reshape(3)
            if gyro is not None:
                self._gyro_offset = np.array(gyro, dtype=float).reshape(3)

    def bias(self) -> tuple[np.ndarray, np.ndarray]:
        """(accel bias, gyro bias) stored on the board."""
        with self._lock:
            return self._accel_bias.astype(float), self._gyro_bias.astype(float)

    @property
    def mode(self) -> PicoMode:
        return self._mode

    @property
    def cooling_speed(self) -> int:
        """The last cooling speed the firmware read (0..15 on the wire; the host sends 0..10)."""
        return self._cooling_speed

    @property
    def pump_speed(self) -> int | None:
        """Pump servo command while cooling runs (30..80: 30 + 5 * speed), None while it is stopped (cooling speed 0,
        or not NOMINAL: the fan is off then too)."""
        if not self._cooling_on:
            return None
        return int(PUMP_MIN + (PUMP_MAX - PUMP_MIN) * 0.1 * self._cooling_speed)

    @property
    def fan_on(self) -> bool:
        return self._cooling_on

    # -- faults
    def set_silent(self, silent: bool = True) -> None:
        """Stop (or resume) streaming while still obeying commands: what a stalled IMU stream looks like."""
        self._silent = silent

    def corrupt_next(self, how: str = "checksum", count: int = 1) -> None:
        if how not in CORRUPTIONS:
            raise ValueError(f"unknown corruption {how!r}; one of {', '.join(CORRUPTIONS)}")
        with self._lock:
            self._corrupt.extend([how] * count)

    def inject_garbage(self, data: bytes) -> None:
        """Bytes sent just before the next packet (never inside one)."""
        with self._lock:
            self._garbage += data

    def set_imu_glitch(self, std: float, *, persistent: bool = False) -> None:
        """Noise of `std` m/s^2 on accel x; a RESET clears it unless persistent (a broken IMU)."""
        with self._lock:
            self._glitch_std = float(std)
            self._glitch_persistent = persistent

    # -- host bytes
    def _on_bytes(self, data: bytes) -> None:
        with self._lock:
            self._rx += data
            if len(self._rx) > _MAX_RX:
                del self._rx[:-_MAX_RX]

    def _read_commands(self) -> None:
        """The firmware's `read_data`: while 5 or more bytes are buffered, take one; if it is 0xFF, take the next 4
        and apply them when length, checksum and trailer are right (the last valid command wins); then drop the
        rest."""
        with self._lock:
            data = bytes(self._rx)
            self._rx.clear()
        i, n = 0, len(data)
        while n - i >= COMMAND_LEN:
            byte = data[i]
            i += 1
            if byte != HEADER:
                continue
            rest = data[i:i + COMMAND_LEN - 1]
            i += COMMAND_LEN - 1
            if rest[0] == COMMAND_REST_LEN and rest[2] == checksum(rest[:2]) and rest[3] == TRAILER:
                self._mode = PicoMode(rest[1] & 3)
                self._cooling_speed = (rest[1] >> 2) & 15
                self.commands.append((self._mode, self._cooling_speed))
            else:
                self.commands_rejected += 1

    # -- firmware
    def _firmware(self) -> None:
        while not self._stop.is_set():
            mode = self._mode
            if mode == PicoMode.NOMINAL:
                self._run_nominal()
            elif mode == PicoMode.IDLE:
                self._run_idle()
            elif mode == PicoMode.RESET:
                with self._lock:  # setup_IMU: a glitching chip comes back clean
                    if not self._glitch_persistent:
                        self._glitch_std = 0.0
                self._mode = PicoMode.IDLE
            else:
                self._calibrate()
                self._mode = PicoMode.IDLE

    def _run_idle(self) -> None:
        self._cooling_on = False
        while not self._stop.is_set():
            self._read_commands()
            if self._mode != PicoMode.IDLE:
                return
            time.sleep(self.idle_poll_s)

    def _run_nominal(self) -> None:
        period = 1.0 / self.rate_hz
        next_send = next_poll = time.monotonic()  # the firmware reads commands (and sets cooling) on entry
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_poll:
                self._read_commands()
                self._cooling_on = self._cooling_speed > 0
                next_poll = now + self.command_poll_s
                if self._mode != PicoMode.NOMINAL:
                    return
            if self.lockstep and now - self._last_tick < LOCKSTEP_IDLE_S:
                next_send = min(next_poll, now + period)  # packets go out on tick() while the steps come
            elif now >= next_send:
                if now - next_send > _MAX_CATCH_UP * period:
                    next_send = now  # a long stall: do not back-fill
                while next_send <= now:
                    self._send_sample()
                    next_send += period
            time.sleep(max(0.0, min(next_send, next_poll) - time.monotonic()))

    def tick(self) -> None:
        """Lockstep: one packet now, if the board is streaming (NOMINAL)."""
        self._last_tick = time.monotonic()
        if self._mode == PicoMode.NOMINAL:
            self._send_sample()

    def _raw(self) -> tuple[np.ndarray, np.ndarray]:
        """What the IMU chip reports now, in float32 SI units (before the board's bias). With `quantize`, through
        the chip's int16 counts at the firmware's scales (gyro 17.5 mdps/LSB, +-573 dps; accel 0.122 mg/LSB, +-4 g),
        saturating like the chip. The firmware's 5-sample moving average (at its 1.5 kHz IMU read rate) is not
        emulated: an adapter can filter if it wants that lag."""
        with self._lock:
            accel = self._accel + self._accel_offset
            gyro = self._gyro + self._gyro_offset
            if self._glitch_std > 0.0:
                accel[0] += self._rng.normal(0.0, self._glitch_std)
        if not self.quantize:
            return accel.astype(np.float32), gyro.astype(np.float32)
        return _counts_to_si(accel, ACCEL_SCALE), _counts_to_si(gyro, GYRO_SCALE)

    def _send_sample(self) -> None:
        if self._silent:
            return
        accel, gyro = self._raw()
        with self._lock:
            accel -= self._accel_bias
            gyro -= self._gyro_bias
            contact = self._contact.copy()
            how = self._corrupt.popleft() if self._corrupt else None
            garbage, self._garbage = bytes(self._garbage), bytearray()
        packet = bytearray(encode_packet(accel, gyro, contact))
        if how is not None:
            packet = _corrupted(packet, how)
        self._send(garbage + bytes(packet))

    def set_reply_delay(self, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """From now on every packet leaves fixed + U(0, jitter) seconds later than it would have: its sample is taken
        on time, so the host sees data that much older at the same rate; a sender thread writes them in order (a
        packet never overtakes the one before it, as on a serial line), and neither the firmware nor a lockstep
        physics step waits for it. ValueError outside [0, 0.1] s; `seed` makes the draws repeatable."""
        self.reply_delay.set(fixed, jitter, seed)

    def _send(self, data: bytes) -> None:
        """A packet out now, or, with a reply delay (or packets still waiting), to the sender, due that much later."""
        with self._outbox_changed:
            if self.reply_delay.active or self._in_flight:
                due = max(time.monotonic() + self.reply_delay.draw(), self._last_due)  # in order, as on a wire
                self._last_due = due
                self._outbox.append((due, data))
                self._in_flight += 1
                self._outbox_changed.notify()
                return
        self._write(data)

    def _send_delayed(self) -> None:
        while not self._stop.is_set():
            with self._outbox_changed:
                if not self._outbox:
                    self._outbox_changed.wait(0.05)
                    continue
                due, data = self._outbox.popleft()
            wait_until(due)
            self._write(data)
            with self._outbox_changed:
                self._in_flight -= 1

    def _write(self, data: bytes) -> None:
        if self._unread() > _MAX_UNREAD:
            self.packets_dropped += 1
            return
        self._pty.send(data)
        self.packets_sent += 1

    def _unread(self) -> int:
        """Bytes the host has not read yet."""
        try:
            buf = fcntl.ioctl(self._peek_fd, termios.FIONREAD, b"\0\0\0\0")
        except OSError:
            return 0
        return struct.unpack("i", buf)[0]

    # -- calibration (the firmware's calibrate_IMU)
    def _calibrate(self) -> None:
        """Send the current bias as a bias report (contact byte 0xFF), wait up to `calibration_wait_s` for a second
        CALIBRATE, average `calibration_samples` raw samples 1 ms apart (10,000 on the board), subtract g from z,
        send the new bias the same way, and keep it ("EEPROM") only on a third CALIBRATE; IDLE either way."""
        with self._lock:
            old_accel, old_gyro = self._accel_bias.copy(), self._gyro_bias.copy()
        self._send(encode_packet(old_accel, old_gyro, bias_report=True))
        if not self._confirmed():
            return
        n = max(1, self.calibration_samples)
        accel_sum, gyro_sum = np.zeros(3), np.zeros(3)
        for _ in range(n):
            if self._stop.is_set():
                return
            accel, gyro = self._raw()
            accel_sum += accel
            gyro_sum += gyro
            time.sleep(0.001)
        new_accel = (accel_sum / n).astype(np.float32)
        new_accel[2] -= np.float32(FIRMWARE_GRAVITY)
        new_gyro = (gyro_sum / n).astype(np.float32)
        self._send(encode_packet(new_accel, new_gyro, bias_report=True))
        if self._confirmed():
            with self._lock:
                self._accel_bias, self._gyro_bias = new_accel, new_gyro

    def _confirmed(self) -> bool:
        """Wait (bounded) for a whole command, read it; True when it asks to go on calibrating."""
        deadline = time.monotonic() + self.calibration_wait_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            with self._lock:
                ready = len(self._rx) >= COMMAND_LEN
            if ready:
                self._read_commands()
                return self._mode == PicoMode.CALIBRATE
            time.sleep(0.01)
        return False


def _counts_to_si(values: np.ndarray, scale: np.float32) -> np.ndarray:
    # np.minimum/np.maximum, not np.clip: the same result at a tenth of the cost for 3 values (1000 packets a second)
    counts = np.minimum(np.maximum(np.rint(values / float(scale)), -32768.0), 32767.0).astype(np.float32)
    return counts * scale


def _corrupted(packet: bytearray, how: str) -> bytearray:
    if how == "checksum":
        packet[5] ^= 0x01  # a data bit flipped in transit; the checksum no longer matches
    elif how == "trailer":
        packet[-1] = 0x00
    elif how == "length":
        packet[1] = 26
    elif how == "header":
        packet[0] = 0x00
    elif how == "flags":
        packet[26] &= 0x7F  # no marker bit, but a consistent checksum
        packet[27] = checksum(packet[1:27])
    elif how == "truncate":
        del packet[15:]
    return packet
