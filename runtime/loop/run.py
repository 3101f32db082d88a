"""One `bruce-run` session: start-up, the 1 kHz read -> update -> write loop, and shutdown on every exit path.

Start-up follows the robot: configure (inactive, reads only) -> load and check the models, warm up their
sessions -> read the measured pose -> start telemetry -> ask for real-time scheduling -> activate -> loop.
A tick: read -> safety triggers -> policy (once per policy period on the backend's clock) -> Eq. 8 -> transfer scheme
(runtime/transfer/: direct, the paper's Eq. 9 on the PINN, ...; with a reference model, the gap monitor
scores its last prediction) -> safety filter -> write -> telemetry -> observers (`runtime.loop.observers`: evaluation
and recording, outside every timed section; they may end the run, never change what is sent). A trip of the safety
stage (or SIGINT/SIGTERM) puts the backend into its damping state at once and holds it for `safety.damping_hold_s`
while still reading; the end of `--duration` shuts the backend down (through damping). The nominal controller is
the ONNX policy, the model-based walking teacher or the standing controller (`CONTROLLERS`); a command schedule
(`runtime.control.commands`) gives it its velocity command on every policy tick. Every exit prints a summary and,
with `--stats`, writes it as JSON; on the mock it includes the ground truth the observers gathered: height, fall,
and how well the base velocity tracked the command. Garbage collection is frozen and disabled inside the loop:
the loop's allocations are acyclic and freed by reference counting.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import queue
import sys
import time
from dataclasses import asdict, dataclass, field
from logging.handlers import QueueHandler, QueueListener
from pathlib import Path

import numpy as np

from bruce_hw.backend import Backend, BackendError, LifecycleError, LifecycleState
from bruce_hw.config import RobotConfig
from bruce_hw.hw import GIL_SWITCH_INTERVAL_S
from bruce_hw.io_priority import above_the_caller
from bruce_hw.types import JointCommand, RobotState
from runtime.control.controller_runner import InlineControllerRunner, make_controller_runner
from runtime.control.controllers import build_controller
from runtime.control.inference import ModelError, OnnxPinn
from runtime.control.mixing import eq8_torque
from runtime.estimation import Estimator, GroundTruthEstimator, tilt_angle
from runtime.estimation.estimators import make_estimator
from runtime.loop.exit import FAULT_CLASSES, NOTHING_ENABLED, ExitCode, StopFlag, StopRequested
from runtime.loop.falls import FALL_TILT_RAD
from runtime.loop.loopstats import LoopStats
from runtime.loop.observers import GroundTruthLog, TickObserver, TickView, ground_truth_observers
from runtime.loop.pacing import Pacer
from runtime.loop.realtime import RealtimeGrant, helper_threads, request_realtime
from runtime.loop.safety import SafetyStage, SafetyState
from runtime.transfer.gap_monitor import GapMonitor
from runtime.transfer.interface import TransferScheme
from runtime.transfer.schemes import build_scheme
from runtime.transfer.shadow_stepper import InlineShadowStepper
from runtime.transfer.stage import settings_for

AT_REST_QD = 0.05            # rad/s: the damping hold ends early once every joint is this slow ...
AT_REST_TICKS = 100          # ... for this many ticks in a row
# Controllers fold torque into their targets (a = q + tau / Kp: the standing controller's ankles, the teacher's
# feed-forward), so a target may leave the joint range. One further than this many times torque_limit / Kp beyond
# the range asks for more torque than the joint has wherever the joint is: the model is broken (refused before the
# motors are enabled, a safety trip after).
TARGET_TORQUE_MULTIPLE = 2.0
# One PINN tick moves q by qd dt (~0.01 rad): a prediction a whole joint range outside the limits, or faster than
# this many times the velocity limit, is a broken model.
PINN_RANGE_MULTIPLE = 1.0
PINN_VELOCITY_MULTIPLE = 2.0


@dataclass
class RunSummary:
    backend: str
    transfer: str = "direct"
    wall_time: float = 0.0
    realtime: bool = False
    final_state: str = "unconfigured"
    stop_cause: str | None = None
    error: str | None = None
    telemetry_dropped: int = 0
    loop: LoopStats = field(default_factory=LoopStats)
    realtime_grant: RealtimeGrant | None = None
    truth: GroundTruthLog | None = None
    exit_code: int = ExitCode.OK
    fault_class: str | None = None   # input, safety, bus, internal (runtime.loop.exit.ExitCode); None: a normal end
    link: dict | None = None         # the backend's bus figures (hw: cycles, lost replies per ID)
    gap: GapMonitor | None = None    # the live gap monitor, with a transfer scheme that has a reference model
    robot_faithful: bool = True      # the control path saw only what a robot measures (not the simulator's truth)
    scheme_report: dict = field(default_factory=dict)  # the transfer scheme's own figures (TransferScheme.report)
    controller: dict | None = None   # where the nominal controller ran and what it cost (controller_runner.report)

    def end(self, code: ExitCode, cause: str | None = None) -> None:
        """Record how the run ended (the first fault wins)."""
        if self.fault_class is None:
            self.exit_code = int(code)
            self.fault_class = FAULT_CLASSES.get(code)
        if cause and self.stop_cause is None:
            self.stop_cause = cause

    @property
    def ticks(self) -> int:
        return self.loop.ticks

    def to_json(self) -> dict:
        out = {k: v for k, v in asdict(self).items()
               if k not in ("truth", "loop", "realtime_grant", "gap", "scheme_report")}
        out.update(self.scheme_report)
        out["exit_code"] = int(self.exit_code)
        out.update(self.loop.to_json())
        out["realtime_grant"] = self.realtime_grant.to_json() if self.realtime_grant else None
        if self.truth is not None:
            out.update(self.truth.to_json())
        if self.gap is not None:
            out.update(self.gap.to_json())
        return out

    def text(self) -> str:
        lines = [f"bruce-run: {self.backend} backend, transfer {self.transfer}, {self.ticks} ticks in "
                 f"{self.wall_time:.2f} s wall"]
        if self.truth is not None:
            t = self.truth
            speed = t.sim_time / self.wall_time if self.wall_time > 0 else float("nan")
            lines.append(f"  simulated {t.sim_time:.3f} s ({speed:.1f}x real time)")
            if self.ticks:
                lines.append(f"  base height {t.base_height_min:.3f}..{t.base_height_max:.3f} m "
                             f"(nominal {t.nominal_base_height:.3f} m), fell: {'yes' if t.fell else 'no'}")
            if t.tracking.samples:
                lines.append(t.tracking.text())
        lines.append(self.loop.text())
        runner = self.controller
        if runner and runner["lag_ticks"]:
            cpu = runner["cpu_us"] or {}
            inside = "in" if runner["runs_on"] == InlineControllerRunner.where else "not in"
            lines.append(f"  controller: on {runner['runs_on']}, its targets {runner['lag_ticks']} tick(s) after its "
                         f"reading; {runner['calls']} calls, CPU p50 {cpu.get('p50') or 0:.0f} / p99 "
                         f"{cpu.get('p99') or 0:.0f} µs each ({inside} the tick's); {runner['late_ticks']} ticks "
                         f"waited for targets due (worst {runner['worst_late_ticks']} ticks late)")
        shadow = self.scheme_report.get("shadow")
        if shadow and shadow["steps_on"] != InlineShadowStepper.where:
            lines.append(f"  shadow: its model steps on {shadow['steps_on']}; {shadow['late']} answers not back in "
                         f"time, {shadow['skipped']} ticks not asked (a step still running): resynchronised instead")
        legs = (self.link or {}).get("legs", {})
        if "replies_lost" in legs:
            lost = {i: n for i, n in legs["replies_lost"].items() if n}
            cycle = legs.get("bus_cycle_us") or {}
            timing = (f" (bus thread: {cycle['rate_hz'] or 0:.0f}/s, cycle p50 {cycle['p50']:.0f} / p99 "
                      f"{cycle['p99']:.0f} / max {cycle['max']:.0f} µs)") if cycle.get("p50") is not None else ""
            lines.append(f"  {legs['bus']}: {legs['cycles']} cycles{timing}, {legs['replies_lost_total']} replies lost "
                         f"({100 * legs['reply_loss_share']:.2f} %)"
                         + (": " + ", ".join(f"ID {i} {n}" for i, n in lost.items()) if lost else "")
                         + (f"; {legs['replies_late']} taken late" if legs.get("replies_late") else ""))
        stalls = (self.link or {}).get("host_stalls")
        if stalls is not None:
            lines.append(f"  host: {stalls['count']} stalls (this process not run for over 2 ms: worst "
                         f"{stalls['worst_ms']:.1f} ms, {stalls['total_ms']:.0f} ms in all)")
        if self.gap is not None and self.gap.samples:
            rms = self.gap.to_json()["gap_residual_rms"]
            worst = max(rms, key=rms.get)
            lines.append(f"  gap monitor: one-step velocity residual RMS, worst {worst} {rms[worst]:.3g} rad/s, "
                         f"median {float(np.median(list(rms.values()))):.3g} rad/s over {self.gap.samples} ticks"
                         + (f", {self.gap.warnings} warnings" if self.gap.warnings else ""))
        if self.telemetry_dropped:
            lines.append(f"  telemetry: {self.telemetry_dropped} rows dropped (buffer full)")
        cause = f" ({self.stop_cause})" if self.stop_cause else ""
        lines.append(f"  final state: {self.final_state}{cause}; exit code {int(self.exit_code)}"
                     + (f" ({self.fault_class})" if self.fault_class else ""))
        if self.error and self.error.partition(": ")[2] != self.stop_cause:  # else the final state says it
            lines.append(f"  error: {self.error}")
        return "\n".join(lines)


class LogRelay:
    """The control thread's log lines go through a queue to a listener thread, never straight to a stream."""

    LOGGERS = ("runtime", "bruce_hw")

    def __init__(self):
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        targets = logging.getLogger().handlers or [logging.StreamHandler(sys.stderr)]
        self.listener = QueueListener(self.queue, *targets, respect_handler_level=True)
        self.saved = []

    def __enter__(self) -> LogRelay:
        handler = QueueHandler(self.queue)
        for name in self.LOGGERS:
            logger = logging.getLogger(name)
            self.saved.append((logger, logger.handlers[:], logger.propagate, logger.level))
            logger.handlers, logger.propagate = [handler], False
            if logger.level == logging.NOTSET:
                logger.setLevel(logging.INFO)
        self.listener.start()
        return self

    def __exit__(self, *exc) -> None:
        self.listener.stop()  # drains what is queued
        for logger, handlers, propagate, level in self.saved:
            logger.handlers, logger.propagate, logger.level = handlers, propagate, level


