"""Reality-gap profiles: what makes a perturbed mock play "the real robot" while the nominal mock is "the simulator".

A `RealityGap` lists the differences (every field defaults to "no gap"); `load_gap` reads one from
`configs/gaps/<name>.yaml` or a path. The mock backend (`bruce_hw.mock.MujocoBackend(gap=...)`) applies it:

- in the model, once (`apply_to_model`): joint Coulomb and viscous friction as MuJoCo's own `dof_frictionloss` and
  `dof_damping` (solved implicitly, so stiff values stay stable), added to the MJCF's; body mass and inertia scales;
  joint armature (scale, then an added reflected inertia); the motors' joint box limits scaled with the torque limit;
- on the command path, every physics tick (`ActuatorGap`): the command applied is the one sent `latency` ticks ago
  (the bus), saturated at the scaled per-actuator limit, scaled by the torque-constant error (`torque_scale`: the
  drive sets the current for the nominal kt, the joint gets the true kt's torque), then followed by a first-order
  torque lag (the motor);
- on the sensor path (`SensorGap`): encoder and IMU noise and bias, the encoder's quantisation, then the state
  reported is the one measured `latency` ticks ago, with the stamps of when it was measured; the IMU sample is
  older still by its own latency (with its own stamp), the foot switches report the contact of `contacts.delay_s`
  before that and chatter for `contacts.bounce_s` after each change.

Per-joint values are a number (every joint) or a mapping joint name -> number (joints left out take the no-gap
value). Simulator ground truth is never perturbed: it is what a run is evaluated against.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from bruce_hw.types import FOOT_CONTACT_NAMES, ImuSample, RobotState
from bruce_hw.yaml_reader import Bound, YamlReader, read_yaml

GAPS_PACKAGE = "configs.gaps"


class GapError(ValueError):
    """A reality-gap profile that cannot be used; the message names the file and the key."""


def _gap_field(key: str, bound: Bound, shape: str = "scalar", default: float = 0.0) -> Any:
    """A gap parameter: its YAML key (section.name), its valid range and its shape (scalar, per_joint or vec3)."""
    return field(default=default, metadata={"key": key, "bound": bound, "shape": shape})


# The ranges bound a plausible difference between BRUCE and its MJCF: a value beyond is a broken robot (a dead link,
# a jammed gear, a different robot), not a reality gap. Scales are of the MJCF's values; noise is a std.
_LATENCY = Bound(0.0, 0.05, "s", "50 ticks at 1 kHz: beyond is a dead link")
_SCALE = Bound(0.5, 2.0, "", "of the MJCF's value")


@dataclass(frozen=True)
class RealityGap:
    source: str = field(default="RealityGap", compare=False)  # where it came from (the YAML file), for errors
    seed: int = 0               # the noise generator's seed (numpy default_rng)
    actuator_latency_s: float = _gap_field("actuator.latency_s", _LATENCY)
    actuator_time_constant_s: float = _gap_field(
        "actuator.time_constant_s", Bound(0.0, 0.05, "s", "torque lag; 50 ms is a 3 Hz torque bandwidth"))
    torque_limit_scale: float = _gap_field(
        "actuator.torque_limit_scale", Bound(0.5, 1.0, "", "of the rated torque: kt spread, heat, battery sag"),
        default=1.0)
    torque_scale: Any = _gap_field(
        "actuator.torque_scale", Bound(0.5, 1.5, "", "of the commanded torque: a torque-constant error"),
        "per_joint", default=1.0)
    coulomb: Any = _gap_field(
        "friction.coulomb", Bound(0.0, 1.0, "N·m", "10 % of a BEAR's torque: beyond, a jammed gear"), "per_joint")
    viscous: Any = _gap_field(
        "friction.viscous", Bound(0.0, 0.5, "N·m·s/rad", "7.5 N·m at 15 rad/s"), "per_joint")
    mass_scale: float = _gap_field("inertia.mass_scale", _SCALE, default=1.0)
    inertia_scale: float = _gap_field("inertia.inertia_scale", _SCALE, default=1.0)
    armature_scale: Any = _gap_field("inertia.armature_scale", _SCALE, "per_joint", default=1.0)
    armature_add: Any = _gap_field(
        "inertia.armature_add", Bound(0.0, 0.01, "kg·m²", "5 BEAR rotors' reflected inertia"), "per_joint")
    q_noise: Any = _gap_field("encoder.q_noise", Bound(0.0, 0.05, "rad", "3 deg std"), "per_joint")
    q_bias: Any = _gap_field("encoder.q_bias", Bound(-0.1, 0.1, "rad", "6 deg: beyond, homing failed"), "per_joint")
    qd_noise: Any = _gap_field("encoder.qd_noise", Bound(0.0, 1.0, "rad/s", "std"), "per_joint")
    qd_bias: Any = _gap_field("encoder.qd_bias", Bound(-1.0, 1.0, "rad/s", "offset"), "per_joint")
    # The reported q is rounded to a multiple of this (after bias and noise); qd is left as it is (the BEAR reports
    # its own filtered velocity, not a difference of counts).
    q_resolution: Any = _gap_field(
        "encoder.q_resolution", Bound(0.0, 0.01, "rad", "0.6 deg per count, a 10-bit encoder's: coarser is no servo"),
        "per_joint")
    gyro_noise: float = _gap_field("imu.gyro_noise", Bound(0.0, 0.5, "rad/s", "std per axis"))
    gyro_bias: Any = _gap_field("imu.gyro_bias", Bound(-0.5, 0.5, "rad/s", "30 deg/s drift"), "vec3")
    accel_noise: float = _gap_field("imu.accel_noise", Bound(0.0, 2.0, "m/s²", "std per axis"))
    accel_bias: Any = _gap_field("imu.accel_bias", Bound(-2.0, 2.0, "m/s²", "a 12 deg calibration tilt"), "vec3")
    orientation_noise: float = _gap_field("imu.orientation_noise", Bound(0.0, 0.1, "rad", "6 deg std per axis"))
    # The IMU sample (gyro, accel, orientation and its stamp) is this much older than the joints' sample.
    imu_latency_s: float = _gap_field(
        "imu.latency_s", Bound(0.0, 0.05, "s", "beyond sensor.latency_s; 50 ticks at 1 kHz: beyond is a dead link"))
    sensor_latency_s: float = _gap_field("sensor.latency_s", _LATENCY)
    # Foot switches: the contact reported is the one of this long before the sample (switch travel, a debounce
    # filter), on top of sensor.latency_s; the stamp stays the sample's (the board cannot see the switch's delay).
    contact_delay_s: float = _gap_field(
        "contacts.delay_s", Bound(0.0, 0.05, "s", "beyond sensor.latency_s; 50 ms is a third of a stance phase"))
    # ... and for this long after each change of the (delayed) contact a switch chatters: each tick it reports a
    # fair coin (as if it flipped with probability 0.5 every tick), drawn from the seeded generator.
    contact_bounce_s: float = _gap_field(
        "contacts.bounce_s", Bound(0.0, 0.02, "s", "chatter after each change; switches bounce 1-5 ms, 20 ms is worn"))

    def __post_init__(self) -> None:
        r = self._reader()
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise r.fail("seed", "an integer >= 0", self.seed)
        for f in fields(self):
            if "key" in f.metadata:
                object.__setattr__(self, f.name, _checked(r, f.metadata, getattr(self, f.name)))

    def _reader(self) -> YamlReader:
        """The reader that checks values already looked up (from the YAML file or given in code)."""
        return YamlReader(self.source, None, GapError)

    def per_joint(self, name: str, joints: Sequence[str]) -> np.ndarray:
        """Field `name` as an array in `joints` order."""
        value = getattr(self, name)
        if not isinstance(value, dict):
            return np.full(len(joints), value)
        f = _FIELDS[name]
        self._reader().check_keys(f.metadata["key"], value, list(joints), what="joint")
        return np.array([value.get(j, f.default) for j in joints])

    def vec3(self, name: str) -> np.ndarray:
        return np.array(getattr(self, name), dtype=float) * np.ones(3)

    def check_joints(self, joints: Sequence[str]) -> None:
        """Every per-joint mapping names joints of `joints` (raises GapError naming the file and key)."""
        for name, f in _FIELDS.items():
            if f.metadata["shape"] == "per_joint":
                self.per_joint(name, joints)


_FIELDS = {f.name: f for f in fields(RealityGap) if "key" in f.metadata}
_ATTR_OF_KEY = {f.metadata["key"]: name for name, f in _FIELDS.items()}
SECTIONS = tuple(dict.fromkeys(key.split(".")[0] for key in _ATTR_OF_KEY))
_NAMES_OF_SECTION = {section: {key.split(".")[1] for key in _ATTR_OF_KEY if key.startswith(f"{section}.")}
                     for section in SECTIONS}
GAP_BOUNDS = {f.metadata["key"]: f.metadata["bound"] for f in _FIELDS.values()}  # docs/config_bounds.md


def _checked(r: YamlReader, meta: Any, value: Any) -> Any:
    """A gap parameter's value (a number, or a mapping joint -> number, or [x, y, z] by its shape) inside its bound."""
    key, bound, shape = meta["key"], meta["bound"], meta["shape"]
    if shape == "per_joint" and isinstance(value, dict):
        return {str(j): r.number(f"{key}.{j}", v, bound) for j, v in value.items()}
    if shape == "vec3" and isinstance(value, list | tuple | np.ndarray):
        return tuple(float(v) for v in r.vector(key, 3, list(value), bound))
    also = {"per_joint": " or a mapping joint name -> number", "vec3": " or a list of 3 numbers"}.get(shape, "")
    return r.number(key, value, bound, also=also)


