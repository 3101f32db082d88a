"""A byte-exact emulator of a BEAR RS-485 chain: N Koala BEARs by ID behind one pseudo-terminal.

The host opens `BearBusEmulator.path` as it would /dev/ttyUSB0 and speaks the BEAR protocol (`drivers.bear_codec`):
PING, READ_STAT, WRITE_STAT, READ_CFG, WRITE_CFG, SAVE_CFG and BULK_COMM are answered as PyBEAR and BRUCE-OP use
them, so any spec-following host works, not only `drivers.bear.BearBus`. A physics adapter drives it through
thread-safe accessors, every 1 ms if it likes: `set_measured[_many]` (present position, velocity, iq) and `command`
/ `commands` (mode, torque_enable, goals, error byte). Faults for tests: `silence`, `unplug`, `set_error`,
`set_estop`, `corrupt_next_reply`, `set_reply_loss`, `set_reply_delay`, `power_cycle`; `drain_events` for the
event log. Where the sources are silent, the choices (a host can observe them) are noted at the code that makes
them.
"""

from __future__ import annotations

import functools
import random
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.bear_codec import StatusParser, checksum, encode_status
from drivers.bear_registers import (
    BROADCAST_ID,
    CONFIG_BY_ADDRESS,
    CONFIG_REGISTERS,
    ERROR_OK,
    FAULT_BITS,
    HEADER,
    MAX_DEVICE_ID,
    MAX_PARAMS,
    STATUS_BY_ADDRESS,
    STATUS_REGISTERS,
    WARNING_BITS,
    BearError,
    Instruction,
    Register,
    TorqueEnable,
    error_flags,
)
from drivers.emulators.pty_device import PtyDevice
from drivers.emulators.reply_delay import ReplyDelay
from drivers.errors import LinkStats
from drivers.framing import skip_to_header

STALE_RX_S = 0.02  # a partial packet this old when new bytes arrive is dropped (an idle-line reset, as UART firmware)
# Plain ints for the hot path (IntFlag arithmetic builds enum members: tens of microseconds per bulk cycle).
_COMM, _OVERHEAT, _ESTOP = int(BearError.COMMUNICATION), int(BearError.OVERHEAT), int(BearError.WATCHDOG_ESTOP)
_JOINT_LIMIT, _HARDWARE = int(BearError.JOINT_LIMIT), int(BearError.HARDWARE)
_FAULTS, _WARNINGS = int(FAULT_BITS), int(WARNING_BITS)
_FAULTS_BUT_ESTOP = _FAULTS & ~_ESTOP
_DISABLED, _ENABLED, _ERROR, _DAMPING = (int(t) for t in (TorqueEnable.DISABLED, TorqueEnable.ENABLED,
                                                          TorqueEnable.ERROR, TorqueEnable.DAMPING))
_DERIVED = ("torque_enable", "error_status", "warning_status")  # status registers that follow the device state
# Writable status registers by address: (name, unpacker).
_STATUS_WRITES = {r.address: (r.name, struct.Struct("<" + r.fmt)) for r in STATUS_BY_ADDRESS.values() if r.writable}
_INSTRUCTION_NAMES = {int(i): i.name for i in Instruction}
CORRUPTIONS = ("checksum", "truncate", "garbage", "foreign", "drop")
LOSS_CORRUPTIONS = ("checksum", "truncate", "garbage")  # what set_reply_loss's `corrupt` does, drawn evenly
MAX_EVENTS = 10_000
# An exchange this much off its course is logged (bench/bench_hw_emulated.py prints those before a trip): a request
# this long after the BEARs last answered (a bulk cycle's longest wait is its 3-ms reply timeout), or a reply this
# long after it was due (the request's arrival plus any reply delay): the host's request late to arrive, or the
# BEARs late to answer it.
LATE_REQUEST_S = 0.004
LATE_REPLY_S = 0.001
HOST_AWAY_S = 1.0  # a longer pause between requests is a host not running its loop (between runs): not logged

