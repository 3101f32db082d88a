"""`bruce-hw-check` (`main`): ping every device the robot config names and report what answers, what is missing,
the error flags, temperatures and voltages, then each bus's round trip and whether it can hold the 1 kHz loop
(`check`); read-only but for the sense board's stream mode. The legs' check is their kind's `diagnose`
(bruce_hw/legs/), the arms' and the sense board's are here, the report they share is bruce_hw/bus_report.py.
`--probe-watchdog` (`run_watchdog_probe`) measures the unit of the BEAR watchdog_timeout register, and writes. Exit
codes, verdicts and the probe's method, as --help prints them: `DESCRIPTION`.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from bruce_hw.bus_report import PRESENCE_TRIES, TICK_S, BusReport, RoundTrips, add_timing, verdict_1khz
from bruce_hw.bus_startup import ids_text
from bruce_hw.config import DEFAULT_CONFIG, RobotConfig, load_config_or_say
from bruce_hw.leg_kinds import leg_kind_of
from bruce_hw.watchdog_probe import PROBE_COUNTS, run_watchdog_probe

PROG = "bruce-hw-check"
DESCRIPTION = """\
`bruce-hw-check`: ping every device the robot config names and report what answers, what is missing, the error
flags, temperatures and voltages. Nothing is enabled or written except reads (and the sense board's stream mode,
which it leaves idle again).

Per bus: BEAR (ping, error byte, torque_enable, winding / power stage / IC temperature, input voltage), Dynamixel
(ping with model number, Hardware Error Status, present temperature and input voltage, through ROBOTIS'
dynamixel-sdk), the sense board (stream rate, specific force, gyro, foot contacts), and the CAN motors when
buses.can.motors is set (one zero command each: position, velocity, torque). Exit status: 0 when every device
answers without a fault flag, 1 when a device is missing or reports a fault (the BEAR E-stop bit alone, which
also means damping, e.g. after a bruce-run, is reported but is not a fault), 2 for a bad config.

Round trips (`--rtt-cycles N`, default 300; 0 skips them): how fast each bus answers, measured from this host, and
whether it can keep up with the 1 kHz loop, the first thing to know after wiring. All read-only: nothing is written,
nothing moves.
- BEAR: N read-only bulk cycles (`BearBus.bulk_cycle(ids, None)`: the tick's bulk read of every answering actuator,
  without its goal writes) back to back, with a 50 ms reply timeout so a slow reply is timed, not lost; a cycle that
  lost a reply anyway is counted, not timed. Skipped while a BEAR reads torque_enable 1: every packet feeds its
  watchdog, which would keep a motor enabled that should go to damping.
- Dynamixel: N sync reads of present velocity and position (the arm thread's read).
- Sense board: N polls 1 ms apart of the stream as a control tick sees it: the packet rate (mean interval) and the
  age of the newest packet at each poll. A fixed latency of the stream cannot be seen from the host (the board sends
  no time); late or bunched packets show in the age.
Printed per bus: p50 / p99 / max and a verdict. A tick is 1 ms and its own work (estimator, policy, safety) takes
about COMPUTE_S = 0.2 ms besides the bus, so a bus "holds 1 kHz" when its p99 <= 0.8 ms; "holds 1 kHz only with late
ticks or a bus thread" when p99 is above that but p50 <= 1 ms (on average it keeps up, but one tick in a hundred or
more overruns unless the bus runs on its own thread, overlapped with the work); otherwise it "cannot hold 1 kHz:
expect N Hz", N = 1 / (p50 + 0.2 ms) rounded down to 10 Hz, what a loop with the bus in series would run at. The arm
bus only needs the arm thread's 50 Hz (p99 within half its 20 ms period); the sense board holds 1 kHz at >= 950
packets/s with a tick's data at most 2 ms old in 99 % of ticks. A bus that cannot keep up is a warning, not a failed
check (the exit status is about the devices).

