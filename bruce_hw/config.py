"""Robot description: YAML -> validated, typed objects.

Every joint-space array is ordered as `joints.names`. A bad file fails with one `ConfigError` that names the
file, the dotted key path and what was expected, before anything talks to a robot.
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bruce_hw.coupling import Coupling
from drivers.can_motor import MitRanges  # the MIT frame ranges: one type for the config and the driver

DEFAULT_CONFIG = "configs/robots/bruce.yaml"
_MODELS_DIR = Path(__file__).resolve().parent / "models"


class ConfigError(ValueError):
    """A robot config that cannot be used; the message names the file, the key and the expectation."""


@dataclass(frozen=True, slots=True)
class PdGains:
    kp: np.ndarray
    kd: np.ndarray


@dataclass(frozen=True, slots=True)
class SerialBus:
    port: str
    baud: int
    ids: tuple[int, ...] = ()
    # Motor-side watchdog: the devices stop (BEAR: damping; Dynamixel: Bus Watchdog stop) after this long without a
    # packet from the host; 0: not configured (the sense board has none).
    watchdog_s: float = 0.0
    # Seconds per count of the device's watchdog register (BEAR: undocumented, assumed until measured with
    # `bruce-hw-check --probe-watchdog`; Dynamixel: 20 ms by the control table).
    watchdog_unit_s: float = 0.0


@dataclass(frozen=True, slots=True)
class CanMotor:
    """One MIT-mode CAN motor: the actuator in the coupling column of joint slot `slot` (joints.names order)."""

    slot: str
    channel: str
    id: int
    gear: float      # actuator output per motor output: motor position = gear * sign * (m - offset)
    sign: float      # +1 or -1
    offset: float    # rad, actuator position at the motor's zero
    ranges: MitRanges


@dataclass(frozen=True, slots=True)
class CanBus:
    interface: str
    channel: str                          # default channel of `motors`
    bitrate: int | None = None            # None: as the interface is set up (socketcan: `ip link`)
    host_id: int = 0                      # arbitration ID the motors reply on
    timeout_s: float | None = None        # per-tick reply timeout; None: the driver's default
    motor_type: str | None = None         # what the ranges were chosen for, e.g. "AK80-9 V1.1"
    motors: tuple[CanMotor, ...] = ()     # legs on CAN: one per joint slot, in joints.names order; () when not

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(m.channel for m in self.motors))


@dataclass(frozen=True, slots=True)
class Buses:
    bear: SerialBus
    dynamixel: SerialBus
    sense: SerialBus
    can: CanBus


@dataclass(frozen=True, slots=True)
class ArmConfig:
    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    hold_pose: np.ndarray


@dataclass(frozen=True, slots=True)
class SafetyConfig:
    damping_kd: float
    damping_hold_s: float
    soft_start_s: float
    torque_ramp_s: float
    position_margin: float
    max_torque_rate: float
    tilt_limit_deg: float
    tilt_ticks: int
    max_sensor_age_s: float
    overrun_streak: int
    reply_loss_max: float        # damping when one motor loses more than this share of its replies ...
    reply_loss_window_s: float   # ... over this window (single lost replies are not faults)


@dataclass(frozen=True, slots=True)
class ModelsConfig:
    policy: Path | None       # ONNX walking policy; None: the standing controller
    # C_T of the policy's gait clock as (vx, C_T) points, linear between them (runtime.walking.gait.GaitClock);
    # a single number in the YAML is a constant C_T.
    gait_period_s: tuple[tuple[float, float], ...]
    pinn: Path | None         # ONNX PINN for --transfer pinn
    # Extra PINN ticks rolled ahead for the Eq. 9 reference (0: the paper's one-step prediction), to cover the
    # actuators' latency: a torque sent now acts that many ticks later.
    pinn_lookahead_ticks: int = 0


@dataclass(frozen=True, slots=True)
class RobotConfig:
    path: Path
    name: str
    mjcf: Path
    loop_hz: int
    policy_hz: int
    joints: tuple[str, ...]
    q_lower: np.ndarray
    q_upper: np.ndarray
    tau_limit: np.ndarray
    qd_limit: np.ndarray
    standing_pose: np.ndarray
    eq8: PdGains
    eq9: PdGains
    actuator_torque_limit: float
    torque_per_amp: float
    coupling: Coupling
    arms: ArmConfig
    safety: SafetyConfig
    models: ModelsConfig
    buses: Buses
    raw: dict

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def dt(self) -> float:
        return 1.0 / self.loop_hz

    @property
    def policy_decimation(self) -> int:
        return self.loop_hz // self.policy_hz

    def joint_indices(self, *kinds: str) -> np.ndarray:
        """Indices of the joints whose names end with any of `kinds` (e.g. "ankle", "hip_roll"), both legs."""
        return np.array([i for i, name in enumerate(self.joints) if name.endswith(kinds)], dtype=int)


class _Reader:
    """Typed access to a parsed YAML tree; every failure names the file and the dotted key."""

    def __init__(self, path: Path, data: Any):
        self.path = path
        self.data = data

    def fail(self, key: str, expected: str, got: Any = None, *, show_got: bool = True) -> ConfigError:
        tail = f", got {got!r}" if show_got else ""
        return ConfigError(f"{self.path}: {key}: expected {expected}{tail}")

    def node(self, key: str) -> Any:
        node = self.data
        walked = []
        for part in key.split("."):
            if not isinstance(node, dict):
                raise self.fail(".".join(walked), "a mapping", node)
            if part not in node:
                raise ConfigError(f"{self.path}: {key}: missing key (expected under '{'.'.join(walked) or '<top>'}')")
            node = node[part]
            walked.append(part)
        return node

    def mapping(self, key: str, allowed: set[str] | None = None) -> dict:
        node = self.node(key)
        if not isinstance(node, dict):
            raise self.fail(key, "a mapping", node)
        if allowed is not None:
            unknown = sorted(set(node) - allowed)
            if unknown:
                raise ConfigError(f"{self.path}: {key}.{unknown[0]}: unknown key (expected one of {sorted(allowed)})")
        return node

    def number(self, key: str, *, positive: bool = False) -> float:
        value = self.node(key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, "a number", value)
        if positive and not value > 0:
            raise self.fail(key, "a number > 0", value)
        return float(value)

    def integer(self, key: str, *, positive: bool = False) -> int:
        value = self.node(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, "an integer", value)
        if positive and value <= 0:
            raise self.fail(key, "an integer > 0", value)
        return value

    def string(self, key: str) -> str:
        value = self.node(key)
        if not isinstance(value, str) or not value:
            raise self.fail(key, "a non-empty string", value)
        return value

    def names(self, key: str, length: int | None = None) -> tuple[str, ...]:
        value = self.node(key)
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise self.fail(key, "a list of names", value)
        if length is not None and len(value) != length:
            raise self.fail(key, f"a list of {length} names, got {len(value)}", show_got=False)
        if len(set(value)) != len(value):
            raise self.fail(key, "unique names", value)
        return tuple(value)

    def vector(self, key: str, length: int, value: Any = None) -> np.ndarray:
        """A list of `length` numbers at `key` (or `value`, already looked up, reported as `key`)."""
        value = self.node(key) if value is None else value
        if not isinstance(value, list):
            raise self.fail(key, f"a list of {length} numbers", value)
        if len(value) != length:
            raise self.fail(key, f"a list of {length} numbers, got {len(value)} entries", show_got=False)
        for i, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise self.fail(f"{key}[{i}]", "a number", v)
        return np.asarray(value, dtype=np.float64)

    def per_joint(self, key: str, joints: tuple[str, ...], width: int = 1) -> np.ndarray:
        """A mapping joint name -> number (or [numbers] of `width`), returned in `joints` order."""
        node = self.mapping(key)
        unknown = [name for name in node if name not in joints]
        if unknown:
            raise ConfigError(f"{self.path}: {key}.{unknown[0]}: unknown joint (expected one of {list(joints)})")
        missing = [name for name in joints if name not in node]
        if missing:
            raise ConfigError(f"{self.path}: {key}.{missing[0]}: missing joint (every joint of {list(joints)} "
                              "needs a value)")
        if width == 1:
            return np.array([self.number(f"{key}.{name}") for name in joints])
        return np.stack([self.vector(f"{key}.{name}", width) for name in joints])


def _resolve_mjcf(config_path: Path, name: str, key: str) -> Path:
    candidate = Path(name)
    for path in (candidate if candidate.is_absolute() else config_path.parent / candidate, _MODELS_DIR / name):
        if path.is_file():
            return path.resolve()
    raise ConfigError(f"{config_path}: {key}: model file {name!r} not found beside the config or in {_MODELS_DIR}")


def _limits(r: _Reader, key: str, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    pairs = r.per_joint(key, names, width=2)
    for name, (lo, hi) in zip(names, pairs, strict=True):
        if not lo < hi:
            raise r.fail(f"{key}.{name}", "[lower, upper] with lower < upper", [float(lo), float(hi)])
    return pairs[:, 0].copy(), pairs[:, 1].copy()


def _gains(r: _Reader, key: str, joints: tuple[str, ...]) -> PdGains:
    r.mapping(key, {"kp", "kd"})
    kp, kd = r.per_joint(f"{key}.kp", joints), r.per_joint(f"{key}.kd", joints)
    for name, values in (("kp", kp), ("kd", kd)):
        if np.any(values < 0):
            bad = joints[int(np.argmax(values < 0))]
            raise r.fail(f"{key}.{name}.{bad}", "a gain >= 0", float(values[joints.index(bad)]))
    return PdGains(kp=kp, kd=kd)


def _serial(r: _Reader, key: str, with_ids: bool, n_ids: int = 0, watchdog_unit_s: float | None = None) -> SerialBus:
    """`watchdog_unit_s`: the register's fixed unit (Dynamixel); None: `watchdog_unit_s` is a key (BEAR)."""
    allowed = {"port", "baud", "ids", "watchdog_s", "watchdog_unit_s"} if with_ids else {"port", "baud"}
    if watchdog_unit_s is not None:
        allowed.discard("watchdog_unit_s")
    node = r.mapping(key, allowed)
    ids: tuple[int, ...] = ()
    if with_ids:
        raw = r.node(f"{key}.ids")
        if not isinstance(raw, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in raw):
            raise r.fail(f"{key}.ids", "a list of integer device IDs", raw)
        if len(raw) != n_ids:
            raise r.fail(f"{key}.ids", f"a list of {n_ids} IDs, got {len(raw)}", show_got=False)
        if len(set(raw)) != len(raw) or not all(0 <= i < 0xFE for i in raw):
            raise r.fail(f"{key}.ids", "unique IDs in 0..253", raw)
        ids = tuple(raw)
    watchdog_s = r.number(f"{key}.watchdog_s") if "watchdog_s" in node else 0.0
    if watchdog_unit_s is None:
        watchdog_unit_s = r.number(f"{key}.watchdog_unit_s", positive=True) if "watchdog_unit_s" in node else 0.001
    return SerialBus(port=r.string(f"{key}.port"), baud=r.integer(f"{key}.baud", positive=True), ids=ids,
                     watchdog_s=watchdog_s, watchdog_unit_s=watchdog_unit_s if with_ids else 0.0)


