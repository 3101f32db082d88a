"""`bruce-eval transfer`: the paper's sim-to-real experiments (§IV-C, Figs. 6-10), rehearsed in the mock.

The nominal mock is "the simulator", the mock with a reality-gap profile (`configs/gaps/`) "the robot". Every
experiment (`EXPERIMENTS`: tracking, circle, reverse, turn) runs the same nominal controller on the same command
schedule once in the nominal mock, the reference, and on the gapped mock under each transfer mode, once per gap
seed; the sweeps vary the actuator latency and the Eq. 9 gains. Runs are scored on the simulator's truth after the
start-up transient and up to a fall (`run_metrics`). Output: DIR/transfer.json (with the acceptance of
`training.evaluation.transfer_acceptance`), DIR/transfer.md and figures; each run is cached under DIR/runs
(`training.evaluation.transfer_cache`), so an interrupted suite resumes. Experiments, metrics and the output's
layout: docs/transfer.md ("How the rehearsal runs").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bruce_hw.config import DEFAULT_CONFIG, REFERENCE_MODELS, TRANSFER_SCHEMES, ConfigError, PdGains, load_config
from bruce_hw.quaternion import euler_of
from bruce_hw.reality_gap import GapError, RealityGap, latency_ticks, load_gap
from runtime.commands import CommandSchedule
from runtime.exit import INTERRUPTS
from runtime.observers import TRACKING_SKIP_S, TickObserver, heading_velocity
from runtime.policy_spec import policy_spec_for
from training.evaluation.report import json_safe
from training.evaluation.transfer_acceptance import (
    BARS,
    ONE_FACTOR_PROFILES,
    acceptance,
    latency_tolerance,
    recommended,
)
from training.evaluation.transfer_cache import RunCache, spec_key, trace

MODES = ("direct", "pinn")
LOOKAHEAD_MODE = "pinn_ahead"  # Eq. 9 with the reference rolled ahead over the gap's latency (not the paper's)
# A mode is a transfer scheme (runtime.transfer_schemes.TRANSFERS) on the configured reference model, or
# SCHEME@nominal: the same scheme on the nominal MuJoCo model, its perfect-model control.
PERFECT_MODEL_SUFFIX = "@nominal"
MODE_NAMES = {"direct": "direct (Eq. 8)", "pinn": "PINN (Eq. 9)", LOOKAHEAD_MODE: "PINN, look-ahead"}
DEFAULT_SECONDS = 20.0
DEFAULT_LATENCIES_MS = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0)
DEFAULT_GAIN_SCALES = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)
# Named lists of profiles (--suite): issue 20's acceptance needs `default` (its bars), `none` (the null test) and the
# one-factor profiles; `mild` and `harsh` bracket `default`.
SUITES = {"acceptance": ("default", "none", *ONE_FACTOR_PROFILES, "mild", "harsh")}


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


class TransferError(ValueError):
    """A transfer evaluation that cannot run as asked; the message names the option."""


# -- one run ---------------------------------------------------------------------------------------------------
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
    # the twin metric (runtime.twin_metric): per joint, RMS of (twin q - robot q) at the end of each 10 ms window
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
    from runtime.run import run_session
    from runtime.twin_metric import TwinMetric

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


# -- metrics ---------------------------------------------------------------------------------------------------
def scored(record: RunRecord, skip_s: float = TRACKING_SKIP_S) -> slice:
    """The ticks of a run that are scored: from `skip_s` on."""
    return slice(int(np.searchsorted(record.t, skip_s - 1e-9)), len(record.t))


def joint_rmse(run: RunRecord, reference: RunRecord, skip_s: float = TRACKING_SKIP_S, what: str = "q") -> np.ndarray:
    """Per-joint RMSE of the true joint angles (`what` = "q") or velocities ("qd") against the reference run, tick
    by tick, after `skip_s`, over the ticks both runs reached: [n] (NaN when none is left)."""
    shorter = run if len(run.t) <= len(reference.t) else reference
    part = scored(shorter, skip_s)
    a, b = getattr(run, what)[part], getattr(reference, what)[part]
    if len(a) == 0:
        return np.full(run.q.shape[1], np.nan)
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def offset_and_shape(run: RunRecord, reference: RunRecord, skip_s: float = TRACKING_SKIP_S,
                     what: str = "q") -> tuple[np.ndarray, np.ndarray]:
    """Each joint's error against the reference (as `joint_rmse` takes it) split in two: the offset, its signed
    mean over the scored ticks, and the shape, the RMS of the rest; offset² + shape² = RMSE² per joint. [n] each."""
    shorter = run if len(run.t) <= len(reference.t) else reference
    part = scored(shorter, skip_s)
    error = getattr(run, what)[part] - getattr(reference, what)[part]
    if len(error) == 0:
        nan = np.full(run.q.shape[1], np.nan)
        return nan, nan.copy()
    offset = error.mean(axis=0)
    return offset, np.sqrt(np.mean((error - offset) ** 2, axis=0))


def deviation_from_simulator(run: RunRecord, reference: RunRecord, skip_s: float = TRACKING_SKIP_S) -> dict:
    """The base path against the simulator's own (the nominal run's): the distance between the two base positions
    at the same tick, mean and max over the scored ticks both runs reached (m)."""
    shorter = run if len(run.t) <= len(reference.t) else reference
    part = scored(shorter, skip_s)
    distance = np.linalg.norm(run.xy[part] - reference.xy[part], axis=1)
    if distance.size == 0:
        return {"mean_deviation_from_simulator": float("nan"), "max_deviation_from_simulator": float("nan")}
    return {"mean_deviation_from_simulator": float(distance.mean()),
            "max_deviation_from_simulator": float(distance.max())}


def ideal_path(command: tuple[float, float, float], t: np.ndarray, start_xy: np.ndarray, start_yaw: float,
               ramp_s: float | None = None) -> np.ndarray:
    """The base path the command schedule asks for, from the start pose: the ramped (vx, vy, wz) integrated
    (trapezoid) in the heading frame. [T, 2]."""
    schedule = CommandSchedule.constant(*command) if ramp_s is None else CommandSchedule.constant(*command,
                                                                                                  ramp_s=ramp_s)
    cmd = np.array([schedule.at(float(ti)) for ti in t])
    if len(t) < 2:
        return np.repeat(np.asarray(start_xy, float)[None], len(t), axis=0)
    dt = np.diff(t)
    yaw = start_yaw + np.concatenate([[0.0], np.cumsum(0.5 * (cmd[1:, 2] + cmd[:-1, 2]) * dt)])
    c, s = np.cos(yaw), np.sin(yaw)
    world = np.stack([c * cmd[:, 0] - s * cmd[:, 1], s * cmd[:, 0] + c * cmd[:, 1]], axis=1)
    steps = 0.5 * (world[1:] + world[:-1]) * dt[:, None]
    return np.asarray(start_xy, float) + np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def distance_to_path(point: np.ndarray, path: np.ndarray) -> float:
    """Shortest distance from `point` to the polyline `path` [T, 2] (a single point when it does not move)."""
    a, b = path[:-1], path[1:]
    if len(path) < 2:
        return float(np.linalg.norm(point - path[0]))
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    s = np.clip(np.einsum("ij,ij->i", point - a, ab) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    nearest = a + s[:, None] * ab
    return float(np.min(np.linalg.norm(point - nearest, axis=1)))


def circle_deviation(record: RunRecord, command: tuple[float, float, float],
                     skip_s: float = TRACKING_SKIP_S) -> dict:
    """The base path against the ideal circle: radius |vx / wz| through the start position, tangent to the start
    heading, on the side the turn goes to. Mean and max | |p - c| - R | after `skip_s`."""
    vx, _, wz = command
    radius = abs(vx / wz)
    yaw0 = float(record.yaw[0])
    side = math.copysign(1.0, wz * vx)  # left of the heading for a forward left turn
    centre = record.xy[0] + side * radius * np.array([-math.sin(yaw0), math.cos(yaw0)])
    part = scored(record, skip_s)
    deviation = np.abs(np.linalg.norm(record.xy[part] - centre, axis=1) - radius)
    if deviation.size == 0:
        return {"mean_radial_deviation": float("nan"), "max_radial_deviation": float("nan"), "radius": radius,
                "centre": centre.tolist()}
    return {"mean_radial_deviation": float(deviation.mean()), "max_radial_deviation": float(deviation.max()),
            "radius": radius, "centre": centre.tolist()}


def drift(record: RunRecord, command: tuple[float, float, float]) -> dict:
    """Where the run ended against the commanded path: `drift` = distance from the path (the start point for a
    turn in place), `endpoint_error` = distance from where the command would have put the base by then,
    `distance_from_origin` = from the start position."""
    if len(record.t) == 0:
        return {"drift": float("nan"), "endpoint_error": float("nan"), "distance_from_origin": float("nan")}
    path = ideal_path(command, record.t, record.xy[0], float(record.yaw[0]))
    end = record.xy[-1]
    return {"drift": distance_to_path(end, path), "endpoint_error": float(np.linalg.norm(end - path[-1])),
            "distance_from_origin": float(np.linalg.norm(end - record.xy[0]))}


def velocity_summary(record: RunRecord, command: tuple[float, float, float],
                     skip_s: float = TRACKING_SKIP_S) -> dict:
    part = scored(record, skip_s)
    if record.velocity[part].size == 0:
        return {"mean_velocity": [float("nan")] * 3, "velocity_error": [float("nan")] * 3}
    mean = record.velocity[part].mean(axis=0)
    return {"mean_velocity": mean.tolist(), "velocity_error": np.abs(mean - np.asarray(command)).tolist()}


def run_metrics(record: RunRecord, nominal: RunRecord, experiment: Experiment) -> dict:
    """Every metric of one run (the nominal run scored against itself has RMSE 0)."""
    per_joint = joint_rmse(record, nominal)
    qd_rmse = joint_rmse(record, nominal, what="qd")
    out = {"fell": record.fell, "seconds": float(len(record.t) * (record.t[1] - record.t[0])) if len(record.t) > 1
           else 0.0, "joint_rmse": float(np.mean(per_joint)), "joint_rmse_per_joint": per_joint.tolist(),
           "joint_velocity_rmse": float(np.mean(qd_rmse)), **drift(record, experiment.command),
           **velocity_summary(record, experiment.command)}
    offset, shape = offset_and_shape(record, nominal)
    out.update(offset=float(np.sqrt(np.mean(offset ** 2))), shape=float(np.sqrt(np.mean(shape ** 2))),
               offset_per_joint=offset.tolist(), shape_per_joint=shape.tolist())
    if record.twin_rmse_per_joint is not None:  # the twin metric (runtime.twin_metric), mean over joints
        out.update(twin_rmse=float(np.mean(record.twin_rmse_per_joint)),
                   twin_rmse_per_joint=record.twin_rmse_per_joint.tolist())
    if experiment.command[2] != 0.0 and experiment.command[0] != 0.0:
        out.update(circle_deviation(record, experiment.command))
        out.update(deviation_from_simulator(record, nominal))
    return out


def aggregate(per_seed: list[dict]) -> dict:
    """Mean over seeds of every number, `fell` = any seed fell, `falls` = how many, `per_seed` kept."""
    out: dict = {"fell": any(m["fell"] for m in per_seed), "falls": sum(m["fell"] for m in per_seed),
                 "seeds": len(per_seed)}
    for key, value in per_seed[0].items():
        if key == "fell" or isinstance(value, str):
            continue
        values = np.array([m[key] for m in per_seed], dtype=float)
        out[key] = values.mean(axis=0).tolist() if values.ndim > 1 else float(values.mean())
        if values.ndim == 1 and len(per_seed) > 1:
            out[f"{key}_std"] = float(values.std(ddof=1))
    out["per_seed"] = per_seed
    return out


# -- the evaluation --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TransferSettings:
    gap: RealityGap
    gap_name: str
    seeds: tuple[int, ...] = (0, 1, 2)
    seconds: float = DEFAULT_SECONDS
    controller: str = "policy"
    estimator: str = "kinematic"
    experiments: tuple[str, ...] = tuple(e.name for e in EXPERIMENTS)
    latencies_ms: tuple[float, ...] = DEFAULT_LATENCIES_MS
    gain_scales: tuple[float, ...] = DEFAULT_GAIN_SCALES
    sweep_seeds: tuple[int, ...] = (0, 1)
    jobs: int = 1
    config: str | None = None
    lookahead: int | str | None = "auto"  # ticks, "auto" (the gap's latency), or None: no look-ahead variant
    schemes: tuple[str, ...] | None = None  # modes to run besides direct (None: Eq. 9 and its look-ahead variant)
    overrides: tuple[str, ...] = ()
    profiles: tuple[tuple[str, RealityGap], ...] = ()  # (name, gap) of every profile; (): gap_name, gap alone

    def per_profile(self) -> list[TransferSettings]:
        """The settings of each profile on its own; the sweeps run on the first profile only."""
        profiles = self.profiles or ((self.gap_name, self.gap),)
        return [dataclasses.replace(self, gap=gap, gap_name=name, profiles=(),
                                    **({} if i == 0 else {"latencies_ms": (), "gain_scales": ()}))
                for i, (name, gap) in enumerate(profiles)]

    @property
    def modes(self) -> tuple[str, ...]:
        if self.schemes is not None:
            return ("direct", *(m for m in self.schemes if m != "direct"))
        return MODES + ((LOOKAHEAD_MODE,) if self.lookahead is not None else ())


def lookahead_ticks(setting: int | str, gap: RealityGap, dt: float = 1e-3) -> int:
    """The look-ahead variant's ticks: a number as given, or "auto": the ticks between reading the joints and the
    torque acting on them that the gap adds (actuator plus sensor latency)."""
    if setting != "auto":
        return int(setting)
    return latency_ticks(gap.actuator_latency_s, dt) + latency_ticks(gap.sensor_latency_s, dt)


def _spec(settings: TransferSettings, experiment: Experiment, mode: str, seed: int | None,
          gap: RealityGap | None = None, **changes) -> RunSpec:
    if mode != "nominal":
        gap = dataclasses.replace(gap or settings.gap, seed=seed)
    if mode == LOOKAHEAD_MODE:
        changes["lookahead"] = lookahead_ticks(settings.lookahead, gap)
    return RunSpec(experiment=experiment.name, command=experiment.command, seconds=settings.seconds, mode=mode,
                   gap=None if mode == "nominal" else gap, controller=settings.controller,
                   estimator=settings.estimator, config=settings.config, overrides=settings.overrides, **changes)


def _sweep_gap(gap: RealityGap, latency_ms: float) -> RealityGap:
    return dataclasses.replace(gap, actuator_latency_s=latency_ms / 1000.0)


EXPERIMENT_BY_NAME = {e.name: e for e in EXPERIMENTS}


def _latency_specs(settings: TransferSettings, latency_ms: float, mode: str) -> list[RunSpec]:
    """The latency sweep's runs of `mode` at `latency_ms`: the tracking command, one per sweep seed."""
    return [dataclasses.replace(_spec(settings, EXPERIMENT_BY_NAME["tracking"], mode, seed,
                                      gap=_sweep_gap(settings.gap, latency_ms)), experiment="sweep_latency")
            for seed in settings.sweep_seeds]