`--probe-watchdog` does something else, and writes: it measures the unit of the BEAR `watchdog_timeout` register
(undocumented; `buses.bear.watchdog_unit_s` in the config) on one BEAR (`--probe-id`, default the first of
buses.bear.ids). The BEAR is put in torque mode with goal current 0, its watchdog_timeout set to a count N, enabled,
fed for 50 ms, then left without a packet for a time W and pinged once: the E-stop / damping bit says whether the
watchdog ran out within W (any packet resets the watchdog, so it cannot be watched, only tried). W doubles from
1 ms until it trips, then bisection brackets the trip time to 1 %; that for two counts (`--probe-counts`, default
100 and 200), the unit is the trip time over N, and the two must agree (linear) within 5 %. Afterwards torque is
disabled and watchdog_timeout and mode are written back as they were (flash is never written). It prints the unit
and the `--set buses.bear.watchdog_unit_s=...` to use; exit status 0 when measured, 1 when the BEAR is silent, in
E-stop or fault, never trips (within 4 s), or the counts disagree, 2 for a bad config or a config without BEARs.
"""  # the --help text
# -- round trips (DESCRIPTION; the 1 kHz criterion: bruce_hw/bus_report.py)
RTT_CYCLES = 300
ARM_RATE_HZ = 50.0            # the arm thread's rate (bruce_hw/hw.py)
SENSE_MIN_RATE_HZ = 950.0
SENSE_MAX_AGE_P99_S = 0.002


def _answered(request, *args):
    """`request(*args)`'s (value, comm result, error) of dynamixel-sdk, asked up to PRESENCE_TRIES times until it
    succeeds."""
    from dynamixel_sdk import COMM_SUCCESS

    for _ in range(PRESENCE_TRIES):
        value, result, error = request(*args)
        if result == COMM_SUCCESS:
            break
    return value, result, error


def check_dynamixel(config: RobotConfig, rtt_cycles: int = 0) -> BusReport:
    from drivers.dynamixel_codec import decode_hardware_error, decode_status_error
    from drivers.dynamixel_registers import (
        ADDR_FIRMWARE_VERSION,
        ADDR_HARDWARE_ERROR,
        ADDR_PRESENT_INPUT_VOLTAGE,
        ADDR_PRESENT_TEMPERATURE,
    )

    bus_cfg = config.buses.dynamixel
    report = BusReport(f"Dynamixel bus {bus_cfg.port} ({bus_cfg.baud} baud, IDs {ids_text(bus_cfg.ids)})")
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
            model, result, error = _answered(handler.ping, port, dxl_id)
            if result != COMM_SUCCESS:
                report.missing.append(dxl_id)
                report.lines.append(f"ID {dxl_id}: MISSING")
                continue
            hardware, r1, _ = _answered(handler.read1ByteTxRx, port, dxl_id, ADDR_HARDWARE_ERROR)
            temperature, r2, _ = _answered(handler.read1ByteTxRx, port, dxl_id, ADDR_PRESENT_TEMPERATURE)
            voltage, r3, _ = _answered(handler.read2ByteTxRx, port, dxl_id, ADDR_PRESENT_INPUT_VOLTAGE)
            firmware, r4, _ = _answered(handler.read1ByteTxRx, port, dxl_id, ADDR_FIRMWARE_VERSION)
            if (r1, r2, r3, r4) != (COMM_SUCCESS,) * 4:
                report.missing.append(dxl_id)
                report.lines.append(f"ID {dxl_id}: answers ping (model {model}) but not reads")
                continue
            flags = decode_status_error(error) + decode_hardware_error(hardware)
            report.lines.append(f"ID {dxl_id}: model {model}, firmware {firmware}; error flags "
                                f"{', '.join(flags) or 'none'}; temperature {temperature} C; "
                                f"input {voltage / 10:.1f} V")
            if flags:
                report.faults.append(f"ID {dxl_id}: {', '.join(flags)}")
        answering = [i for i in bus_cfg.ids if i not in report.missing]
        if rtt_cycles and answering:
            trips = dynamixel_round_trips(port, handler, answering, rtt_cycles)
            arm, holds = arm_verdict(trips)
            add_timing(report, trips, (f"{arm}; {verdict_1khz(trips)[0]}", holds))
    finally:
        port.closePort()
    return report


def check_sense(config: RobotConfig, listen_s: float = 0.2, polls: int = 0) -> BusReport:
    """`polls` > 0: the stream timed over that many 1 ms polls (which then replace the `listen_s` wait)."""
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
            timing = None
            if polls > 0:
                timing = sense_stream_timing(board, polls)
                rate = timing.rate_hz
            else:
                count, t0 = board.sample_count, time.monotonic()
                time.sleep(listen_s)
                rate = (board.sample_count - count) / (time.monotonic() - t0)
            imu, _ = board.read()
        except DriverError as exc:
            report.error = str(exc)
            return report
        closed = [name for name, c in zip(("r_toe", "r_heel", "l_toe", "l_heel"), imu.contact, strict=True) if c]
        report.lines.append(f"streaming {rate:.0f} samples/s; specific force {_vec(imu.accel)} m/s^2 "
                            f"(|a| {math.sqrt(float(imu.accel @ imu.accel)):.2f}); gyro {_vec(imu.gyro)} rad/s; "
                            f"contacts closed: {', '.join(closed) or 'none'}")
        if timing is not None:
            add_timing(report, timing, timing.verdict())
            max_age = getattr(config.safety, "max_sensor_age_s", math.inf)
            if timing.ages and max(timing.ages) > max_age:
                report.warnings.append(f"a tick saw data {1e3 * max(timing.ages):.1f} ms old, beyond "
                                       f"safety.max_sensor_age_s ({1e3 * max_age:g} ms): a run would stop on it")
        stats = board.stats
        if stats.rejected_total:
            report.warnings.append(f"{stats.rejected_total} rejected packets ({dict(stats.rejected)})")
    return report


# -- round trips (DESCRIPTION) ----------------------------------------------------------------------------------
def arm_verdict(trips: RoundTrips) -> tuple[str, bool]:
    """Whether the arm thread's 50 Hz is safe: p99 within half its period."""
    budget = 0.5 / ARM_RATE_HZ
    if trips.seconds and trips.p99 <= budget:
        return f"holds the arm thread's {ARM_RATE_HZ:.0f} Hz", True
    return f"cannot hold the arm thread's {ARM_RATE_HZ:.0f} Hz (p99 > {1e3 * budget:.0f} ms)", False


