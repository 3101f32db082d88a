"""The `hw` backend slot: BRUCE's real buses (BEAR RS-485, Dynamixel, sense board, CAN).

The drivers it is composed from live in `drivers/`. Until they exist this module says precisely what is
missing, both in the software and on this machine, instead of half-starting a robot.
"""

from __future__ import annotations

import importlib.util
import os

from bruce_hw.backend import Backend, BackendError
from bruce_hw.config import RobotConfig

# driver module -> what it speaks; the hw backend needs all of the serial ones for BRUCE.
REQUIRED_DRIVERS = {
    "drivers.bear": "BEAR actuators over RS-485 (buses.bear)",
    "drivers.dynamixel": "Dynamixel arm servos (buses.dynamixel)",
    "drivers.sense": "sense board IMU and foot contacts (buses.sense)",
}


def missing_for_hw(config: RobotConfig) -> list[str]:
    """Everything that stops the hw backend from starting here, one line each."""
    missing = [f"driver {module} for {what} is not installed"
               for module, what in REQUIRED_DRIVERS.items() if importlib.util.find_spec(module) is None]
    for key, port in (("buses.bear.port", config.buses.bear.port),
                      ("buses.dynamixel.port", config.buses.dynamixel.port),
                      ("buses.sense.port", config.buses.sense.port)):
        if not os.path.exists(port):
            missing.append(f"device {port} ({key}) does not exist; set another with --set {key}=PATH")
    return missing


def make_hw_backend(config: RobotConfig, **options) -> Backend:
    missing = missing_for_hw(config)
    if missing:
        raise BackendError("backend 'hw' cannot start:\n  - " + "\n  - ".join(missing))
    raise BackendError("backend 'hw': drivers are present but no hw backend composes them in this version")
