"""bruce-hw-check's diagnosis of the BEAR legs (`check_bear`): each BEAR's presence, error flags, torque_enable,
temperatures and input voltage, and the bus's round trip (read-only bulk cycles; criteria: hw_check.DESCRIPTION)."""

from __future__ import annotations

import time

from bruce_hw.bus_report import (
    PRESENCE_TIMEOUT_S,
    PRESENCE_TRIES,
    RTT_REPLY_TIMEOUT_S,
    BusReport,
    RoundTrips,
    add_timing,
    verdict_1khz,
)
from bruce_hw.bus_startup import ids_text
from bruce_hw.config import RobotConfig

BEAR_REGISTERS = ("torque_enable", "winding_temperature", "powerstage_temperature", "ic_temperature",
                  "input_voltage")
TEMPERATURE_WARN_C = 75.0  # BRUCE-OP v0.0.7's warnings (top-level display)
VOLTAGE_WARN_V = 14.5


def check_bear(config: RobotConfig, rtt_cycles: int = 0) -> BusReport:
    from drivers.bear import BearBus
    from drivers.bear_registers import FAULT_BITS, BearError
    from drivers.errors import DriverError

    bus_cfg = config.buses.bear
    report = BusReport(f"BEAR bus {bus_cfg.port} ({bus_cfg.baud} baud, IDs {ids_text(bus_cfg.ids)})")
    try:
        # A late answer is still an answer: how late is the round trip's business, not a reason to call it missing.
        bus = BearBus(bus_cfg.port, bus_cfg.baud, reply_timeout_s=PRESENCE_TIMEOUT_S)
    except DriverError as exc:
        report.error = str(exc)
        report.missing = list(bus_cfg.ids)
        return report
    enabled: list[int] = []
    with bus:
        for device_id in bus_cfg.ids:
            answer = bear_presence(bus, device_id)
            if answer is None:
                report.missing.append(device_id)
                report.lines.append(f"ID {device_id}: MISSING")
                continue
            ping, values = answer
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
            if int(values["torque_enable"]) == 1:
                enabled.append(device_id)
        answering = [i for i in bus_cfg.ids if i not in report.missing]
        if rtt_cycles and answering:
            if enabled:
                report.lines.append(f"round trip not measured: ID(s) {ids_text(enabled)} read torque_enable 1 (each "
                                    "packet would feed the watchdog of a motor that is on); disable torque first")
            else:
                bus.reply_timeout_s = RTT_REPLY_TIMEOUT_S
                trips = bear_round_trips(bus, answering, rtt_cycles)
                add_timing(report, trips, verdict_1khz(trips))
                timeout = getattr(bus_cfg, "reply_timeout_s", 0.0) or 0.002
                slow = sum(t > timeout for t in trips.seconds)
                if slow:
                    report.warnings.append(f"{slow} of {len(trips.seconds)} bulk cycles took longer than the "
                                           f"{1e3 * timeout:g} ms reply timeout: their replies would be lost in a run")
    return report


def bear_presence(bus, device_id: int):
    """(ping, status registers) of one BEAR, asked up to PRESENCE_TRIES times; None: it never answered."""
    from drivers.errors import BusTimeout

    for _ in range(PRESENCE_TRIES):
        try:
            return bus.ping(device_id), bus.read_status(device_id, BEAR_REGISTERS)
        except BusTimeout:
            continue
    return None


def bear_round_trips(bus, ids, cycles: int) -> RoundTrips:
    """`cycles` read-only bulk cycles of `ids` on an open BearBus, back to back (partial: a lost reply is counted,
    not timed, and not retried)."""
    ids = list(ids)
    trips = RoundTrips(f"read-only bulk cycles of {len(ids)} IDs")
    for _ in range(cycles):
        start = time.perf_counter()
        reply = bus.bulk_cycle(ids, None, partial=True)
        took = time.perf_counter() - start
        if reply.answered is not None and not reply.answered.all():
            trips.lost += 1
        else:
            trips.seconds.append(took)
    return trips