def dynamixel_round_trips(port, handler, ids, cycles: int) -> RoundTrips:
    """`cycles` sync reads of present velocity and position of `ids` through dynamixel-sdk (an open PortHandler,
    a Protocol 2.0 PacketHandler)."""
    from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead

    from drivers.dynamixel_registers import ADDR_PRESENT_POSITION, ADDR_PRESENT_VELOCITY

    # present velocity (128) and present position (132), 4 bytes each
    reader = GroupSyncRead(port, handler, ADDR_PRESENT_VELOCITY, ADDR_PRESENT_POSITION + 4 - ADDR_PRESENT_VELOCITY)
    for dxl_id in ids:
        reader.addParam(dxl_id)
    trips = RoundTrips(f"sync reads of {len(ids)} servos")
    for _ in range(cycles):
        start = time.perf_counter()
        result = reader.txRxPacket()
        took = time.perf_counter() - start
        if result == COMM_SUCCESS:
            trips.seconds.append(took)
        else:
            trips.lost += 1
    return trips


@dataclass
class StreamTiming:
    """The sense board's stream as a 1 kHz tick sees it: packets over `seconds`, the newest one's age per poll."""

    seconds: float
    packets: int
    ages: list[float]

    @property
    def rate_hz(self) -> float:
        return self.packets / self.seconds if self.seconds > 0 else 0.0

    def line(self) -> str:
        interval = f"{1e3 / self.rate_hz:.3f} ms" if self.packets else "none"
        ages = np.asarray(self.ages) * 1e3
        return (f"stream over {len(self.ages)} ticks of 1 ms: {self.rate_hz:.0f} packets/s (mean interval {interval}); "
                f"age of the newest packet at a tick p50 {np.percentile(ages, 50):.3f} ms, p99 "
                f"{np.percentile(ages, 99):.3f} ms, max {ages.max():.3f} ms")

    def verdict(self) -> tuple[str, bool]:
        age_p99 = float(np.percentile(self.ages, 99))
        if self.rate_hz >= SENSE_MIN_RATE_HZ and age_p99 <= SENSE_MAX_AGE_P99_S:
            return (f"holds 1 kHz (>= {SENSE_MIN_RATE_HZ:.0f} packets/s, age p99 <= {1e3 * SENSE_MAX_AGE_P99_S:.0f} "
                    "ms)"), True
        return (f"cannot hold 1 kHz: {self.rate_hz:.0f} packets/s, a tick's data up to {1e3 * age_p99:.1f} ms old "
                "(p99)"), False


