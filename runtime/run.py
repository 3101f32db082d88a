"""One `bruce-run` session: start-up, the read -> update -> write loop, and shutdown on every exit path.

Start-up follows the robot: configure (inactive, reads only) -> read the measured pose -> activate -> soft
start to the standing pose -> hold with the Eq. 8 PD. SIGINT/SIGTERM, the end of `--duration` and any error
all end in the backend's damping state, a printed summary and, with `--stats`, a JSON file.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bruce_hw.backend import Backend, LifecycleState
from bruce_hw.config import RobotConfig
from bruce_hw.types import GroundTruth, JointCommand
from runtime.mixing import eq8_torque
from runtime.pacing import Pacer
from runtime.standing import StandingController

FALL_HEIGHT_FRACTION = 0.6   # fallen when the base is below this share of its nominal standing height
FALL_TILT_RAD = math.pi / 4  # ... or the base is tilted more than this


def yaw_of(quat: np.ndarray) -> float:
    w, x, y, z = quat
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def tilt_of(quat: np.ndarray) -> float:
    """Angle between the base's z axis and the world's."""
    w, x, y, z = quat
    return math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y))))


@dataclass
class GroundTruthLog:
    """What the simulator's truth says about a run (mock only)."""

    nominal_base_height: float
    base_height_min: float = math.inf
    base_height_max: float = -math.inf
    base_xy_start: list[float] | None = None
    base_xy_end: list[float] | None = None
    base_yaw_end: float | None = None
    sim_time: float = 0.0
    fell: bool = False

    def update(self, truth: GroundTruth) -> None:
        z = float(truth.base_pos[2])
        self.base_height_min = min(self.base_height_min, z)
        self.base_height_max = max(self.base_height_max, z)
        xy = [float(truth.base_pos[0]), float(truth.base_pos[1])]
        if self.base_xy_start is None:
            self.base_xy_start = xy
        self.base_xy_end = xy
        self.base_yaw_end = yaw_of(truth.base_quat)
        self.sim_time = truth.sim_time
        if z < FALL_HEIGHT_FRACTION * self.nominal_base_height or tilt_of(truth.base_quat) > FALL_TILT_RAD:
            self.fell = True


@dataclass
class RunSummary:
    backend: str
    ticks: int = 0
    wall_time: float = 0.0
    realtime: bool = False
    late_ticks: int = 0
    skipped_ticks: int = 0
    final_state: str = "unconfigured"
    stop_cause: str | None = None
    error: str | None = None
    truth: GroundTruthLog | None = field(default=None)

    def to_json(self) -> dict:
        out = {k: v for k, v in asdict(self).items() if k != "truth"}
        if self.truth is not None:
            out.update(asdict(self.truth))
            for key in ("base_height_min", "base_height_max"):
                if not math.isfinite(out[key]):
                    out[key] = None
        return out

    def text(self) -> str:
        lines = [f"bruce-run: {self.backend} backend, {self.ticks} ticks in {self.wall_time:.2f} s wall"]
        if self.truth is not None:
            t = self.truth
            speed = t.sim_time / self.wall_time if self.wall_time > 0 else float("nan")
            lines.append(f"  simulated {t.sim_time:.3f} s ({speed:.1f}x real time)")
            if self.ticks:
                lines.append(f"  base height {t.base_height_min:.3f}..{t.base_height_max:.3f} m "
                             f"(nominal {t.nominal_base_height:.3f} m), fell: {'yes' if t.fell else 'no'}")
        if self.realtime:
            lines.append(f"  paced: {self.late_ticks} late ticks, {self.skipped_ticks} skipped")
        cause = f" ({self.stop_cause})" if self.stop_cause else ""
        lines.append(f"  final state: {self.final_state}{cause}")
        if self.error:
            lines.append(f"  error: {self.error}")
        return "\n".join(lines)


class StopFlag:
    """Set from a signal handler; the loop polls it once per tick."""

    def __init__(self):
        self.cause: str | None = None

    def __call__(self, signum, _frame) -> None:
        self.cause = signal.Signals(signum).name


def run_session(backend: Backend, config: RobotConfig, *, duration: float | None, realtime: bool,
                stats_path: Path | None = None) -> RunSummary:
    summary = RunSummary(backend=backend.name, realtime=realtime)
    stop = StopFlag()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    wall_start = time.perf_counter()
    try:
        backend.configure()
        state = backend.read()
        truth = backend.ground_truth()
        if truth is not None:
            summary.truth = GroundTruthLog(nominal_base_height=backend.nominal_base_height)
        controller = StandingController(config)
        controller.reset(state.joints.q)
        backend.activate()
        until = "until Ctrl-C" if duration is None else f"for {duration:g} s"
        print(f"bruce-run: {backend.name} backend active, standing {until}"
              f"{' (paced to the wall clock)' if realtime else ''}", flush=True)

        n_ticks = None if duration is None else round(duration * config.loop_hz)
        decimation = config.policy_decimation
        gains = config.eq8
        pacer = Pacer(config.dt)
        pacer.start()
        tick = 0
        a = state.joints.q
        while stop.cause is None and (n_ticks is None or tick < n_ticks):
            if realtime:
                pacer.wait()
            state = backend.read()
            if tick % decimation == 0:
                a = controller(state)
                if summary.truth is not None:
                    summary.truth.update(backend.ground_truth())
            backend.write(JointCommand(tau_ff=eq8_torque(a, state.joints.q, state.joints.qd, gains)))
            tick += 1
            summary.ticks = tick
        summary.late_ticks, summary.skipped_ticks = pacer.late_ticks, pacer.skipped_ticks
        summary.stop_cause = stop.cause or "duration reached"
        if summary.truth is not None:
            summary.truth.update(backend.ground_truth())
        summary.final_state = backend.state.value
        if stop.cause is not None:
            backend.fault(stop.cause)
            summary.final_state = f"{backend.state.value}: damping"
    except BaseException as exc:
        summary.error = f"{type(exc).__name__}: {exc}"
        summary.stop_cause = summary.stop_cause or "error"
        if backend.state not in (LifecycleState.UNCONFIGURED, LifecycleState.FAULT):
            backend.fault(summary.error)
        summary.final_state = f"{backend.state.value}: damping" if backend.state is LifecycleState.FAULT \
            else backend.state.value
        raise
    finally:
        summary.wall_time = time.perf_counter() - wall_start
        try:
            backend.shutdown()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            print(summary.text(), file=sys.stderr if summary.error else sys.stdout, flush=True)
            if stats_path is not None:
                stats_path.parent.mkdir(parents=True, exist_ok=True)
                stats_path.write_text(json.dumps(summary.to_json(), indent=2) + "\n")
    return summary