# Power-on values. Gains and limits are BRUCE-OP v0.0.7's; the rest are plausible choices.
DEFAULT_CONFIG: dict[str, int | float] = {
    "id": 0, "mode": 0, "baudrate": 8_000_000, "homing_offset": 0.0,
    "p_gain_id": 0.277, "i_gain_id": 0.061, "d_gain_id": 0.0,
    "p_gain_iq": 0.277, "i_gain_iq": 0.061, "d_gain_iq": 0.0,
    "p_gain_velocity": 1.0, "i_gain_velocity": 0.0, "d_gain_velocity": 0.0,
    "p_gain_position": 60.0, "i_gain_position": 0.0, "d_gain_position": 1.0,
    "p_gain_force": 10.0, "i_gain_force": 0.0, "d_gain_force": 1.0,
    "limit_acc_max": 1000.0, "limit_i_max": 30.0, "limit_velocity_max": 100.0,
    "limit_position_min": -3.0, "limit_position_max": 3.0,
    "min_voltage": 10.0, "max_voltage": 40.0, "watchdog_timeout": 0,
    "temp_limit_low": 70.0, "temp_limit_high": 90.0, "return_time_delay": 0,
}
DEFAULT_STATUS: dict[str, int | float] = {
    "homing_complete": 1, "goal_id": 0.0, "goal_iq": 0.0, "goal_velocity": 0.0, "goal_position": 0.0,
    "present_id": 0.0, "present_iq": 0.0, "present_velocity": 0.0, "present_position": 0.0,
    "input_voltage": 24.0, "winding_temperature": 30.0, "powerstage_temperature": 30.0, "ic_temperature": 30.0,
}


def _f32(value: float) -> float:
    """The value a BEAR stores: rounded to float32."""
    return struct.unpack("<f", struct.pack("<f", value))[0]


@dataclass(frozen=True)
class MotorCommand:
    """What a BEAR has been told, for the physics adapter."""

    id: int
    mode: int
    torque_enable: int  # as read: 0 off, 1 on, 2 error (output off), 3 damping
    goal_position: float
    goal_velocity: float
    goal_iq: float
    goal_id: float
    error: int


class EventLog:
    """Timestamped lines of what happened inside an emulator, for a log that tests and people check: thread-safe and
    bounded (at most `maxlen` wait; the oldest go first, counted in `dropped`); `drain()` takes them."""

    def __init__(self, maxlen: int = MAX_EVENTS):
        self._events: deque[tuple[float, str]] = deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self.dropped = 0

    def add(self, text: str, stamp: float | None = None) -> None:
        with self._lock:
            if len(self._events) == self._events.maxlen:
                self.dropped += 1
            self._events.append((time.monotonic() if stamp is None else stamp, text))

    def drain(self) -> list[tuple[float, str]]:
        with self._lock:
            out = list(self._events)
            self._events.clear()
            return out


