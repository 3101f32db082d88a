"""Koala BEAR actuators (Westwood Robotics) on RS-485: `BearBus`, a pyserial driver with bounded timeouts whose
`bulk_cycle` does one control tick's I/O, and its reply types. The register tables are in `drivers.bear_registers`,
the wire format, the packet encoders and the resynchronising reply parser in `drivers.bear_codec`.

Sources: Westwood's PyBEAR SDK and BRUCE-OP v0.0.7; where they are silent or disagree, the choice is noted at the
code that makes it, and drivers/emulators/bear.py makes the same ones.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import struct
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.bear_codec import (
    StatusPacket,
    StatusParser,
    bulk_layout,
    decode_values,
    encode_bulk,
    encode_ping,
    encode_read,
    encode_save_config,
    encode_write,
    reply_length,
)
from drivers.bear_registers import (
    BROADCAST_ID,
    CYCLE_READS,
    ERROR_OK,
    FAULT_BITS,
    GOALS_BY_MODE,
    REGISTER_ALIASES,
    BearError,
    Mode,
    Register,
    TorqueEnable,
    config_register,
    error_flags,
    status_register,
)
from drivers.errors import PORT_ERRORS, BusTimeout, DeviceFault, DriverError, LinkStats

DEFAULT_BAUD = 8_000_000
# Timeouts: all replies of a request must be in within `reply_timeout_s` (2 ms: BRUCE's bulk_timeout, AOS) plus the
# wire time of request and replies, `tries` = 2 (AOS). Serial reads block at most `read_slice_s` each, so no call
# blocks for long whatever the device does.
# Longest pause between two replies of one request before the rest counts as lost: the BEARs answer back to back,
# and a USB adapter in low-latency mode delivers what it holds at least every millisecond.
REPLY_GAP_S = 0.0015
# A read returns within its slice plus this much scheduling; a pass that took longer means the host did not run us.
STALL_TOLERANCE_S = 0.0005
# A flush and write of a request take microseconds; one that took longer than this was held by the host (the kernel's
# tty work for this port not run: docs/timing.md, "Scheduling") and the request had not gone out meanwhile.
SEND_STALL_S = 0.001
# Most host time a call does not count against the device: beyond it the readings are too old for any data-age limit
# (safety.max_sensor_age_s is at most 50 ms), so waiting longer would gain nothing.
MAX_STALL_CREDIT_S = 0.05
# Reads of at most 4 KiB each that take in the late replies before a request: ten replies are a few hundred bytes, so
# this only bounds what a babbling port can cost.
HARVEST_READS = 8


# -- replies --------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PingReply:
    id: int
    error: int
    data: bytes  # firmware/hardware version bytes (content undocumented): raw, of any length

    @property
    def flags(self) -> tuple[str, ...]:
        return error_flags(self.error)


@dataclass(frozen=True)
class RegisterReply:
    id: int
    error: int
    values: dict[str, int | float]

    @property
    def flags(self) -> tuple[str, ...]:
        return error_flags(self.error)

    def __getitem__(self, name: str) -> int | float:
        return self.values[REGISTER_ALIASES.get(name, name)]


# The error bits as ints: an IntFlag's `&` builds a flag each time, ten times a cycle on the bus thread.
ESTOP_BIT, FAULT_MASK = int(BearError.WATCHDOG_ESTOP), int(FAULT_BITS)


@dataclass(frozen=True)
class BulkReply:
    """One BULK_COMM's answers, rows in the order of `ids`. u32 values are exact in float64."""

    bus: str
    ids: tuple[int, ...]
    registers: tuple[str, ...]
    values: np.ndarray  # (len(ids), len(registers)) float64; NaN rows for IDs that did not answer (partial replies)
    error: np.ndarray  # (len(ids),) uint8 error bytes; 0 where nothing was read (write-only bulk, no answer)
    answered: np.ndarray | None = None  # (len(ids),) bool; None: every ID answered
    sent_at: float = math.nan  # time.monotonic() when the request these replies answer began to go out
    # Replies to the previous partial bulk request that came after its deadline and before this request (rows for
    # those IDs only, its own `sent_at`): data all the same, no older than that request (`BearBus.bulk_comm`).
    late: BulkReply | None = None

    @property
    def lost_ids(self) -> tuple[int, ...]:
        """IDs whose reply did not come (partial replies only)."""
        if self.answered is None:
            return ()
        return tuple(i for i, ok in zip(self.ids, self.answered.tolist(), strict=True) if not ok)

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.registers.index(name)]

    @property
    def position(self) -> np.ndarray:
        return self.column("present_position")

    @property
    def velocity(self) -> np.ndarray:
        return self.column("present_velocity")

    @property
    def iq(self) -> np.ndarray:
        return self.column("present_iq")

    def flags(self, device_id: int) -> tuple[str, ...]:
        return error_flags(int(self.error[self.ids.index(device_id)]))

    def in_order(self, ids: Sequence[int], rows: np.ndarray | None = None) -> BulkReply:
        """The same answers with rows in the order of `ids` (the same IDs, in another order; `late` as it is).
        `rows`: where each of `ids` is in this reply, for a caller that knows (a cycle's turned order: its inverse),
        so the bus thread does not look each one up every cycle."""
        ids = tuple(ids)
        if ids == self.ids:
            return self
        if rows is None:
            row = {device_id: k for k, device_id in enumerate(self.ids)}
            rows = np.array([row[i] for i in ids])
        answered = None if self.answered is None else self.answered[rows]
        return BulkReply(self.bus, ids, self.registers, self.values[rows], self.error[rows], answered, self.sent_at,
                         self.late)

    def faulted_ids(self) -> tuple[int, ...]:
        """IDs reporting a fault bit (2-6; not the warnings)."""
        return tuple(i for i, e in zip(self.ids, self.error.tolist(), strict=True) if e & FAULT_MASK)

    def estop_ids(self) -> tuple[int, ...]:
        """IDs reporting the watchdog / E-stop bit."""
        return tuple(i for i, e in zip(self.ids, self.error.tolist(), strict=True) if e & ESTOP_BIT)

    def raise_for_faults(self) -> None:
        """DeviceFault naming the first faulted ID and its flags, if any ID reports a fault."""
        for device_id in self.faulted_ids():
            raise DeviceFault(self.bus, device_id, self.flags(device_id))


