"""Koala BEAR register tables, instructions, modes, limits and the error byte (sources: Westwood's PyBEAR SDK and
BRUCE-OP v0.0.7; where they are silent, the choice is noted here). Pure data: no I/O."""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum, IntFlag

import numpy as np

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE
MAX_DEVICE_ID = 0xFD  # 0xFE is the broadcast ID, and an ID of 0xFF would read as a header byte
MAX_BULK_REGISTERS = 15  # one nibble each for the read and the write count
MAX_PARAMS = 253  # LEN is one byte: n_params + 2 <= 255
MAX_FRAME = 4 + 255  # FF FF ID LEN + LEN bytes
FLOAT32_MAX = 3.4028234663852886e38
# The Koala BEAR's rated current (BRUCE-OP: limit_i_max 30 A = 10.5 N m at 0.35 N m/A). No current register is ever
# written beyond it, whatever a caller computed: a wrong torque constant in a config must not reach the windings.
RATED_CURRENT_A = 30.0
RATED_LIMITS = {"limit_i_max": RATED_CURRENT_A, "goal_iq": RATED_CURRENT_A, "goal_id": RATED_CURRENT_A}



class Instruction(IntEnum):
    PING = 0x01
    READ_STAT = 0x02
    WRITE_STAT = 0x03
    READ_CFG = 0x04
    WRITE_CFG = 0x05
    SAVE_CFG = 0x06
    SET_POSITION = 0x08  # absolute-position reset of battery-backed BEARs; probably not on Koala, unused here
    BULK_COMM = 0x12


class Mode(IntEnum):
    """Config register `mode`."""

    TORQUE = 0  # goal_iq
    VELOCITY = 1  # goal_velocity
    POSITION = 2  # goal_position
    FORCE = 3  # "direct force": spring-damper around goal_position/goal_velocity plus goal_iq feed-forward


class TorqueEnable(IntEnum):
    """Status register `torque_enable`: 0, 1 and 3 are written; 2 is only read (the BEAR is in error)."""

    DISABLED = 0
    ENABLED = 1
    ERROR = 2
    DAMPING = 3


# The goals each mode's bulk cycle writes, in the order they go on the wire (BRUCE's run_bear.py).
GOALS_BY_MODE: dict[Mode, tuple[str, ...]] = {
    Mode.TORQUE: ("goal_iq",),
    Mode.VELOCITY: ("goal_velocity",),
    Mode.POSITION: ("goal_position",),
    Mode.FORCE: ("goal_position", "goal_velocity", "goal_iq"),
}
CYCLE_READS = ("present_position", "present_velocity", "present_iq")


# -- register tables ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Register:
    name: str
    address: int
    kind: str  # "u32" or "f32"
    table: str  # "config" or "status"
    writable: bool = True

    @property
    def fmt(self) -> str:
        """struct format character of the value."""
        return "I" if self.kind == "u32" else "f"

    def check(self, value) -> int | float:
        """The value as it will be packed: an int for u32 (never a float: PyBEAR's bulk path encodes u32 as float32,
        which the sources call a bug), a finite float for f32 (a NaN goal is never sent to a motor)."""
        if self.kind == "u32":
            if isinstance(value, bool | np.bool_ | int | np.integer):
                number = int(value)
            elif isinstance(value, float | np.floating) and float(value).is_integer():
                number = int(value)
            else:
                raise ValueError(f"{self.name} is u32: {value!r} is not an integer")
            if not 0 <= number <= 0xFFFFFFFF:
                raise ValueError(f"{self.name} is u32: {number} is out of range")
            return number
        try:
            number = float(value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.name} is f32: {value!r} is not a number") from exc
        if not math.isfinite(number) or abs(number) > FLOAT32_MAX:
            raise ValueError(f"{self.name} is f32: {value!r} is not a finite float32")
        rated = RATED_LIMITS.get(self.name)
        if rated is not None and abs(number) > rated:
            raise ValueError(f"{self.name} {number:g} A is beyond the Koala BEAR's rated {rated:g} A")
        return number

    def encode(self, value) -> bytes:
        return struct.pack("<" + self.fmt, self.check(value))

    def decode(self, raw: bytes) -> int | float:
        return struct.unpack("<" + self.fmt, raw)[0]


def _table(table: str, rows: Sequence[tuple[int, str, str]], read_only: Iterable[str] = ()) -> dict[str, Register]:
    read_only = set(read_only)
    return {name: Register(name, address, kind, table, name not in read_only) for address, name, kind in rows}