class _Bear:
    """One actuator: config and status register files, flash, and the flags behind its error byte.

    Error bits: 0 is set by a corrupted packet (bad checksum) carrying this ID, an unknown register address, an
    unsupported instruction or a malformed packet, and cleared once reported. 1 (overheat) while a temperature is
    above temp_limit_low, 5 (hardware) while input_voltage is outside [min_voltage, max_voltage], 4 (joint limit)
    while present_position is outside the position limits: these follow the state, unlatched. 3 while damping or the
    E-stop input is asserted. Injected bits latch until torque_enable = 0 is written.
    torque_enable reads 3 while damping or E-stopped, 2 while enabled with a fault bit (2, 4, 5, 6) set, else the
    0/1 last written. present_position is what the physics adapter set (the homing offset is the adapter's)."""

    def __init__(self, device_id: int, now: float):
        self.config = {name: _f32(v) if CONFIG_REGISTERS[name].kind == "f32" else v
                       for name, v in DEFAULT_CONFIG.items()}
        self.config["id"] = device_id
        self.flash = dict(self.config)
        self.status = {name: _f32(v) if STATUS_REGISTERS[name].kind == "f32" else v
                       for name, v in DEFAULT_STATUS.items()}
        self.enable = 0  # the 0/1 last written to torque_enable
        self.damping = False  # torque_enable = 3 written, or watchdog expiry; left by writing 0 or 1
        self.estop = False  # external E-stop input
        self.latched = 0  # injected error bits, cleared by writing torque_enable = 0
        self.comm_warning = False
        self.silent = False
        self.last_rx = now
        self.logged_enable = 0  # torque_enable as read when last logged: changes are logged against it

    @property
    def id(self) -> int:
        return int(self.config["id"])

    def error_byte(self) -> int:
        c, s = self.config, self.status
        error = ERROR_OK | self.latched
        if self.comm_warning:
            error |= _COMM
        if self.estop or self.damping:
            error |= _ESTOP
        if max(s["winding_temperature"], s["powerstage_temperature"], s["ic_temperature"]) > c["temp_limit_low"]:
            error |= _OVERHEAT
        if not c["min_voltage"] <= s["input_voltage"] <= c["max_voltage"]:
            error |= _HARDWARE
        low, high = c["limit_position_min"], c["limit_position_max"]
        if low < high and not low <= s["present_position"] <= high:
            error |= _JOINT_LIMIT
        return error

    def torque_enable(self, error: int | None = None) -> int:
        """As read; `error`: the error byte if the caller has it already (it is not computed again)."""
        if self.estop or self.damping:
            return _DAMPING
        if self.enable == _ENABLED and (self.error_byte() if error is None else error) & _FAULTS_BUT_ESTOP:
            return _ERROR
        return self.enable

    def value(self, register: Register) -> int | float:
        if register.table == "config":
            return self.config[register.name]
        return self._status_value(register.name)

    def _status_value(self, name: str) -> int | float:
        if name == "torque_enable":
            return self.torque_enable()
        if name == "error_status":
            return self.error_byte() & _FAULTS
        if name == "warning_status":
            return self.error_byte() & _WARNINGS
        return self.status[name]

    def read(self, table: str, addresses: bytes) -> bytes:
        """The registers at these addresses of one table ("status" or "config"), packed as the wire has them."""
        packer, names, unknown = _read_plan(table, bytes(addresses))
        if unknown:
            self.comm_warning = True
        if table == "config":
            files = self.config
            return packer.pack(*[0 if name is None else files[name] for name in names])
        files = self.status
        return packer.pack(*[0 if name is None else self._status_value(name) if name in _DERIVED else files[name]
                             for name in names])

    def write_status(self, address: int, raw: bytes) -> None:
        """An unknown or read-only register is skipped with bit 0. torque_enable: 0 disables and clears latched
        faults and damping, 1 enables, 3 enters damping; other values are ignored with bit 0."""
        entry = _STATUS_WRITES.get(address)
        if entry is None:
            self.comm_warning = True
            return
        name, unpacker = entry
        value = unpacker.unpack(raw)[0]
        if name != "torque_enable":
            self.status[name] = value
        elif value == _DISABLED:
            self.enable, self.damping, self.latched = 0, False, 0
        elif value == _ENABLED:
            self.enable, self.damping = 1, False
        elif value == _DAMPING:
            self.damping = True
        else:  # 2 is only ever read; a float-encoded 1.0 (0x3F800000) lands here too
            self.comm_warning = True

    def write_config(self, pairs: list[tuple[int, bytes]], taken: set[int]) -> list[str] | None:
        """The names of the registers taken; None when the whole packet is refused: torque enabled (torque_enable
        reads anything but 0), without an error bit, since the sources say only that config registers "can only be
        written while torque is disabled" and writes get no reply (a host sees it by reading back). An unknown
        address, a mode above 3 or an `id` that is taken are skipped with bit 0; a new `id` moves the BEAR."""
        if self.torque_enable() != TorqueEnable.DISABLED:
            return None  # the whole packet is refused while torque is enabled
        written = []
        for address, raw in pairs:
            register = CONFIG_BY_ADDRESS.get(address)
            if register is None:
                self.comm_warning = True
                continue
            value = struct.unpack("<" + register.fmt, raw)[0]
            refused = (register.name == "mode" and value > 3) or \
                (register.name == "id" and (value > MAX_DEVICE_ID or (value in taken and value != self.id)))
            if refused:
                self.comm_warning = True
            else:
                self.config[register.name] = value
                written.append(register.name)
        return written

    def check_watchdog(self, now: float) -> float | None:
        """Damping if the watchdog ran out; returns how long the BEAR went without a packet when it trips now.
        watchdog_timeout (units undocumented) is taken as milliseconds, 0 off; it runs in torque mode (mode 0),
        enabled, on packets addressed to this BEAR (its ID, the broadcast ID, or a BULK_COMM entry)."""
        timeout_ms = self.config["watchdog_timeout"]
        if (timeout_ms and now - self.last_rx > timeout_ms / 1000.0 and self.config["mode"] == 0
                and self.torque_enable() == _ENABLED):
            self.damping = True
            return now - self.last_rx
        return None

    def fault_cause(self) -> str:
        """Why torque_enable moved between 1 and 2 by itself: the fault bits now set (E-stop / damping aside)."""
        flags = error_flags(self.error_byte() & _FAULTS_BUT_ESTOP)
        return f"fault: {', '.join(flags)}" if flags else "fault cleared"


@functools.lru_cache(maxsize=512)
def _read_plan(table: str, addresses: bytes) -> tuple[struct.Struct, tuple[str | None, ...], bool]:
    """How to answer a read of these addresses: one packer for all values, the register names (None: unknown
    address, read as 4 zero bytes), whether any is unknown. Cached: a host asks the same reads every tick."""
    by_address = CONFIG_BY_ADDRESS if table == "config" else STATUS_BY_ADDRESS
    registers = [by_address.get(address) for address in addresses]
    fmt = "<" + "".join("I" if r is None else r.fmt for r in registers)
    return struct.Struct(fmt), tuple(None if r is None else r.name for r in registers), None in registers