@functools.lru_cache(maxsize=64)
def _bulk_registers(read_regs: tuple[str | int, ...], write_regs: tuple[str | int, ...]
                    ) -> tuple[tuple[Register, ...], tuple[Register, ...]]:
    """The status registers a bulk request names (looked up once per set: the bus thread names the same every cycle)."""
    return tuple(status_register(n) for n in read_regs), tuple(status_register(n) for n in write_regs)


# -- the bus --------------------------------------------------------------------------------------------------------
def _names(keys: str | int | Sequence[str | int]) -> list[str | int]:
    return [keys] if isinstance(keys, str | int) else list(keys)


class BearBus:
    """One RS-485 chain of BEARs on a USB-serial adapter (BRUCE: /dev/ttyUSB0, 8 Mbaud, IDs 1-10).

    Every call is bounded in time: a reply comes within `reply_timeout_s` plus wire time or the request is retried
    (`tries` in all), and then `BusTimeout(port, silent_ids)` names exactly the IDs that did not answer. Rejected
    bytes and packets are counted in `stats` and never raised. Device errors come back as decoded flags; call
    `BulkReply.raise_for_faults()` (or `ping` / `clear_errors`) to turn them into `DeviceFault`.
    """

    def __init__(self, port: str, baud: int = DEFAULT_BAUD, *, reply_timeout_s: float = 0.002, tries: int = 2,
                 read_slice_s: float = 0.0005, write_timeout_s: float = 0.05, stats: LinkStats | None = None):
        import serial  # lazily: the stack imports without pyserial

        if tries < 1:
            raise ValueError("tries must be at least 1")
        self.port = port
        self.baud = baud
        self.reply_timeout_s = reply_timeout_s
        self.tries = tries
        self.read_slice_s = read_slice_s
        self.stats = stats if stats is not None else LinkStats()
        # Time the host held this port's I/O, not the devices' silence: `on_host_stall(start, end)` hears of each
        # (a send held past SEND_STALL_S, a read pass the host was late for); `held_since(now)` of one in progress.
        self.on_host_stall: Callable[[float, float], None] | None = None
        # The port call in progress: (when it has taken longer than it takes by itself, since when it is then held)
        self._call: tuple[float, float] | None = None
        self._parser = StatusParser(self.stats)
        self._sent_at = math.nan  # when the last request began to go out
        # A partial bulk request whose deadline passed with IDs unanswered: (those IDs, its read registers, when it
        # went out), until the next request; the parser keeps the bytes of a reply cut by the deadline meanwhile.
        self._awaited: tuple[tuple[int, ...], list[Register], float] | None = None
        self._io_errors = PORT_ERRORS
        try:
            # 8N1; the read timeout is one slice, so a read returns at the latest after read_slice_s.
            self._serial = serial.Serial(port, baud, timeout=read_slice_s, write_timeout=write_timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"{port}: cannot open the BEAR bus at {baud} baud: {exc}") from exc
        self.low_latency = self._low_latency()

    def _low_latency(self) -> str:
        """Ask the adapter for low latency (ASYNC_LOW_LATENCY; on an FTDI the kernel then sets its latency timer to
        1 ms instead of 16 ms, which would otherwise hold every reply back); what was granted, in words."""
        setter = getattr(self._serial, "set_low_latency_mode", None)
        if setter is None:
            return "low-latency mode: not available on this OS"
        try:
            setter(True)
        except (ValueError, OSError) as exc:
            return f"low-latency mode: not available on {self.port} ({str(exc).split(': ')[-1]})"
        timer = _latency_timer_ms(self.port)
        return "low-latency mode on" + (f", latency timer {timer} ms" if timer is not None else "")

    # -- lifecycle --
    def close(self) -> None:
        serial_port = getattr(self, "_serial", None)
        if serial_port is not None and serial_port.is_open:
            serial_port.close()

    def __enter__(self) -> BearBus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- instructions --
    def ping(self, device_id: int) -> PingReply:
        packet = self._request(encode_ping(device_id), device_id, None, "PING")
        return PingReply(packet.id, packet.error, packet.data)

    def scan(self, ids: Iterable[int]) -> dict[int, PingReply]:
        """Ping each ID; the ones that answer (silent IDs are left out, not raised)."""
        found = {}
        for device_id in ids:
            try:
                found[device_id] = self.ping(device_id)
            except BusTimeout:
                pass
        return found

    def read_status(self, device_id: int, names: str | int | Sequence[str | int], tries: int | None = None
                    ) -> RegisterReply:
        """`tries`: this request's tries (default: the bus's); 1 inside a control tick, which cannot wait twice."""
        return self._read(device_id, [status_register(n) for n in _names(names)], tries)

    def read_config(self, device_id: int, names: str | int | Sequence[str | int]) -> RegisterReply:
        return self._read(device_id, [config_register(n) for n in _names(names)])

    def write_status(self, device_id: int, values: Mapping[str | int, int | float]) -> None:
        registers = [status_register(n) for n in values]
        read_only = [r.name for r in registers if not r.writable]
        if read_only:
            raise ValueError(f"read-only BEAR status registers: {read_only}")
        self._send(encode_write(device_id, list(zip(registers, values.values(), strict=True))))

    def write_config(self, device_id: int, values: Mapping[str | int, int | float], verify: bool = True) -> None:
        """Write config registers; with `verify`, read them back and raise DriverError if the BEAR did not take
        them: it ignores config writes while torque is enabled (Rust driver) and gives no reply to writes."""
        registers = [config_register(n) for n in values]
        pairs = list(zip(registers, values.values(), strict=True))
        self._send(encode_write(device_id, pairs))
        if not verify or device_id == BROADCAST_ID:
            return
        readback_id = int(values.get("id", values.get(0, device_id)))  # the BEAR answers under its new ID
        got = self._read(readback_id, registers).values
        wrong = [r.name for r, v in pairs if got[r.name] != _as_sent(r, v)]
        if wrong:
            raise DriverError(f"{self.port}: ID {device_id} did not take config {', '.join(wrong)} "
                              "(config registers are writable only while torque is disabled)")

    def save_config(self, device_id: int) -> None:
        """Store the config registers in flash (no reply)."""
        self._send(encode_save_config(device_id))

    def set_torque_enable(self, ids: Iterable[int], value: int) -> None:
        """torque_enable to each ID: 0 disable (also clears errors), 1 enable, 3 damping."""
        if int(value) not in (TorqueEnable.DISABLED, TorqueEnable.ENABLED, TorqueEnable.DAMPING):
            raise ValueError("torque_enable is written 0 (disable), 1 (enable) or 3 (damping)")
        for device_id in ids:
            self.write_status(device_id, {"torque_enable": int(value)})

    def clear_errors(self, device_id: int, attempts: int = 6) -> PingReply:
        """BRUCE's start-up rule: while the BEAR reports an error without the E-stop bit, write torque_enable = 0
        and ping again (at most `attempts` times). DeviceFault if the E-stop bit is set or the error stays."""
        reply = self.ping(device_id)
        for _ in range(attempts):
            if reply.error == ERROR_OK or reply.error & BearError.WATCHDOG_ESTOP:
                break
            self.write_status(device_id, {"torque_enable": TorqueEnable.DISABLED})
            reply = self.ping(device_id)
        if reply.error & BearError.WATCHDOG_ESTOP:
            raise DeviceFault(self.port, device_id, reply.flags + ("release the E-stop",))
        if reply.error & FAULT_BITS:
            raise DeviceFault(self.port, device_id, reply.flags)
        return reply

    def bulk_comm(self, ids: Sequence[int], read_regs: Sequence[str | int] = (), write_regs: Sequence[str | int] = (),
                  values=None, partial: bool = False) -> BulkReply:
        """One BULK_COMM: read `read_regs` of every ID and write `values[k]` (one row per ID, in `write_regs` order)
        to ids[k]. Motors that do not answer are asked again (`tries` in all); BusTimeout names those that never do.

        `partial`: one try, never a retry (a control tick cannot wait for one), and whatever came back is returned:
        rows of IDs that did not answer are NaN and `answered` says which; the caller keeps their last sample."""
        layout = bulk_layout(ids, *_bulk_registers(tuple(read_regs), tuple(write_regs)))
        ids, reads, writes = layout.ids, layout.reads, layout.writes
        if writes and (values is None or len(values) != len(ids)):
            raise ValueError(f"BULK_COMM writes {len(writes)} registers: give one row of values per ID ({len(ids)})")
        request = layout.encode(values)  # validates first
        names = layout.read_names
        if not reads:  # nobody answers a write-only bulk
            self._send(request)
            return BulkReply(self.port, ids, names, np.zeros((len(ids), 0)), np.zeros(len(ids), np.uint8))
        late = self._harvest() if partial and self._awaited is not None else None
        got: dict[int, StatusPacket] = {}
        pending = list(ids)
        for attempt in range(1 if partial else self.tries):
            if attempt:
                self.stats.retries += 1
                # only to the motors that did not answer: their goals are written again (goal writes are idempotent)
                request = encode_bulk(pending, reads, writes,
                                      [values[ids.index(i)] for i in pending] if writes else None)
            got.update(self._exchange(request, pending, reply_length(len(reads)), keep_tail=partial))
            pending = [i for i in pending if i not in got]
            if not pending:
                break
        sent_at = self._sent_at
        if pending:
            self.stats.timeouts += 1
            if not partial:
                raise BusTimeout(self.port, pending, f"BULK_COMM, {self.tries} tries")
            self._awaited = (tuple(pending), list(reads), sent_at)
            lost = (math.nan,) * len(reads)
            table = np.array([layout.unpack_reply(got[i].data) if i in got else lost for i in ids], dtype=np.float64)
            errors = np.array([got[i].error if i in got else 0 for i in ids], dtype=np.uint8)
            return BulkReply(self.port, ids, names, table, errors, np.array([i in got for i in ids]), sent_at, late)
        table = np.array([layout.unpack_reply(got[i].data) for i in ids], dtype=np.float64)
        return BulkReply(self.port, ids, names, table, np.array([got[i].error for i in ids], dtype=np.uint8),
                         None, sent_at, late)

    def bulk_cycle(self, ids: Sequence[int], mode: Mode | int | str | None, goal_position=None, goal_velocity=None,
                   goal_iq=None, partial: bool = False, extra_reads: Sequence[str] = ()) -> BulkReply:
        """One control tick: read present_position, present_velocity and present_iq of every ID and write the
        mode's goals (force: goal_position, goal_velocity, goal_iq; torque: goal_iq; position: goal_position;
        velocity: goal_velocity; None: read only). Goals are arrays in ID order; the reply's `position`,
        `velocity`, `iq` and `error` are arrays in ID order. `extra_reads`: status registers read in the same
        request (`column(name)`), e.g. temperatures now and then, at a few bytes of wire time instead of a request
        of their own. `partial`: see `bulk_comm`."""
        writes: tuple[str, ...] = ()
        columns = []
        if mode is not None:
            mode = Mode[mode.upper()] if isinstance(mode, str) else Mode(mode)
            writes = GOALS_BY_MODE[mode]
            goals = {"goal_position": goal_position, "goal_velocity": goal_velocity, "goal_iq": goal_iq}
            for name in writes:
                if goals[name] is None:
                    raise ValueError(f"{mode.name.lower()} mode writes {name}: give it")
                column = np.asarray(goals[name], dtype=np.float64).reshape(-1)
                if column.shape != (len(ids),):
                    raise ValueError(f"{name}: {column.size} values for {len(ids)} IDs")
                columns.append(column)
        values = np.column_stack(columns) if columns else None
        return self.bulk_comm(ids, CYCLE_READS + tuple(extra_reads), writes, values, partial=partial)

    def cycle_budget_s(self, n_ids: int, n_read: int = len(CYCLE_READS), n_write: int = 3) -> float:
        """Longest a bulk call can take before BusTimeout, all tries included (excluding the host's scheduling)."""
        request = 4 + n_ids + n_read + n_write + 4 * n_write * n_ids + 4
        replies = n_ids * (4 + reply_length(n_read))
        return self.tries * (self.reply_timeout_s + self._wire_s(request + replies) + self.read_slice_s)

    # -- I/O --
    def _wire_s(self, n_bytes: int) -> float:
        return n_bytes * 10 / self.baud  # 8N1: 10 bits a byte

    def _send(self, packet: bytes) -> None:
        """Flush stale input (late replies of an earlier request), then write the whole packet. The flush waits in
        the kernel for the port's receive work to finish (a tty worker that real-time threads keep from its CPU holds
        it for milliseconds): that wait is the host's, reported to `on_host_stall`."""
        self._awaited = None  # the flush drops replies still awaited: they are no one's now
        with self._port_call("write") as start:
            self._sent_at = start
            self._serial.reset_input_buffer()
            self._serial.write(packet)

    @contextlib.contextmanager
    def _port_call(self, what: str):
        """A call into the port that waits for its receive work in the kernel (a flush, a read of what is there):
        yields its start; one that took longer than SEND_STALL_S was held by the host, reported to `on_host_stall`
        (and seen by `held_since` while it lasts); a port error is a DriverError naming the port and `what`."""
        start = time.monotonic()
        self._call = (start + SEND_STALL_S, start)
        try:
            yield start
        except self._io_errors as exc:
            raise DriverError(f"{self.port}: {what} failed: {exc}") from exc
        finally:
            self._call = None
            end = time.monotonic()
            if end - start > SEND_STALL_S:
                self._host_stall(start, end)

    def _harvest(self) -> BulkReply | None:
        """The replies to the last partial bulk request that came after its deadline, read before the next request
        flushes them away: rows for the IDs that answered late, stamped with that request's `sent_at`.

        On a half-duplex bus the BEARs speak only when asked and the host asks one request at a time, so bytes in
        the input before the next request are answers to an earlier one, and what the flush does not drop answers
        the last (`_send` flushes before every request). Most come late because the host did not hand them over in
        time (the kernel's tty work for the port behind real-time threads, a USB adapter's latency timer), not
        because the motor was slow: they are the motor's state at some moment after that request went out. A reply
        that never comes is still silence, which the data age catches as before. Reading a tty first waits for its
        receive work in progress (as the flush does): that wait is the host's, reported like a held send."""
        ids, reads, sent_at = self._awaited
        self._awaited = None
        fileno = getattr(self._serial, "fileno", None)
        if fileno is None:  # no POSIX descriptor (Windows): the flush drops them, as it did
            self._parser.clear()
            return None
        data = bytearray()
        with self._port_call("read"):
            fd = fileno()
            for _ in range(HARVEST_READS):  # pyserial keeps the descriptor non-blocking
                try:
                    chunk = os.read(fd, 4096)
                except BlockingIOError:  # nothing more (and no receive work left in flight)
                    break
                if not chunk:
                    break
                data += chunk
        self._parser.expect(reply_length(len(reads)), ids)
        got: dict[int, StatusPacket] = {}
        self._take(data, got)
        if len(got) < len(ids) and self._parser.pending:
            self.stats.reject("truncated")
        self._parser.clear()
        if not got:
            return None
        answered = tuple(i for i in ids if i in got)
        self.stats.late_replies += len(answered)
        fmt = "<" + "".join(r.fmt for r in reads)
        table = np.array([struct.unpack(fmt, got[i].data) for i in answered], dtype=np.float64)
        return BulkReply(self.port, answered, tuple(r.name for r in reads), table,
                         np.array([got[i].error for i in answered], dtype=np.uint8), None, sent_at)

    def _take(self, data: bytes, got: dict[int, StatusPacket]) -> int | None:
        """The replies in `data` into `got`, the first one per ID (a second is counted as a duplicate); returns the ID
        of the last packet in `data`, taken or not (None: none)."""
        newest = None
        for packet in self._parser.feed(data):
            newest = packet.id
            if packet.id in got:
                self.stats.reject("duplicate")
            else:
                got[packet.id] = packet
        return newest

    def held_since(self, now: float) -> float | None:
        """If the port call in progress (a send, a read pass) has taken longer than it takes by itself, since when
        the host has held it (a send: from its start, the request not out; a read: from the end of its slice), else
        None: a call that never ends is seen before it ends."""
        call = self._call
        return call[1] if call is not None and now > call[0] else None

    def _host_stall(self, start: float, end: float) -> None:
        self.stats.host_stalls += 1
        if self.on_host_stall is not None:
            self.on_host_stall(start, end)

    def _read(self, device_id: int, registers: list[Register], tries: int | None = None) -> RegisterReply:
        if not registers:
            raise ValueError("name at least one register to read")
        name = "READ_CFG" if registers[0].table == "config" else "READ_STAT"
        packet = self._request(encode_read(device_id, registers), device_id, reply_length(len(registers)), name,
                               tries)
        values = decode_values(registers, packet.data)
        return RegisterReply(device_id, packet.error, {r.name: v for r, v in zip(registers, values, strict=True)})

    def _request(self, request: bytes, device_id: int, length: int | None, what: str,
                 tries: int | None = None) -> StatusPacket:
        if device_id == BROADCAST_ID:
            raise ValueError(f"{what} to the broadcast ID gets no reply")
        tries = self.tries if tries is None else tries
        for attempt in range(tries):
            if attempt:
                self.stats.retries += 1
            got = self._exchange(request, [device_id], length)
            if device_id in got:
                return got[device_id]
        self.stats.timeouts += 1
        raise BusTimeout(self.port, [device_id], f"{what}, {tries} tries")

    def _exchange(self, request: bytes, ids: Sequence[int], length: int | None, keep_tail: bool = False
                  ) -> dict[int, StatusPacket]:
        """Send one request and collect one reply per ID until all are in or the deadline passes. `keep_tail`: a
        reply cut by the deadline stays in the parser for `_harvest` to complete."""
        per_reply = 4 + (length if length is not None else 2)
        budget = self.reply_timeout_s + self._wire_s(len(request) + per_reply * len(ids))
        self._parser.clear()
        self._parser.expect(length, ids)
        self._send(request)
        deadline, credit = time.monotonic() + budget, MAX_STALL_CREDIT_S
        allowance = self.read_slice_s + STALL_TOLERANCE_S  # a pass's own time: its read slice and the scheduling
        got: dict[int, StatusPacket] = {}
        while len(got) < len(ids):
            now = time.monotonic()
            if now >= deadline:
                break
            missing = (len(ids) - len(got)) * per_reply - self._parser.pending
            self._call = (now + allowance, now + allowance)
            try:
                chunk = self._serial.read(max(1, missing))  # returns when `missing` bytes are in or after a slice
            except self._io_errors as exc:
                raise DriverError(f"{self.port}: read failed: {exc}") from exc
            finally:
                self._call = None
            if chunk:
                # The replies come back to back: once they have started, a pause longer than REPLY_GAP_S means the
                # rest is lost, so a lost reply costs that gap, not the whole timeout (which covers the bus delay
                # before the first reply).
                deadline = min(deadline, now + REPLY_GAP_S + self._wire_s(missing))
            newest = self._take(chunk, got)
            # A pass takes at most its allowance unless the host did not run this thread (preempted, a paused VM):
            # the replies that came meanwhile are still on their way through the kernel (the tty's work item was
            # stalled too), so that time is the host's, not the device's, and does not count against the reply (up
            # to MAX_STALL_CREDIT_S in all: a call stays bounded).
            end = time.monotonic()
            stalled = min(end - now - allowance, credit)
            if stalled > 0:
                deadline += stalled
                credit -= stalled
                self._host_stall(end - stalled, end)
            if newest == ids[-1]:
                # Replies come in request order: once the last ID's reply is the newest, one still missing before it
                # is lost, not late. Not merely once the last ID has answered: the replies to an earlier request that
                # the kernel held may come first, in that request's order (BearLegs turns it each cycle), and its
                # first reply may be from this request's last ID.
                break
        if len(got) < len(ids) and keep_tail:
            return got
        if len(got) < len(ids) and self._parser.pending:
            self.stats.reject("truncated")
        self._parser.clear()
        return got


def _latency_timer_ms(port: str) -> int | None:
    """The FTDI latency timer of a USB-serial port (sysfs), None where there is none."""
    import os

    name = os.path.basename(os.path.realpath(port))
    try:
        with open(f"/sys/bus/usb-serial/devices/{name}/latency_timer") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def _as_sent(register: Register, value) -> int | float:
    """What the BEAR stores for a written value: f32 values come back rounded to float32."""
    checked = register.check(value)
    return checked if register.kind == "u32" else struct.unpack("<f", struct.pack("<f", checked))[0]