_CAN_KEYS = {"interface", "channel", "bitrate", "host_id", "timeout_s", "motor_type", "ranges", "motors"}
_CAN_MOTOR_KEYS = {"id", "channel", "gear", "sign", "offset", "ranges"}
_CAN_RANGE_KEYS = ("p", "v", "kp", "kd", "t")


def _can_ranges(r: _Reader, key: str) -> MitRanges:
    r.mapping(key, set(_CAN_RANGE_KEYS))
    pairs = {}
    for name in _CAN_RANGE_KEYS:
        lo, hi = (float(x) for x in r.vector(f"{key}.{name}", 2))
        gain = name in ("kp", "kd")
        if not lo < hi or (gain and lo < 0):
            raise r.fail(f"{key}.{name}", "[min, max] with min < max" + (" and min >= 0" if gain else ""), [lo, hi])
        pairs[name] = (lo, hi)
    return MitRanges(**pairs)


def _can_motor(r: _Reader, key: str, slot: str, channel: str, default_ranges: MitRanges | None) -> CanMotor:
    node = r.mapping(key, _CAN_MOTOR_KEYS)
    motor_id = r.integer(f"{key}.id")
    gear = r.number(f"{key}.gear", positive=True) if "gear" in node else 1.0
    sign = r.number(f"{key}.sign") if "sign" in node else 1.0
    if sign not in (1.0, -1.0):
        raise r.fail(f"{key}.sign", "1 or -1", node["sign"])
    offset = r.number(f"{key}.offset") if "offset" in node else 0.0
    if "ranges" in node:
        ranges = _can_ranges(r, f"{key}.ranges")
    elif default_ranges is None:
        raise ConfigError(f"{r.path}: {key}.ranges: missing key (and no buses.can.ranges default)")
    else:
        ranges = default_ranges
    return CanMotor(slot=slot, channel=str(node.get("channel", channel)), id=motor_id, gear=gear, sign=sign,
                    offset=offset, ranges=ranges)


