"""Per-episode domain randomisation: the ranges (`RandomisationRanges`), a batch of draws (`draw` -> `Draws`) and
their application to one environment's MjModel (`apply_draw`).

The paper's ground friction, sensor noise and inference delay, plus the reality-gap profiles' parameters, whose model
part goes through the mock's own `bruce_hw.reality_gap.apply_to_model`. On `sim_model`'s PD actuators the
torque-constant error scales the gains and the saturated torque (the mock scales the torque after its saturation),
and the torque lag filters the PD target: it approximates a lag of the torque (Eq. 8's q and qd terms are not lagged).
Latency and noise are applied by the environment.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import mujoco
import numpy as np

from bruce_hw.reality_gap import GAP_BOUNDS, RealityGap, apply_to_model
from bruce_hw.yaml_reader import Bound, YamlReader
from training.rl.sim_model import RANDOMISED_FIELDS, SimModel


def _range(key: str, default: tuple[float, float], bound: Bound, per: str = "episode") -> Any:
    """A randomised quantity: its YAML key, its [low, high] default and the bound both ends must be inside.
    `per`: "episode" (one draw per episode), "joint" (one per joint per episode) or "axis" (one per base axis x, y, z
    per episode)."""
    return field(default=default, metadata={"key": key, "bound": bound, "per": per})


_NOISE = Bound(0.0, 1.0, "", "a noise std")
_BIAS = Bound(-0.2, 0.2, "", "a sensor's constant offset")


@dataclass(frozen=True)
class RandomisationRanges:
    """Each field a [low, high] range, drawn uniformly per episode (per joint where said); checked on construction
    (errors name `source` and the key under `key`)."""

    source: str = field(default="RandomisationRanges", compare=False)  # where the values came from (a YAML file)
    key: str = field(default="randomisation", compare=False)           # ... and under which key
    ground_friction: tuple[float, float] = _range(
        "ground_friction", (0.5, 1.25), Bound(0.05, 2.0, "", "sliding friction coefficient, floor and feet"))
    joint_coulomb_nm: tuple[float, float] = _range("joint_coulomb_nm", (0.0, 0.3), GAP_BOUNDS["friction.coulomb"],
                                                   "joint")
    joint_viscous_nms: tuple[float, float] = _range("joint_viscous_nms", (0.0, 0.1), GAP_BOUNDS["friction.viscous"],
                                                    "joint")
    mass_scale: tuple[float, float] = _range("mass_scale", (0.9, 1.2), GAP_BOUNDS["inertia.mass_scale"])
    inertia_scale: tuple[float, float] = _range("inertia_scale", (0.9, 1.2), GAP_BOUNDS["inertia.inertia_scale"])
    # Armature: the MJCF's one BEAR rotor per joint, scaled, plus up to a second rotor's (gap profiles: +0.00182 on
    # the two-BEAR joints, x1.3 in `harsh`).
    armature_scale: tuple[float, float] = _range("armature_scale", (0.8, 1.3), GAP_BOUNDS["inertia.armature_scale"],
                                                 "joint")
    armature_add_kgm2: tuple[float, float] = _range("armature_add_kgm2", (0.0, 0.0025),
                                                    GAP_BOUNDS["inertia.armature_add"], "joint")
    torque_scale: tuple[float, float] = _range("torque_scale", (0.85, 1.15), GAP_BOUNDS["actuator.torque_scale"],
                                               "joint")
    torque_limit_scale: tuple[float, float] = _range("torque_limit_scale", (0.75, 1.0),
                                                     GAP_BOUNDS["actuator.torque_limit_scale"])
    # Actuator latency and the sensors' lumped into one delay of the PD target (gap profiles: 0 to 7 ms together).
    latency_ticks: tuple[int, int] = _range(
        "latency_ticks", (0, 8), Bound(0, 9, "ticks", "1 ms ticks, inside one 10 ms policy period", integer=True))
    torque_lag_s: tuple[float, float] = _range("torque_lag_s", (0.0, 0.006),
                                               GAP_BOUNDS["actuator.time_constant_s"])
    # Observation noise: the std of each is drawn per episode, the noise itself per policy step.
    noise_q_rad: tuple[float, float] = _range("noise.q_rad", (0.0, 0.003), _NOISE)
    noise_qd_rads: tuple[float, float] = _range("noise.qd_rads", (0.0, 0.1), _NOISE)
    noise_linvel_ms: tuple[float, float] = _range("noise.linvel_ms", (0.0, 0.05), _NOISE)
    noise_angvel_rads: tuple[float, float] = _range("noise.angvel_rads", (0.0, 0.03), _NOISE)
    noise_euler_rad: tuple[float, float] = _range("noise.euler_rad", (0.0, 0.01), _NOISE)
    # Sensor offsets, constant over an episode (gap profiles: encoder zero offsets up to 0.01 rad, gyro drift up to
    # 0.01 rad/s in `harsh`; an attitude filter's slow error).
    bias_q_rad: tuple[float, float] = _range("bias.q_rad", (0.0, 0.0), _BIAS, "joint")
    bias_angvel_rads: tuple[float, float] = _range("bias.angvel_rads", (0.0, 0.0), _BIAS, "axis")
    bias_euler_rad: tuple[float, float] = _range("bias.euler_rad", (0.0, 0.0), _BIAS, "axis")

    def __post_init__(self) -> None:
        r = YamlReader(self.source, None, ValueError)
        for f in _RANGES:
            key = f"{self.key}.{f.metadata['key']}" if self.key else f.metadata["key"]
            object.__setattr__(self, f.name, _checked_range(r, key, getattr(self, f.name), f.metadata["bound"]))

    @classmethod
    def read(cls, r: YamlReader, key: str) -> RandomisationRanges:
        """The ranges under `key` of the reader's tree (every key optional: the defaults fill in)."""
        keys = [f.metadata["key"] for f in _RANGES]
        node = r.mapping(key, {k.split(".")[0] for k in keys})
        groups = {group: r.mapping(f"{key}.{group}", {k.removeprefix(f"{group}.") for k in keys
                                                      if k.startswith(f"{group}.")}) if group in node else {}
                  for group in _GROUPS}
        values = {}
        for f, k in zip(_RANGES, keys, strict=True):
            group, _, name = k.rpartition(".")
            where = groups[group] if group else node
            if name in where:
                values[f.name] = where[name]
        return cls(source=str(r.source), key=key, **values)


