"""The safety stage: always the last thing before `write()`; the torque it returns is what is sent and logged.

Per tick, in this order:
1. Triggers of the damping state, in the order they are checked (the first found is the cause): a host stall
   beyond `safety.host_stall_max_s` since the previous tick; an e-stop input (a press is the cause a person needs
   to read, but a stall that long comes first: it lets the BEARs' own watchdog set the same error bit 3); an
   achieved loop rate below `safety.min_rate_hz` over the last `safety.rate_window_s` (on the backend's clock: the
   robot's time; a late tick alone is not a fault, docs/timing.md); non-finite joint or IMU data; joint or IMU data
   older than `safety.max_sensor_age_s`; tilt beyond `safety.tilt_limit_deg` for `safety.tilt_ticks` ticks. Ages
   and the rate are judged on the time the process was run: a host stall (`stalled`, the backend's
   `stalled_between`; for the joints also the leg bus's port calls the host held, `joint_stalled`) is neither old
   data nor a slow loop, up to the bound (docs/safety.md, "Host stalls"). The loop adds its own (a model returning
   non-finite values, SIGINT or SIGTERM) through `trip()`.
2. The command filter: a non-finite torque trips; torque that pushes a joint further past a position soft
   limit (`joints.position_limits` shrunk by `safety.position_margin`) or further beyond its velocity limit is
   removed; the soft start scales torques in over `safety.torque_ramp_s`; the rate of change is limited to
   `safety.max_torque_rate`; then the per-joint clamp (`joints.torque_limits`) and the per-actuator clamp
   through the coupling (`actuators.torque_limit`), so what leaves is within every limit.
Once tripped the stage stays in DAMPING (left only by a new run) and returns the damping torque -kd qd, the
torque the backend itself applies in its fault state. Each transition logs one line with its cause.
"""

from __future__ import annotations

import enum
import logging
import math

import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import RobotState, all_finite
from runtime.estimation import cos_tilt, tilt_angle

log = logging.getLogger("runtime.loop.safety")


class SafetyState(enum.IntEnum):
    SOFT_START = 0
    RUNNING = 1
    DAMPING = 2


