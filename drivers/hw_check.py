"""`bruce-hw-check`: ping every device the robot config names and report what answers, what is missing, the error
flags, temperatures and voltages. Nothing is enabled or written except reads (and the sense board's stream mode,
which it leaves idle again).

Per bus: BEAR (ping, error byte, torque_enable, winding / power stage / IC temperature, input voltage), Dynamixel
(ping with model number, Hardware Error Status, present temperature and input voltage, through ROBOTIS'
dynamixel-sdk), the sense board (stream rate, specific force, gyro, foot contacts), and the CAN motors when
buses.can.motors is set (one zero command each: position, velocity, torque). Exit status: 0 when every device
answers without a fault flag, 1 when a device is missing or reports a fault (the BEAR E-stop bit alone, which
also means damping, e.g. after a bruce-run, is reported but is not a fault), 2 for a bad config.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, RobotConfig, load_config

PROG = "bruce-hw-check"
BEAR_REGISTERS = ("torque_enable", "winding_temperature", "powerstage_temperature", "ic_temperature",
                  "input_voltage")
DXL_HARDWARE_ERROR, DXL_INPUT_VOLTAGE, DXL_TEMPERATURE = 70, 144, 146  # X-series control table
TEMPERATURE_WARN_C = 75.0  # BRUCE-OP's warnings (research notes §5.5)
VOLTAGE_WARN_V = 14.5


@dataclass
class BusReport:
    name: str
    lines: list[str] = field(default_factory=list)   # one per device, for people
    missing: list[int] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)  # "ID n: flags"
    warnings: list[str] = field(default_factory=list)
    error: str | None = None                         # the bus itself could not be used

    @property
    def ok(self) -> bool:
        return self.error is None and not self.missing and not self.faults

    def text(self) -> str:
        head = f"{self.name}: " + ("OK" if self.ok else "PROBLEM")
        body = [f"  {line}" for line in self.lines]
        if self.error:
            body.append(f"  cannot use the bus: {self.error}")
        if self.missing:
            body.append(f"  missing ID(s): {', '.join(str(i) for i in self.missing)}")
        body += [f"  fault: {f}" for f in self.faults] + [f"  warning: {w}" for w in self.warnings]
        return "\n".join([head, *body])


def check_bear(config: RobotConfig) -> BusReport:
    from drivers.bear import FAULT_BITS, BearBus, BearError
    from drivers.errors import BusTimeout, DriverError

    bus_cfg = config.buses.bear
    report = BusReport(f"BEAR bus {bus_cfg.port} ({bus_cfg.baud} baud, IDs {_ids(bus_cfg.ids)})")
    try:
        bus = BearBus(bus_cfg.port, bus_cfg.baud)
    except DriverError as exc:
        report.error = str(exc)
        report.missing = list(bus_cfg.ids)
        return report
    with bus:
        for device_id in bus_cfg.ids:
            try:
                ping = bus.ping(device_id)
                values = bus.read_status(device_id, BEAR_REGISTERS)
            except BusTimeout:
                report.missing.append(device_id)
                report.lines.append(f"ID {device_id}: MISSING")
                continue
            flags = ", ".join(ping.flags) or "none"
            hottest = max(values[name] for name in BEAR_REGISTERS[1:4])
            report.lines.append(
                f"ID {device_id}: error flags {flags}; torque_enable {int(values['torque_enable'])}; temperature "
                f"winding {values['winding_temperature']:.1f} / power stage {values['powerstage_temperature']:.1f} "
                f"/ IC {values['ic_temperature']:.1f} C; input {values['input_voltage']:.1f} V")
            if ping.error & FAULT_BITS & ~BearError.WATCHDOG_ESTOP:
                report.faults.append(f"ID {device_id}: {flags}")
            if ping.error & BearError.WATCHDOG_ESTOP:
                report.warnings.append(f"ID {device_id}: E-stop / damping bit set (release the E-stop; a "
                                       "shutdown leaves the BEARs damping)")
            if hottest > TEMPERATURE_WARN_C:
                report.warnings.append(f"ID {device_id}: {hottest:.0f} C > {TEMPERATURE_WARN_C:.0f} C")
            if values["input_voltage"] < VOLTAGE_WARN_V:
                report.warnings.append(f"ID {device_id}: input {values['input_voltage']:.1f} V < {VOLTAGE_WARN_V} V")
    return report


def check_dynamixel(config: RobotConfig) -> BusReport:
    from drivers.dynamixel import decode_hardware_error, decode_status_error

    bus_cfg = config.buses.dynamixel
    report = BusReport(f"Dynamixel bus {bus_cfg.port} ({bus_cfg.baud} baud, IDs {_ids(bus_cfg.ids)})")
    try:
        from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler
    except ImportError as exc:
        report.error = f"the dynamixel-sdk package is not installed ({exc})"
        return report
    port, handler = PortHandler(bus_cfg.port), PacketHandler(2.0)
    try:
        opened = port.openPort() and port.setBaudRate(bus_cfg.baud)
    except Exception as exc:  # serial.SerialException, OSError: the SDK does not wrap them
        opened, report.error = False, str(exc)
    if not opened:
        report.error = report.error or f"cannot open at {bus_cfg.baud} baud"
        report.missing = list(bus_cfg.ids)
        return report
    try:
        for dxl_id in bus_cfg.ids:
            model, result, error = handler.ping(port, dxl_id)
            if result != COMM_SUCCESS:
                report.missing.append(dxl_id)
                report.lines.append(f"ID {dxl_id}: MISSING")
                continue
            hardware, r1, _ = handler.read1ByteTxRx(port, dxl_id, DXL_HARDWARE_ERROR)
            temperature, r2, _ = handler.read1ByteTxRx(port, dxl_id, DXL_TEMPERATURE)
            voltage, r3, _ = handler.read2ByteTxRx(port, dxl_id, DXL_INPUT_VOLTAGE)
            if (r1, r2, r3) != (COMM_SUCCESS,) * 3:
                report.missing.append(dxl_id)
                report.lines.append(f"ID {dxl_id}: answers ping (model {model}) but not reads")
                continue
            flags = decode_status_error(error) + decode_hardware_error(hardware)
            report.lines.append(f"ID {dxl_id}: model {model}; error flags {', '.join(flags) or 'none'}; "
                                f"temperature {temperature} C; input {voltage / 10:.1f} V")
            if flags:
                report.faults.append(f"ID {dxl_id}: {', '.join(flags)}")
    finally:
        port.closePort()
    return report


def check_sense(config: RobotConfig, listen_s: float = 0.2) -> BusReport:
    from drivers.errors import DriverError
    from drivers.sense import SenseBoard

    bus_cfg = config.buses.sense
    report = BusReport(f"sense board {bus_cfg.port} ({bus_cfg.baud} baud)")
    try:
        board = SenseBoard(bus_cfg.port, bus_cfg.baud)
    except DriverError as exc:
        report.error = str(exc)
        return report
    with board:
        try:
            board.start(check_imu=False)
            count, t0 = board.sample_count, time.monotonic()
            time.sleep(listen_s)
            rate = (board.sample_count - count) / (time.monotonic() - t0)
            imu, contacts = board.read()
        except DriverError as exc:
            report.error = str(exc)
            return report
        closed = [name for name, c in zip(("r_toe", "r_heel", "l_toe", "l_heel"), contacts.contact, strict=True) if c]
        report.lines.append(f"streaming {rate:.0f} samples/s; specific force {_vec(imu.accel)} m/s^2 "
                            f"(|a| {math.sqrt(float(imu.accel @ imu.accel)):.2f}); gyro {_vec(imu.gyro)} rad/s; "
                            f"contacts closed: {', '.join(closed) or 'none'}")
        stats = board.stats
        if stats.rejected_total:
            report.warnings.append(f"{stats.rejected_total} rejected packets ({dict(stats.rejected)})")
    return report


def check_can(config: RobotConfig) -> BusReport:
    from drivers.can_motor import CanMotorGroup
    from drivers.errors import BusTimeout, DriverError

    can = config.buses.can
    ids = [m.id for m in can.motors]
    report = BusReport(f"CAN {can.interface} {', '.join(can.channels)} (motor IDs {_ids(ids)})")
    try:
        group = CanMotorGroup.from_config(can)
    except (DriverError, ValueError) as exc:
        report.error = str(exc)
        report.missing = ids
        return report
    with group:
        try:
            state = group.read()  # the all-zero command: ignored in rest mode, answered
        except BusTimeout as exc:
            report.missing = list(exc.silent_ids)
            state = group.state
        for k, (slot, motor_id) in enumerate(zip(config.joints, ids, strict=True)):
            if motor_id in report.missing:
                report.lines.append(f"ID {motor_id} ({slot}): MISSING")
            else:
                report.lines.append(f"ID {motor_id} ({slot}): position {state.position[k]:+.3f} rad, velocity "
                                    f"{state.velocity[k]:+.3f} rad/s, torque {state.torque[k]:+.2f} Nm")
    return report


def check(config: RobotConfig) -> list[BusReport]:
    reports = [check_can(config)] if config.buses.can.motors else [check_bear(config)]
    return [*reports, check_dynamixel(config), check_sense(config)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key path, e.g. buses.bear.port=/dev/ttyUSB3 (repeatable)")
    args = p.parse_args(argv)
    try:
        config = load_config(args.config, args.overrides)
    except ConfigError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    reports = check(config)
    for report in reports:
        print(report.text())
    problems = [r for r in reports if not r.ok]
    if problems:
        missing = "; ".join(f"{r.name.split(' (')[0]}: missing {_ids(r.missing)}" for r in problems if r.missing)
        print(f"{PROG}: PROBLEMS on {len(problems)} bus(es)" + (f" ({missing})" if missing else ""))
        return 1
    print(f"{PROG}: OK, every device answers")
    return 0


def _ids(ids) -> str:
    return ", ".join(str(i) for i in ids)


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(x):+.2f}" for x in v) + ")"


if __name__ == "__main__":
    sys.exit(main())