def _can(r: _Reader, joints: tuple[str, ...]) -> CanBus:
    """buses.can: the interface and channel, and optionally the legs on MIT-mode CAN motors (`motors`)."""
    node = r.mapping("buses.can", _CAN_KEYS)
    channel = str(r.node("buses.can.channel"))
    host_id = r.integer("buses.can.host_id") if "host_id" in node else 0
    if not 0 <= host_id <= 0x7FF:
        raise r.fail("buses.can.host_id", "a standard CAN ID 0..2047", host_id)
    motors: tuple[CanMotor, ...] = ()
    if "motors" in node:
        default_ranges = _can_ranges(r, "buses.can.ranges") if "ranges" in node else None
        table = r.mapping("buses.can.motors")
        unknown = [name for name in table if name not in joints]
        if unknown:
            raise ConfigError(f"{r.path}: buses.can.motors.{unknown[0]}: unknown joint (expected one of "
                              f"{list(joints)})")
        missing = [name for name in joints if name not in table]
        if missing:
            raise ConfigError(f"{r.path}: buses.can.motors.{missing[0]}: missing joint (every joint slot of "
                              f"{list(joints)} needs a motor)")
        motors = tuple(_can_motor(r, f"buses.can.motors.{name}", name, channel, default_ranges) for name in joints)
        ids = [m.id for m in motors]
        if len(set(ids)) != len(ids) or not all(1 <= i <= 0xFF and i != host_id for i in ids):
            raise r.fail("buses.can.motors", f"unique motor IDs in 1..255, other than host_id {host_id}", ids)
    elif "ranges" in node:
        _can_ranges(r, "buses.can.ranges")
    return CanBus(
        interface=r.string("buses.can.interface"),
        channel=channel,
        bitrate=r.integer("buses.can.bitrate", positive=True) if "bitrate" in node else None,
        host_id=host_id,
        timeout_s=r.number("buses.can.timeout_s", positive=True) if "timeout_s" in node else None,
        motor_type=r.string("buses.can.motor_type") if "motor_type" in node else None,
        motors=motors,
    )


