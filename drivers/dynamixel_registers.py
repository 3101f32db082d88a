"""The Dynamixel X-series control table as BRUCE's arms use it: the addresses, the units, and the joint <-> servo
conversions (`counts_to_joint`, `joint_to_counts`, ...), the Bus Watchdog's counts, the indirect read block. Apart
from the bus logic, as the BEAR's register table is (`drivers/bear_registers.py`)."""

from __future__ import annotations

import math

import numpy as np

# -- X-series control table addresses used by the driver ----------------------------------------------------------
ADDR_FIRMWARE_VERSION = 6         # 1 byte, read-only
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