def _gain_specs(settings: TransferSettings, scale: float) -> list[RunSpec]:
    return [dataclasses.replace(_spec(settings, EXPERIMENT_BY_NAME["tracking"], "pinn", seed, eq9_scale=scale),
                                experiment="sweep_gain") for seed in settings.sweep_seeds]


def plan(settings: TransferSettings) -> list[RunSpec]:
    """Every run the evaluation of one profile needs, in a fixed order: per experiment the nominal run, then each
    mode per seed; then the latency sweep and the Eq. 9 gain sweep on the tracking command."""
    specs = []
    for name in settings.experiments:
        experiment = EXPERIMENT_BY_NAME[name]
        specs.append(_spec(settings, experiment, "nominal", None))
        specs += [_spec(settings, experiment, mode, seed) for mode in settings.modes for seed in settings.seeds]
    if "tracking" not in settings.experiments and (settings.latencies_ms or settings.gain_scales):
        specs.append(_spec(settings, EXPERIMENT_BY_NAME["tracking"], "nominal", None))
    for latency in settings.latencies_ms:
        for mode in settings.modes:
            specs += _latency_specs(settings, latency, mode)
    for scale in settings.gain_scales if "pinn" in settings.modes else ():
        specs += _gain_specs(settings, scale)
    return specs


