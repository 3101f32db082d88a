"""The BEAR watchdog's unit, measured (`bruce-hw-check --probe-watchdog`): the BEAR documents its watchdog_timeout
register but not its unit, so one BEAR is made to trip at two counts and the trip times bracketed
(`probe_watchdog`); a linear result is the unit to configure as `buses.bear.watchdog_unit_s`. Torque mode, goal
current 0: the joint goes limp, then damps, a few times; the BEAR's saved registers are restored after."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from bruce_hw.config import RobotConfig
from bruce_hw.leg_kinds import leg_kind_of

PROG = "bruce-hw-check"

PROBE_COUNTS = (100, 200)
PROBE_FEED_S = 0.05          # fed this long after each enable, so the trial starts from a running watchdog
PROBE_FEED_PERIOD_S = 0.005
PROBE_FIRST_WAIT_S = 0.001
PROBE_MAX_WAIT_S = 4.0       # longest silence tried: up to 20 ms per count at 200 counts
PROBE_BUDGET_S = 25.0        # the whole probe, restoring included, stays under 30 s
PROBE_RELATIVE = 0.01        # the trip time is bracketed to 1 % ...
PROBE_ABSOLUTE_S = 0.0003    # ... or 0.3 ms, whichever is wider
PROBE_LINEAR = 0.05          # the two counts' units agree within 5 %: seconds per count it is
PROBE_BAD_TRIALS = 4         # consecutive trials spoiled by a lost packet before giving up


class ProbeError(Exception):
    """The probe cannot go on; the message is one line for people."""


@dataclass
class WatchdogTrip:
    """How long one watchdog_timeout value lets a BEAR go without a packet: it did not trip after `not_tripped_s`
    of silence, it did after `tripped_s`."""

    count: int
    not_tripped_s: float
    tripped_s: float
    trials: int

    @property
    def trip_s(self) -> float:
        return 0.5 * (self.not_tripped_s + self.tripped_s)

    @property
    def unit_s(self) -> float:
        return self.trip_s / self.count


@dataclass
class WatchdogProbe:
    trips: list[WatchdogTrip]

    @property
    def unit_s(self) -> float:
        """Seconds per count: the mean of the counts' ratios."""
        return sum(t.unit_s for t in self.trips) / len(self.trips)

    @property
    def spread(self) -> float:
        """(largest - smallest ratio) / mean: 0 for a watchdog linear in its count with no offset."""
        units = [t.unit_s for t in self.trips]
        return (max(units) - min(units)) / self.unit_s

    @property
    def linear(self) -> bool:
        return self.spread <= PROBE_LINEAR

    def slope_offset(self) -> tuple[float, float]:
        """Seconds per count and fixed seconds from the first and last counts (what a non-linear result means)."""
        a, b = self.trips[0], self.trips[-1]
        slope = (b.trip_s - a.trip_s) / (b.count - a.count) if b.count != a.count else a.unit_s
        return slope, a.trip_s - slope * a.count


def probe_watchdog(bus, device_id: int, counts=PROBE_COUNTS, *, feed_s: float = PROBE_FEED_S,
                   max_wait_s: float = PROBE_MAX_WAIT_S, budget_s: float = PROBE_BUDGET_S,
                   say=print) -> WatchdogProbe:
    """Measure how long a BEAR's watchdog_timeout of each count lets it go without a packet (the unit is
    undocumented). A BEAR cannot be polled without feeding its watchdog (any packet resets it), so each trial
    re-arms it (torque_enable 0 clears damping, then 1, in torque mode with goal_iq 0, fed with goal_iq-0 BULK_COMMs
    for `feed_s`), stays silent for a chosen time W, then pings once: error bit 3 set means it tripped within W.
    W doubles from 1 ms until it trips, then bisection brackets the trip time to 1 % (or 0.3 ms). Silences are
    measured from the start of the last feeding request to the start of the ping (the wire latency cancels); a
    trial with a retried request is repeated. The motor only ever gets goal_iq 0. The caller restores the BEAR
    (`restore_after_probe`). ProbeError (one line) on a silent BEAR, an E-stop, a fault, no trip or the budget."""
    from drivers.bear_registers import FAULT_BITS, BearError, Mode
    from drivers.errors import BusTimeout, DriverError

    deadline = time.monotonic() + budget_s
    try:
        reply = bus.ping(device_id)
    except BusTimeout:
        raise ProbeError(f"BEAR ID {device_id} on {bus.port} does not answer: check power, wiring, ID and baud "
                         "rate") from None
    try:
        bus.set_torque_enable([device_id], 0)
        bus.write_status(device_id, {"goal_iq": 0.0})
        reply = bus.ping(device_id)
        if reply.error & BearError.WATCHDOG_ESTOP:
            raise ProbeError(f"BEAR ID {device_id} reports the E-stop input (error bit 3) with torque disabled: "
                             "release the E-stop")
        if reply.error & FAULT_BITS:
            raise ProbeError(f"BEAR ID {device_id} reports {', '.join(reply.flags)}: clear the fault first")
        trips: list[WatchdogTrip] = []
        for count in counts:
            bus.set_torque_enable([device_id], 0)  # a trial may leave it enabled; config is written disabled only
            bus.write_config(device_id, {"mode": int(Mode.TORQUE), "watchdog_timeout": int(count)})  # read back
            first = PROBE_FIRST_WAIT_S
            if trips:  # start near what the last count predicts, at half of it, so one or two doublings bracket it
                first = max(first, 0.5 * trips[-1].unit_s * count)
            trip = _bracket_trip(bus, device_id, count, first, feed_s, max_wait_s, deadline)
            say(f"  watchdog_timeout {count}: trips after {1e3 * trip.trip_s:.1f} ms without a packet (not after "
                f"{1e3 * trip.not_tripped_s:.1f} ms, after {1e3 * trip.tripped_s:.1f} ms; {trip.trials} trials)")
            trips.append(trip)
    except BusTimeout as exc:
        raise ProbeError(f"BEAR ID {device_id} stopped answering during the probe ({exc})") from None
    except DriverError as exc:
        raise ProbeError(str(exc)) from None
    return WatchdogProbe(trips)