class BearBusEmulator:
    """BEARs with the given IDs on one emulated RS-485 bus. `start()` opens the pty; `handle(bytes) -> bytes` is the
    same device logic without one (the bytes a host sends in, the bytes the devices answer out)."""

    def __init__(self, ids: Iterable[int] = range(1, 11), name: str = "bear", ping_data: bytes = b"\x01\x01"):
        self.name = name
        self.ping_data = bytes(ping_data)  # firmware and hardware version (content undocumented)
        self.stats = LinkStats()  # what the devices received: packets, and rejected bytes by reason
        self.requests: Counter[str] = Counter()  # instruction name -> packets handled
        self._lock = threading.RLock()
        now = time.monotonic()
        self._bears = {int(i): _Bear(int(i), now) for i in ids}
        if any(not 0 <= i <= MAX_DEVICE_ID for i in self._bears):
            raise ValueError(f"BEAR IDs are 0..{MAX_DEVICE_ID}")
        self._rx = bytearray()
        self._rx_time = 0.0
        # Called (with the emulator's lock held) once a BULK_COMM's replies are sent: a lockstep physics adapter
        # steps here with the goals it wrote (Plant(lockstep)). The replies carry the present values when the
        # packet came, as on the real bus; the physics moves while the host computes its next tick.
        self.on_bulk: Callable[[], None] | None = None
        self._bulk_seen = False
        self._corruptions: list[tuple[str, int | None]] = []
        self._pty: PtyDevice | None = None
        self._events = EventLog()
        self._unplugged = False
        self.unplugged_bytes = 0  # bytes from the host lost to the cut wire
        self._loss: tuple[float, float, random.Random] | None = None  # (drop, corrupt, generator)
        self.replies = 0  # reply packets the BEARs produced, spoiled or dropped ones included
        self.reply_losses: Counter[str] = Counter()  # set_reply_loss: "drop", "checksum", "truncate", "garbage"
        self.reply_delay = ReplyDelay()  # set_reply_delay: how late the answers start
        self._estop_unsent = False  # the E-stop input went on, and no reply has carried its bit yet
        self._answered: float | None = None  # when the BEARs last answered (or took a request that gets no reply)

    # -- lifecycle --
    def start(self) -> BearBusEmulator:
        if self._pty is None:
            self._pty = PtyDevice(self.name, self._on_bytes).start()
        return self

    @property
    def path(self) -> str:
        if self._pty is None:
            raise RuntimeError("start() the emulator first")
        return self._pty.path

    def close(self) -> None:
        if self._pty is not None:
            self._pty.close()

    def __enter__(self) -> BearBusEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def ids(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(sorted(self._bears))

    # -- fault injection --
    def silence(self, ids: Iterable[int], silent: bool = True) -> None:
        """These BEARs stop answering (and applying) anything, as if unplugged; `silent=False` brings them back."""
        with self._lock:
            for device_id in ids:
                self._bears[device_id].silent = silent

    def unplug(self, unplugged: bool = True) -> None:
        """Cut the bus's wire both ways (`unplugged=False` mends it): bytes from the host are discarded unread and
        nothing is answered, so no packet reaches any BEAR and their watchdogs run out. The BEARs keep their state
        and per-ID `silence`; a partial packet on the wire when it is cut is lost."""
        with self._lock:
            if bool(unplugged) == self._unplugged:
                return
            self._unplugged = bool(unplugged)
            self._rx.clear()
            self._events.add(f"{self.name} {'unplug' if unplugged else 'plug'}")

    @property
    def unplugged(self) -> bool:
        return self._unplugged

    def set_reply_loss(self, drop: float = 0.0, corrupt: float = 0.0, seed: int | None = None) -> None:
        """From now on every reply packet is independently dropped with probability `drop`, or corrupted with
        probability `corrupt` (a bad checksum, truncated to half, or noise with a false header before it, drawn
        evenly); counted by kind in `reply_losses`. (0, 0) turns it off. `seed` makes the draws repeatable."""
        drop, corrupt = float(drop), float(corrupt)
        if not (0.0 <= drop <= 1.0 and 0.0 <= corrupt <= 1.0 and drop + corrupt <= 1.0):
            raise ValueError(f"reply loss probabilities must be in [0, 1] with drop + corrupt <= 1, got {drop}, "
                             f"{corrupt}")
        with self._lock:
            self._loss = (drop, corrupt, random.Random(seed)) if drop or corrupt else None
            self._events.add(f"{self.name} reply loss drop {drop:g} corrupt {corrupt:g}")

    def set_reply_delay(self, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """From now on every answer starts fixed + U(0, jitter) seconds after the bytes that asked for it arrived
        (a BULK_COMM's replies as a whole: the first is delayed, the others follow it at once, as they do without
        a delay). ValueError for a value outside [0, 0.1] s; `seed` makes the draws repeatable."""
        self.reply_delay.set(fixed, jitter, seed)
        self._events.add(f"{self.name} reply delay {self.reply_delay.text()}")

    def set_error(self, device_id: int, bit: int | BearError, on: bool = True) -> None:
        """Raise (or drop) an error bit: a bit number 0-6 or a BearError. Bit 3 is the E-stop input (held until
        dropped); bit 0 is reported once; the others latch until torque_enable = 0 is written."""
        mask = int(bit) if isinstance(bit, BearError) else 1 << int(bit)
        with self._lock:
            bear = self._bears[device_id]
            if mask & BearError.WATCHDOG_ESTOP:
                bear.estop = on
                self._estop_unsent = on
            if mask & BearError.COMMUNICATION:
                bear.comm_warning = on
            rest = int(mask & ~(_ESTOP | _COMM) & 0x7F)
            bear.latched = bear.latched | rest if on else bear.latched & ~rest
            cause = "e-stop input" if mask & BearError.WATCHDOG_ESTOP else \
                f"injected {', '.join(error_flags(rest)) or 'nothing'}"
            self._track(bear, time.monotonic(), cause)

    def set_estop(self, on: bool = True, ids: Iterable[int] | None = None) -> None:
        """The external E-stop input of these BEARs (all by default)."""
        for device_id in self.ids if ids is None else ids:
            self.set_error(device_id, BearError.WATCHDOG_ESTOP, on)

    def corrupt_next_reply(self, kind: str = "checksum", device_id: int | None = None) -> None:
        """Spoil the next reply (of `device_id`, or of anyone): "checksum" (bad last byte), "truncate" (half a
        packet), "garbage" (noise with a false header before it), "foreign" (a valid packet from ID 0xFD before it),
        "drop" (no reply). One call spoils one reply."""
        if kind not in CORRUPTIONS:
            raise ValueError(f"corruption is one of {CORRUPTIONS}")
        with self._lock:
            self._corruptions.append((kind, device_id))

    # -- physics adapter --
    def set_measured(self, device_id: int, position: float, velocity: float, iq: float) -> None:
        with self._lock:
            bear = self._bears[device_id]
            status = bear.status
            status["present_position"], status["present_velocity"], status["present_iq"] = \
                _f32(position), _f32(velocity), _f32(iq)
            if bear.enable and bear.torque_enable() != bear.logged_enable:  # a joint limit crossed while enabled
                self._track(bear, time.monotonic(), bear.fault_cause())

    def set_measured_many(self, ids: Sequence[int], positions, velocities, iqs) -> None:
        # Rounded to float32 in one go (what _f32 does one value at a time): the physics calls this every step.
        columns = [np.asarray(v, dtype=np.float32).astype(np.float64).tolist()
                   for v in (positions, velocities, iqs)]
        with self._lock:
            for device_id, p, v, i in zip(ids, *columns, strict=True):
                bear = self._bears[device_id]
                status = bear.status
                status["present_position"], status["present_velocity"], status["present_iq"] = p, v, i
                if bear.enable and bear.torque_enable() != bear.logged_enable:  # a joint limit crossed while enabled
                    self._track(bear, time.monotonic(), bear.fault_cause())

    def command(self, device_id: int) -> MotorCommand:
        with self._lock:
            bear = self._bears[device_id]
            self._check_watchdog(bear, time.monotonic())
            s = bear.status
            return MotorCommand(bear.id, int(bear.config["mode"]), bear.torque_enable(), s["goal_position"],
                                s["goal_velocity"], s["goal_iq"], s["goal_id"], bear.error_byte())

    def commands(self, ids: Sequence[int] | None = None) -> dict[str, np.ndarray]:
        """Arrays in `ids` order (default: sorted IDs): mode, torque_enable, goal_position, goal_velocity,
        goal_iq, goal_id, error. What `command` gives per ID, in one pass (the physics calls it every step)."""
        with self._lock:
            now = time.monotonic()
            rows = []
            for device_id in (self.ids if ids is None else ids):
                bear = self._bears[device_id]
                self._check_watchdog(bear, now)
                s = bear.status
                error = bear.error_byte()
                rows.append((bear.config["mode"], bear.torque_enable(error), s["goal_position"], s["goal_velocity"],
                             s["goal_iq"], s["goal_id"], error))
        mode, enable, position, velocity, iq, i_d, error = zip(*rows, strict=True) if rows else ((),) * 7
        return {"goal_position": np.array(position, dtype=np.float64),
                "goal_velocity": np.array(velocity, dtype=np.float64),
                "goal_iq": np.array(iq, dtype=np.float64), "goal_id": np.array(i_d, dtype=np.float64),
                "mode": np.array(mode, dtype=np.int64), "torque_enable": np.array(enable, dtype=np.int64),
                "error": np.array(error, dtype=np.uint8)}

    def register_value(self, device_id: int, name: str, table: str = "status") -> int | float:
        """A register as the bus would read it."""
        registers = CONFIG_REGISTERS if table == "config" else STATUS_REGISTERS
        with self._lock:
            return self._bears[device_id].value(registers[name])

    def set_register_value(self, device_id: int, name: str, value: int | float, table: str = "status") -> None:
        """Set a register directly (temperatures, voltage, limits...), past the bus rules; not torque_enable."""
        registers = CONFIG_REGISTERS if table == "config" else STATUS_REGISTERS
        register = registers[name]
        if name in ("torque_enable", "error_status", "warning_status") or (table == "config" and name == "id"):
            raise ValueError(f"{name} follows the device state; it is not set directly")
        with self._lock:
            bear = self._bears[device_id]
            files = bear.config if table == "config" else bear.status
            files[name] = _f32(float(value)) if register.kind == "f32" else int(value)
            now = time.monotonic()
            if name == "watchdog_timeout":
                self._events.add(f"{self.name} {bear.id} watchdog_timeout {bear.config[name]}", now)
            self._track(bear, now, f"{name} set")

    def saved_config(self, device_id: int) -> dict[str, int | float]:
        """The config registers as last stored in flash by SAVE_CFG."""
        with self._lock:
            return dict(self._bears[device_id].flash)

    def power_cycle(self, ids: Iterable[int] | None = None) -> None:
        """Restart these BEARs: config from flash, status registers and flags back to power-on values."""
        with self._lock:
            for device_id in list(self.ids if ids is None else ids):
                old = self._bears.pop(device_id)
                now = time.monotonic()
                bear = _Bear(int(old.flash["id"]), now)
                bear.config, bear.flash = dict(old.flash), dict(old.flash)
                bear.estop, bear.silent = old.estop, old.silent  # wiring, not state
                bear.logged_enable = old.logged_enable
                self._bears[bear.id] = bear
                if bear.config["watchdog_timeout"] != old.config["watchdog_timeout"]:
                    self._events.add(f"{self.name} {bear.id} watchdog_timeout {bear.config['watchdog_timeout']}", now)
                self._track(bear, now, "power cycle")

    # -- event log --
    def drain_events(self) -> list[tuple[float, str]]:
        """(time.monotonic() stamp, text) of every event since the last drain, oldest first, stamped when it
        happened (a watchdog expiry: when detected): every change of a BEAR's torque_enable as read, with its cause
        (`bear 3 torque_enable 1 -> 3 (watchdog: 51.2 ms without a packet)`, `(host write)`, `(e-stop input)`,
        `(fault: joint_limit)`, `(power cycle)`, ...); a watchdog_timeout taking effect; a config write ignored
        because torque is enabled; unplug / plug; reply loss and reply delay settings; the first reply that carries
        the E-stop bit after the input went on (`bear first reply with the E-stop bit sent`); a request more than
        LATE_REQUEST_S after the BEARs last answered (`bear request 7.1 ms after the last answer`, stamped when it
        came) and a reply more than LATE_REPLY_S after it was due (`bear reply 2.3 ms after it was due`, stamped when
        it left). "bear" is `name`."""
        return self._events.drain()

    @property
    def events_dropped(self) -> int:
        """Events lost because 10,000 were waiting undrained."""
        return self._events.dropped

    def _track(self, bear: _Bear, now: float, cause: str) -> None:
        """Log a change of the BEAR's torque_enable (as read) since the last one logged."""
        value = int(bear.torque_enable())
        if value != bear.logged_enable:
            self._events.add(f"{self.name} {bear.id} torque_enable {bear.logged_enable} -> {value} ({cause})", now)
            bear.logged_enable = value

    def _check_watchdog(self, bear: _Bear, now: float) -> None:
        silent_s = bear.check_watchdog(now)
        if silent_s is not None:
            self._track(bear, now, f"watchdog: {1e3 * silent_s:.1f} ms without a packet")

    # -- the wire --
    def _on_bytes(self, data: bytes) -> None:
        arrived = time.monotonic()
        if self._answered is not None and LATE_REQUEST_S < arrived - self._answered <= HOST_AWAY_S:
            self._events.add(f"{self.name} request {1e3 * (arrived - self._answered):.1f} ms after the last "
                             "answer", arrived)
        self._answered = arrived
        with self._lock:
            reply = self.handle(data)
            bulk, self._bulk_seen = self._bulk_seen, False
            # Decided where the reply is built: one built before the input went on and sent after it (a reply
            # delay in between) does not carry the bit.
            first_estop = self._estop_unsent and any(packet.error & _ESTOP for packet in StatusParser().feed(reply))
            if first_estop:
                self._estop_unsent = False
        # Answered outside the lock: a reply delay (and the write) holds up neither the physics nor a command.
        if reply and self._pty is not None:
            due = self.reply_delay.wait(arrived)
            # Logged as the reply leaves, before its write: stamped then, so the host cannot have it before its
            # stamp, and the log stays in time order.
            leaving = time.monotonic()
            if leaving - due > LATE_REPLY_S:
                self._events.add(f"{self.name} reply {1e3 * (leaving - due):.1f} ms after it was due", leaving)
            if first_estop:  # when the host could first know: the reply that carries the bit leaves
                self._events.add(f"{self.name} first reply with the E-stop bit sent", leaving)
            self._pty.send(reply)
            self._answered = time.monotonic()
        if bulk and self.on_bulk is not None:
            with self._lock:
                self.on_bulk()

    def check_watchdogs(self) -> None:
        """Run every BEAR's watchdog now (a device clock: a lockstep plant calls it every millisecond). `handle`
        runs them too, so an expiry is detected within a millisecond while a plant runs, at the next packet
        otherwise."""
        with self._lock:
            now = time.monotonic()
            for bear in self._bears.values():
                self._check_watchdog(bear, now)

    def handle(self, data: bytes) -> bytes:
        """Bytes from the host in, the devices' answer out (b"" when nobody answers)."""
        with self._lock:
            now = time.monotonic()
            for bear in self._bears.values():
                self._check_watchdog(bear, now)
            if self._unplugged:  # the wire is cut: nothing reaches the BEARs (their clocks run on, above)
                self.unplugged_bytes += len(data)
                return b""
            if self._rx and now - self._rx_time > STALE_RX_S:
                self.stats.reject("truncated")
                self._rx.clear()
            self._rx_time = now
            self._rx += data
            out = bytearray()
            for device_id, code, params in self._frames():
                out += self._execute(device_id, code, params, now)
            return bytes(out)

    def _frames(self):
        """Complete, checksum-valid packets from the receive buffer; resynchronises on FF FF after garbage."""
        buf = self._rx
        while True:
            if not skip_to_header(buf, HEADER, self.stats):
                return
            if len(buf) < 4:
                return
            device_id, length = buf[2], buf[3]
            if device_id == 0xFF or length < 2:
                self.stats.reject("garbage" if device_id == 0xFF else "length")
                del buf[:1]
                continue
            total = 4 + length
            if len(buf) < total:
                return
            if checksum(buf[2:total - 1]) != buf[total - 1]:
                self.stats.reject("checksum")
                bear = self._bears.get(device_id)
                if bear is not None:
                    bear.comm_warning = True
                del buf[:1]
                continue
            frame = bytes(buf[:total])
            del buf[:total]
            self.stats.packets += 1
            yield device_id, frame[4], frame[5:-1]

    def _execute(self, device_id: int, code: int, params: bytes, now: float) -> bytes:
        if code & 0x80:
            return b""  # another device's status packet on the bus: not an instruction
        name = _INSTRUCTION_NAMES.get(code)
        instruction = None if name is None else Instruction(code)
        self.requests[name or f"0x{code:02X}"] += 1
        if instruction is Instruction.BULK_COMM:
            return self._bulk(params, now) if device_id == BROADCAST_ID else b""
        if device_id == BROADCAST_ID:
            targets = [b for b in self._bears.values() if not b.silent]
        else:
            bear = self._bears.get(device_id)
            targets = [] if bear is None or bear.silent else [bear]
        out = b""
        for bear in targets:
            bear.last_rx = now
            data = None
            if instruction is Instruction.PING and not params:
                data = self.ping_data
            # A read whose reply would not fit one packet (over 63 addresses) gets no reply, and bit 0.
            elif instruction is Instruction.READ_STAT and 4 * len(params) <= MAX_PARAMS:
                data = bear.read("status", params)
            elif instruction is Instruction.READ_CFG and 4 * len(params) <= MAX_PARAMS:
                data = bear.read("config", params)
            elif instruction in (Instruction.WRITE_STAT, Instruction.WRITE_CFG) and params and len(params) % 5 == 0:
                pairs = [(params[k], params[k + 1:k + 5]) for k in range(0, len(params), 5)]
                if instruction is Instruction.WRITE_STAT:
                    for address, raw in pairs:
                        bear.write_status(address, raw)
                    self._track(bear, now, "host write")
                else:
                    self._write_config(bear, pairs, now)
            elif instruction is Instruction.SAVE_CFG and not params:
                if bear.torque_enable() == TorqueEnable.DISABLED:  # ignored while enabled, as config writes
                    bear.flash = dict(bear.config)
            else:  # malformed, unknown or unsupported (SET_POSITION: battery-backed BEARs only)
                bear.comm_warning = True
            if data is not None and device_id != BROADCAST_ID:  # no reply to writes, nor to the broadcast ID
                out = self._reply(bear, data)
        self._rekey()
        return out

    def _bulk(self, params: bytes, now: float) -> bytes:
        """One status packet per listed motor, in request order (none without reads); a motor's writes are
        applied before its registers are read."""
        if len(params) < 2:
            self.stats.reject("bulk_length")
            return b""
        n_motors, n_read, n_write = params[0], params[1] >> 4, params[1] & 0x0F
        head, stride = 2 + n_read + n_write, 1 + 4 * n_write
        if len(params) != head + n_motors * stride:
            self.stats.reject("bulk_length")
            return b""
        reads, writes = bytes(params[2:2 + n_read]), params[2 + n_read:head]
        tracked = STATUS_REGISTERS["torque_enable"].address in writes
        listed = []
        self._bulk_seen = True
        bears = self._bears
        for k in range(head, head + n_motors * stride, stride):
            bear = bears.get(params[k])
            if bear is None or bear.silent:
                continue
            bear.last_rx = now
            for j, address in enumerate(writes):
                bear.write_status(address, params[k + 1 + 4 * j:k + 5 + 4 * j])
            if tracked:  # only a torque_enable write changes torque_enable (goals do not): logged if it did
                self._track(bear, now, "host write")
            listed.append(bear)
        if not n_read:
            return b""
        return b"".join([self._reply(bear, bear.read("status", reads)) for bear in listed])

    def _write_config(self, bear: _Bear, pairs: list[tuple[int, bytes]], now: float) -> None:
        before = bear.torque_enable()
        written = bear.write_config(pairs, taken=set(self._bears))
        if written is None:
            self._events.add(f"{self.name} {bear.id} config write ignored (torque_enable {int(before)})", now)
            return
        if "watchdog_timeout" in written:
            self._events.add(f"{self.name} {bear.id} watchdog_timeout {bear.config['watchdog_timeout']}", now)
        self._track(bear, now, "host config write")  # limits and voltages move the fault bits

    def _reply(self, bear: _Bear, data: bytes) -> bytes:
        packet = _status_packet(bear.id, bear.error_byte(), data)
        bear.comm_warning = False  # reported: the warning resets
        self.replies += 1
        for k, (kind, target) in enumerate(self._corruptions):
            if target is None or target == bear.id:
                del self._corruptions[k]
                return _spoil(packet, kind)
        if self._loss is not None:
            drop, corrupt, rng = self._loss
            draw = rng.random()
            if draw < drop:
                self.reply_losses["drop"] += 1
                return b""
            if draw < drop + corrupt:
                kind = rng.choice(LOSS_CORRUPTIONS)
                self.reply_losses[kind] += 1
                return _spoil(packet, kind)
        return packet

    def _rekey(self) -> None:
        if any(bear.id != key for key, bear in self._bears.items()):
            self._bears = {bear.id: bear for bear in self._bears.values()}


def _status_packet(device_id: int, error: int, data: bytes) -> bytes:
    """drivers.bear.encode_status without its checks (the emulator's IDs and data are valid): every reply."""
    body = bytes((device_id, len(data) + 2, error)) + data
    return HEADER + body + bytes((~sum(body) & 0xFF,))


def _spoil(packet: bytes, kind: str) -> bytes:
    if kind == "checksum":
        return packet[:-1] + bytes((packet[-1] ^ 0xFF,))
    if kind == "truncate":
        return packet[:len(packet) // 2]
    if kind == "garbage":  # noise with a lone FF, then a false header claiming ID 1 and LEN 2
        return b"\x00\x55\xff\x13\xff\xff\x01\x02" + packet
    if kind == "foreign":  # a well-formed reply from an ID nobody asked
        return encode_status(0xFD, ERROR_OK, packet[5:-1]) + packet
    return b""  # drop