_TOP_KEYS = {"name", "mjcf", "rates", "joints", "gains", "actuators", "coupling", "arms", "safety", "policy", "pinn",
             "buses"}

_SAFETY_KEYS = {"damping_kd", "damping_hold_s", "soft_start_s", "torque_ramp_s", "position_margin", "max_torque_rate",
                "tilt_limit_deg", "tilt_ticks", "max_sensor_age_s", "overrun_streak", "reply_loss_max",
                "reply_loss_window_s"}


def _safety(r: _Reader) -> SafetyConfig:
    r.mapping("safety", _SAFETY_KEYS)
    return SafetyConfig(
        damping_kd=r.number("safety.damping_kd"),
        damping_hold_s=r.number("safety.damping_hold_s"),
        soft_start_s=r.number("safety.soft_start_s", positive=True),
        torque_ramp_s=r.number("safety.torque_ramp_s"),
        position_margin=r.number("safety.position_margin"),
        max_torque_rate=r.number("safety.max_torque_rate", positive=True),
        tilt_limit_deg=r.number("safety.tilt_limit_deg", positive=True),
        tilt_ticks=r.integer("safety.tilt_ticks", positive=True),
        max_sensor_age_s=r.number("safety.max_sensor_age_s", positive=True),
        overrun_streak=r.integer("safety.overrun_streak", positive=True),
        reply_loss_max=r.number("safety.reply_loss_max", positive=True),
        reply_loss_window_s=r.number("safety.reply_loss_window_s", positive=True),
    )