def _bracket_trip(bus, device_id: int, count: int, first_wait_s: float, feed_s: float, max_wait_s: float,
                  deadline: float) -> WatchdogTrip:
    not_tripped, tripped = 0.0, math.inf
    wait, trials = first_wait_s, 0
    while True:
        if math.isinf(tripped):
            if wait > max_wait_s:
                raise ProbeError(f"watchdog_timeout {count} did not trip within {1e3 * not_tripped:.0f} ms without "
                                 f"a packet: the watchdog is off in this firmware, or a count is longer than "
                                 f"{not_tripped / count:.3g} s")
        elif tripped - not_tripped <= max(PROBE_ABSOLUTE_S, PROBE_RELATIVE * tripped):
            return WatchdogTrip(count, not_tripped, tripped, trials)
        else:
            wait = 0.5 * (not_tripped + tripped)
        if time.monotonic() + feed_s + wait + 0.1 > deadline:
            raise ProbeError(f"the probe ran out of its time budget at watchdog_timeout {count} "
                             f"(trips between {1e3 * not_tripped:.1f} and {1e3 * tripped:.1f} ms so far)")
        silence, trip = _trial(bus, device_id, wait, feed_s)
        trials += 1
        if trip:
            tripped = min(tripped, silence)
        else:
            not_tripped = max(not_tripped, silence)
            if math.isinf(tripped):
                wait *= 2
        if not_tripped >= tripped:  # jitter contradicted an earlier trial: widen around the newest
            not_tripped, tripped = (0.0, silence) if trip else (silence, math.inf)
            wait = max(PROBE_FIRST_WAIT_S, silence)


def _trial(bus, device_id: int, wait_s: float, feed_s: float) -> tuple[float, bool]:
    """Re-arm, feed, stay silent about `wait_s`, ping: (the silence measured, whether bit 3 came back set)."""
    from drivers.bear_registers import BearError, Mode
    from drivers.errors import BusTimeout

    for _ in range(PROBE_BAD_TRIALS):
        retries = bus.stats.retries
        try:
            bus.set_torque_enable([device_id], 0)  # out of damping (and clears latched faults)
            bus.set_torque_enable([device_id], 1)
            enable = int(bus.read_status(device_id, "torque_enable")["torque_enable"])
            if enable != 1:
                if enable == 2:
                    raise ProbeError(f"BEAR ID {device_id} reads torque_enable 2 (a fault) when enabled")
                continue  # the enable write was lost (writes get no reply): again
            feed_until = time.monotonic() + feed_s
            while True:
                sent = time.monotonic()
                reply = bus.bulk_cycle([device_id], Mode.TORQUE, goal_iq=[0.0])
                if reply.error[0] & BearError.WATCHDOG_ESTOP:
                    raise ProbeError(f"BEAR ID {device_id} went to damping while fed every "
                                     f"{1e3 * PROBE_FEED_PERIOD_S:.0f} ms: its watchdog is shorter than that at this "
                                     "count (try larger --probe-counts), or the E-stop was pressed")
                if sent >= feed_until:
                    break
                time.sleep(max(0.0, sent + PROBE_FEED_PERIOD_S - time.monotonic()))
            _sleep_until(sent + wait_s)
            pinged = time.monotonic()
            reply = bus.ping(device_id)
        except BusTimeout:
            continue
        if bus.stats.retries != retries:
            continue  # a request went twice: which one the BEAR heard last is unknown
        return pinged - sent, bool(reply.error & BearError.WATCHDOG_ESTOP)
    raise ProbeError(f"BEAR ID {device_id}: {PROBE_BAD_TRIALS} trials in a row lost a packet; the bus is too "
                     "unreliable to time the watchdog")