# Saved to flash by SAVE_CFG; writable only while torque is disabled. 0x1D is not documented anywhere.
CONFIG_REGISTERS = _table("config", [
    (0x00, "id", "u32"),
    (0x01, "mode", "u32"),
    (0x02, "baudrate", "u32"),  # encoding undocumented
    (0x03, "homing_offset", "f32"),
    (0x04, "p_gain_id", "f32"), (0x05, "i_gain_id", "f32"), (0x06, "d_gain_id", "f32"),
    (0x07, "p_gain_iq", "f32"), (0x08, "i_gain_iq", "f32"), (0x09, "d_gain_iq", "f32"),
    (0x0A, "p_gain_velocity", "f32"), (0x0B, "i_gain_velocity", "f32"), (0x0C, "d_gain_velocity", "f32"),
    (0x0D, "p_gain_position", "f32"), (0x0E, "i_gain_position", "f32"), (0x0F, "d_gain_position", "f32"),
    (0x10, "p_gain_force", "f32"), (0x11, "i_gain_force", "f32"), (0x12, "d_gain_force", "f32"),
    (0x13, "limit_acc_max", "f32"),
    (0x14, "limit_i_max", "f32"),
    (0x15, "limit_velocity_max", "f32"),
    (0x16, "limit_position_min", "f32"),
    (0x17, "limit_position_max", "f32"),
    (0x18, "min_voltage", "f32"),
    (0x19, "max_voltage", "f32"),
    (0x1A, "watchdog_timeout", "u32"),  # units undocumented
    (0x1B, "temp_limit_low", "f32"),
    (0x1C, "temp_limit_high", "f32"),
    (0x1E, "return_time_delay", "u32"),  # Rust driver only, "experimental"
])

# Volatile. BULK_COMM only reaches these. Those other than torque_enable and the goals are read-only: the driver
# refuses to write them. homing_complete is u32 (PyBEAR and AOS; the Rust driver types it f32); error_status and
# warning_status stay (AOS lists them; the Rust driver dropped them as unused).
STATUS_REGISTERS = _table("status", [
    (0x00, "torque_enable", "u32"),
    (0x01, "homing_complete", "u32"),
    (0x02, "goal_id", "f32"),
    (0x03, "goal_iq", "f32"),
    (0x04, "goal_velocity", "f32"),
    (0x05, "goal_position", "f32"),
    (0x06, "present_id", "f32"),
    (0x07, "present_iq", "f32"),
    (0x08, "present_velocity", "f32"),
    (0x09, "present_position", "f32"),
    (0x0A, "input_voltage", "f32"),
    (0x0B, "winding_temperature", "f32"),
    (0x0C, "powerstage_temperature", "f32"),
    (0x0D, "ic_temperature", "f32"),
    (0x0E, "error_status", "u32"),
    (0x0F, "warning_status", "u32"),
], read_only=("homing_complete", "present_id", "present_iq", "present_velocity", "present_position",
              "input_voltage", "winding_temperature", "powerstage_temperature", "ic_temperature",
              "error_status", "warning_status"))

REGISTER_ALIASES = {"limit_iq_max": "limit_i_max"}
CONFIG_BY_ADDRESS = {r.address: r for r in CONFIG_REGISTERS.values()}
STATUS_BY_ADDRESS = {r.address: r for r in STATUS_REGISTERS.values()}


def _lookup(table: str, key: str | int | Register) -> Register:
    by_name, by_address = (CONFIG_REGISTERS, CONFIG_BY_ADDRESS) if table == "config" else \
        (STATUS_REGISTERS, STATUS_BY_ADDRESS)
    if isinstance(key, Register):
        if key.table != table:
            raise ValueError(f"{key.name} is a {key.table} register, not a {table} register")
        return key
    found = by_address.get(key) if isinstance(key, int) else by_name.get(REGISTER_ALIASES.get(key, key))
    if found is None:
        raise ValueError(f"no BEAR {table} register {key!r}")
    return found


def config_register(key: str | int | Register) -> Register:
    """A config register by name, alias or address."""
    return _lookup("config", key)


def status_register(key: str | int | Register) -> Register:
    """A status register by name or address."""
    return _lookup("status", key)


# -- error byte -----------------------------------------------------------------------------------------------------
class BearError(IntFlag):
    """Bits of the error byte every reply carries. Bit 7 is always set: 0x80 means no error, and a packet whose
    error byte lacks it is an instruction (an echo, another host), rejected as "foreign". Bits 0 and 1 are
    warnings that reset by themselves; bits 2-6 are faults (`FAULT_BITS`)."""

    COMMUNICATION = 0x01  # a corrupted packet was received (warning, resets by itself)
    OVERHEAT = 0x02  # a temperature is above temp_limit_low (warning, resets by itself)
    ABSOLUTE_POSITION = 0x04
    WATCHDOG_ESTOP = 0x08  # external E-stop, torque_enable = 3 written, or watchdog expiry in torque mode
    JOINT_LIMIT = 0x10
    HARDWARE = 0x20  # input voltage out of range or MOSFET driver fault
    INITIALIZATION = 0x40  # corrupted flash save; recalibration needed


ERROR_OK = 0x80
WARNING_BITS = BearError.COMMUNICATION | BearError.OVERHEAT
FAULT_BITS = 0x7F & ~WARNING_BITS


def error_flags(error: int) -> tuple[str, ...]:
    """Names of the bits set in an error byte, e.g. ("watchdog_estop",); () for 0x80."""
    return tuple(flag.name.lower() for flag in BearError if error & flag)