def plan_suite(settings: TransferSettings) -> list[RunSpec]:
    """Every run of every profile (the nominal runs, shared, appear once per profile; `execute` runs them once)."""
    return [spec for profile in settings.per_profile() for spec in plan(profile)]


def nominal_of(spec: RunSpec) -> RunSpec:
    """The nominal run `spec` is scored against (a sweep's: the tracking experiment's)."""
    name = spec.experiment if spec.experiment in EXPERIMENT_BY_NAME else "tracking"
    return dataclasses.replace(spec, experiment=name, mode="nominal", gap=None, eq9_scale=1.0, lookahead=0)


@dataclass
class RunResults:
    """Every run's metrics against its nominal reference, and the records kept (the nominal references whole, the
    runs the figures draw as traces), by `spec_key`."""

    metrics: dict[str, dict] = field(default_factory=dict)
    records: dict[str, RunRecord] = field(default_factory=dict)

    def of(self, spec: RunSpec) -> dict:
        return self.metrics[spec_key(spec)]

    def record(self, spec: RunSpec) -> RunRecord | None:
        return self.records.get(spec_key(spec))


_REFERENCES: dict[tuple[str, str], RunRecord] = {}  # nominal records a worker process has loaded


def _run_scored(spec: RunSpec, cache_root: str, kept: bool) -> tuple[dict, RunRecord | None]:
    """Run `spec` and score it against its nominal reference (read from the cache; itself when it is nominal).
    Returns the metrics and, when `kept`, the record (a nominal one whole, any other as a figure trace)."""
    record = run_one(spec)
    if spec.mode == "nominal":
        reference = record
    else:
        nominal = nominal_of(spec)
        key = (cache_root, spec_key(nominal))
        if key not in _REFERENCES:
            _REFERENCES[key] = RunCache(Path(cache_root)).record(key[1], nominal, RunRecord)
        reference = _REFERENCES[key]
    metrics = run_metrics(record, reference, EXPERIMENT_BY_NAME[nominal_of(spec).experiment])
    return metrics, (record if spec.mode == "nominal" else trace(record)) if kept else None