def _sleep_until(t: float) -> None:
    """time.sleep to within half a millisecond of `t`, then spin: the silence should be what was asked."""
    while True:
        left = t - time.monotonic()
        if left <= 0:
            return
        if left > 0.0005:
            time.sleep(left - 0.0005)


def restore_after_probe(bus, device_id: int, saved: dict) -> str:
    """Torque disabled, the saved config registers written back (verified). Returns a line for people."""
    bus.set_torque_enable([device_id], 0)
    bus.write_config(device_id, saved)
    return ", ".join(f"{name} {value}" for name, value in saved.items())


def run_watchdog_probe(config: RobotConfig, device_id: int | None, counts) -> int:
    from drivers.bear import BearBus
    from drivers.errors import DriverError

    bus_cfg = config.buses.bear
    if leg_kind_of(config).name != "bear" or not bus_cfg.ids:
        print(f"{PROG}: --probe-watchdog needs a BEAR bus (buses.bear.ids); this config has none")
        return 2
    device_id = bus_cfg.ids[0] if device_id is None else device_id
    counts = tuple(sorted({int(n) for n in counts}))
    if len(counts) < 2 or counts[0] < 1:
        print(f"{PROG}: --probe-counts needs two different positive counts")
        return 2
    try:
        # A generous reply timeout: a slow reply should cost a wait, not a spoiled trial.
        bus = BearBus(bus_cfg.port, bus_cfg.baud, reply_timeout_s=0.02)
    except DriverError as exc:
        print(f"{PROG}: cannot probe the BEAR watchdog: {exc}")
        return 1
    started = time.monotonic()
    with bus:
        try:
            saved = dict(bus.read_config(device_id, ["watchdog_timeout", "mode"]).values)
        except DriverError as exc:
            print(f"{PROG}: cannot probe the BEAR watchdog: BEAR ID {device_id} on {bus_cfg.port} does not answer "
                  f"({exc}): check power, wiring, ID and baud rate")
            return 1
        print(f"{PROG}: probing the watchdog of BEAR ID {device_id} on {bus_cfg.port}: torque mode, goal current 0 "
              f"(the joint goes limp, then damps, over and over; keep the robot supported)", flush=True)
        result, failure = None, None
        try:
            result = probe_watchdog(bus, device_id, counts, say=lambda text: print(text, flush=True))
        except ProbeError as exc:
            failure = str(exc)
        finally:
            try:
                restored = restore_after_probe(bus, device_id, saved)
            except DriverError as exc:
                restored = None
                print(f"{PROG}: WARNING: could not restore BEAR ID {device_id} ({exc}): write torque_enable 0 and "
                      f"watchdog_timeout {saved['watchdog_timeout']}, mode {saved['mode']} yourself")
    took = time.monotonic() - started
    back = f"restored torque disabled, {restored}" if restored is not None else "NOT restored"
    if failure is not None:
        print(f"{PROG}: watchdog probe failed: {failure} ({back})")
        return 1
    unit = float(f"{result.unit_s:.3g}")
    per_count = ", ".join(f"{t.count}: {1e3 * t.trip_s:.1f} ms" for t in result.trips)
    if not result.linear:
        slope, offset = result.slope_offset()
        print(f"{PROG}: BEAR watchdog NOT linear in its count (seconds per count differ by {100 * result.spread:.0f} "
              f"%; {per_count}; slope {slope:.3g} s per count, offset {1e3 * offset:.1f} ms); no unit to configure "
              f"({back}; {took:.1f} s)")
        return 1
    print(f"{PROG}: BEAR watchdog unit {unit:g} s per count ({per_count}; linear within {100 * result.spread:.1f} %; "
          f"{back}; {took:.1f} s); configure it with --set buses.bear.watchdog_unit_s={unit:g} "
          f"(YAML: watchdog_unit_s: {unit:g} under buses.bear)")
    return 0