def build_gap_monitor(config: RobotConfig, scheme: TransferScheme) -> GapMonitor | None:
    """The live gap monitor of a scheme that has a reference model (None for direct transfer)."""
    if scheme.reference is None:
        return None
    settings = settings_for(config).gap_monitor
    return GapMonitor(config.joints, max(1, round(settings.window_s * config.loop_hz)), settings.warn_rms)


def target_bounds(config: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the targets a working controller can give (see TARGET_TORQUE_MULTIPLE)."""
    reach = TARGET_TORQUE_MULTIPLE * config.tau_limit / np.maximum(config.eq8.kp, 1e-9)
    return config.q_lower - reach, config.q_upper + reach


def check_models(config: RobotConfig, controller, name: str, pinn: OnnxPinn | None, robot: RobotState,
                 estimator: Estimator) -> None:
    """Before the motors are enabled: the controller on the measured state (zero command) and one PINN step from it
    must give finite values within physical ranges (targets within `target_bounds`;
    PINN q within PINN_RANGE_MULTIPLE joint ranges of the limits, qd within PINN_VELOCITY_MULTIPLE velocity
    limits). Raises ModelError naming the model, the joint and the value. Leaves the models reset."""
    q, qd = robot.joints.q, robot.joints.qd
    controller.reset(q)
    estimator.reset(robot)
    estimator.update(robot)
    a = np.asarray(_refusing(controller, robot, estimator.estimate(), np.zeros(3)), dtype=np.float64)
    _check_range(config, f"{name}: warm-up on the measured pose: target", a, *target_bounds(config),
                 f"joints.position_limits widened by {TARGET_TORQUE_MULTIPLE:g} x torque_limit / Kp")
    if pinn is not None:
        pinn.reset()
        q_hat, qd_hat = _refusing(pinn.step, q, qd, eq8_torque(a, q, qd, config.eq8))
        span = PINN_RANGE_MULTIPLE * (config.q_upper - config.q_lower)
        what = f"PINN model {pinn.path}: warm-up on the measured pose"
        _check_range(config, f"{what}: q_next", q_hat, config.q_lower - span, config.q_upper + span,
                     f"joints.position_limits widened by {PINN_RANGE_MULTIPLE:g} joint range")
        limit = PINN_VELOCITY_MULTIPLE * config.qd_limit
        _check_range(config, f"{what}: qd_next", qd_hat, -limit, limit,
                     f"{PINN_VELOCITY_MULTIPLE:g} x joints.velocity_limits")
        pinn.reset()
    controller.reset(q)
    estimator.reset(robot)


def _refusing(call, *args):
    try:
        return call(*args)
    except ModelError as exc:
        raise ModelError(f"{exc} on the measured pose; refused before the motors were enabled") from None


def first_outside(values: np.ndarray, low: np.ndarray, high: np.ndarray) -> int | None:
    """Index of the first value outside [low, high] (NaN included), or None."""
    inside = (values >= low) & (values <= high)  # NaN fails both
    return None if inside.all() else int(np.argmin(inside))


def _check_range(config: RobotConfig, what: str, values: np.ndarray, low: np.ndarray, high: np.ndarray,
                 bound: str) -> None:
    if values.shape != (config.n_joints,):
        raise ModelError(f"{what}: expected {config.n_joints} values, got shape {values.shape}")
    i = first_outside(values, low, high)
    if i is not None:
        raise ModelError(f"{what} {values[i]:.4g} for {config.joints[i]} outside [{low[i]:.3g}, {high[i]:.3g}] "
                         f"({bound}); refused before the motors were enabled")


def stats_path_error(path: Path) -> str | None:
    """Why `--stats PATH` could not be written, checked before anything moves (None: it can): its folder is made
    and the file opened for appending, as the summary's write at the end will."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("a"):
            pass
    except OSError as exc:
        return f"--stats {path}: cannot be written ({exc.strerror or exc})"
    return None


def write_stats(summary: RunSummary, path: Path | None) -> None:
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary.to_json(), indent=2) + "\n")