def _profile_label(spec: RunSpec) -> str:
    return "no gap" if spec.gap is None else Path(spec.gap.source).stem


def execute(specs: list[RunSpec], out: Path, jobs: int, keep: list[RunSpec] = (),
            progress: bool = True) -> RunResults:
    """Run every distinct spec once (the nominal references first), `jobs` at a time, each run's metrics (and the
    records kept: nominal runs and `keep`) cached under OUT/runs as it finishes (`transfer_cache`); what the cache
    already holds is not run again."""
    cache = RunCache(Path(out) / "runs")
    unique: dict[str, RunSpec] = {}
    for spec in specs:
        unique.setdefault(spec_key(spec), spec)
    for spec in list(unique.values()):
        unique.setdefault(spec_key(nominal_of(spec)), nominal_of(spec))
    kept = {spec_key(s) for s in keep} | {k for k, s in unique.items() if s.mode == "nominal"}
    results = RunResults()
    done = 0

    def report(spec: RunSpec, how: str) -> None:
        if progress:
            print(f"bruce-eval transfer: {done}/{len(unique)} {spec.experiment} {spec.mode} "
                  f"({_profile_label(spec)}){how}", file=sys.stderr)

    for stage in (lambda s: s.mode == "nominal", lambda s: s.mode != "nominal"):
        todo = []
        for key, spec in ((k, s) for k, s in unique.items() if stage(s)):
            metrics = cache.metrics(key)
            record = cache.record(key, spec, RunRecord) if key in kept and metrics is not None else None
            if metrics is not None and (record is not None or key not in kept):
                results.metrics[key] = metrics
                if record is not None:
                    results.records[key] = record
                done += 1
                report(spec, " cached")
            else:
                todo.append((key, spec))
        for key, spec, metrics, record in _run_stage(todo, str(cache.root), kept, jobs):
            cache.save_metrics(key, spec, metrics)
            results.metrics[key] = cache.metrics(key)  # as a resumed run reads it back (NaN -> None)
            if record is not None:
                cache.save_record(key, record)
                results.records[key] = record
            done += 1
            report(spec, "")
    return results


def _run_stage(todo: list[tuple[str, RunSpec]], cache_root: str, kept: set[str], jobs: int):
    """(key, spec, metrics, record) of each run of `todo` as it finishes."""
    if jobs <= 1 or len(todo) <= 1:
        for key, spec in todo:
            yield (key, spec, *_run_scored(spec, cache_root, key in kept))
        return
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(_run_scored, spec, cache_root, key in kept): (key, spec) for key, spec in todo}
        for future in as_completed(futures):
            yield (*futures[future], *future.result())


def evaluate(settings: TransferSettings, results: RunResults) -> tuple[dict, dict]:
    """(report, traces) of one profile: per experiment and mode the metrics aggregated over seeds, plus the nominal
    run's own; the sweeps with each mode's latency tolerance; the records the figures draw."""
    report: dict = {}
    traces: dict = {}
    for name in settings.experiments:
        experiment = EXPERIMENT_BY_NAME[name]
        nominal = _spec(settings, experiment, "nominal", None)
        entry = {"command": list(experiment.command), "seconds": settings.seconds, "nominal": results.of(nominal)}
        traces[name] = {"nominal": results.record(nominal)}
        for mode in settings.modes:
            specs = [_spec(settings, experiment, mode, seed) for seed in settings.seeds]
            entry[mode] = aggregate([results.of(spec) for spec in specs])
            traces[name][mode] = results.record(specs[0])
        direct = entry["direct"]
        for mode in settings.modes[1:]:
            entry[f"{mode}_over_direct"] = {
                key: (entry[mode][key] / direct[key] if direct[key] else float("nan"))
                for key in ("joint_rmse", "mean_radial_deviation", "mean_deviation_from_simulator", "drift")
                if key in direct and direct[key] is not None and entry[mode].get(key) is not None}
        report[name] = entry
    sweeps: dict = {"latency": [], "eq9_gain": []}
    for latency in settings.latencies_ms:
        row = {"latency_ms": latency}
        for mode in settings.modes:
            specs = _latency_specs(settings, latency, mode)
            metrics = aggregate([results.of(spec) for spec in specs])
            row[mode] = {"joint_rmse": metrics["joint_rmse"], "falls": metrics["falls"], "seeds": metrics["seeds"]}
            if mode == LOOKAHEAD_MODE:
                row[mode]["lookahead_ticks"] = specs[0].lookahead
        sweeps["latency"].append(row)
    if sweeps["latency"]:
        sweeps["latency_tolerance_ms"] = {mode: latency_tolerance(sweeps["latency"], mode) for mode in settings.modes}
    for scale in settings.gain_scales if "pinn" in settings.modes else ():
        metrics = aggregate([results.of(spec) for spec in _gain_specs(settings, scale)])
        sweeps["eq9_gain"].append({"scale": scale, "pinn": {"joint_rmse": metrics["joint_rmse"],
                                                           "falls": metrics["falls"], "seeds": metrics["seeds"]}})
    # Eq. 8 alone does not depend on the Eq. 9 gains
    sweeps["eq9_gain_direct_reference"] = report["tracking"]["direct"]["joint_rmse"] if "tracking" in report else None
    report["sweeps"] = sweeps
    return report, traces


