"""A Dynamixel Protocol 2.0 bus of X-series servos on a pseudo-terminal, byte-exact to the ROBOTIS protocol, so that
ROBOTIS' own dynamixel-sdk (or any other spec-following host) opens `path` as if it were a U2D2 / USB adapter.

`DynamixelBusEmulator(ids)`: the servos (`XSeriesServo`: control table, access rules, Bus Watchdog) answer PING,
READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR and SYNC_/BULK_ READ and WRITE; anything else
addressed to one of our IDs gets Instruction Error (FAST_SYNC_READ / FAST_BULK_READ are not emulated). Thread-safe
accessors for a physics adapter (every 1 ms): `set_present`, `set_joint_state`, `goal_position`,
`goal_joint_positions`, `torque_enabled`, `torque_enabled_all`; `drain_events` for the event log; faults for tests:
`silence`, `set_hardware_error`, `corrupt_replies`, `set_reply_delay`, `clear_faults`. Where the sources are silent
(BRUCE's exact model is not stated anywhere), the choice is noted at the code that makes it.

The servos' time (Bus Watchdog, Realtime Tick, the inter-byte gap, event stamps) is `clock`, time.monotonic by default;
a test passes a clock it advances itself (`clock=`) to run the servos in lockstep with it, in virtual time.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.dynamixel_codec import (
    BROADCAST_ID,
    ERR_ACCESS,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
    ERR_INSTRUCTION,
    ERR_RESULT_FAIL,
    ERROR_ALERT,
    INST_ACTION,
    INST_BULK_READ,
    INST_BULK_WRITE,
    INST_CLEAR,
    INST_FACTORY_RESET,
    INST_PING,
    INST_READ,
    INST_REBOOT,
    INST_REG_WRITE,
    INST_STATUS,
    INST_SYNC_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    MAX_ID,
    Packet,
    PacketParser,
    encode_hardware_error,
    encode_status,
)
from drivers.dynamixel_registers import (
    BUS_WATCHDOG_ERROR,
    BUS_WATCHDOG_MAX,
    BUS_WATCHDOG_UNIT_S,
    POSITION_UNIT,
    counts_to_joint,
    joint_velocity_to_counts,
)
from drivers.emulators.pty_device import PtyDevice
from drivers.emulators.reply_delay import ReplyDelay
from drivers.errors import LinkStats

# The model emulated: XM430-W350, firmware 52, and its Protocol 2.0 control table (EEPROM 0..63, RAM 64..147,
# Indirect Address 1..28 at 168..222 -> Indirect Data 1..28 at 224..251, Indirect Address 29..56 at 578..632 ->
# Indirect Data 29..56 at 634..661). Reserved gaps read as 0 and refuse writes (Access Error).
XM430_W350 = 1020
FIRMWARE_VERSION = 52
TABLE_SIZE = 662
EEPROM_END = 64
MAX_EVENTS = 10_000                # the event log keeps the newest this many
GOAL_ITEMS = frozenset({"goal_pwm", "goal_current", "goal_velocity", "goal_position"})   # read-only in watchdog error


@dataclass(frozen=True, slots=True)
class Item:
    address: int
    size: int
    name: str
    writable: bool
    default: int
    signed: bool = False
    valid: tuple[int, int] | frozenset | None = None   # accepted values of a write: (lo, hi) or a set

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END


def _items(model_number: int, firmware: int) -> list[Item]:
    gain = (0, 16383)
    items = [
        Item(0, 2, "model_number", False, model_number),
        Item(2, 4, "model_information", False, 0),
        Item(6, 1, "firmware_version", False, firmware),
        Item(7, 1, "id", True, 1, valid=(0, MAX_ID)),
        Item(8, 1, "baud_rate", True, 1, valid=(0, 7)),    # stored, not applied
        Item(9, 1, "return_delay_time", True, 250),        # stored, not waited (set_reply_delay delays answers)
        Item(10, 1, "drive_mode", True, 0),
        Item(11, 1, "operating_mode", True, 3, valid=frozenset({0, 1, 3, 4, 5, 16})),
        Item(12, 1, "secondary_id", True, 255),
        Item(13, 1, "protocol_type", True, 2, valid=frozenset({1, 2})),
        Item(20, 4, "homing_offset", True, 0, signed=True, valid=(-1044479, 1044479)),
        Item(24, 4, "moving_threshold", True, 10, valid=(0, 1023)),
        Item(31, 1, "temperature_limit", True, 80, valid=(0, 100)),
        Item(32, 2, "max_voltage_limit", True, 160, valid=(95, 160)),
        Item(34, 2, "min_voltage_limit", True, 95, valid=(95, 160)),
        Item(36, 2, "pwm_limit", True, 885, valid=(0, 885)),
        Item(38, 2, "current_limit", True, 1193, valid=(0, 1193)),
        Item(44, 4, "velocity_limit", True, 200, valid=(0, 1023)),
        Item(48, 4, "max_position_limit", True, 4095, valid=(0, 4095)),
        Item(52, 4, "min_position_limit", True, 0, valid=(0, 4095)),
        Item(60, 1, "startup_configuration", True, 0),
        Item(63, 1, "shutdown", True, 52),
        Item(64, 1, "torque_enable", True, 0, valid=(0, 1)),
        Item(65, 1, "led", True, 0, valid=(0, 1)),
        Item(68, 1, "status_return_level", True, 2, valid=(0, 2)),
        Item(69, 1, "registered_instruction", False, 0),
        Item(70, 1, "hardware_error_status", False, 0),
        Item(76, 2, "velocity_i_gain", True, 1920, valid=gain),
        Item(78, 2, "velocity_p_gain", True, 100, valid=gain),
        Item(80, 2, "position_d_gain", True, 0, valid=gain),
        Item(82, 2, "position_i_gain", True, 0, valid=gain),
        Item(84, 2, "position_p_gain", True, 800, valid=gain),
        Item(88, 2, "feedforward_2nd_gain", True, 0, valid=gain),
        Item(90, 2, "feedforward_1st_gain", True, 0, valid=gain),
        Item(98, 1, "bus_watchdog", True, 0, signed=True, valid=(BUS_WATCHDOG_ERROR, BUS_WATCHDOG_MAX)),
        Item(100, 2, "goal_pwm", True, 885, signed=True),
        Item(102, 2, "goal_current", True, 1193, signed=True),
        Item(104, 4, "goal_velocity", True, 0, signed=True),
        Item(108, 4, "profile_acceleration", True, 0, valid=(0, 32767)),
        Item(112, 4, "profile_velocity", True, 0, valid=(0, 32767)),
        Item(116, 4, "goal_position", True, 2048, signed=True),
        Item(120, 2, "realtime_tick", False, 0),
        Item(122, 1, "moving", False, 0),
        Item(123, 1, "moving_status", False, 0),
        Item(124, 2, "present_pwm", False, 0, signed=True),
        Item(126, 2, "present_current", False, 0, signed=True),
        Item(128, 4, "present_velocity", False, 0, signed=True),
        Item(132, 4, "present_position", False, 2048, signed=True),
        Item(136, 4, "velocity_trajectory", False, 0, signed=True),
        Item(140, 4, "position_trajectory", False, 0, signed=True),
        Item(144, 2, "present_input_voltage", False, 120),
        Item(146, 1, "present_temperature", False, 30),
        Item(147, 1, "backup_ready", False, 0),
    ]
    for block, (addr0, data0) in enumerate(((168, 224), (578, 634))):  # Indirect Address: RAM, as in the X series
        for k in range(28):
            n = block * 28 + k + 1
            items.append(Item(addr0 + 2 * k, 2, f"indirect_address_{n}", True, data0 + k, valid=(64, TABLE_SIZE - 1)))
            items.append(Item(data0 + k, 1, f"indirect_data_{n}", True, 0))
    return items


INDIRECT_DATA = {**{224 + k: 168 + 2 * k for k in range(28)}, **{634 + k: 578 + 2 * k for k in range(28)}}


class XSeriesServo:
    """One servo's control table and instruction semantics. Not locked: the bus emulator holds its lock."""

    def __init__(self, dxl_id: int, model_number: int = XM430_W350, firmware: int = FIRMWARE_VERSION,
                 track_goals: bool = True, clock: Callable[[], float] = time.monotonic):
        self.clock = clock                 # the servo's time in seconds (Realtime Tick; the bus stamps packets)
        self.items = {item.name: item for item in _items(model_number, firmware)}
        self.owner: list[Item | None] = [None] * TABLE_SIZE
        for item in self.items.values():
            for a in range(item.address, item.address + item.size):
                self.owner[a] = item
        self.table = bytearray(TABLE_SIZE)
        self.track_goals = track_goals
        self._registered: tuple[int, bytes] | None = None
        self._reset(keep=())
        self._put("id", dxl_id)
        self.last_rx = clock()             # when this servo last heard an instruction packet (Bus Watchdog)
        self.notes: list[str] = []         # event texts not yet taken by the bus (see take_notes)
        self._torque_seen = self.torque

    # -- raw access --------------------------------------------------------------------------------------------
    def get(self, name: str, table: bytearray | None = None) -> int:
        item = self.items[name]
        raw = (self.table if table is None else table)[item.address:item.address + item.size]
        return int.from_bytes(raw, "little", signed=item.signed)

    def _put(self, name: str, value: int) -> None:
        item = self.items[name]
        bits = 8 * item.size
        self.table[item.address:item.address + item.size] = (int(value) & ((1 << bits) - 1)).to_bytes(item.size,
                                                                                                       "little")

    @property
    def id(self) -> int:
        return self.table[7]

    @property
    def torque(self) -> bool:
        return bool(self.table[64])

    @property
    def alert(self) -> int:
        return ERROR_ALERT if self.table[70] else 0

    @property
    def watchdog_error(self) -> bool:
        return self.get("bus_watchdog") == BUS_WATCHDOG_ERROR

    def _reset(self, keep: Iterable[str]) -> None:
        kept = {name: self.get(name) for name in keep}
        for item in self.items.values():
            self._put(item.name, item.default)
        for name, value in kept.items():
            self._put(name, value)
        self._registered = None

    def _target(self, address: int) -> int:
        """Indirect Data resolves to the byte its Indirect Address names."""
        ref = INDIRECT_DATA.get(address)
        if ref is None:
            return address
        return int.from_bytes(self.table[ref:ref + 2], "little")

    # -- instructions ------------------------------------------------------------------------------------------
    def read(self, address: int, length: int) -> tuple[int, bytes]:
        """(error number, data)."""
        if address + length > TABLE_SIZE:
            return ERR_ACCESS, b""
        self._put("realtime_tick", int(self.clock() * 1000) % 32768)
        return 0, bytes(self.table[self._target(a)] for a in range(address, address + length))

    def check_write(self, address: int, data: bytes) -> tuple[int, bytearray | None]:
        """(error number, the table after the write) without changing anything."""
        error, new, _ = self._check_write(address, data)
        return error, new

    def _check_write(self, address: int, data: bytes) -> tuple[int, bytearray | None, set[str]]:
        """(error number, the table after the write or None, the names of the items the write touches).

        A packet is applied all or nothing. Access Error: a read-only item, a gap, beyond the table, EEPROM (0..63)
        while Torque Enable is 1. Data Range Error: a value outside an item's `valid`; goals and Bus Watchdog > 0
        while in Bus Watchdog Error. Data Limit Error: goal position outside the position limits in position mode.
        Result Fail: Torque Enable = 1 while a hardware error bit that is in Shutdown (63) is set, until REBOOT."""
        if not data:
            return ERR_DATA_LENGTH, None, set()
        if address + len(data) > TABLE_SIZE:
            return ERR_ACCESS, None, set()
        new = bytearray(self.table)
        touched: set[str] = set()
        for offset, byte in enumerate(data):
            target = self._target(address + offset)
            item = self.owner[target] if 0 <= target < TABLE_SIZE else None
            if item is None or not item.writable or (item.eeprom and self.torque):
                return ERR_ACCESS, None, touched
            new[target] = byte
            touched.add(item.name)
        for name in touched:
            valid, value = self.items[name].valid, self.get(name, new)
            if isinstance(valid, tuple) and not valid[0] <= value <= valid[1] or \
                    isinstance(valid, frozenset) and value not in valid:
                return ERR_DATA_RANGE, None, touched
        if self.watchdog_error:
            # Bus Watchdog Error: the goals are read-only, and only 0 (or -1 again) may be written to Bus Watchdog.
            if touched & GOAL_ITEMS or ("bus_watchdog" in touched and self.get("bus_watchdog", new) > 0):
                return ERR_DATA_RANGE, None, touched
        if "goal_position" in touched and self.get("operating_mode", new) == 3:
            goal = self.get("goal_position", new)
            if not self.get("min_position_limit", new) <= goal <= self.get("max_position_limit", new):
                return ERR_DATA_LIMIT, None, touched
        if "torque_enable" in touched and new[64] and not self.torque and self.table[70] & self.table[63]:
            return ERR_RESULT_FAIL, None, touched
        return 0, new, touched

    def write(self, address: int, data: bytes) -> int:
        error, new, touched = self._check_write(address, data)
        if error:
            return error
        torque_on = new[64] and not self.torque
        was_error = self.watchdog_error
        self.table[:] = new
        if torque_on:  # no jump: the goal starts where the servo is
            self._put("goal_position", self.get("present_position"))
        if "bus_watchdog" in touched:
            self._watchdog_written(was_error)
        if self.track_goals and self.torque:
            self._put("present_position", self.get("goal_position"))
            self._put("present_velocity", 0)
        return 0

    # -- Bus Watchdog ------------------------------------------------------------------------------------------
    # Item 98 (1 byte, RAM, signed): 0 off (writing 0 also clears a Bus Watchdog Error), 1..127 armed in units of
    # 20 ms, -1 (reads 0xFF) in error. Every valid instruction packet on the bus counts as heard, whatever its ID
    # or instruction (each servo sees all traffic); bad CRCs, cut-short packets and other devices' status packets
    # do not, and a `silence`d servo is unplugged: it hears nothing. Armed with torque on and silent for longer, the
    # servo stops (`_stop`) and reads -1; only 0 clears the error (1..127 is refused: the manual says only 0 clears
    # it, our choice where it is silent), a host write of -1 puts it in the error as an expiry would, and REBOOT /
    # FACTORY_RESET clear it with the rest of RAM.
    def _watchdog_written(self, was_error: bool) -> None:
        value = self.get("bus_watchdog")
        if value == BUS_WATCHDOG_ERROR:
            if not was_error:
                self._stop()
            self.notes.append(f"dynamixel {self.id} bus watchdog -1 (error written by the host"
                              f"{', already in it' if was_error else ': stopped'})")
        elif value == 0:
            self.notes.append(f"dynamixel {self.id} bus watchdog 0 (off{', error cleared' if was_error else ''})")
        else:
            self.notes.append(f"dynamixel {self.id} bus watchdog {value} "
                              f"({round(value * BUS_WATCHDOG_UNIT_S * 1000)} ms)")

    def heard(self, now: float) -> None:
        """A valid instruction packet reached this servo (whatever its ID)."""
        self.last_rx = now

    def check_watchdog(self, now: float) -> bool:
        """Bus Watchdog armed, torque on and more than its time since the last packet: stop, Bus Watchdog := -1.
        True when it expired now."""
        value = self.get("bus_watchdog")
        silent_s = now - self.last_rx
        if value <= 0 or not self.torque or silent_s <= value * BUS_WATCHDOG_UNIT_S:
            return False
        self._stop()
        self._put("bus_watchdog", BUS_WATCHDOG_ERROR)
        self.notes.append(f"dynamixel {self.id} bus watchdog: stopped after {round(silent_s * 1000)} ms "
                          f"without a packet")
        return True

    def _stop(self) -> None:
        """The servo stops where it is, torque staying on: goal position := present position in the position modes
        (3, 4, 5), so a physics adapter reading `goal_joint_positions` sees it hold; goal velocity, current or PWM
        := 0 in modes 1, 0 and 16."""
        mode = self.get("operating_mode")
        if mode in (3, 4, 5):
            self._put("goal_position", self.get("present_position"))
        elif mode == 1:
            self._put("goal_velocity", 0)
        elif mode == 0:
            self._put("goal_current", 0)
        elif mode == 16:
            self._put("goal_pwm", 0)
        if self.track_goals:
            self._put("present_velocity", 0)

    def take_notes(self) -> list[str]:
        """Event texts since the last call, a change of Torque Enable included (whatever changed it)."""
        if self.torque != self._torque_seen:
            self._torque_seen = self.torque
            self.notes.append(f"dynamixel {self.id} torque {'on' if self.torque else 'off'}")
        notes, self.notes = self.notes, []
        return notes

    def reg_write(self, address: int, data: bytes) -> int:
        error, _ = self.check_write(address, data)
        if not error:
            self._registered = (address, bytes(data))
            self._put("registered_instruction", 1)
        return error

    def action(self) -> int:
        if self._registered is None:
            return 0
        address, data = self._registered
        self._registered = None
        self._put("registered_instruction", 0)
        return self.write(address, data)

    def reboot(self) -> None:
        """RAM back to its initial values; EEPROM kept; hardware errors and a Bus Watchdog Error cleared."""
        self._reset_noted(keep=[item.name for item in self.items.values() if item.eeprom] + ["present_position"],
                          why="reboot")

    def factory_reset(self, option: int) -> None:
        keep = {0xFF: [], 0x01: ["id"], 0x02: ["id", "baud_rate"]}[option]
        self._reset_noted(keep=keep + ["present_position"], why="factory reset")

    def _reset_noted(self, keep: list[str], why: str) -> None:
        """`_reset`, with its torque off and watchdog reset noted under the ID the servo had (a factory reset may
        change it)."""
        dxl_id, watchdog = self.id, self.get("bus_watchdog")
        self.notes = self.take_notes()     # a torque change before the reset, noted first
        self._reset(keep=keep)
        if self._torque_seen and not self.torque:
            self._torque_seen = False
            self.notes.append(f"dynamixel {dxl_id} torque off")
        if watchdog:
            self.notes.append(f"dynamixel {dxl_id} bus watchdog 0 (off, {why}"
                              f"{', error cleared' if watchdog == BUS_WATCHDOG_ERROR else ''})")

    def set_hardware_error(self, bits: int) -> None:
        self._put("hardware_error_status", bits)
        if bits & self.table[63]:
            self._put("torque_enable", 0)