def exit_code_of(exc: BaseException) -> ExitCode:
    """The exit code of a run that ended with `exc`. Refused inputs are ValueErrors (ConfigError, GapError, a bad
    option), ModelErrors or TelemetryErrors (a sink that cannot be opened)."""
    from runtime.telemetry import TelemetryError  # rerun itself loads only when telemetry starts

    if isinstance(exc, StopRequested | KeyboardInterrupt):
        return ExitCode.OK
    if isinstance(exc, ValueError | ModelError | TelemetryError):
        return ExitCode.BAD_INPUT
    if isinstance(exc, BackendError):
        return ExitCode.BUS_FAULT
    return ExitCode.INTERNAL


def run_session(backend: Backend, config: RobotConfig, *, duration: float | None, realtime: bool,
                stats_path: Path | None = None, transfer: str = "direct", policy: Path | None = None,
                pinn: Path | None = None, rerun=None, controller=None, controller_kind: str = "policy",
                estimator: str | Estimator | None = None, commands=None,
                observers: list[TickObserver] | tuple[TickObserver, ...] = (),
                stop: StopFlag | None = None, privileged: bool = False) -> RunSummary:
    """Run one session. `rerun` is a `runtime.telemetry.RerunSink` (None: no telemetry); `controller_kind` picks
    the nominal controller (`build_controller`), and `controller` replaces it (anything with reset(q) and
    __call__(state, base, command) -> a); `estimator` is an estimator kind (`estimation.estimators.ESTIMATORS`) or
    an `Estimator` (default: the truth where the backend has one, else the kinematic estimator); `commands` has
    `at(t) -> (vx, vy, yaw rate)` for t in seconds since activation, e.g. a `runtime.control.commands.CommandSchedule`
    (default: stand still). `observers` (`runtime.loop.observers.TickObserver`, e.g. `training.collect`'s recorder) see
    every tick after the write, outside the timed sections, after the mock's own ground-truth observers (which fill
    `summary.truth`); a non-empty string one returns ends the run after that tick, as the end of `duration` does,
    with that string as the stop cause. A run is robot-faithful (`summary.robot_faithful`: the simulator's truth is
    sealed to all but the observers, `Backend.truth_sealed`) unless the estimator is `truth` or the controller is
    `privileged` (a training teacher that plans on the simulator's truth).

    SIGINT/SIGTERM (`stop`, installed here if not given) before activation end start-up at once with nothing
    enabled (the summary says so, exit code 0, nothing raised); after, the loop ends through damping. Every model is
    checked on the measured state before the motors are enabled (`check_models`). The summary's `exit_code` and
    `fault_class` say how the run ended (runtime.loop.exit.ExitCode); the stats are written on every path. Errors are
    re-raised after the summary is written (StopRequested is not an error)."""
    summary = RunSummary(backend=backend.name, realtime=realtime, transfer=transfer)
    stop = stop or StopFlag()
    stop.abort = False  # until the try below, which arms it: nothing outside it may be cut short
    stop.install()
    relay = LogRelay().__enter__()
    wall_start = time.perf_counter()
    grant: RealtimeGrant | None = None
    telemetry = None
    scheme: TransferScheme | None = None
    runner = None
    switch_interval: float | None = None
    activating = False  # from here on a motor may be enabled: a failure must end in damping
    try:
        stop.arm()
        backend.configure()
        robot = backend.read()
        watching = list(observers)
        has_truth = backend.ground_truth() is not None
        if has_truth:
            summary.truth = GroundTruthLog(nominal_base_height=backend.nominal_base_height)
            watching[:0] = ground_truth_observers(summary.truth)
        if estimator is None or isinstance(estimator, str):
            kind = estimator or ("truth" if has_truth else "kinematic")
            estimator = make_estimator(kind, backend, config)
        # Robot-faithful unless the controller is fed the simulator's truth (a labelled diagnostic): then nothing but
        # the observers may read the truth, and a read anywhere else raises (Backend.truth_sealed).
        summary.robot_faithful = not (privileged or isinstance(estimator, GroundTruthEstimator))
        sealed = has_truth and summary.robot_faithful
        backend.truth_sealed = sealed
        # A twin scheme runs a second instance of the robot's own nominal controller (a controller object passed in
        # cannot be copied: its twin gets the configured policy).
        twin_controller = None if controller is not None else (
            lambda: build_controller(config, policy, controller_kind)[0])
        scheme = build_scheme(config, transfer, pinn, base_state=None if summary.robot_faithful else
                              backend.ground_truth, twin_controller=twin_controller, estimator=estimator,
                              paced=realtime)
        summary.gap = build_gap_monitor(config, scheme)
        pinn_runner = None if scheme.reference is None else scheme.reference.pinn  # checked on the measured pose below
        if controller is None:
            controller, controller_name = build_controller(config, policy, controller_kind)
        else:
            controller_name = type(controller).__name__
        runner = make_controller_runner(controller, config.policy_lag_ticks, paced=realtime)
        if rerun is not None:
            from runtime.telemetry import make_telemetry  # rerun-sdk loads only when telemetry is on

            telemetry = make_telemetry(config, rerun, model=backend.model,
                                       gap=summary.gap is not None)
        if telemetry is not None:
            telemetry.start()  # its threads start before the loop thread asks for real-time scheduling
        if realtime:
            grant = summary.realtime_grant = request_realtime()
            # The threads beside the loop (the controller's, the twin's) hold the GIL through their Python; the
            # control thread waits at most the switch interval for it (CPython's default, 5 ms, is five ticks).
            switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(switch_interval, GIL_SWITCH_INTERVAL_S))
        # Collect before the motors are enabled: in a large process a full collection takes up to a second, and
        # an enabled robot would stand that long on its last (zero) command.
        gc.collect()
        gc.freeze()
        check_models(config, controller, controller_name, pinn_runner, robot, estimator)
        # From here a signal only sets the flag: the loop brings the robot down through damping.
        stop.abort = False
        if stop.cause is not None:  # came while `abort` was being cleared
            raise StopRequested(f"{stop.cause} received")
        controller.reset(robot.joints.q)
        runner.reset()
        runner.start()  # before the loop, as the twin's: a thread's first start costs the tick that makes it
        estimator.reset(robot)
        scheme.reset()
        activating = True
        backend.activate()  # the last step before the loop: the first tick's reading is as fresh as it can be
        if grant is not None and grant.scheduler.startswith("SCHED_FIFO"):
            others = helper_threads()
            priority, restore = above_the_caller(others)
            grant._restore.insert(0, restore)  # undone last: after the loop thread's own scheduling
            grant.helpers = f"{len(others)} other threads at SCHED_FIFO {priority}" if priority else None
        until = "until Ctrl-C" if duration is None else f"for {duration:g} s"
        commanded = "" if commands is None else f", {getattr(commands, 'name', type(commands).__name__)}"
        print(f"bruce-run: {backend.name} backend active, {controller_name}{commanded}, transfer {transfer}, {until}"
              f"{' (paced to the wall clock)' if realtime else ''}", flush=True)
        if grant is not None:
            print(f"bruce-run: {grant.text()}", flush=True)
        gc.disable()
        _loop(backend, config, runner, robot.joints.q, estimator, commands, scheme, telemetry, summary, stop,
              duration, realtime, tuple(watching), sealed)
        summary.final_state = backend.state.value
        if backend.state is LifecycleState.FAULT:
            summary.final_state = f"{backend.state.value}: damping"
    except StopRequested as exc:
        stop.abort = False  # a second signal must not cut the shutdown below short
        summary.end(ExitCode.OK, f"{exc} {NOTHING_ENABLED}")
        _settle(backend, summary)
    except BaseException as exc:
        stop.abort = False
        summary.error = f"{type(exc).__name__}: {exc}"
        summary.end(exit_code_of(exc), str(exc))
        # Refused during start-up (a model file, a scheme): nothing was enabled, so nothing to damp ("inactive").
        if activating and backend.state not in (LifecycleState.UNCONFIGURED, LifecycleState.FAULT):
            backend.fault(summary.error)
        _settle(backend, summary)
        raise
    finally:
        stop.abort = False
        gc.enable()
        gc.unfreeze()
        summary.wall_time = time.perf_counter() - wall_start
        backend.truth_sealed = False
        try:
            if runner is not None:
                runner.close()
                summary.controller = runner.report()
            if scheme is not None:
                scheme.close()
                summary.scheme_report = scheme.report()
            if grant is not None:
                grant.release()
            if switch_interval is not None:
                sys.setswitchinterval(switch_interval)
            if telemetry is not None:
                telemetry.close()
                summary.telemetry_dropped = telemetry.dropped
            if backend.state is not LifecycleState.UNCONFIGURED:
                summary.link = backend.link_report()
            backend.shutdown()
        finally:
            stop.restore()
            relay.__exit__(None, None, None)
            write_stats(summary, stats_path)  # before printing: nothing may keep the stats from being written
            print(summary.text(), file=sys.stderr if summary.error else sys.stdout, flush=True)
    return summary