# -- outputs ---------------------------------------------------------------------------------------------------
def _fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}g}"


def markdown(report: dict, meta: dict) -> str:
    experiments = [entry for name, entry in report.items() if name != "sweeps"]
    modes = list(meta.get("modes") or [m for m in ("direct", "pinn", LOOKAHEAD_MODE)
                                        if experiments and m in experiments[0]])
    names = {m: mode_label(m) for m in modes}
    ahead = f"; look-ahead: {meta['lookahead']} ticks" if LOOKAHEAD_MODE in modes else ""
    lines = [f"# Transfer rehearsal: gap profile `{meta['gap_name']}`", "",
             f"Controller `{meta['controller']}`, estimator `{meta['estimator']}`, {meta['seconds']:g} s per run, "
             f"gap seeds {meta['seeds']} (mean over seeds; falls = seeds that fell){ahead}. Scored after "
             f"{TRACKING_SKIP_S:g} s on simulator truth against the nominal mock (Eq. 8, no gap); a run that fell "
             "is scored up to its fall.", "",
             "| experiment | metric | nominal | " + " | ".join(names[m] for m in modes) + " | "
             + " | ".join(f"{names[m]} / direct" for m in modes[1:]) + " |",
             "|---|---|---|" + "---|" * (2 * len(modes) - 1)]
    rows = (("tracking", "joint_rmse", "joint RMSE (rad)"),
            ("tracking", "joint_velocity_rmse", "joint velocity RMSE (rad/s)"),
            ("circle", "mean_radial_deviation", "mean radial deviation (m)"),
            ("circle", "mean_deviation_from_simulator", "deviation from the simulator's path (m)"),
            ("reverse", "drift", "drift (m)"), ("turn", "drift", "drift (m)"))
    for name, key, label in rows:
        if name not in report:
            continue
        entry = report[name]
        direct = entry["direct"].get(key)
        values = [_fmt(entry[m].get(key)) for m in modes]
        ratios = [_fmt(entry[m].get(key, float("nan")) / direct if direct else None) for m in modes[1:]]
        lines.append(f"| {name} | {label} | {_fmt(entry['nominal'].get(key))} | " + " | ".join(values) + " | "
                     + " | ".join(ratios) + " |")
    for name in ("tracking", "circle", "reverse", "turn"):
        if name in report:
            entry = report[name]
            lines.append(f"| {name} | falls | {int(entry['nominal']['fell'])}/1 | "
                         + " | ".join(f"{entry[m]['falls']}/{entry[m]['seeds']}" for m in modes)
                         + " |" * len(modes))
    sweeps = report.get("sweeps", {})
    if sweeps.get("latency"):
        swept = [m for m in modes if m in sweeps["latency"][0]]
        lines += ["", "Tracking joint RMSE (rad) against actuator latency (falls in brackets):", "",
                  "| latency (ms) | " + " | ".join(names[m] for m in swept) + " |", "|---|" + "---|" * len(swept)]
        for row in sweeps["latency"]:
            cells = [f"{_fmt(row[m]['joint_rmse'])}" + (f" ({row[m]['falls']}/{row[m]['seeds']} fell)"
                                                         if row[m]["falls"] else "") for m in swept]
            lines.append(f"| {row['latency_ms']:g} | " + " | ".join(cells) + " |")
    if sweeps.get("eq9_gain"):
        lines += ["", f"Tracking joint RMSE (rad) against the Eq. 9 gains (scale on Kp', Kd'); direct transfer: "
                      f"{_fmt(sweeps.get('eq9_gain_direct_reference'))}:", "", "| scale | PINN (Eq. 9) |",
                  "|---|---|"]
        for row in sweeps["eq9_gain"]:
            fell = f" ({row['pinn']['falls']}/{row['pinn']['seeds']} fell)" if row["pinn"]["falls"] else ""
            lines.append(f"| {row['scale']:g} | {_fmt(row['pinn']['joint_rmse'])}{fell} |")
    return "\n".join(lines) + "\n"


def _mean_std(entry: dict, key: str) -> str:
    value, std = entry.get(key), entry.get(f"{key}_std")
    return _fmt(value) + (f" ± {_fmt(std, 2)}" if std is not None and value is not None else "")


