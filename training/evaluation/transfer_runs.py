"""One run of the transfer rehearsal (`bruce-eval transfer`): what it is (`RunSpec`: experiment, command, mode, gap,
seed), how it runs (`run_one`: a fresh mock through `runtime.loop.run.run_session`, the simulator's truth recorded by an
observer) and what it leaves (`RunRecord`). Modes name a transfer scheme, or SCHEME@nominal, its perfect-model
control."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from bruce_hw.config import DEFAULT_CONFIG, PdGains, load_config
from bruce_hw.quaternion import euler_of
from bruce_hw.reality_gap import RealityGap
from runtime.control.commands import CommandSchedule
from runtime.loop.exit import INTERRUPTS
from runtime.loop.observers import TickObserver, heading_velocity

MODES = ("direct", "pinn")
LOOKAHEAD_MODE = "pinn_ahead"  # Eq. 9 with the reference rolled ahead over the gap's latency (not the paper's)
# A mode is a transfer scheme (runtime.transfer.registry.scheme_names) on the configured reference model, or
# SCHEME@nominal: the same scheme on the nominal MuJoCo model, its perfect-model control.
PERFECT_MODEL_SUFFIX = "@nominal"
MODE_NAMES = {"direct": "direct (Eq. 8)", "pinn": "PINN (Eq. 9)", LOOKAHEAD_MODE: "PINN, look-ahead"}


@dataclass(frozen=True)
class Experiment:
    name: str
    command: tuple[float, float, float]  # vx m/s, vy m/s, wz rad/s (heading frame), ramped in by the schedule
    figure: str


EXPERIMENTS = (
    Experiment("tracking", (0.4, 0.0, 0.0), "fig6_tracking.png"),
    Experiment("circle", (0.4, 0.0, 0.4), "fig7_circle.png"),
    Experiment("reverse", (-0.5, 0.0, 0.0), "fig8_reverse.png"),
    Experiment("turn", (0.0, 0.0, 0.5), "fig9_turn.png"),
)


@dataclass(frozen=True)
class RunSpec:
    experiment: str
    command: tuple[float, float, float]
    seconds: float
    mode: str                      # "nominal" (no gap, Eq. 8), "direct" (gap, Eq. 8), "pinn" (gap, Eq. 9) or
    gap: RealityGap | None         # "pinn_ahead" (gap, Eq. 9 with the reference `lookahead` ticks further ahead)
    controller: str = "policy"
    estimator: str = "kinematic"   # "truth": a diagnostic run fed the simulator's truth
    eq9_scale: float = 1.0
    config: str | None = None
    lookahead: int = 0
    overrides: tuple[str, ...] = ()  # KEY=VALUE settings of the robot config (bruce-run's --set), e.g. transfer.*


def scheme_of(mode: str) -> tuple[str, str | None]:
    """(transfer scheme, reference model or None for the configured one) of a mode."""
    if mode in ("nominal", "direct"):
        return "direct", None
    if mode == LOOKAHEAD_MODE:
        return "pinn", None
    scheme, _, model = mode.partition("@")
    return scheme, model or None


def mode_label(mode: str) -> str:
    scheme, model = scheme_of(mode)
    return MODE_NAMES.get(mode) or (f"{scheme}, perfect model" if model == "nominal" else scheme)


@dataclass
class RunRecord:
    """One run, at every 1 kHz tick until it ended: simulator truth and the torque sent."""

    spec: RunSpec
    t: np.ndarray             # s since activation
    q: np.ndarray             # [T, n] true joint angles
    qd: np.ndarray            # [T, n] true joint velocities
    tau: np.ndarray           # [T, n] torque written (after safety)
    xy: np.ndarray            # [T, 2] base position, world
    yaw: np.ndarray           # [T] base yaw, world
    velocity: np.ndarray      # [T, 3] (vx, vy, wz) of the base in its heading frame
    fell: bool
    stop_cause: str
    fall_time: float | None = None
    extra: dict = field(default_factory=dict)
    # the twin metric (runtime.transfer.twin_metric): per joint, RMS of (twin q - robot q) at the end of each 10 ms
    # window
    twin_rmse_per_joint: np.ndarray | None = None


class _TruthRecorder(TickObserver):
    """An observer of the run loop: the simulator truth after every tick (evaluation only, never fed back)."""

    def __init__(self, n_ticks: int, n_joints: int):
        self.count = 0
        self.q = np.full((n_ticks, n_joints), np.nan)
        self.qd = np.full((n_ticks, n_joints), np.nan)
        self.tau = np.full((n_ticks, n_joints), np.nan)
        self.pose = np.full((n_ticks, 3), np.nan)
        self.velocity = np.full((n_ticks, 3), np.nan)

    def on_tick(self, view) -> None:
        i = self.count
        if i >= len(self.q):
            return None
        truth = view.truth
        self.q[i], self.qd[i], self.tau[i] = truth.joint_q, truth.joint_qd, view.tau
        self.pose[i] = (truth.base_pos[0], truth.base_pos[1], euler_of(truth.base_quat)[2])
        self.velocity[i] = heading_velocity(truth)
        self.count += 1
        return None


def run_one(spec: RunSpec) -> RunRecord:
    """One run of `spec` in a fresh mock; module-level so that a process pool can call it."""
    from bruce_hw.mock import MujocoBackend
    from runtime.loop.run import run_session
    from runtime.transfer.twin_metric import TwinMetric

    scheme, model = scheme_of(spec.mode)
    overrides = list(spec.overrides) + ([f"transfer.reference_model={model}"] if model else [])
    config = load_config(spec.config or DEFAULT_CONFIG, overrides)
    if spec.eq9_scale != 1.0:
        config = dataclasses.replace(config, eq9=PdGains(kp=config.eq9.kp * spec.eq9_scale,
                                                         kd=config.eq9.kd * spec.eq9_scale))
    if spec.lookahead:
        config = dataclasses.replace(config, models=dataclasses.replace(config.models,
                                                                        pinn_lookahead_ticks=spec.lookahead))
    backend = MujocoBackend(config, gap=spec.gap if spec.mode != "nominal" else None)
    n_ticks = round(spec.seconds * config.loop_hz)
    recorder, twin = _TruthRecorder(n_ticks, config.n_joints), TwinMetric()
    summary = run_session(backend, config, duration=spec.seconds, realtime=False,
                          transfer=scheme,
                          controller_kind=spec.controller,
                          estimator=spec.estimator, commands=CommandSchedule.constant(*spec.command),
                          observers=[recorder, twin])
    if summary.stop_cause in INTERRUPTS:  # cut short by the operator: not a result, and not to be cached as one
        raise KeyboardInterrupt(summary.stop_cause)
    n = recorder.count
    truth = summary.truth
    fell = bool(truth is not None and truth.fell)
    return RunRecord(spec=spec, t=np.arange(n) * config.dt, q=recorder.q[:n], qd=recorder.qd[:n],
                     tau=recorder.tau[:n], xy=recorder.pose[:n, :2], yaw=np.unwrap(recorder.pose[:n, 2]),
                     velocity=recorder.velocity[:n], fell=fell, stop_cause=summary.stop_cause or "",
                     fall_time=(n * config.dt) if fell else None, twin_rmse_per_joint=twin.rmse_per_joint)