def _settle(backend: Backend, summary: RunSummary) -> None:
    summary.final_state = f"{backend.state.value}: damping" if backend.state is LifecycleState.FAULT \
        else backend.state.value


def _loop(backend: Backend, config: RobotConfig, runner: InlineControllerRunner, start_pose: np.ndarray,
          estimator: Estimator, commands, scheme: TransferScheme, telemetry, summary: RunSummary, stop: StopFlag,
          duration: float | None, realtime: bool, observers: tuple[TickObserver, ...] = (),
          sealed: bool = False) -> None:
    """The ticks. `runner` runs the nominal controller; until its first targets are in force (`rates.policy_lag_ticks`
    > 0) the targets are `start_pose`, the pose it was reset to. `sealed`: the backend's truth is sealed, and opened
    only while the observers run."""
    stats = summary.loop  # each section timed on the wall clock and on the thread's CPU clock (the loop's own cost)
    stats.period_s = config.dt
    safety = SafetyStage(config, stalled=backend.stalled_between, joint_stalled=backend.joint_stalled_between)
    n_ticks = None if duration is None else round(duration * config.loop_hz)
    # The policy runs on the backend's clock, once per policy period from the first tick: a missed deadline does not
    # slow the gait clock or the command schedule (docs/timing.md).
    policy_period_us = round(1e6 / config.policy_hz)
    policy_period = -1
    first_now = None
    eq8 = config.eq8
    gap = summary.gap
    poses = telemetry is not None and backend.body_poses() is not None
    witnessed, last_now = backend.host_witness, backend.clock()  # host stalls go to the telemetry's events
    pose_every = telemetry.pose_decimation if telemetry is not None else 0
    events_sent = 0
    clock0 = backend.clock()
    view = TickView(backend, clock0)
    view.scheme, view.safety, view.gap = scheme, safety, gap
    backend.truth_sealed = False
    for observer in observers:
        observer.on_start(backend, config)
    backend.truth_sealed = sealed
    perf = time.perf_counter_ns
    cpu = time.thread_time_ns  # the control thread's own CPU clock (stats.cpu)
    pacer = Pacer(config.dt)
    late_ns = pacer.late_ns
    stats.late_after_s = late_ns / 1e9
    pacer.start()
    tick, previous_start, first_start = 0, 0, 0
    c0 = 0
    a = np.array(start_pose, dtype=np.float64)
    residual = None  # the gap monitor's residual this tick (None: no monitor, or no prediction to score)
    observer_stop = None
    standstill = np.zeros(3)
    command = standstill
    a_low, a_high = target_bounds(config)
    try:
        while stop.cause is None and (n_ticks is None or tick < n_ticks):
            if realtime:
                behind = pacer.wait()
                if behind > late_ns:
                    # The loop's own share: its CPU time since the previous tick's start beyond one period (late
                    # even had that tick started on time and run without a pause); lateness it inherited from a
                    # late start is not its own.
                    stats.overrun(behind, time.monotonic(), cpu() - c0 - pacer.period_ns if tick else None)
            c0 = cpu()
            t0 = perf()
            robot = backend.read()
            t1, c1 = perf(), cpu()
            now = backend.clock()  # read once: the age check and the telemetry timeline share it
            stats.data_age.add(max(0, int(1e9 * (now - min(robot.joints.stamp, robot.imu.stamp)))))
            safety.check(robot, now)
            if safety.tripped:
                break
            q, qd = robot.joints.q, robot.joints.qd
            estimator.update(robot)
            if first_now is None:
                first_now = now
            period_now = round(1e6 * (now - first_now)) // policy_period_us
            if period_now != policy_period:
                policy_period = period_now
                command = scheme.steer(standstill if commands is None else commands.at(now - clock0))
                runner.post(tick, robot, estimator.estimate(), command)
            try:
                targets = runner.targets(tick)
            except ModelError as exc:
                safety.trip(str(exc))
                break
            if targets is not None:
                i = first_outside(targets, a_low, a_high)
                if i is not None:
                    safety.trip(f"controller target {targets[i]:.4g} rad for {config.joints[i]} outside "
                                f"[{a_low[i]:.3g}, {a_high[i]:.3g}] (asks more than {TARGET_TORQUE_MULTIPLE:g} x "
                                "its torque limit)")
                    break
                a = targets
            if realtime:
                pacer.breathe()  # after the costliest section: a long tick lets a worker on its CPU run
            t2, c2 = perf(), cpu()
            tau_star = eq8_torque(a, q, qd, eq8)
            t3, c3 = perf(), cpu()
            if gap is not None:  # last tick's prediction against this tick's measurement
                residual = gap.update(scheme.one_step, q, qd)
            try:
                scheme.predict(a, q, qd, tau_star, command)
            except ModelError as exc:
                safety.trip(str(exc))
                break
            t4, c4 = perf(), cpu()
            tau = scheme.torque(tau_star, q, qd)
            t5, c5 = perf(), cpu()
            tau = safety.filter(tau, robot)
            if safety.tripped:
                break
            t6, c6 = perf(), cpu()
            try:
                backend.write(JointCommand(tau_ff=tau))
            except LifecycleError:
                # The backend went to damping on its own in this tick's read without raising: the hw backend on an
                # IMU stream it judges stopped a tick ahead, or a host stall beyond the bound, where the safety stage
                # judged the same moments a little apart and did not trip. Its cause ends the run, as the stage's.
                if backend.state is not LifecycleState.FAULT:
                    raise
                safety.trip(backend.fault_cause or f"{backend.name} backend: damping")
                break
            t7, c7 = perf(), cpu()
            if telemetry is not None:
                elapsed = now - clock0
                telemetry.append(tick, elapsed, q, qd, scheme.q_hat, scheme.qd_hat, a, tau_star, tau,
                                 (t0 - previous_start) / 1e3 if tick else math.nan, (t7 - t0) / 1e3, int(safety.state),
                                 None if residual is None else (residual.qd, residual.q, gap.window_rms))
                if poses and tick % pose_every == 0:
                    telemetry.append_pose(tick, elapsed, *backend.body_poses())
                if len(safety.transitions) > events_sent:
                    for _, text in safety.transitions[events_sent:]:
                        telemetry.event(tick, elapsed, text, "info")
                    events_sent = len(safety.transitions)
                if witnessed:  # a host stall since the last tick: on the timeline, where it happened
                    stalled = backend.stalled_between(last_now, now)
                    if stalled > 0.0:
                        telemetry.event(tick, elapsed, f"host stall: not run for {1e3 * stalled:.1f} ms", "warn")
                last_now = now
            t8, c8 = perf(), cpu()
            if observers:  # evaluation only: in the tick's work, in no section
                view.fill(tick, now, robot, command, a, tau_star, tau)
                backend.truth_sealed = False
                for observer in observers:
                    cause = observer.on_tick(view)
                    if cause:
                        observer_stop = observer_stop or cause
                backend.truth_sealed = sealed
            stats.add_sections((t0, t1, t2, t3, t4, t5, t6, t7, t8), (c0, c1, c2, c3, c4, c5, c6, c7, c8))
            stats.work.add(perf() - t0)
            stats.cpu.add(cpu() - c0)
            if tick:
                stats.period.add(t0 - previous_start)
            else:
                first_start = t0
            previous_start = t0
            tick += 1
            stats.ticks = tick
            if observer_stop:
                break
    finally:  # a backend error raised from read() still leaves correct counters
        stats.late_ticks, stats.skipped_ticks, stats.breaths = pacer.late_ticks, pacer.skipped_ticks, pacer.breaths
        if realtime:  # late ticks attributed to the machine, the loop's own CPU time, or the loop not run
            stats.attribute(backend.stalled_between if backend.host_witness else None)
        if tick > 1:
            stats.loop_s = (previous_start - first_start) / 1e9
        backend.truth_sealed = False  # the evaluation after the loop reads it; the damping hold does not

    if stop.cause is not None:
        safety.trip(f"{stop.cause} received")
    if not safety.tripped:
        summary.end(ExitCode.OK, observer_stop or "duration reached")
        for observer in observers:
            observer.on_end(summary)
        return
    if stop.cause is not None:
        summary.end(ExitCode.OK, stop.cause)
    else:
        summary.end(ExitCode.SAFETY_TRIP, safety.cause)
    for observer in observers:
        observer.on_end(summary)  # the evaluation covers the controlled part of the run
    backend.fault(summary.stop_cause)
    _hold_damping(backend, config, safety, telemetry, tick, clock0, realtime)


