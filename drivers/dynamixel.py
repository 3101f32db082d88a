"""BRUCE's arms: six Dynamixel X-series servos (IDs 11-16), Protocol 2.0 at 2 Mbaud, through ROBOTIS' dynamixel-sdk.

`DynamixelArms`, the driver: the SDK's PortHandler and PacketHandler(2.0), a GroupSyncRead of present position and
velocity and a GroupSyncWrite of goal position, per tick; the Bus Watchdog set up so that a killed host or an
unplugged bus stops the arms (docs/safety.md). Choices where BRUCE-OP v0.0.7's `run_dxl` and the SDK are silent are
noted at the code that makes them. The wire format without I/O is `drivers/dynamixel_codec.py` (which the emulator,
`drivers/emulators/dynamixel.py`, speaks through); the control table and units are `drivers/dynamixel_registers.py`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from drivers.dynamixel_codec import (
    ERROR_ALERT,
    MAX_ID,
    PacketParser,
    decode_hardware_error,
    decode_status_error,
)
from drivers.dynamixel_registers import (
    ADDR_BUS_WATCHDOG,
    ADDR_DRIVE_MODE,
    ADDR_GOAL_POSITION,
    ADDR_HARDWARE_ERROR,
    ADDR_INDIRECT_DATA_READ,
    ADDR_INDIRECT_READ,
    ADDR_OPERATING_MODE,
    ADDR_POSITION_D_GAIN,
    ADDR_POSITION_I_GAIN,
    ADDR_POSITION_P_GAIN,
    ADDR_TORQUE_ENABLE,
    OPERATING_MODE_POSITION,
    READ_BLOCK_LENGTH,
    counts_to_joint,
    decode_read_block,
    indirect_read_map,
    joint_to_counts,
    velocity_counts_to_joint,
    watchdog_counts,
)
from drivers.errors import PORT_ERRORS, BusTimeout, DeviceFault, DriverError, LinkStats

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