def sense_stream_timing(board, polls: int) -> StreamTiming:
    """Poll a streaming SenseBoard `polls` times, 1 ms apart (sleep, then spin to each deadline): the newest
    packet's age at each poll, and the packets that came meanwhile."""
    ages: list[float] = []
    first = board.sample_count
    start = deadline = time.monotonic()
    for _ in range(max(1, polls)):
        deadline += TICK_S
        while (now := time.monotonic()) < deadline:
            if deadline - now > 0.0002:
                time.sleep(deadline - now - 0.0002)
        ages.append(board.age(now))
    return StreamTiming(time.monotonic() - start, board.sample_count - first, ages)


def check(config: RobotConfig, rtt_cycles: int = 0) -> list[BusReport]:
    """Every bus's report; `rtt_cycles` > 0 adds the round trips (DESCRIPTION)."""
    legs = leg_kind_of(config).diagnose(config, rtt_cycles)
    return [legs, check_dynamixel(config, rtt_cycles), check_sense(config, polls=rtt_cycles)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value by dotted key path, e.g. buses.bear.port=/dev/ttyUSB3 (repeatable)")
    p.add_argument("--rtt-cycles", default=str(RTT_CYCLES), metavar="N",
                   help="round trips timed per bus: BEAR bulk cycles, Dynamixel sync reads, 1 ms polls of the sense "
                        "board (default %(default)s; 0: no timing)")
    p.add_argument("--probe-watchdog", action="store_true",
                   help="instead of the check, measure the BEAR watchdog's unit (seconds per watchdog_timeout count) "
                        "on one BEAR: it is enabled in torque mode with goal current 0 (limp, then damping, "
                        "repeatedly; keep the robot supported) and restored after; about 5 s, at most 30 s")
    p.add_argument("--probe-id", type=int, default=None, metavar="ID",
                   help="the BEAR --probe-watchdog uses (default: the first of buses.bear.ids)")
    p.add_argument("--probe-counts", type=int, nargs=2, default=list(PROBE_COUNTS), metavar=("N1", "N2"),
                   help="the two watchdog_timeout counts timed (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        rtt_cycles = int(args.rtt_cycles)
    except ValueError:
        rtt_cycles = -1
    if not 0 <= rtt_cycles <= 100_000:
        print(f"{PROG}: --rtt-cycles: {args.rtt_cycles!r} is not a count in 0..100000", file=sys.stderr)
        return 2
    config = load_config_or_say(PROG, args.config, args.overrides)
    if config is None:
        return 2
    if args.probe_watchdog:
        return run_watchdog_probe(config, args.probe_id, args.probe_counts)
    reports = check(config, rtt_cycles)
    for report in reports:
        print(report.text())
    problems = [r for r in reports if not r.ok]
    if problems:
        print(f"{PROG}: PROBLEMS on {len(problems)} bus(es): " + "; ".join(r.problem() for r in problems))
        return 1
    print(f"{PROG}: OK, every device answers")
    return 0


def _vec(v) -> str:
    return "(" + ", ".join(f"{float(x):+.2f}" for x in v) + ")"


if __name__ == "__main__":
    sys.exit(main())
