"""The plant in a process of its own (`PhysicsProcess`): what `bruce-emulate --realtime` runs, so that the emulated
devices cost the host's machine what real devices cost a robot computer, nothing it has to wait for.

In one process, the devices' threads (real-time) and the physics shared an interpreter lock and a CPU, and either
way one held the other up: at the devices' priority the physics kept the kernel's tty worker (normal priority) off
the CPU for 5-10 ms at a time, so the host's requests sat undelivered in the pty; at normal priority a physics step
preempted by any other process held the lock the device threads needed (ftrace, docs/results/timing.md). Here the
devices' process keeps only the devices and a bridge thread; the physics steps `Plant` in a child at normal priority
and `PHYSICS_NICE`, which every tty worker and device thread preempts, and which holds no lock of theirs.

They meet in shared memory (`_Block`, a sequence counter around each write) at each physics step, in the order the
in-process plant keeps: before the step the child asks the bridge for the legs' commands (`FETCH`) and waits for
them: the bridge runs the leg kind's torque law (`LegEmulation.torques`) on the newest measurement and the devices'
commands of that moment (`COMMAND`); after the step the child writes what the actuators, the IMU and the foot
switches measure (`WORLD`) and tells the bridge (`PUBLISH`), which hands it to the emulators at once. So the physics
acts on the commands of the step's own moment, as in one process. (A bridge that exchanged on its own 1-ms clock put
the commands and the measurement up to a period behind each: walks then ended on the BEARs' joint limits, the loop's
latency past what the gait holds.) The arms step at their own 50 Hz (`plant.ARM_EVERY_STEPS`), and only then does
the child ask for the servos' goals (`FETCH_ARMS`) and hand over what they measure (`PUBLISH_ARMS`): the bridge's
work at every step is the legs' and the sense board's (the servos' goals and states, read and written at every step,
were 45 % of it). The operator's commands (place, stand, status) go over a pipe.
"""

from __future__ import annotations

import multiprocessing
import os
import select
import threading
from multiprocessing import shared_memory

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import GroundTruth

PHYSICS_NICE = 10    # below every thread at normal priority on the machine: tty workers preempt it at once
START_TIMEOUT_S = 60.0
REPLY_TIMEOUT_S = 5.0
# the child's requests to the bridge, and the bridge's answer to a fetch
FETCH, PUBLISH, FETCH_ARMS, PUBLISH_ARMS, DONE = b"f", b"p", b"g", b"a", b"k"
READ_TRIES = 1000  # copies of a shared block before a reader gives up on a writer that died mid-write
FETCH_TIMEOUT_S = 0.1  # a bridge that does not answer (its process gone): the step goes on with the last commands


def _layout(config: RobotConfig) -> tuple[dict[str, int], dict[str, int]]:
    n, a = config.n_joints, len(config.arms.names)
    world = {"m": n, "md": n, "tau": n, "accel": 3, "gyro": 3, "contacts": 4, "arm_q": a, "arm_qd": a}
    command = {"tau": n, "enabled": 1, "all_off": 1, "arm_goal": a, "arm_on": a}
    return world, command


