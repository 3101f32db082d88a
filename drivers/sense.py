"""BRUCE's sense board (Raspberry Pi Pico, BRUCE-OP v0.0.5/v0.0.7 firmware) on USB serial: IMU and foot contacts.

`SenseBoard`, a daemon thread that keeps the newest sample, with the official start-up checks bounded in time; the
wire protocol (packets, commands, the parser) is in `drivers.sense_codec`. The board gives no orientation (the
backend's attitude filter adds it), the spec gives no IMU -> body rotation (the official estimator treats IMU axes as
body axes), and it has no e-stop input: BRUCE's wireless stop is wired to the BEARs, so an e-stop reaches the stack
through their error byte. Timestamps are the host's `time.monotonic()` when a packet's bytes were read (the board
sends no time).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np

from drivers.errors import PORT_ERRORS, BusTimeout, DriverError, LinkStats
from drivers.sense_codec import PicoMode, SenseParser, SenseSample, encode_command


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
