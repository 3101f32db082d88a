"""Observers of the tick: everything that watches a run without acting on the robot.

The loop (`runtime.loop.run`) hands every observer the same `TickView` once per tick, after the write and outside every
timed section: what was read, the command and targets in force, tau* and the torque written. An observer may end
the run (a non-empty string from `on_tick` is the stop cause, as the end of `--duration` is); it never changes
what the robot is sent. Evaluation lives here, not in the loop: on the mock, every run gets the ground-truth
observers (`ground_truth_observers`: base height and path, falls by `runtime.loop.falls`, velocity tracking), which fill
the summary's `GroundTruthLog`; callers add their own (bruce-collect's recorder, bruce-eval transfer's truth
recorder and twin metric, DAgger's pushes).

The view is one object, refilled each tick (no allocation); the simulator's truth is read at most once per tick,
when an observer first asks for it (`view.truth`). The arrays are the loop's: copy what you keep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from bruce_hw.backend import Backend
from bruce_hw.config import RobotConfig
from bruce_hw.quaternion import euler_of, world_z_in_body
from bruce_hw.types import GroundTruth, RobotState
from runtime.control.commands import COMMAND_AXES
from runtime.loop.falls import has_fallen

TRUTH_PHASE = 5              # the truth observers sample this tick of each policy period, not with the policy
TRACKING_SKIP_S = 2.0        # velocity tracking is scored after this start-up transient (soft start, first steps)


class TickView:
    """One tick as the observers see it (refilled by the loop every tick)."""

    __slots__ = ("backend", "tick", "now", "clock0", "robot", "q", "qd", "command", "a", "tau_star", "tau",
                 "scheme", "safety", "gap", "_truth")

    def __init__(self, backend: Backend, clock0: float):
        self.backend = backend
        self.clock0 = clock0                 # the backend's clock when the loop started
        self.tick = 0
        self.now = clock0                    # the backend's clock at this tick's read
        self.robot: RobotState | None = None
        self.q = self.qd = None              # the joint state read (robot.joints)
        self.command = None                  # (vx, vy, yaw rate) in force
        self.a = None                        # the controller's targets in force
        self.tau_star = None                 # Eq. 8 on them
        self.tau = None                      # what was written (the safety stage's output)
        # The loop's stages, set once before the first tick (None outside the loop): the transfer scheme (q_hat,
        # qd_hat), the safety stage (state) and the gap monitor (last residual; None without a reference model).
        self.scheme = self.safety = self.gap = None
        self._truth: GroundTruth | None = None

    def fill(self, tick: int, now: float, robot: RobotState, command: np.ndarray, a: np.ndarray,
             tau_star: np.ndarray, tau: np.ndarray) -> None:
        """This tick's values (the loop's own objects: no copies)."""
        self.tick, self.now, self.robot, self.q, self.qd = tick, now, robot, robot.joints.q, robot.joints.qd
        self.command, self.a, self.tau_star, self.tau, self._truth = command, a, tau_star, tau, None

    @property
    def elapsed(self) -> float:
        """Seconds since the loop started, on the backend's clock."""
        return self.now - self.clock0

    @property
    def truth(self) -> GroundTruth:
        """The simulator's truth at this tick (mock only), read once per tick."""
        if self._truth is None:
            self._truth = self.backend.ground_truth()
        return self._truth


class TickObserver:
    """The interface (every method optional to override): `on_start` before the first tick, `on_tick` after each
    write (a non-empty string ends the run after this tick, as its stop cause), `on_end` once the loop has ended
    (after the stop cause is set, before any damping hold; not when the loop raised)."""

    def on_start(self, backend: Backend, config: RobotConfig) -> None:
        pass

    def on_tick(self, view: TickView) -> str | None:
        return None

    def on_end(self, summary) -> None:
        pass


class EachTick(TickObserver):
    """An observer made of one function of the view (what it returns is `on_tick`'s: a string ends the run)."""

    def __init__(self, on_tick):
        self.on_tick = on_tick


# -- the ground truth of a run (mock) -----------------------------------------------------------------------
def heading_velocity(truth: GroundTruth) -> np.ndarray:
    """(vx, vy, yaw rate) of the base: the linear velocity in the heading frame (yaw only), the world-z rate."""
    yaw = float(euler_of(truth.base_quat)[2])
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy, _ = truth.base_linvel
    zx, zy, zz = world_z_in_body(truth.base_quat)
    wx, wy, wz = truth.base_angvel  # base frame: the world z rate is the world's z axis in the base frame times it
    yaw_rate = zx * wx + zy * wy + zz * wz
    return np.array([c * vx + s * vy, c * vy - s * vx, yaw_rate])