class DynamixelBusEmulator:
    """X-series servos with the given IDs on one pty."""

    def __init__(self, ids: Sequence[int], *, signs: Sequence[float] | None = None,
                 model_number: int = XM430_W350, firmware: int = FIRMWARE_VERSION, track_goals: bool = True,
                 frame_gap_s: float = 0.01, name: str = "dynamixel", clock: Callable[[], float] = time.monotonic):
        ids = tuple(int(i) for i in ids)
        if not ids or len(set(ids)) != len(ids) or not all(0 <= i <= MAX_ID for i in ids):
            raise ValueError(f"ids must be unique servo IDs in 0..{MAX_ID}, got {ids}")
        self.ids = ids
        if signs is None:
            signs = (1.0,) * len(ids)
        self.signs = np.asarray(signs, dtype=np.float64)
        self.clock = clock    # device time, seconds (see the module's docstring); reply delays stay on the wall clock
        self.servos = [XSeriesServo(i, model_number, firmware, track_goals, clock) for i in ids]
        self.name = name
        self.frame_gap_s = frame_gap_s
        self.stats = LinkStats()
        self._parser = PacketParser(self.stats)
        self._lock = threading.RLock()
        self._silent: set[int] = set()
        self._corrupt: dict[int, list] = {}       # id -> [mode, remaining or None]
        self._last_rx = 0.0
        self._events: deque[tuple[float, str]] = deque(maxlen=MAX_EVENTS)
        self.events_dropped = 0            # events pushed out of the full log, oldest first
        self._pty: PtyDevice | None = None
        self.reply_delay = ReplyDelay()   # set_reply_delay: how late the answers start

    # -- transport ---------------------------------------------------------------------------------------------
    def start(self) -> DynamixelBusEmulator:
        self._pty = PtyDevice(self.name, self._on_bytes).start()
        return self

    @property
    def path(self) -> str:
        if self._pty is None:
            raise RuntimeError("emulator not started")
        return self._pty.path

    def close(self) -> None:
        if self._pty is not None:
            self._pty.close()
            self._pty = None

    def __enter__(self) -> DynamixelBusEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _on_bytes(self, data: bytes) -> None:
        # A partial packet is dropped when no byte arrived for `frame_gap_s` (an inter-byte timeout).
        arrived, now = time.monotonic(), self.clock()
        with self._lock:
            if self._parser.pending and now - self._last_rx > self.frame_gap_s:
                self._parser.discard()
            self._last_rx = now
        reply = self.handle(data)
        if reply and self._pty is not None:
            self.reply_delay.wait(arrived)  # outside the lock: the physics' accessors go on meanwhile
            self._pty.send(reply)

    def set_reply_delay(self, fixed: float, jitter: float = 0.0, seed: int | str | None = None) -> None:
        """From now on every answer starts fixed + U(0, jitter) seconds after the bytes that asked for it arrived
        (a SYNC_READ's status packets as a whole). ValueError outside [0, 0.1] s; `seed` makes draws repeatable."""
        self.reply_delay.set(fixed, jitter, seed)

    def handle(self, data: bytes) -> bytes:
        """Bytes from the host -> the bytes the servos answer (the pty thread calls this; tests may call it too)."""
        with self._lock:
            now = self.clock()
            self._tick(now)     # the silence before these bytes first: a watchdog may have run out in it
            out = []
            for packet in self._parser.feed(data):
                if packet.instruction != INST_STATUS:
                    for servo in self.servos:
                        if servo.id not in self._silent:
                            servo.heard(now)
                out += self._process(packet)
                self._note(now)
            for dxl_id in self._parser.take_crc_failures():  # a bad CRC addressed to one of ours: CRC Error
                servo = self._servo(dxl_id)
                if servo is not None:
                    out.append(self._status(servo, ERR_CRC))
            return b"".join(out)

    # -- Bus Watchdog and the event log ------------------------------------------------------------------------
    def _note(self, stamp: float) -> None:
        """The servos' new event texts into the log, stamped."""
        for servo in self.servos:
            for text in servo.take_notes():
                if len(self._events) == MAX_EVENTS:
                    self.events_dropped += 1
                self._events.append((stamp, text))

    def _tick(self, now: float | None = None) -> None:
        """Every servo's Bus Watchdog checked at `now` (default: this moment); events logged. Time is checked
        lazily, whenever the emulator is touched (bytes received, before they count as heard; every accessor), so
        the state anyone observes is up to date and an expiry's event is stamped when it was detected."""
        now = self.clock() if now is None else now
        for servo in self.servos:
            servo.check_watchdog(now)
        self._note(now)

    def check_watchdogs(self) -> list[int]:
        """Check every servo's Bus Watchdog now (the accessors do it too); the IDs whose watchdog ran out now."""
        with self._lock:
            now = self.clock()
            expired = [servo.id for servo in self.servos if servo.check_watchdog(now)]
            self._note(now)
            return expired

    def drain_events(self) -> list[tuple[float, str]]:
        """(`clock` stamp, text) of the events since the last drain, oldest first (the newest
        `MAX_EVENTS` are kept, `events_dropped` counts the rest): every change of Torque Enable, whatever its cause
        ("dynamixel 11 torque on"), Bus Watchdog writes ("dynamixel 11 bus watchdog 20 (400 ms)"), a reboot's reset
        of it, and expiries. A packet's events carry the time its bytes arrived; an expiry, when it was detected.
        Thread-safe."""
        with self._lock:
            self._tick()
            events = list(self._events)
            self._events.clear()
            return events

    # -- dispatch ----------------------------------------------------------------------------------------------
    def _servo(self, dxl_id: int) -> XSeriesServo | None:
        """The answering servo with that ID (None when absent or silenced)."""
        for servo in self.servos:
            if servo.id == dxl_id:
                return None if dxl_id in self._silent else servo
        return None

    def _live(self) -> list[XSeriesServo]:
        return sorted((s for s in self.servos if s.id not in self._silent), key=lambda s: s.id)

    def _status(self, servo: XSeriesServo, error: int, data: bytes = b"", dxl_id: int | None = None) -> bytes:
        dxl_id = servo.id if dxl_id is None else dxl_id
        packet = encode_status(dxl_id, error | servo.alert, data)
        fault = self._corrupt.get(dxl_id)
        if fault is None:
            return packet
        mode, remaining = fault
        if remaining is not None:
            fault[1] -= 1
            if fault[1] <= 0:
                del self._corrupt[dxl_id]
        if mode == "crc":
            return packet[:-1] + bytes([packet[-1] ^ 0xFF])
        if mode == "truncate":
            return packet[:len(packet) // 2]
        if mode == "noise":
            return b"\x00\xff\x55\xaa\xff\xff\x13" + packet
        return encode_status((dxl_id + 100) % (MAX_ID + 1), error | servo.alert, data)   # "foreign"

    def _process(self, packet: Packet) -> list[bytes]:
        ins, params = packet.instruction, packet.params
        if ins == INST_STATUS:
            self.stats.reject("foreign")  # another device's reply; servos only take instructions
            return []
        if ins in (INST_SYNC_READ, INST_SYNC_WRITE, INST_BULK_READ, INST_BULK_WRITE):
            return self._group(packet) if packet.id == BROADCAST_ID else []
        if packet.id == BROADCAST_ID:
            targets, broadcast = self._live(), True
        else:
            servo = self._servo(packet.id)
            if servo is None:
                if packet.id not in self._silent:
                    self.stats.reject("foreign")
                return []
            targets, broadcast = [servo], False
        out = []
        for servo in targets:
            level = servo.get("status_return_level")
            error, data = self._instruction(servo, ins, params)
            if ins == INST_PING or (not broadcast and (level == 2 or (ins == INST_READ and level >= 1))):
                out.append(self._status(servo, error, data))   # from the old ID, before any reset
            if ins in (INST_REBOOT, INST_FACTORY_RESET) and not error:
                if ins == INST_REBOOT:
                    servo.reboot()
                else:
                    servo.factory_reset(params[0])
        return out

    def _instruction(self, servo: XSeriesServo, ins: int, params: bytes) -> tuple[int, bytes]:
        """One servo executes one instruction: (error number, status data). REBOOT / FACTORY_RESET are validated
        here and carried out by the caller after the reply is built."""
        if ins == INST_PING:
            return 0, bytes(servo.table[0:2] + servo.table[6:7])
        if ins == INST_READ:
            if len(params) != 4:
                return ERR_DATA_LENGTH, b""
            return servo.read(params[0] | params[1] << 8, params[2] | params[3] << 8)
        if ins in (INST_WRITE, INST_REG_WRITE):
            if len(params) < 3:
                return ERR_DATA_LENGTH, b""
            write = servo.write if ins == INST_WRITE else servo.reg_write
            return write(params[0] | params[1] << 8, params[2:]), b""
        if ins == INST_ACTION:
            return servo.action(), b""
        if ins == INST_REBOOT:
            return 0, b""
        if ins == INST_FACTORY_RESET:
            if len(params) != 1:
                return ERR_DATA_LENGTH, b""
            return (0 if params[0] in (0xFF, 0x01, 0x02) else ERR_DATA_RANGE), b""
        if ins == INST_CLEAR:
            # Clears the multi-turn revolution count: present position back into one turn.
            servo._put("present_position", servo.get("present_position") % 4096)
            return 0, b""
        return ERR_INSTRUCTION, b""

    def _group(self, packet: Packet) -> list[bytes]:
        """SYNC_/BULK_ READ and WRITE (broadcast): replies in the order of the request; a silent servo is skipped
        and the others still answer."""
        ins, p = packet.instruction, packet.params
        out: list[bytes] = []
        if ins in (INST_SYNC_READ, INST_SYNC_WRITE):
            if len(p) < 4:
                self.stats.reject("length")
                return out
            address, length, rest = p[0] | p[1] << 8, p[2] | p[3] << 8, p[4:]
            if ins == INST_SYNC_READ:
                for dxl_id in rest:
                    servo = self._servo(dxl_id)
                    if servo is not None:
                        error, data = servo.read(address, length)
                        out.append(self._status(servo, error, data))
                return out
            if length == 0 or len(rest) % (1 + length):
                self.stats.reject("length")
                return out
            for k in range(0, len(rest), 1 + length):
                servo = self._servo(rest[k])
                if servo is not None:
                    servo.write(address, rest[k + 1:k + 1 + length])
            return out
        if ins == INST_BULK_READ:
            if len(p) % 5:
                self.stats.reject("length")
                return out
            for k in range(0, len(p), 5):
                servo = self._servo(p[k])
                if servo is not None:
                    error, data = servo.read(p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8)
                    out.append(self._status(servo, error, data))
            return out
        k = 0   # BULK_WRITE: (ID, address, length, data) repeated
        while k + 5 <= len(p):
            dxl_id, address, length = p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
            data = p[k + 5:k + 5 + length]
            if len(data) != length:
                self.stats.reject("length")
                break
            servo = self._servo(dxl_id)
            if servo is not None:
                servo.write(address, data)
            k += 5 + length
        return out

    # -- accessors for a physics adapter (thread-safe) ---------------------------------------------------------
    @property
    def track_goals(self) -> bool:
        """True: ideal servos (present position jumps to the goal while torque is on). A physics adapter sets it
        False (or constructs with track_goals=False) and writes the measured values itself."""
        return all(servo.track_goals for servo in self.servos)

    @track_goals.setter
    def track_goals(self, value: bool) -> None:
        with self._lock:
            for servo in self.servos:
                servo.track_goals = bool(value)

    def _by_id(self, dxl_id: int) -> XSeriesServo:
        for servo in self.servos:
            if servo.id == dxl_id:
                return servo
        raise KeyError(f"no servo with ID {dxl_id} on {self.name} (IDs {[s.id for s in self.servos]})")

    def set_present(self, dxl_id: int, position: float | None = None, velocity: float | None = None,
                    unit: str = "counts") -> None:
        """Measured values of one servo. unit "counts": raw register values; "rad": shaft angle in rad
        (0..2*pi, 2048 counts = pi) and shaft velocity in rad/s."""
        if unit not in ("counts", "rad"):
            raise ValueError(f"unit must be 'counts' or 'rad', got {unit!r}")
        with self._lock:
            self._tick()
            servo = self._by_id(dxl_id)
            if position is not None:
                counts = position / POSITION_UNIT if unit == "rad" else position
                servo._put("present_position", int(round(counts)))
            if velocity is not None:
                counts = joint_velocity_to_counts(np.array([velocity]), np.ones(1))[0] if unit == "rad" else velocity
                servo._put("present_velocity", int(round(counts)))

    def set_joint_state(self, q: Sequence[float], qd: Sequence[float] | None = None) -> None:
        """Measured joint positions (rad) and velocities (rad/s) in the order of `ids`, through the driver's joint
        convention (servo angle = sign * q + pi)."""
        q = np.asarray(q, dtype=np.float64)
        qd = np.zeros_like(q) if qd is None else np.asarray(qd, dtype=np.float64)
        if q.shape != (len(self.ids),) or qd.shape != q.shape:
            raise ValueError(f"expected {len(self.ids)} joint values, got {q.shape} and {qd.shape}")
        # What set_present(..., unit="rad") does per servo, for all at once (the physics calls this at 50 Hz).
        positions = np.rint((self.signs * q + math.pi) / POSITION_UNIT).astype(np.int64).tolist()
        velocities = joint_velocity_to_counts(self.signs * qd, np.ones(len(self.ids))).tolist()
        with self._lock:
            self._tick()
            for dxl_id, position, velocity in zip(self.ids, positions, velocities, strict=True):
                servo = self._by_id(dxl_id)
                servo._put("present_position", position)
                servo._put("present_velocity", velocity)

    def goal_position(self, dxl_id: int, unit: str = "counts") -> float:
        with self._lock:
            self._tick()
            counts = self._by_id(dxl_id).get("goal_position")
        return counts * POSITION_UNIT if unit == "rad" else counts

    def goal_joint_positions(self) -> np.ndarray:
        """Goal positions in joint rad, in the order of `ids`."""
        with self._lock:
            self._tick()
            counts = np.array([self._by_id(i).get("goal_position") for i in self.ids])
        return counts_to_joint(counts, self.signs)

    def torque_enabled(self, dxl_id: int) -> bool:
        with self._lock:
            self._tick()
            return self._by_id(dxl_id).torque

    def torque_enabled_all(self) -> np.ndarray:
        with self._lock:
            self._tick()
            return np.array([self._by_id(i).torque for i in self.ids])

    def item(self, dxl_id: int, name: str) -> int:
        """Any control table item of one servo, by its snake_case name (e.g. "position_p_gain")."""
        with self._lock:
            self._tick()
            return self._by_id(dxl_id).get(name)

    # -- faults for tests --------------------------------------------------------------------------------------
    def silence(self, ids: Iterable[int], silent: bool = True) -> None:
        """Servos that neither answer nor act (unplugged); `silent=False` brings them back."""
        with self._lock:
            self._tick()
            (self._silent.update if silent else self._silent.difference_update)(int(i) for i in ids)

    def set_hardware_error(self, dxl_id: int, flags: Sequence[str] | int) -> None:
        """Hardware Error Status of one servo (flag names or raw bits): every status packet it sends then has the
        Alert bit, and torque goes off for bits in Shutdown (63). REBOOT clears it."""
        bits = flags if isinstance(flags, int) else encode_hardware_error(flags)
        with self._lock:
            self._tick()
            self._by_id(dxl_id).set_hardware_error(bits)
            self._note(self.clock())

    def corrupt_replies(self, ids: Iterable[int] | None = None, mode: str = "crc", count: int | None = None) -> None:
        """Corrupt the next `count` (None: all) status packets of `ids` (None: every servo). Modes: "crc" (bad CRC),
        "truncate" (first half only), "noise" (garbage before a valid packet), "foreign" (another ID)."""
        if mode not in ("crc", "truncate", "noise", "foreign"):
            raise ValueError(f"unknown corruption mode {mode!r}")
        with self._lock:
            for dxl_id in (self.ids if ids is None else ids):
                self._corrupt[int(dxl_id)] = [mode, count]

    def clear_faults(self) -> None:
        """Everyone answers again, uncorrupted, with hardware errors cleared."""
        with self._lock:
            self._tick()
            self._silent.clear()
            self._corrupt.clear()
            for servo in self.servos:
                servo._put("hardware_error_status", 0)