def _model_file(r: _Reader, key: str) -> Path | None:
    """An optional model path (None when null), resolved beside the config; existence is checked at load time
    by the runtime, which names the file."""
    value = r.node(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise r.fail(key, "a model file path or null", value)
    path = Path(value)
    return path if path.is_absolute() else (r.path.parent / path)


def _gait_cadence(r: _Reader) -> tuple[tuple[float, float], ...]:
    key = "policy.gait_period_s"
    value = r.node(key)
    if isinstance(value, int | float) and not isinstance(value, bool):
        return ((0.0, r.number(key, positive=True)),)
    expected = "a period > 0 (s) or a list of [vx (m/s), period > 0 (s)] pairs in increasing vx"
    if not isinstance(value, list) or not value:
        raise r.fail(key, expected, value)
    points = []
    for point in value:
        if (not isinstance(point, list) or len(point) != 2
                or any(isinstance(x, bool) or not isinstance(x, int | float) for x in point) or not point[1] > 0):
            raise r.fail(key, expected, point)
        points.append((float(point[0]), float(point[1])))
    if any(b[0] <= a[0] for a, b in itertools.pairwise(points)):
        raise r.fail(key, expected, value)
    return tuple(points)


def _models(r: _Reader) -> ModelsConfig:
    r.mapping("policy", {"model", "gait_period_s"})
    pinn = r.mapping("pinn", {"model", "lookahead_ticks"})
    lookahead = 0
    if "lookahead_ticks" in pinn:
        lookahead = r.integer("pinn.lookahead_ticks")
        if lookahead < 0:
            raise r.fail("pinn.lookahead_ticks", "an integer >= 0 (0: the paper's one-step reference)", lookahead)
    return ModelsConfig(policy=_model_file(r, "policy.model"),
                        gait_period_s=_gait_cadence(r),
                        pinn=_model_file(r, "pinn.model"), pinn_lookahead_ticks=lookahead)


def parse_config(data: Any, path: Path) -> RobotConfig:
    r = _Reader(path, data)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: <top>: expected a mapping of sections {sorted(_TOP_KEYS)}, got {data!r}")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: {unknown[0]}: unknown key (expected one of {sorted(_TOP_KEYS)})")

    r.mapping("rates", {"loop_hz", "policy_hz"})
    loop_hz, policy_hz = r.integer("rates.loop_hz", positive=True), r.integer("rates.policy_hz", positive=True)
    if loop_hz % policy_hz:
        raise r.fail("rates.policy_hz", f"a divisor of rates.loop_hz ({loop_hz})", policy_hz)

    r.mapping("joints", {"names", "position_limits", "torque_limits", "velocity_limits", "standing_pose"})
    joints = r.names("joints.names")
    n = len(joints)
    q_lower, q_upper = _limits(r, "joints.position_limits", joints)
    tau_limit = r.per_joint("joints.torque_limits", joints)
    qd_limit = r.per_joint("joints.velocity_limits", joints)
    for key, values in (("joints.torque_limits", tau_limit), ("joints.velocity_limits", qd_limit)):
        if np.any(values <= 0):
            raise r.fail(f"{key}.{joints[int(np.argmax(values <= 0))]}", "a limit > 0", float(values.min()))
    standing = r.per_joint("joints.standing_pose", joints)
    outside = (standing < q_lower) | (standing > q_upper)
    if outside.any():
        name = joints[int(np.argmax(outside))]
        raise r.fail(f"joints.standing_pose.{name}", "a position inside joints.position_limits",
                     float(standing[joints.index(name)]))

    r.mapping("gains", {"eq8", "eq9"})
    eq8, eq9 = _gains(r, "gains.eq8", joints), _gains(r, "gains.eq9", joints)

    r.mapping("actuators", {"torque_limit", "torque_per_amp"})
    r.mapping("coupling", {"joint_from_actuator"})
    rows = r.node("coupling.joint_from_actuator")
    if not isinstance(rows, list) or len(rows) != n:
        got = len(rows) if isinstance(rows, list) else rows
        raise r.fail("coupling.joint_from_actuator", f"a {n}x{n} matrix (one row per joint), got {got!r} rows",
                     show_got=False)
    matrix = np.stack([r.vector(f"coupling.joint_from_actuator[{i}]", n, row) for i, row in enumerate(rows)])
    if abs(np.linalg.det(matrix)) < 1e-9:
        raise r.fail("coupling.joint_from_actuator", "an invertible matrix", "singular", show_got=True)

    r.mapping("arms", {"names", "position_limits", "hold_pose"})
    arm_names = r.names("arms.names")
    clash = set(arm_names) & set(joints)
    if clash:
        raise r.fail("arms.names", "names distinct from joints.names", sorted(clash))
    arm_lower, arm_upper = _limits(r, "arms.position_limits", arm_names)
    hold = r.per_joint("arms.hold_pose", arm_names)

    r.mapping("buses", {"bear", "dynamixel", "sense", "can"})
    buses = Buses(
        bear=_serial(r, "buses.bear", with_ids=True, n_ids=n),
        dynamixel=_serial(r, "buses.dynamixel", with_ids=True, n_ids=len(arm_names), watchdog_unit_s=0.02),
        sense=_serial(r, "buses.sense", with_ids=False),
        can=_can(r, joints),
    )

    return RobotConfig(
        path=path,
        name=r.string("name"),
        mjcf=_resolve_mjcf(path, r.string("mjcf"), "mjcf"),
        loop_hz=loop_hz,
        policy_hz=policy_hz,
        joints=joints,
        q_lower=q_lower,
        q_upper=q_upper,
        tau_limit=tau_limit,
        qd_limit=qd_limit,
        standing_pose=standing,
        eq8=eq8,
        eq9=eq9,
        actuator_torque_limit=r.number("actuators.torque_limit", positive=True),
        torque_per_amp=r.number("actuators.torque_per_amp", positive=True),
        coupling=Coupling(matrix),
        arms=ArmConfig(names=arm_names, lower=arm_lower, upper=arm_upper, hold_pose=hold),
        safety=_safety(r),
        models=_models(r),
        buses=buses,
        raw=data,
    )