@dataclass
class VelocityTracking:
    """Running sums of the measured base velocity and the command in force, per axis (vx, vy, wz)."""

    samples: int = 0
    measured_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    command_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    squared_error_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def add(self, measured: np.ndarray, command: np.ndarray) -> None:
        self.samples += 1
        self.measured_sum += measured
        self.command_sum += command
        error = measured - command
        self.squared_error_sum += error * error

    def _per_axis(self, values: np.ndarray) -> dict[str, float] | None:
        """(vx, vy, wz) by name; None before the first sample (the callers' max(samples, 1) only avoids 0 / 0)."""
        return dict(zip(COMMAND_AXES, values.tolist(), strict=True)) if self.samples else None

    @property
    def measured_mean(self) -> dict[str, float] | None:
        return self._per_axis(self.measured_sum / max(self.samples, 1))

    @property
    def command_mean(self) -> dict[str, float] | None:
        return self._per_axis(self.command_sum / max(self.samples, 1))

    @property
    def error(self) -> dict[str, float] | None:
        """|mean(v) - mean(cmd)|: a walking base sways within each step, so its mean is what tracks."""
        return self._per_axis(np.abs(self.measured_sum - self.command_sum) / max(self.samples, 1))

    @property
    def rmse(self) -> dict[str, float] | None:
        """RMS of v - cmd over every tick: the step-by-step sway (a walking base's yaw rate swings ~1 rad/s within each
        step) as much as tracking; `error` is what tracks."""
        return self._per_axis(np.sqrt(self.squared_error_sum / max(self.samples, 1)))

    def to_json(self) -> dict:
        return {"tracking_samples": self.samples, "command_mean": self.command_mean,
                "velocity_mean": self.measured_mean, "tracking_error": self.error, "tracking_rmse": self.rmse}

    def text(self) -> str:
        def triple(values: dict[str, float], sign: str = "") -> str:
            return "/".join(f"{v:{sign}.3f}" for v in values.values())

        return (f"  velocity after {TRACKING_SKIP_S:g} s (vx/vy m/s, wz rad/s, {self.samples} samples): command mean "
                f"{triple(self.command_mean, '+')}, measured mean {triple(self.measured_mean, '+')}\n"
                f"    tracking error |mean(v) - mean(cmd)| {triple(self.error)}; rms of v - cmd per tick (the gait's "
                f"sway within each step included) {triple(self.rmse)}")


@dataclass
class GroundTruthLog:
    """What the simulator's truth says about a run (mock only): the summary's record, filled by the observers."""

    nominal_base_height: float
    base_height_min: float = math.inf
    base_height_max: float = -math.inf
    base_xy_start: list[float] | None = None
    base_xy_end: list[float] | None = None
    base_yaw_end: float | None = None
    sim_time: float = 0.0
    fell: bool = False
    tracking: VelocityTracking = field(default_factory=VelocityTracking)

    def update(self, truth: GroundTruth) -> None:
        """The base's extent and path so far."""
        z = float(truth.base_pos[2])
        self.base_height_min = min(self.base_height_min, z)
        self.base_height_max = max(self.base_height_max, z)
        xy = [float(truth.base_pos[0]), float(truth.base_pos[1])]
        if self.base_xy_start is None:
            self.base_xy_start = xy
        self.base_xy_end = xy
        self.base_yaw_end = float(euler_of(truth.base_quat)[2])
        self.sim_time = truth.sim_time

    def track(self, truth: GroundTruth, elapsed: float, command: np.ndarray) -> None:
        """Score the base velocity against the command in force, `elapsed` s after activation."""
        if elapsed >= TRACKING_SKIP_S:
            self.tracking.add(heading_velocity(truth), command)

    @property
    def tracking_error(self) -> dict[str, float] | None:
        return self.tracking.error

    @property
    def tracking_rmse(self) -> dict[str, float] | None:
        return self.tracking.rmse

    def to_json(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "tracking"}
        for key in ("base_height_min", "base_height_max"):
            if not math.isfinite(out[key]):
                out[key] = None
        out.update(self.tracking.to_json())
        return out


class _TruthSampler(TickObserver):
    """Samples the truth on tick TRUTH_PHASE of each policy period (between policy ticks) into a GroundTruthLog."""

    def __init__(self, log: GroundTruthLog):
        self.log = log
        self.backend: Backend | None = None
        self.decimation = 1

    def on_start(self, backend: Backend, config: RobotConfig) -> None:
        self.backend, self.decimation = backend, config.policy_decimation

    def on_tick(self, view: TickView) -> None:
        if view.tick % self.decimation == TRUTH_PHASE:
            self.sample(view)

    def sample(self, view: TickView) -> None:
        raise NotImplementedError


class BasePathObserver(_TruthSampler):
    """The base's height extent, start and end position, end yaw and the simulated time; the end state included."""

    def sample(self, view: TickView) -> None:
        self.log.update(view.truth)

    def on_end(self, summary) -> None:
        self.log.update(self.backend.ground_truth())


class FallObserver(_TruthSampler):
    """`fell` (runtime.loop.falls) at any sample or at the end of the loop."""

    def sample(self, view: TickView) -> None:
        if has_fallen(view.truth, self.log.nominal_base_height):
            self.log.fell = True

    def on_end(self, summary) -> None:
        if has_fallen(self.backend.ground_truth(), self.log.nominal_base_height):
            self.log.fell = True


class FallStop(TickObserver):
    """Ends the run at the first tick the robot has fallen (runtime.loop.falls, checked every tick; mock only)."""

    def __init__(self):
        self.fell_at: int | None = None  # the tick that ended the run
        self.nominal_base_height = math.nan
        self.dt = 0.0

    def on_start(self, backend: Backend, config: RobotConfig) -> None:
        self.nominal_base_height, self.dt = backend.nominal_base_height, config.dt
        self.fell_at = None

    def on_tick(self, view: TickView) -> str | None:
        truth = view.truth
        if not has_fallen(truth, self.nominal_base_height):
            return None
        self.fell_at = view.tick
        return f"fell at {view.tick * self.dt:.3f} s (base height {float(truth.base_pos[2]):.3f} m)"


class VelocityTrackingObserver(_TruthSampler):
    """The base velocity in its heading frame against the command in force, after TRACKING_SKIP_S."""

    def sample(self, view: TickView) -> None:
        self.log.track(view.truth, view.elapsed, view.command)


def ground_truth_observers(log: GroundTruthLog) -> list[TickObserver]:
    """Every run's evaluation on the mock: base path, falls, velocity tracking, into `log` (the summary's truth)."""
    return [BasePathObserver(log), FallObserver(log), VelocityTrackingObserver(log)]
