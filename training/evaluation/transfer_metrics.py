"""The transfer rehearsal's metrics: a run's joints against the nominal run's (`joint_rmse`, `offset_and_shape`), its
base path against the simulator's (`deviation_from_simulator`) and the ideal one (`circle_deviation`, `drift`),
scored after the start-up transient and up to a fall (`run_metrics`), and their mean over gap seeds (`aggregate`)."""

from __future__ import annotations

import math

import numpy as np

from runtime.control.commands import CommandSchedule
from runtime.loop.observers import TRACKING_SKIP_S
from training.evaluation.transfer_runs import Experiment, RunRecord


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
    if record.twin_rmse_per_joint is not None:  # the twin metric (runtime.transfer.twin_metric), mean over joints
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