class _Block:
    """Named float64 arrays in one shared-memory block, written by one side and read by the other: a counter before
    the arrays is odd while a write is under way, so a reader copies until it reads the same even count on both
    sides of its copy (a torn read is retried, never used)."""

    def __init__(self, fields: dict[str, int], name: str | None = None):
        size = 8 * (1 + sum(fields.values()))
        self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=size)
        self._owner = name is None
        buf = np.ndarray((size // 8,), dtype=np.float64, buffer=self.shm.buf)
        if self._owner:
            buf[:] = 0.0
        self._seq = buf[:1]
        self.arrays, k = {}, 1
        for key, width in fields.items():
            self.arrays[key] = buf[k:k + width]
            k += width

    @property
    def name(self) -> str:
        return self.shm.name

    def write(self, **values) -> None:
        self._seq[0] += 1
        for key, value in values.items():
            self.arrays[key][:] = value
        self._seq[0] += 1

    def read(self) -> dict[str, np.ndarray] | None:
        """A consistent copy, or None when READ_TRIES copies all met a write under way (the writer died mid-write:
        the caller keeps its last copy). Each side reads only when the other has said its write is done, so a
        retry is rare."""
        for _ in range(READ_TRIES):
            before = self._seq[0]
            if before % 2 == 0:
                copy = {key: array.copy() for key, array in self.arrays.items()}
                if self._seq[0] == before:
                    return copy
        return None

    def close(self) -> None:
        self._seq = None
        self.arrays = {}
        self.shm.close()
        if self._owner:
            self.shm.unlink()


# -- the child's side: the emulators as the plant sees them, backed by the shared blocks ---------------------------
class _Exchange:
    """The child's end of the per-step exchange: `fetch` asks the bridge for the commands of this moment (the legs',
    or with FETCH_ARMS the servos') and waits for them; `publish` tells it a new measurement is in `WORLD` (the legs'
    and the sense board's, or with PUBLISH_ARMS the servos'; it does not wait)."""

    def __init__(self, world: _Block, command: _Block, request, answer):
        self.world, self.command = world, command
        self._request, self._answer = request.fileno(), answer.fileno()
        self._keep = (request, answer)  # the connections own the file descriptors
        self.commands = command.read()  # the newest fetched

    def fetch(self, what: bytes = FETCH) -> dict[str, np.ndarray]:
        try:
            os.write(self._request, what)
            if select.select([self._answer], [], [], FETCH_TIMEOUT_S)[0]:
                os.read(self._answer, 64)
        except OSError:  # the devices' process is gone: nothing more to fetch
            return self.commands
        self.commands = self.command.read() or self.commands
        return self.commands

    def publish(self, what: bytes = PUBLISH) -> None:
        try:
            os.write(self._request, what)
        except OSError:
            pass


class _Legs:
    def __init__(self, exchange: _Exchange):
        self.exchange = exchange
        self.lock = None

    def torques(self, m, md):
        c = self.exchange.fetch()  # the law ran on this measurement (the newest published) in the bridge
        return c["tau"], bool(c["enabled"][0]), bool(c["all_off"][0])

    def publish(self, m, md, tau_m) -> None:
        self.exchange.world.write(m=m, md=md, tau=tau_m)


class _Sense:
    def __init__(self, exchange: _Exchange):
        self.exchange = exchange

    def set_measurement(self, accel=None, gyro=None, contacts=None) -> None:
        self.exchange.world.write(**{k: v for k, v in (("accel", accel), ("gyro", gyro), ("contacts", contacts))
                                     if v is not None})


class _Servos:
    def __init__(self, exchange: _Exchange):
        self.exchange = exchange

    def goal_joint_positions(self) -> np.ndarray:
        return self.exchange.fetch(FETCH_ARMS)["arm_goal"]  # the servos' goals of this moment, at the arms' step

    def torque_enabled_all(self) -> np.ndarray:
        return self.exchange.fetch(FETCH_ARMS)["arm_on"] > 0.5

    def set_joint_state(self, q, qd=None) -> None:
        self.exchange.world.write(arm_q=q, arm_qd=0.0 if qd is None else qd)
        self.exchange.publish(PUBLISH_ARMS)


def _child(config: RobotConfig, world_name: str, command_name: str, pipe, request, answer, nice: int) -> None:
    """The physics process: normal priority at `nice`, `Plant` stepping on its thread, the operator's commands on
    this one."""
    from bruce_hw.emulation.plant import Plant, leave_real_time

    leave_real_time()  # spawned from a real-time thread, which it inherits
    try:
        os.nice(nice)
    except (AttributeError, OSError):
        pass
    world_fields, command_fields = _layout(config)
    world, command = _Block(world_fields, world_name), _Block(command_fields, command_name)
    exchange = _Exchange(world, command, request, answer)
    plant = Plant(config, legs=_Legs(exchange), dynamixel=_Servos(exchange), sense=_Sense(exchange),
                  after_step=exchange.publish)
    exchange.publish()  # the held standing pose
    plant.start()
    pipe.send("ready")
    try:
        while True:
            what, arg = pipe.recv()
            if what == "close":
                break
            if what == "place":
                plant.place()
                exchange.publish()
                pipe.send(None)
            elif what == "stand":
                plant.stand(arg)
                exchange.publish()
                pipe.send(None)
            elif what == "status":
                pipe.send(plant.status())
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        plant.close()
        world.close()
        command.close()


# -- the devices' side ---------------------------------------------------------------------------------------------
class PhysicsProcess:
    """`Plant`'s surface for `EmulatedRobot` and `bruce-emulate` (start, close, place, stand, status; ground_truth,
    steps, held for the tests), with the physics in a child process and a bridge thread here."""

    def __init__(self, config: RobotConfig, *, legs=None, dynamixel=None, sense=None, nice: int = PHYSICS_NICE):
        self.config, self.legs, self.dynamixel, self.sense = config, legs, dynamixel, sense
        world_fields, command_fields = _layout(config)
        self._world, self._command = _Block(world_fields), _Block(command_fields)
        self._pipe, child_pipe = multiprocessing.Pipe()
        # The per-step exchange: the child's requests (FETCH, PUBLISH) and the bridge's answers, one byte each.
        self._request_r, self._request_w = multiprocessing.Pipe(duplex=False)
        self._answer_r, self._answer_w = multiprocessing.Pipe(duplex=False)
        self._lock = threading.Lock()  # one operator request at a time on the pipe
        context = multiprocessing.get_context("spawn")  # never fork a process with threads
        self.process = context.Process(target=_child, name="bruce-physics", daemon=True,
                                       args=(config, self._world.name, self._command.name, child_pipe,
                                             self._request_w, self._answer_r, nice))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._bridge, name="physics-bridge", daemon=True)
        self.bridge_cycles = 0
        self._final: dict | None = None  # the last status, kept by close() for the shutdown's summary

    def start(self) -> PhysicsProcess:
        self.process.start()
        if not self._pipe.poll(START_TIMEOUT_S) or self._pipe.recv() != "ready":
            self.close()
            raise RuntimeError(f"the physics process did not start in {START_TIMEOUT_S:g} s")
        self._thread.start()
        return self

    def _bridge(self) -> None:
        """At the devices' priority, woken by the child: PUBLISH hands the newest measurement to the legs' and the
        sense board's emulators; FETCH runs the legs' torque law on it with the devices' commands of this moment,
        writes the torques to `COMMAND` and answers; at the arms' steps, PUBLISH_ARMS hands the servos what they
        measure and FETCH_ARMS writes their goals and answers. The child steps only after the answer, so reading the
        commands at each step also runs the BEARs' watchdogs between packets, and the arms' reads the servos' at
        50 Hz, as in one process."""
        legs, servos, sense = self.legs, self.dynamixel, self.sense
        request, answer = self._request_r.fileno(), self._answer_w.fileno()
        w = self._world.read()
        zeros = np.zeros(self.config.n_joints)
        while not self._stop.is_set():
            if not select.select([request], [], [], 0.05)[0]:
                continue
            try:
                asked = os.read(request, 64)
            except OSError:
                return
            if not asked:  # the child is gone
                return
            w = self._world.read() or w  # the child wrote it before asking: complete unless it died mid-way
            if PUBLISH in asked:
                if legs is not None:
                    legs.publish(w["m"], w["md"], w["tau"])
                if sense is not None:
                    sense.set_measurement(accel=w["accel"], gyro=w["gyro"], contacts=w["contacts"] > 0.5)
            if PUBLISH_ARMS in asked and servos is not None:
                servos.set_joint_state(w["arm_q"], w["arm_qd"])
            answers = 0
            if FETCH in asked:
                if legs is not None:
                    tau, enabled, all_off = legs.torques(w["m"], w["md"])
                else:
                    tau, enabled, all_off = zeros, False, True
                self._command.write(tau=tau, enabled=float(enabled), all_off=float(all_off))
                self.bridge_cycles += 1
                answers += asked.count(FETCH)
            if FETCH_ARMS in asked:
                if servos is not None:
                    self._command.write(arm_goal=servos.goal_joint_positions(),
                                        arm_on=servos.torque_enabled_all().astype(float))
                answers += asked.count(FETCH_ARMS)
            if answers:
                try:
                    os.write(answer, DONE * answers)
                except OSError:
                    return

    def _ask(self, what: str, arg=None):
        with self._lock:
            self._pipe.send((what, arg))
            if not self._pipe.poll(REPLY_TIMEOUT_S):
                raise RuntimeError(f"the physics process did not answer {what!r} in {REPLY_TIMEOUT_S:g} s")
            return self._pipe.recv()

    def place(self) -> None:
        self._ask("place")

    def stand(self, on: bool) -> None:
        self._ask("stand", bool(on))

    def status(self) -> dict:
        """Counters, the arms and the ground truth; after close(), those it had then."""
        if self._final is None and not self.process.is_alive():  # it ended on its own: nothing more to ask
            self._final = {"steps": 0, "late_steps": 0, "skipped_steps": 0, "held": True,
                           "arm_q": np.zeros(len(self.config.arms.names)), "truth": None,
                           "nominal_base_height": float("nan")}
        if self._final is not None:
            return self._final
        return self._ask("status")

    def ground_truth(self) -> GroundTruth:
        return self.status()["truth"]

    @property
    def nominal_base_height(self) -> float:
        return self.status()["nominal_base_height"]

    @property
    def steps(self) -> int:
        return self.status()["steps"]

    @property
    def held(self) -> bool:
        return self.status()["held"]

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        if self.process.is_alive():
            try:
                self._final = self._ask("status")
            except (OSError, EOFError, RuntimeError):
                pass
            try:
                self._pipe.send(("close", None))
            except (OSError, ValueError):
                pass
            self.process.join(timeout=3.0)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(timeout=2.0)
        for connection in (self._request_r, self._request_w, self._answer_r, self._answer_w):
            connection.close()
        if self._world is not None:
            self._world.close()
            self._command.close()
            self._world = self._command = None

    def __enter__(self) -> PhysicsProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