# -- loading -------------------------------------------------------------------------------------------------
def profile_names() -> list[str]:
    """The shipped profiles (configs/gaps/*.yaml)."""
    return sorted(p.name[:-5] for p in resources.files(GAPS_PACKAGE).iterdir() if p.name.endswith(".yaml"))


def gap_path(name_or_path: str | Path) -> Path:
    """A bare name is a shipped profile (configs/gaps/<name>.yaml); anything with a directory or a .yaml/.yml
    suffix is a path."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or len(path.parts) > 1:
        if not path.is_file():
            raise GapError(f"{path}: reality-gap profile file not found")
        return path
    packaged = resources.files(GAPS_PACKAGE) / f"{path.name}.yaml"
    if packaged.is_file():
        return Path(str(packaged))
    raise GapError(f"unknown reality-gap profile {str(name_or_path)!r}: expected a YAML path or one of "
                   f"{profile_names()} (configs/gaps/)")


def parse_gap(data: Any, source: str, joints: Sequence[str] | None = None) -> RealityGap:
    """A parsed YAML tree -> RealityGap; unknown sections or keys, wrong types and out-of-range values raise
    GapError naming `source` and the key. With `joints`, per-joint mappings are checked against them. An empty file
    is refused (a typo'd path to an empty file would otherwise be a robot without any gap): `none` says "no gap"."""
    if data is None:
        raise GapError(f"{source}: empty: a reality-gap profile sets at least one of {', '.join(SECTIONS)} "
                       "(configs/gaps/none.yaml lists every key; --gap none is the robot without a gap)")
    r = YamlReader(source, data, GapError)
    top = r.mapping("", {"seed", *SECTIONS})
    values: dict[str, Any] = {"seed": top["seed"]} if "seed" in top else {}
    for section in SECTIONS:
        if top.get(section) is not None:  # an empty section is no gap
            for name, value in r.mapping(section, _NAMES_OF_SECTION[section]).items():
                values[_ATTR_OF_KEY[f"{section}.{name}"]] = value
    gap = RealityGap(source=source, **values)  # checks the values
    if joints is not None:
        gap.check_joints(joints)
    return gap


def load_gap(name_or_path: str | Path, joints: Sequence[str] | None = None) -> RealityGap:
    """The profile `name_or_path`: a shipped name (configs/gaps/<name>.yaml) or a YAML file."""
    path = gap_path(name_or_path)
    return parse_gap(read_yaml(path, GapError, "reality-gap profile"), str(path), joints)


def latency_ticks(seconds: float, dt: float) -> int:
    """A latency in whole physics ticks (rounded to the nearest)."""
    return round(seconds / dt)


# -- what the mock does with a gap ---------------------------------------------------------------------------
def apply_to_model(gap: RealityGap, model: mujoco.MjModel, dofs: slice, acts: slice,
                   joints: Sequence[str], scratch: mujoco.MjData | None = None) -> None:
    """Put the gap's friction, inertia and torque limits into the model, on top of the MJCF's values. Each change is
    made only when it changes something, so the "none" profile leaves the model bit-identical. `scratch`: an MjData
    of the model to reuse (making one costs ~0.5 ms)."""
    coulomb, viscous = gap.per_joint("coulomb", joints), gap.per_joint("viscous", joints)
    armature_scale, armature_add = gap.per_joint("armature_scale", joints), gap.per_joint("armature_add", joints)
    if np.any(coulomb):
        model.dof_frictionloss[dofs] += coulomb
    if np.any(viscous):
        model.dof_damping[dofs] += viscous
    inertial = False
    if np.any(armature_scale != 1.0) or np.any(armature_add):
        model.dof_armature[dofs] = model.dof_armature[dofs] * armature_scale + armature_add
        inertial = True
    if gap.mass_scale != 1.0:
        model.body_mass[:] *= gap.mass_scale
        inertial = True
    if gap.inertia_scale != 1.0:
        model.body_inertia[:] *= gap.inertia_scale
        inertial = True
    if gap.torque_limit_scale != 1.0:
        model.actuator_ctrlrange[acts] *= gap.torque_limit_scale
    if inertial:
        # Derived constants (subtree masses, the constraint solver's inverse weights) as if compiled that way.
        mujoco.mj_setConst(model, mujoco.MjData(model) if scratch is None else scratch)


class DelayLine:
    """A fixed delay of `len(items)` ticks: each `pass_through(value)` returns what went in that many calls ago
    (at first, `items`, oldest first); no delay when empty."""

    def __init__(self, items: Sequence[Any] = ()):
        self.fill(items)

    def fill(self, items: Sequence[Any]) -> None:
        self._ring = list(items)
        self._at = 0

    def pass_through(self, value: Any) -> Any:
        ring = self._ring
        if not ring:
            return value
        out, ring[self._at] = ring[self._at], value
        self._at = (self._at + 1) % len(ring)
        return out


class ActuatorGap:
    """The command path: a delay line of what was sent (bus latency), the torque-constant error and the motor's
    first-order torque lag."""

    def __init__(self, latency: int, time_constant_s: float, dt: float, n_joints: int,
                 torque_scale: np.ndarray | float = 1.0):
        self.latency = latency
        self._sent = DelayLine([None] * latency)
        # Exact discretisation of tau_applied' = (tau_cmd - tau_applied) / T under a zero-order-hold command.
        self.alpha = 1.0 - math.exp(-dt / time_constant_s) if time_constant_s > 0.0 else 1.0
        self.torque_scale = np.broadcast_to(np.asarray(torque_scale, float), (n_joints,)).copy()
        self._scaled = np.zeros(n_joints) if np.any(self.torque_scale != 1.0) else None
        self._applied = np.zeros(n_joints)
        self._change = np.zeros(n_joints)

    def reset(self) -> None:
        """Nothing sent yet, motors at zero torque."""
        self._sent.fill([None] * self.latency)
        self._applied[:] = 0.0

    def delayed(self, sent: Any) -> Any:
        """What reaches the motors this tick, given what was sent (None before the first command)."""
        return self._sent.pass_through(sent)

    def lag(self, tau: np.ndarray) -> np.ndarray:
        """The torque the motors apply during this tick, given the saturated command that arrived: scaled by the
        torque-constant error, then lagged (an internal buffer, or `tau` itself: copy what you keep)."""
        if self._scaled is not None:
            tau = np.multiply(tau, self.torque_scale, out=self._scaled)
        if self.alpha >= 1.0:
            return tau
        np.subtract(tau, self._applied, out=self._change)
        self._change *= self.alpha
        self._applied += self._change
        return self._applied


class SensorGap:
    """The sensor path: encoder and IMU noise and bias and the encoder's quantisation on each measurement, then the
    reported state is the one measured `latency` ticks ago; its IMU sample `imu_ticks` ticks older still (with its
    own stamp); its foot contacts those of `contact_ticks` ticks before its sample (the contacts' stamp stays the
    sample's), each switch chattering for `bounce_ticks` ticks after each change of that delayed contact.

    The extra delays and the bounce are whole ticks (`latency_ticks` of the gap's seconds and the physics tick
    `dt`, each rounded on its own). With the IMU latency and the contact delay and bounce all zero, none of that
    runs: the path is the one without them, draw for draw."""

    def __init__(self, gap: RealityGap, joints: Sequence[str], latency: int, dt: float):
        self.rng = np.random.default_rng(gap.seed)
        self.latency = latency
        self.q_bias, self.qd_bias = gap.per_joint("q_bias", joints), gap.per_joint("qd_bias", joints)
        self.q_noise, self.qd_noise = gap.per_joint("q_noise", joints), gap.per_joint("qd_noise", joints)
        self.gyro_bias, self.accel_bias = gap.vec3("gyro_bias"), gap.vec3("accel_bias")
        self.gyro_noise, self.accel_noise = gap.gyro_noise, gap.accel_noise
        self.orientation_noise = gap.orientation_noise
        self._encoder_noise = bool(np.any(self.q_noise) or np.any(self.qd_noise))
        self._bias = bool(np.any(self.q_bias) or np.any(self.qd_bias) or np.any(self.gyro_bias)
                          or np.any(self.accel_bias))
        self._measured = DelayLine()
        # Quantisation: q -> round(q / step) * step on the joints whose step is > 0 (a scratch array, no allocation).
        q_resolution = gap.per_joint("q_resolution", joints)
        self._quantised = bool(np.any(q_resolution))
        self._q_partly = None if np.all(q_resolution > 0.0) else q_resolution > 0.0  # the joints quantised, if not all
        self._q_step = np.where(q_resolution > 0.0, q_resolution, 1.0)
        self._counts = np.zeros(len(joints))
        # Extra IMU delay, contact delay and bounce, in ticks.
        self.imu_ticks = latency_ticks(gap.imu_latency_s, dt)
        self.contact_ticks = latency_ticks(gap.contact_delay_s, dt)
        self.bounce_ticks = latency_ticks(gap.contact_bounce_s, dt)
        self._staggered = bool(self.imu_ticks or self.contact_ticks or self.bounce_ticks)  # beyond the common latency
        self._imu, self._contacts = DelayLine(), DelayLine()
        self._reset = False  # the IMU and contact delay lines are filled by `reset`
        # Bounce: each switch's last delayed contact and the ticks its window has left.
        self._last_contact = np.zeros(len(FOOT_CONTACT_NAMES), dtype=bool)
        self._changed = np.zeros(len(FOOT_CONTACT_NAMES), dtype=bool)
        self._bouncing = np.zeros(len(FOOT_CONTACT_NAMES), dtype=bool)
        self._window = np.zeros(len(FOOT_CONTACT_NAMES), dtype=np.int64)
        self._uniform = np.zeros(len(FOOT_CONTACT_NAMES))
        self._flip = np.zeros(len(FOOT_CONTACT_NAMES), dtype=bool)
        self._last_key = b""
        self._open = 0  # ticks until every window has closed

    def reset(self, measure: Callable[[], RobotState]) -> None:
        """Fill the delay lines with measurements of the state just placed (what a robot reports before any
        newer sample has come through)."""
        self._measured.fill([self._corrupt(measure()) for _ in range(self.latency)])
        if not self._staggered:
            return
        # One more measurement for the IMU and contact lines: with the IMU's bias but no noise (no draw taken, so
        # the noise that follows is the same as without these lines).
        # The IMU and contact delay lines full of the placed state's (copies of its one measurement); no switch
        # bouncing.
        placed = measure()
        placed.imu.gyro += self.gyro_bias
        placed.imu.accel += self.accel_bias
        self._reset = True
        self._imu.fill([_copied_imu(placed.imu) for _ in range(self.imu_ticks)])
        self._contacts.fill([placed.contacts.contact.copy() for _ in range(self.contact_ticks)])
        self._last_contact[:] = placed.contacts.contact
        self._last_key = self._last_contact.tobytes()
        self._window[:] = 0
        self._open = 0

    def report(self, measured: RobotState) -> RobotState:
        state = self._measured.pass_through(self._corrupt(measured))
        if self._staggered:
            self._stagger(state)
        return state

    def _stagger(self, state: RobotState) -> None:
        """The extra IMU delay, the contact delay and the bounce, on the state leaving the common delay line (no
        longer held by it, so its fields can be swapped)."""
        if not self._reset:
            raise ValueError("SensorGap: report before reset (the IMU and contact delay lines are empty)")
        if self.imu_ticks:
            state.imu = self._imu.pass_through(state.imu)
        contacts = state.contacts
        if self.contact_ticks:
            contacts.contact = self._contacts.pass_through(contacts.contact)
        if self.bounce_ticks:
            self._bounce(contacts.contact)

    def _bounce(self, contact: np.ndarray) -> None:
        """Switch chatter, in place on the (delayed) contact array: a change of a switch's contact opens a window
        of `bounce_ticks` ticks, that tick included, in which the switch reports a fair coin."""
        window = self._window
        key = contact.tobytes()
        if key != self._last_key:  # some switch changed: (re)open its window
            np.not_equal(contact, self._last_contact, out=self._changed)
            np.copyto(window, self.bounce_ticks, where=self._changed)
            self._last_contact[:] = contact
            self._last_key = key
            self._open = self.bounce_ticks
        elif not self._open:  # no switch bouncing: nothing to do (most ticks)
            return
        self._open -= 1  # the longest window's ticks left after this one
        bouncing = np.greater(window, 0, out=self._bouncing)
        flip = np.less(self.rng.random(out=self._uniform), 0.5, out=self._flip)  # drawn only while bouncing
        flip &= bouncing
        contact ^= flip
        window -= bouncing

    def _corrupt(self, state: RobotState) -> RobotState:
        """Noise, bias and quantisation, in place on the measurement's own arrays."""
        joints, imu = state.joints, state.imu
        normal = self.rng.standard_normal
        if self._bias:
            joints.q += self.q_bias
            joints.qd += self.qd_bias
            imu.gyro += self.gyro_bias
            imu.accel += self.accel_bias
        if self._encoder_noise:
            joints.q += self.q_noise * normal(joints.q.shape[0])
            joints.qd += self.qd_noise * normal(joints.qd.shape[0])
        if self._quantised:
            counts = np.divide(joints.q, self._q_step, out=joints.q if self._q_partly is None else self._counts)
            np.round(counts, out=counts)
            counts *= self._q_step
            if self._q_partly is not None:
                np.copyto(joints.q, counts, where=self._q_partly)
        if self.gyro_noise:
            imu.gyro += self.gyro_noise * normal(3)
        if self.accel_noise:
            imu.accel += self.accel_noise * normal(3)
        if self.orientation_noise and imu.orientation is not None:
            # A small rotation (rotation vector ~ N(0, std^2) per axis) in the IMU frame; the result stays unit.
            mujoco.mju_quatIntegrate(imu.orientation, self.orientation_noise * normal(3), 1.0)
        return state


def _copied_imu(imu: ImuSample) -> ImuSample:
    return ImuSample(gyro=imu.gyro.copy(), accel=imu.accel.copy(),
                     orientation=None if imu.orientation is None else imu.orientation.copy(), stamp=imu.stamp)