def _hold_damping(backend: Backend, config: RobotConfig, safety: SafetyStage, telemetry, tick: int,
                  clock0: float, realtime: bool) -> None:
    """Keep reading while the backend damps, so the robot settles under observation (and it is logged)."""
    if telemetry is not None:
        telemetry.event(tick, backend.clock() - clock0, f"safety: damping: {safety.cause}", "warn")
    pacer = Pacer(config.dt)
    pacer.start()
    resting = 0
    for hold_tick in range(round(config.safety.damping_hold_s * config.loop_hz)):
        if realtime:
            pacer.wait()
        try:
            robot = backend.read()
        except BackendError:
            return  # the backend is gone; its own fault handling is all that is left
        tau = safety.filter(np.zeros(config.n_joints), robot)  # in DAMPING: the damping torque -kd qd
        if telemetry is not None:
            q, qd = robot.joints.q, robot.joints.qd
            telemetry.append(tick + hold_tick, backend.clock() - clock0, q, qd, None, None, q, tau, tau, 0.0, 0.0,
                             int(SafetyState.DAMPING))
        at_rest = np.max(np.abs(robot.joints.qd)) < AT_REST_QD and tilt_angle(robot.imu) < FALL_TILT_RAD
        resting = resting + 1 if at_rest else 0
        if resting >= AT_REST_TICKS:
            return