def suite_markdown(reports: dict[str, dict], modes, table: dict, estimator: str = "kinematic") -> str:
    """Every profile x mode x experiment (mean ± std over seeds, falls), the latency each mode tolerates, and the
    acceptance bars of each mode with the recommendation."""
    names = {m: "Eq. 9 (paper)" if m in ("pinn", "eq9") else mode_label(m) for m in modes}
    lines = ["## Every profile", "",
             "Joint RMSE (rad) against the nominal run, offset / shape its split (RMS over joints of each joint's "
             "mean error / of the rest); circle: distance from the simulator's own base path at the same tick and "
             "from the ideal circle (m); falls over seeds.", "",
             "| profile | scheme | tracking RMSE | offset / shape | circle RMSE | circle dev. vs simulator | "
             "circle dev. (ideal) | falls |", "|---|---|---|---|---|---|---|---|"]
    for profile, report in reports.items():
        tracking, circle = report.get("tracking", {}), report.get("circle", {})
        for mode in modes:
            t, c = tracking.get(mode, {}), circle.get(mode, {})
            falls = " · ".join(f"{name} {report[name][mode]['falls']}/{report[name][mode]['seeds']}"
                               for name in report if name != "sweeps" and mode in report[name])
            lines.append(f"| {profile} | {names[mode]} | {_mean_std(t, 'joint_rmse')} | {_fmt(t.get('offset'))} / "
                         f"{_fmt(t.get('shape'))} | {_mean_std(c, 'joint_rmse')} | "
                         f"{_mean_std(c, 'mean_deviation_from_simulator')} | {_mean_std(c, 'mean_radial_deviation')} "
                         f"| {falls} |")
    tolerance = next((r["sweeps"]["latency_tolerance_ms"] for r in reports.values()
                      if "latency_tolerance_ms" in r.get("sweeps", {})), None)
    if tolerance:
        lines += ["", f"Actuator latency tolerated (ms; the largest swept latency up to which no seed fell), on "
                      f"`{next(iter(reports))}`:", "", "| " + " | ".join(names[m] for m in modes) + " |",
                  "|" + "---|" * len(modes), "| " + " | ".join(_fmt(tolerance.get(m)) for m in modes) + " |"]
    lines += ["", f"## Acceptance ({estimator}: issue {BARS[estimator].issue}'s bars)", "",
              "| scheme | bar | value | limit | pass |", "|---|---|---|---|---|"]
    for mode, bars in table.items():
        for bar, result in bars.items():
            where = f" ({result['experiment']})" if "experiment" in result else ""
            note = f" ({result['note']})" if "note" in result else ""
            lines.append(f"| {names.get(mode, mode)} | {bar}{where} | {_fmt(result['value'])} | "
                         f"{_fmt(result['limit'])} | {'yes' if result['pass'] else 'no'}{note} |")
    choice = recommended(table)
    lines += ["", f"Recommended: **{names[choice]}**" if choice else
              "Recommended: none (no scheme other than Eq. 9 and the perfect-model controls passes every bar)."]
    return "\n".join(lines) + "\n"


def plot(out: Path, report: dict, traces: dict, joint_names: tuple[str, ...]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = [m for m in (traces.get("tracking") or next(iter(traces.values()), {})) if m != "nominal"]
    cycle = ("tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
    colours = {"nominal": "k", "direct": "tab:red", "pinn": "tab:blue", LOOKAHEAD_MODE: "tab:green"}
    for mode in modes:
        colours.setdefault(mode, cycle[len(colours) % len(cycle)])
    labels = {"nominal": "simulator (nominal)", **{m: mode_label(m) for m in modes}}
    written = []
    if "tracking" in traces:
        fig, axes = plt.subplots(2, 3, figsize=(15, 7.5))
        for mode, record in traces["tracking"].items():
            kw = {"color": colours[mode], "label": labels[mode], "lw": 0.8}
            window = (record.t >= 10.0) & (record.t < 11.0)
            axes[0, 0].plot(record.t[window], record.q[window, 0], **kw)
            axes[0, 1].plot(record.t[window], record.qd[window, 0], **kw)
            axes[0, 2].plot(record.t[window], record.tau[window, 0], **kw)
            axes[1, 0].plot(record.q[window, 0], record.qd[window, 0], **kw)
            axes[1, 1].plot(record.t[::10], record.velocity[::10, 0], **kw)
        for ax, title in zip(axes.flat, (f"{joint_names[0]} angle (rad)", f"{joint_names[0]} velocity (rad/s)",
                                         f"{joint_names[0]} torque (N m)", f"{joint_names[0]} phase portrait",
                                         "forward velocity (m/s)"), strict=False):
            ax.set_title(title)
            ax.legend(fontsize=7)
        entry = report["tracking"]
        x = np.arange(len(joint_names))
        shown = [m for m in modes if m in entry]
        width = 0.8 / len(shown)
        for i, mode in enumerate(shown):
            axes[1, 2].bar(x + (i - (len(shown) - 1) / 2) * width, entry[mode]["joint_rmse_per_joint"], width,
                           color=colours[mode], label=labels[mode])
        axes[1, 2].set_xticks(x, joint_names, rotation=60, fontsize=7)
        axes[1, 2].set_title("joint RMSE against the simulator (rad)")
        axes[1, 2].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "fig6_tracking.png", dpi=110)
        plt.close(fig)
        written.append("fig6_tracking.png")
    for name, figure in (("circle", "fig7_circle.png"), ("reverse", "fig8_reverse.png"), ("turn", "fig9_turn.png")):
        if name not in traces:
            continue
        fig, (path_ax, speed_ax) = plt.subplots(1, 2, figsize=(12, 5))
        command = tuple(report[name]["command"])
        for mode, record in traces[name].items():
            kw = {"color": colours[mode], "label": labels[mode], "lw": 1.0}
            path_ax.plot(record.xy[:, 0], record.xy[:, 1], **kw)
            axis = 2 if command[0] == 0.0 else 0
            speed_ax.plot(record.t[::10], record.velocity[::10, axis], **kw)
        nominal = traces[name]["nominal"]
        if name == "circle":
            circle = report[name]["nominal"]
            theta = np.linspace(0, 2 * np.pi, 200)
            path_ax.plot(circle["centre"][0] + circle["radius"] * np.cos(theta),
                         circle["centre"][1] + circle["radius"] * np.sin(theta), "k--", lw=0.8, label="ideal circle")
        elif len(nominal.t):
            ideal = ideal_path(command, nominal.t, nominal.xy[0], float(nominal.yaw[0]))
            path_ax.plot(ideal[:, 0], ideal[:, 1], "k--", lw=0.8, label="commanded path")
        path_ax.set_aspect("equal", adjustable="datalim")
        path_ax.set_title(f"{name}: base path (m), command {command}")
        speed_ax.set_title("yaw rate (rad/s)" if command[0] == 0.0 else "forward velocity (m/s)")
        path_ax.legend(fontsize=7)
        speed_ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / figure, dpi=110)
        plt.close(fig)
        written.append(figure)
    sweeps = report.get("sweeps", {})
    if sweeps.get("latency") or sweeps.get("eq9_gain"):
        fig, (lat_ax, gain_ax) = plt.subplots(1, 2, figsize=(12, 4.5))
        if sweeps.get("latency"):
            lat = [r["latency_ms"] for r in sweeps["latency"]]
            for mode in (m for m in colours if m in sweeps["latency"][0]):
                lat_ax.plot(lat, [r[mode]["joint_rmse"] for r in sweeps["latency"]], "o-", color=colours[mode],
                            label=labels[mode])
            lat_ax.set_xlabel("actuator latency (ms)")
            lat_ax.set_ylabel("tracking joint RMSE (rad)")
            lat_ax.legend(fontsize=8)
        if sweeps.get("eq9_gain"):
            scale = [r["scale"] for r in sweeps["eq9_gain"]]
            gain_ax.plot(scale, [r["pinn"]["joint_rmse"] for r in sweeps["eq9_gain"]], "o-", color=colours["pinn"],
                         label=MODE_NAMES["pinn"])
            if sweeps.get("eq9_gain_direct_reference") is not None:
                gain_ax.axhline(sweeps["eq9_gain_direct_reference"], color=colours["direct"], ls="--",
                                label=labels["direct"])
            gain_ax.set_xlabel("Eq. 9 gain scale (Kp', Kd')")
            gain_ax.set_ylabel("tracking joint RMSE (rad)")
            gain_ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "fig10_sweeps.png", dpi=110)
        plt.close(fig)
        written.append("fig10_sweeps.png")
    return written