class SafetyStage:
    def __init__(self, config: RobotConfig, stalled=None, joint_stalled=None):
        cfg = config.safety
        self.config = config
        self.lower_soft = config.q_lower + cfg.position_margin
        self.upper_soft = config.q_upper - cfg.position_margin
        self.qd_limit = config.qd_limit
        self.tau_limit = config.tau_limit
        self.rate_per_tick = cfg.max_torque_rate * config.dt
        self.ramp_ticks = max(1, round(cfg.torque_ramp_s * config.loop_hz))
        self.cos_tilt_limit = math.cos(math.radians(cfg.tilt_limit_deg))
        self.tilt_ticks = cfg.tilt_ticks
        self.max_age = cfg.max_sensor_age_s
        # The rate floor: the last `rate_ticks` tick starts must span at most `rate_window_s`. A ring of their
        # times, filled from the first check on (a window is judged once it is full).
        self.min_rate_hz = cfg.min_rate_hz
        self.rate_window_s = cfg.rate_window_s
        self.rate_ticks = max(2, math.ceil(cfg.min_rate_hz * cfg.rate_window_s))
        self.damping_kd = cfg.damping_kd
        self.stalled = stalled or (lambda t0, t1: 0.0)  # seconds of [t0, t1] the process was not run
        self.joint_stalled = joint_stalled  # ... or the joint readings were held back by the host (None: the same)
        self.host_stall_max = cfg.host_stall_max_s
        self.reset()

    def reset(self) -> None:
        self.state = SafetyState.SOFT_START
        self.cause: str | None = None
        self.tick = 0
        self.previous = np.zeros(self.config.n_joints)
        self.tilted_ticks = 0
        self.starts = np.full(self.rate_ticks, -math.inf)  # the backend's clock at each of the last checks
        self.checks = 0
        self.transitions: list[tuple[int, str]] = []

    @property
    def tripped(self) -> bool:
        return self.state is SafetyState.DAMPING

    def _enter(self, state: SafetyState, text: str) -> None:
        self.state = state
        self.transitions.append((self.tick, text))
        log.warning(text) if state is SafetyState.DAMPING else log.info(text)

    def trip(self, cause: str) -> None:
        """Enter the damping state now (idempotent: the first cause is kept)."""
        if self.state is SafetyState.DAMPING:
            return
        self.cause = cause
        self._enter(SafetyState.DAMPING, f"safety: damping at tick {self.tick}: {cause}")

    # -- triggers ----------------------------------------------------------------------------------------
    def check(self, robot: RobotState, now: float) -> None:
        """Sensor-side triggers for this tick's reading, and the rate floor; `now` is on the backend's clock."""
        if self.state is SafetyState.DAMPING:
            return
        k = self.checks % self.rate_ticks
        oldest = self.starts[k]  # the start `rate_ticks` ticks ago
        previous = self.starts[(k - 1) % self.rate_ticks]
        self.starts[k] = now
        self.checks += 1
        stalled = self.stalled(previous, now) if previous > -math.inf else 0.0
        if stalled > self.host_stall_max:
            return self.trip(f"host stall: this process was not run for {1e3 * stalled:.1f} ms since the previous "
                             f"tick > safety.host_stall_max_s {1e3 * self.host_stall_max:g} ms (the motors held their "
                             f"last current meanwhile)")
        if robot.estop:
            return self.trip("e-stop input asserted")
        if now - oldest > self.rate_window_s and oldest > -math.inf and \
                now - oldest - self.stalled(oldest, now) > self.rate_window_s:
            return self.trip(f"loop ran {self.rate_ticks} ticks in {1e3 * (now - oldest):.1f} ms: below "
                             f"safety.min_rate_hz {self.min_rate_hz:g} Hz over safety.rate_window_s "
                             f"{1e3 * self.rate_window_s:g} ms")
        joints, imu = robot.joints, robot.imu
        if not all_finite(joints.q, joints.qd):
            return self.trip("non-finite joint reading (q or qd)")
        if not all_finite(imu.gyro, imu.accel):
            return self.trip("non-finite IMU reading")
        if now - min(joints.stamp, imu.stamp) > self.max_age:  # only then can either be stale
            sources = (("joint", joints.stamp, self.joint_stalled or self.stalled), ("IMU", imu.stamp, self.stalled))
            for which, stamp, held in sorted(sources, key=lambda source: source[1]):  # the older named first
                age = now - stamp
                if age > self.max_age and age - held(stamp, now) > self.max_age:
                    return self.trip(f"stale {which} data: {1e3 * age:.1f} ms old > safety.max_sensor_age_s "
                                     f"{1e3 * self.max_age:.1f} ms")
        if cos_tilt(imu) < self.cos_tilt_limit:
            self.tilted_ticks += 1
            if self.tilted_ticks >= self.tilt_ticks:
                tilt = math.degrees(tilt_angle(imu))
                return self.trip(f"tilt {tilt:.0f} deg > safety.tilt_limit_deg for {self.tilted_ticks} ticks")
        else:
            self.tilted_ticks = 0

    # -- command filter ----------------------------------------------------------------------------------
    def filter(self, tau: np.ndarray, robot: RobotState) -> np.ndarray:
        """The torque to send this tick."""
        q, qd = robot.joints.q, robot.joints.qd
        if self.state is not SafetyState.DAMPING and not all_finite(tau):
            bad = [self.config.joints[i] for i in np.flatnonzero(~np.isfinite(tau))]
            self.trip(f"non-finite torque command for {', '.join(bad)}")
        if self.state is SafetyState.DAMPING:
            self.previous = -self.damping_kd * qd
            return self.previous
        # Remove torque that pushes further past a position soft limit or further beyond a velocity limit.
        up = (q > self.upper_soft) | (qd > self.qd_limit)
        down = (q < self.lower_soft) | (qd < -self.qd_limit)
        tau = np.where((up & (tau > 0)) | (down & (tau < 0)), 0.0, tau)
        self.tick += 1
        if self.state is SafetyState.SOFT_START:
            tau = tau * (self.tick / self.ramp_ticks)
            if self.tick >= self.ramp_ticks:
                self._enter(SafetyState.RUNNING, f"safety: running (torque ramp done after {self.tick} ticks)")
        # np.minimum/np.maximum: half the cost of np.clip on 10 elements
        tau = np.minimum(np.maximum(tau, self.previous - self.rate_per_tick), self.previous + self.rate_per_tick)
        tau = np.minimum(np.maximum(tau, -self.tau_limit), self.tau_limit)
        tau = self.config.coupling.saturate(tau, self.config.actuator_torque_limit)
        self.previous = tau
        return tau