def apply_overrides(data: dict, overrides: list[str], path: Path) -> dict:
    """Apply `KEY=VALUE` overrides (dotted key paths, VALUE parsed as YAML) to a copy of the raw tree.

    Only existing keys can be set, so a typo fails instead of being ignored.
    """
    data = copy.deepcopy(data)
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"{path}: --set {item!r}: expected KEY=VALUE with a dotted key path")
        parts = key.split(".")
        node = data
        for depth, part in enumerate(parts):
            if not isinstance(node, dict) or part not in node:
                parent = ".".join(parts[:depth]) or "<top>"
                raise ConfigError(f"{path}: {key}: no such key to --set (nothing named {part!r} under {parent})")
            if depth == len(parts) - 1:
                node[part] = yaml.safe_load(text) if text else ""
            else:
                node = node[part]
    return data


def resolve_config_path(path: str | Path = DEFAULT_CONFIG) -> Path:
    """A config path as given; a relative `configs/robots/NAME.yaml` missing from the working directory falls
    back to the copy installed with the package, so the default works from any directory."""
    path = Path(path)
    if path.is_file():
        return path.resolve()
    if not path.is_absolute() and path.parent.as_posix() == "configs/robots":
        packaged = resources.files("configs.robots") / path.name
        if packaged.is_file():
            return Path(str(packaged))
    raise ConfigError(f"{path}: robot config file not found")


def load_config(path: str | Path = DEFAULT_CONFIG, overrides: list[str] | None = None) -> RobotConfig:
    resolved = resolve_config_path(path)
    try:
        data = yaml.safe_load(resolved.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{resolved}: not valid YAML: {exc}") from exc
    if overrides:
        data = apply_overrides(data, overrides, resolved)
    return parse_config(data, resolved)