def _numbers(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip()) if text.strip() else ()
    except ValueError:
        raise TransferError(f"{option}: expected comma-separated numbers, got {text!r}") from None


def add_parser(commands) -> argparse.ArgumentParser:
    p = commands.add_parser("transfer", help="sim-to-real rehearsal: direct vs PINN transfer on a gapped mock",
                            description=__doc__.split("\n\n")[0])
    p.add_argument("--gap", default=None,
                   help="reality-gap profile: a name in configs/gaps or a YAML path, or several, comma-separated: "
                        "each is evaluated, the sweeps on the first (default: default)")
    p.add_argument("--suite", choices=sorted(SUITES), default=None,
                   help="a named list of profiles instead of --gap: " + "; ".join(
                       f"{name} = {','.join(profiles)}" for name, profiles in SUITES.items()))
    p.add_argument("--out", type=Path, required=True, help="directory for transfer.json, transfer.md and PNGs")
    p.add_argument("--seeds", default="0,1,2", help="gap noise seeds per mode (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=DEFAULT_SECONDS, help="per run (default: %(default)s)")
    p.add_argument("--controller", choices=("policy", "teacher"), default="policy",
                   help="nominal controller (default: the committed policy)")
    p.add_argument("--estimator", choices=("kinematic", "truth"), default="kinematic",
                   help="base state for every controller and scheme: kinematic (default; robot-faithful): IMU + leg "
                        "kinematics + contact switches on the gapped sensors, as on the robot, and the twin "
                        "resynchronised from that estimate; truth: the simulator's truth (a diagnostic: no robot "
                        "has it)")
    p.add_argument("--experiments", default=",".join(e.name for e in EXPERIMENTS),
                   help="subset of %(default)s")
    p.add_argument("--latencies-ms", default=",".join(f"{v:g}" for v in DEFAULT_LATENCIES_MS),
                   help="actuator latency sweep, '' to skip (default: %(default)s)")
    p.add_argument("--gain-scales", default=",".join(f"{v:g}" for v in DEFAULT_GAIN_SCALES),
                   help="Eq. 9 gain sweep, '' to skip (default: %(default)s)")
    p.add_argument("--sweep-seeds", default="0,1", help="gap noise seeds per sweep point (default: %(default)s)")
    p.add_argument("--lookahead", default="auto",
                   help="the look-ahead variant's extra PINN ticks: N, 'auto' (the gap's actuator + sensor latency) "
                        "or 'off' (default: %(default)s)")
    p.add_argument("--schemes", default=None,
                   help="comma-separated modes to compare with direct transfer: transfer schemes (direct, pinn = eq9, "
                        "shadow, observer) and SCHEME@nominal for a scheme's perfect-model control (default: pinn and "
                        "its look-ahead variant)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="robot config override for every run, e.g. transfer.observer.time_constant_s=0.5 (repeatable)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel runs (default: CPU count)")
    p.add_argument("--config", default=None, help="robot config (default: BRUCE's)")
    return p


def profiles_from_args(args) -> tuple[tuple[str, RealityGap], ...]:
    """(name, gap) of each profile of --gap or --suite, in order."""
    suite, gaps = getattr(args, "suite", None), getattr(args, "gap", None)
    if suite is not None and gaps is not None:
        raise TransferError("--gap and --suite: give one (a suite is a list of profiles)")
    names = SUITES[suite] if suite is not None else tuple(n.strip() for n in (gaps or "default").split(","))
    if not all(names):
        raise TransferError(f"--gap: an empty profile name in {gaps!r}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise TransferError(f"--gap: {twice[0]!r} given twice")
    return tuple((name, load_gap(name)) for name in names)


def settings_from_args(args) -> TransferSettings:
    names = tuple(n.strip() for n in args.experiments.split(",") if n.strip())
    known = {e.name for e in EXPERIMENTS}
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise TransferError(f"--experiments: {unknown or names!r} not among {sorted(known)}")
    seeds = tuple(int(s) for s in _numbers(args.seeds, "--seeds"))
    sweep_seeds = tuple(int(s) for s in _numbers(args.sweep_seeds, "--sweep-seeds"))
    if not seeds:
        raise TransferError("--seeds: at least one seed")
    if not args.seconds > TRACKING_SKIP_S:
        raise TransferError(f"--seconds: must exceed the {TRACKING_SKIP_S:g} s start-up that is not scored")
    latencies, scales = _numbers(args.latencies_ms, "--latencies-ms"), _numbers(args.gain_scales, "--gain-scales")
    if (latencies or scales) and not sweep_seeds:
        raise TransferError("--sweep-seeds: at least one seed when sweeping")
    lookahead: int | str | None = args.lookahead
    if lookahead == "off":
        lookahead = None
    elif lookahead != "auto":
        try:
            lookahead = int(lookahead)
        except ValueError:
            raise TransferError(f"--lookahead: expected ticks >= 1, 'auto' or 'off', got {args.lookahead!r}") from None
        if lookahead < 1:
            raise TransferError(f"--lookahead: expected ticks >= 1, 'auto' or 'off', got {args.lookahead!r}")
    schemes = None
    if getattr(args, "schemes", None) is not None:
        schemes = tuple(m.strip() for m in args.schemes.split(",") if m.strip())
        for mode in schemes:
            scheme, model = scheme_of(mode)
            if scheme not in TRANSFER_SCHEMES or model not in (None, *REFERENCE_MODELS):
                raise TransferError(f"--schemes: {mode!r}: expected SCHEME or SCHEME@MODEL with SCHEME one of "
                                    f"{', '.join(TRANSFER_SCHEMES)} and MODEL one of {', '.join(REFERENCE_MODELS)}")
    overrides = tuple(getattr(args, "overrides", None) or ())
    if overrides:
        overridden = load_config(args.config or DEFAULT_CONFIG, list(overrides))  # a bad --set fails here
        policy = overridden.models.policy
        if policy is not None and not Path(policy).is_file():  # before the worker processes, which would raise
            raise TransferError(f"--set policy.model: {policy}: policy file not found")
        if policy is not None:
            policy_spec_for(overridden, Path(policy))  # a bad spec is one line here, not a worker's traceback
    profiles = profiles_from_args(args)
    return TransferSettings(gap=profiles[0][1], gap_name=profiles[0][0], profiles=profiles, lookahead=lookahead,
                            seeds=seeds, schemes=schemes, overrides=overrides,
                            seconds=args.seconds,
                            controller=args.controller, estimator=args.estimator, experiments=names,
                            latencies_ms=latencies, gain_scales=scales, sweep_seeds=sweep_seeds,
                            jobs=max(1, args.jobs), config=args.config)


def run_transfer(args, argv: list[str]) -> int:
    try:
        settings = settings_from_args(args)
        config = load_config(settings.config) if settings.config else load_config()
    except (TransferError, GapError, ConfigError) as exc:
        print(f"bruce-eval: error: {exc}", file=sys.stderr)
        return 1
    profiles = settings.per_profile()
    first = profiles[0]
    figure_runs = [_spec(first, EXPERIMENT_BY_NAME[name], mode, first.seeds[0]) for name in first.experiments
                   for mode in first.modes]
    args.out.mkdir(parents=True, exist_ok=True)
    results = execute(plan_suite(settings), args.out, settings.jobs, keep=figure_runs)
    reports = {profile.gap_name: evaluate(profile, results)[0] for profile in profiles[1:]}
    report, traces = evaluate(first, results)
    reports = {first.gap_name: report, **reports}
    meta = {"command": "bruce-eval " + " ".join(argv), "gap_name": settings.gap_name, "profiles": list(reports),
            "gap": {k: v for k, v in dataclasses.asdict(settings.gap).items()}, "controller": settings.controller,
            "estimator": settings.estimator, "seconds": settings.seconds, "seeds": list(settings.seeds),
            "sweep_seeds": list(settings.sweep_seeds), "joints": list(config.joints),
            "lookahead": None if settings.lookahead is None else (
                f"auto ({lookahead_ticks('auto', settings.gap)})" if settings.lookahead == "auto"
                else settings.lookahead),
            "scored_after_s": TRACKING_SKIP_S, "modes": list(settings.modes), "overrides": list(settings.overrides)}
    table = acceptance(reports, settings.modes, settings.estimator)
    document = {"meta": meta, "recommended": recommended(table), "acceptance": table, **report}
    if len(reports) > 1:
        document["profiles"] = reports
    (args.out / "transfer.json").write_text(json.dumps(json_safe(document), indent=2) + "\n")
    text = markdown(report, meta) + "\n" + suite_markdown(reports, settings.modes, table, settings.estimator)
    (args.out / "transfer.md").write_text(text)
    try:
        figures = plot(args.out, report, traces, tuple(config.joints))
    except ModuleNotFoundError as exc:  # matplotlib comes with the `train` extra; the numbers do not need it
        figures = [f"no figures ({exc.name} is not installed: pip install -e '.[train]')"]
    print(text)
    print(f"bruce-eval: wrote {args.out}/transfer.json, transfer.md, {', '.join(figures)}")
    return 0