_RANGES = tuple(f for f in fields(RandomisationRanges) if "key" in f.metadata)
_GROUPS = ("noise", "bias")


def _checked_range(r: YamlReader, key: str, value: Any, bound: Bound) -> tuple:
    """[low, high] (a list or tuple of 2 numbers, each inside `bound`, low <= high) as a tuple."""
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise r.fail(key, "[low, high] (a list of 2 numbers)", value)
    low, high = (r.number(f"{key}[{i}]", v, bound) for i, v in enumerate(value))
    if low > high:
        raise r.fail(key, "[low, high] with low <= high", [low, high])
    return low, high


@dataclass
class Draws:
    """The randomised quantities of a batch of n episodes: (n,) arrays, (n, n_joints) for the per-joint ones, (n, 3)
    for the per-axis ones."""

    ground_friction: np.ndarray
    joint_coulomb_nm: np.ndarray
    joint_viscous_nms: np.ndarray
    mass_scale: np.ndarray
    inertia_scale: np.ndarray
    armature_scale: np.ndarray
    armature_add_kgm2: np.ndarray
    torque_scale: np.ndarray
    torque_limit_scale: np.ndarray
    latency_ticks: np.ndarray
    torque_lag_s: np.ndarray
    noise_q_rad: np.ndarray
    noise_qd_rads: np.ndarray
    noise_linvel_ms: np.ndarray
    noise_angvel_rads: np.ndarray
    noise_euler_rad: np.ndarray
    bias_q_rad: np.ndarray
    bias_angvel_rads: np.ndarray
    bias_euler_rad: np.ndarray

    def assign(self, envs: np.ndarray, other: Draws) -> None:
        """Rows `envs` of this batch take the rows of `other`, in order."""
        for f in fields(self):
            getattr(self, f.name)[envs] = getattr(other, f.name)

    def row(self, i: int) -> dict[str, Any]:
        return {f.name: getattr(self, f.name)[i] for f in fields(self)}


def draw(ranges: RandomisationRanges, rng: np.random.Generator, n: int, n_joints: int) -> Draws:
    """n episodes' draws, uniform in `ranges` (latency: integers, both ends included)."""
    values = {}
    for f in _RANGES:
        low, high = getattr(ranges, f.name)
        shape = {"episode": (n,), "joint": (n, n_joints), "axis": (n, 3)}[f.metadata["per"]]
        if f.metadata["bound"].integer:
            values[f.name] = rng.integers(low, high, size=shape, endpoint=True)
        else:
            values[f.name] = rng.uniform(low, high, size=shape)
    return Draws(**values)


def apply_draw(sim: SimModel, model: mujoco.MjModel, joints: tuple[str, ...], row: dict[str, Any],
               scratch: mujoco.MjData) -> None:
    """Put one episode's draw (`Draws.row`) into `model`, a copy of `sim.model`, from its nominal values; `scratch`
    is an MjData of `sim.model` for the derived constants."""
    for name in RANDOMISED_FIELDS:
        getattr(model, name)[:] = sim.nominal[name]
    gap = RealityGap(source="randomisation", coulomb=dict(zip(joints, row["joint_coulomb_nm"].tolist(), strict=True)),
                     viscous=dict(zip(joints, row["joint_viscous_nms"].tolist(), strict=True)),
                     mass_scale=float(row["mass_scale"]), inertia_scale=float(row["inertia_scale"]),
                     armature_scale=dict(zip(joints, row["armature_scale"].tolist(), strict=True)),
                     armature_add=dict(zip(joints, row["armature_add_kgm2"].tolist(), strict=True)))
    apply_to_model(gap, model, sim.dofs, sim.acts, joints, scratch)
    if gap.mass_scale == 1.0 and gap.inertia_scale == 1.0 and np.all(row["armature_scale"] == 1.0) and \
            not np.any(row["armature_add_kgm2"]):
        mujoco.mj_setConst(model, scratch)  # apply_to_model did not: the nominal inertia is back
    friction = float(row["ground_friction"])
    model.geom_friction[sim.floor_geom, 0] = friction
    model.geom_friction[sim.foot_geoms, 0] = friction  # the contact takes the larger of the two geoms'
    acts, scale = sim.acts, row["torque_scale"]
    model.actuator_gainprm[acts, 0] = sim.kp * scale
    model.actuator_biasprm[acts, 1] = -sim.kp * scale
    model.actuator_biasprm[acts, 2] = -sim.kd * scale
    limit = sim.torque_limit * float(row["torque_limit_scale"]) * scale
    model.actuator_forcerange[acts] = np.stack([-limit, limit], axis=1)
    model.actuator_dynprm[acts, 0] = float(row["torque_lag_s"])
