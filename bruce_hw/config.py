"""Robot description: YAML -> validated, typed objects.

Every joint-space array is ordered as `joints.names`. A bad file fails with one `ConfigError` that names the
file, the dotted key path and what was expected, before anything talks to a robot.

Every numeric setting has a physical range in `BOUNDS` (dotted key patterns -> `Bound`; docs/config_bounds.md is
the same table for users); relations between settings (a standing pose inside the soft limits, a torque limit the
actuators can reach) narrow it further where the file is read. The file is read through
`bruce_hw.yaml_reader.YamlReader`, as the reality-gap profiles and the command scenarios are.
"""

from __future__ import annotations

import itertools
import math
import sys
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from bruce_hw.coupling import Coupling
from bruce_hw.yaml_reader import Bound, YamlReader, apply_overrides, bound_lookup, read_yaml
from drivers.bear_registers import CONFIG_REGISTERS as BEAR_CONFIG_REGISTERS
from drivers.bear_registers import RATED_CURRENT_A
from drivers.can_motor_codec import MitRanges  # the MIT frame ranges: one type for the config and the driver

DEFAULT_CONFIG = "configs/robots/bruce.yaml"
# The BEAR's watchdog_timeout unit is undocumented: this is assumed until `bruce-hw-check --probe-watchdog` measures
# it and `buses.bear.watchdog_unit_s` says so.
ASSUMED_BEAR_WATCHDOG_UNIT_S = 0.001
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
    # How long one request waits for its replies (BEAR bus: a bulk cycle's, on the bus thread; 0: the driver's own).
    reply_timeout_s: float = 0.0
    # BEAR bus: the actuators' own PID gain registers, written with torque disabled and read back at start-up.
    gains: tuple[tuple[str, float], ...] = ()


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
    servo_signs: np.ndarray  # +1 or -1 per arm joint: joint angle = sign x servo angle (how each servo is mounted)


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
    min_rate_hz: float           # damping when the loop runs fewer ticks than this per second ...
    rate_window_s: float         # ... over this window (on the backend's clock; a late tick alone is not a fault)
    reply_loss_max: float        # damping when one motor loses more than this share of its replies ...
    reply_loss_window_s: float   # ... over this window (single lost replies are not faults)
    host_stall_max_s: float      # a host stall (the process not run) up to this long is ridden through


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
    # The PINN's mean one-step velocity error on the simulator itself (predicted minus simulated qd, rad/s, per
    # joint; None: not measured), which the residual observer takes off (runtime/transfer/observer.py).
    pinn_residual_bias: np.ndarray | None = None
    # The policy's observation/action spec (runtime/control/policy_spec.py); None: its sidecar's, else Table I.
    policy_spec: Path | None = None


@dataclass(frozen=True, slots=True)
class EstimatorConfig:
    """The kinematic base estimator's settings (`estimator` section, optional; runtime/estimation/kinematic.py)."""

    # > 0: for this long after the estimator starts, while both feet are flat, the accelerometer's horizontal bias
    # is learned so that gravity points along the feet plane's normal ("level is where the feet are"); 0: off.
    level_from_feet_s: float = 0.0


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
    raw: dict  # the YAML tree as read; the runtime reads its own `transfer` section from it (runtime/transfer/stage.py)
    estimator: EstimatorConfig = EstimatorConfig()
    # Ticks from a policy tick's reading to its targets taking effect (runtime/control/controller_runner.py): 0, on
    # that tick; >= 1, the controller runs beside the loop on a paced run and its targets are used that many ticks on.
    policy_lag_ticks: int = 0

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


# -- valid ranges ------------------------------------------------------------------------------------------------
BEAR_RATED_TORQUE = 10.5  # N·m, Koala BEAR: 30 A x 0.35 N·m/A (BRUCE-OP)
_TURN = 2 * math.pi
_MIT_RANGES = {  # each end of a MIT frame field's span; wider spans leave the 12/16-bit fields too coarse
    "p": Bound(-100.0, 100.0, "rad", "16-bit field: 3 mrad steps at ±100"),
    "v": Bound(-100.0, 100.0, "rad/s", "12-bit field: 0.05 rad/s steps at ±100"),
    "kp": Bound(0.0, 1000.0, "N·m/rad", "12-bit field"),
    "kd": Bound(0.0, 100.0, "N·m·s/rad", "12-bit field"),
    "t": Bound(-200.0, 200.0, "N·m", "12-bit field: 0.1 N·m steps at ±200"),
}

# Every numeric setting of a robot config: dotted key patterns ("*" one name, "[*]" one list index) -> Bound.
# Relations to other settings narrow some further where they are read (docs/config_bounds.md, "Relations").
BOUNDS: dict[str, Bound] = {
    "rates.loop_hz": Bound(100, 10_000, "Hz", "PD/bus loop: slower destabilises the PD, no bus keeps up faster",
                           integer=True),
    "rates.policy_hz": Bound(1, 10_000, "Hz", "walking policy; must divide rates.loop_hz", integer=True),
    "rates.policy_lag_ticks": Bound(0, 100, "ticks", "the policy's targets in force this many ticks after its reading; "
                                    "less than rates.loop_hz / rates.policy_hz", integer=True),
    "joints.position_limits.*[*]": Bound(-_TURN, _TURN, "rad", "a turn either way"),
    "joints.torque_limits.*": Bound(0.0, 120.0, "N·m", "at most what the actuators reach at the joint",
                                    low_open=True),
    "joints.velocity_limits.*": Bound(0.0, 50.0, "rad/s", "above any BRUCE leg joint's speed", low_open=True),
    "joints.standing_pose.*": Bound(-_TURN, _TURN, "rad", "inside the soft position limits"),
    "gains.*.kp.*": Bound(0.0, 500.0, "N·m/rad", "MIT-drive kp span; at 500 a 0.02 rad error asks 10 N·m"),
    "gains.*.kd.*": Bound(0.0, 5.0, "N·m·s/rad", "MIT-drive kd span; more is unstable at 1 kHz on light joints"),
    "actuators.torque_limit": Bound(0.0, 60.0, "N·m", "per actuator, at most its rating", low_open=True),
    "actuators.torque_per_amp": Bound(0.2, 0.5, "N·m/A", "Koala BEAR rating, nominal 0.35"),
    "coupling.joint_from_actuator[*][*]": Bound(-10.0, 10.0, "", "transmission ratio (BRUCE: 0, ±0.5, ±1)"),
    "arms.position_limits.*[*]": Bound(-_TURN, _TURN, "rad", "a turn either way"),
    "arms.hold_pose.*": Bound(-_TURN, _TURN, "rad", "inside arms.position_limits"),
    "arms.servo_signs.*": Bound(-1.0, 1.0, "", "+1 or -1: how the servo is mounted", integer=True),
    "safety.damping_kd": Bound(0.0, 5.0, "N·m·s/rad", "> 0 removes energy; more is unstable at 1 kHz",
                               low_open=True),
    "safety.damping_hold_s": Bound(0.0, 60.0, "s", "damping after a trip before release", low_open=True),
    "safety.soft_start_s": Bound(0.0, 30.0, "s", "ramp to the standing pose", low_open=True),
    "safety.torque_ramp_s": Bound(0.0, 5.0, "s", "torque fade-in; 0: none"),
    "safety.position_margin": Bound(0.0, 0.5, "rad", "soft limits inside the hard ones"),
    "safety.max_torque_rate": Bound(0.0, 1e5, "N·m/s", "torque slew limit", low_open=True),
    "safety.tilt_limit_deg": Bound(0.0, 90.0, "deg", "0 trips at once, 90 is lying down", low_open=True,
                                   high_open=True),
    "safety.tilt_ticks": Bound(1, 1000, "ticks", "1 s at 1 kHz", integer=True),
    "safety.max_sensor_age_s": Bound(0.0, 0.05, "s", "50 ms-old data is no feedback", low_open=True),
    "safety.min_rate_hz": Bound(50.0, 1000.0, "Hz", "achieved loop rate floor; at most rates.loop_hz"),
    "safety.rate_window_s": Bound(0.01, 1.0, "s", "window of the rate floor"),
    "safety.reply_loss_max": Bound(0.0, 0.5, "", "share of one motor's replies", low_open=True),
    "safety.reply_loss_window_s": Bound(0.05, 60.0, "s", "window of the reply-loss share"),
    "safety.host_stall_max_s": Bound(0.0, 0.5, "s", "held torque a walking BRUCE survives, less a margin "
                                     "(docs/safety.md); below the motors' watchdog"),
    "policy.gait_period_s": Bound(0.1, 2.0, "s", "a step cycle", low_open=True),
    "policy.gait_period_s[*][0]": Bound(-2.0, 2.0, "m/s", "vx of a cadence point"),
    "policy.gait_period_s[*][1]": Bound(0.1, 2.0, "s", "a step cycle", low_open=True),
    "pinn.lookahead_ticks": Bound(0, 50, "ticks", "50 ms of actuator latency", integer=True),
    "pinn.residual_bias.*": Bound(-1.0, 1.0, "rad/s", "the PINN's mean one-step qd error on the simulator"),
    "estimator.level_from_feet_s": Bound(0.0, 10.0, "s", "start-up levelling: the robot stands still that long"),
    "buses.*.baud": Bound(9600, 12_000_000, "bit/s", "UART rates up to the FTDI's 12 Mbaud", integer=True),
    "buses.bear.ids[*]": Bound(0, 253, "", "BEAR IDs; 254 is broadcast", integer=True),
    "buses.bear.watchdog_s": Bound(0.005, 1.0, "s", "a lost host must end in damping"),
    "buses.bear.watchdog_unit_s": Bound(1e-6, 1.0, "s", "seconds per watchdog count"),
    "buses.bear.reply_timeout_s": Bound(0.0005, 0.02, "s", "a bulk cycle's reply wait (BRUCE-OP: 2 ms)"),
    "buses.bear.gains.*": Bound(0.0, 1000.0, "", "a BEAR PID gain register (float32), never negative"),
    "buses.dynamixel.ids[*]": Bound(0, 252, "", "Dynamixel Protocol 2.0 IDs", integer=True),
    "buses.dynamixel.watchdog_s": Bound(0.02, 2.54, "s", "Bus Watchdog register 1..127 x 20 ms", step=0.02),
    "buses.can.bitrate": Bound(10_000, 1_000_000, "bit/s", "classic CAN", integer=True),
    "buses.can.host_id": Bound(0, 0x7FF, "", "standard CAN ID", integer=True),
    "buses.can.timeout_s": Bound(0.0, 0.1, "s", "per-tick reply wait", low_open=True),
    "buses.can.motors.*.id": Bound(1, 255, "", "MIT motor CAN ID", integer=True),
    "buses.can.motors.*.gear": Bound(0.0, 20.0, "", "actuator output per motor output", low_open=True),
    "buses.can.motors.*.sign": Bound(-1, 1, "", "motor direction", step=2),
    "buses.can.motors.*.offset": Bound(-_TURN, _TURN, "rad", "actuator position at the motor's zero"),
    **{f"{where}.{name}[*]": bound for where in ("buses.can.ranges", "buses.can.motors.*.ranges")
       for name, bound in _MIT_RANGES.items()},
}


bound_for = bound_lookup(BOUNDS, "BOUNDS")  # the Bound of a concrete key, e.g. "joints.velocity_limits.r_knee"


def find_mjcf(name: str | Path, beside: Path | None = None) -> Path | None:
    """A MuJoCo model file: `name` as a path (relative to the directory `beside`, else the working directory),
    else the file of that name shipped in bruce_hw/models/; None when neither exists."""
    candidate = Path(name)
    if not candidate.is_absolute() and beside is not None:
        candidate = beside / candidate
    for path in (candidate, _MODELS_DIR / candidate.name):
        if path.is_file():
            return path.resolve()
    return None


def _resolve_mjcf(config_path: Path, name: str, key: str) -> Path:
    path = find_mjcf(name, beside=config_path.parent)
    if path is None:
        raise ConfigError(f"{config_path}: {key}: model file {name!r} not found beside the config or in {_MODELS_DIR}")
    return path


def _limits(r: YamlReader, key: str, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    pairs = r.per_joint(key, names, width=2)
    for name, (lo, hi) in zip(names, pairs, strict=True):
        if not lo < hi:
            raise r.fail(f"{key}.{name}", "[lower, upper] with lower < upper", [float(lo), float(hi)])
    return pairs[:, 0].copy(), pairs[:, 1].copy()


def _inside(key: str, names: tuple[str, ...], lower: np.ndarray, upper: np.ndarray, why: str) -> list[Bound]:
    """Per-joint bounds of `key` narrowed to [lower, upper] (`why`: where those come from, "{name}" filled in)."""
    return [BOUNDS[f"{key}.*"].narrowed(why.format(name=name), lo, hi)
            for name, lo, hi in zip(names, lower, upper, strict=True)]


def _gains(r: YamlReader, key: str, joints: tuple[str, ...]) -> PdGains:
    r.mapping(key, {"kp", "kd"})
    return PdGains(kp=r.per_joint(f"{key}.kp", joints), kd=r.per_joint(f"{key}.kd", joints))


def _coupling(r: YamlReader, n: int) -> np.ndarray:
    key = "coupling.joint_from_actuator"
    r.mapping("coupling", {"joint_from_actuator"})
    rows = r.node(key)
    if not isinstance(rows, list) or len(rows) != n:
        got = len(rows) if isinstance(rows, list) else rows
        raise r.fail(key, f"a {n}x{n} matrix (one row per joint), got {got!r} rows", show_got=False)
    matrix = np.stack([r.vector(f"{key}[{i}]", n, row) for i, row in enumerate(rows)])
    singular = np.linalg.svd(matrix, compute_uv=False)
    if not singular[-1] > 1e-6 * singular[0]:  # a near-singular map turns small actuator errors into huge joint ones
        raise r.fail(key, "an invertible matrix (condition number < 1e6)", "singular")
    return matrix


def _serial(r: YamlReader, key: str, n_ids: int | None = None, watchdog_unit_s: float | None = None,
            min_watchdog_s: float = 0.0) -> SerialBus:
    """A serial bus; with `n_ids`, its device IDs and motor-side watchdog. `watchdog_unit_s`: the register's fixed
    unit (Dynamixel: `watchdog_s` optional, 0 when left out); None: a `watchdog_unit_s` key (BEAR: `watchdog_s`
    required and at least `min_watchdog_s`, since a lost host must end in damping)."""
    allowed = {"port", "baud"}
    if n_ids is not None:
        allowed |= {"ids", "watchdog_s"}
        if watchdog_unit_s is None:  # the BEAR bus
            allowed |= {"watchdog_unit_s", "reply_timeout_s", "gains"}
    node = r.mapping(key, allowed)
    bus = SerialBus(port=r.string(f"{key}.port"), baud=r.number(f"{key}.baud"))
    if n_ids is None:
        return bus
    raw = r.node(f"{key}.ids")
    if not isinstance(raw, list):
        raise r.fail(f"{key}.ids", "a list of integer device IDs", raw)
    if len(raw) != n_ids:
        raise r.fail(f"{key}.ids", f"a list of {n_ids} IDs, got {len(raw)}", show_got=False)
    ids = tuple(r.number(f"{key}.ids[{i}]", device_id) for i, device_id in enumerate(raw))
    if len(set(ids)) != len(ids):
        raise r.fail(f"{key}.ids", "unique IDs", raw)
    if watchdog_unit_s is None:
        watchdog_s = r.number(f"{key}.watchdog_s", bound=bound_for(f"{key}.watchdog_s").narrowed(
            "at least 2 ticks of rates.loop_hz, or one late tick trips it", low=min_watchdog_s))
        watchdog_unit_s = ASSUMED_BEAR_WATCHDOG_UNIT_S
        if "watchdog_unit_s" in node:
            watchdog_unit_s = r.number(f"{key}.watchdog_unit_s", bound=bound_for(f"{key}.watchdog_unit_s").narrowed(
                f"at most {key}.watchdog_s: one register count", high=watchdog_s))
    else:
        watchdog_s = r.number(f"{key}.watchdog_s") if "watchdog_s" in node else 0.0
    reply_timeout_s = r.number(f"{key}.reply_timeout_s") if "reply_timeout_s" in node else 0.0
    gains = _bear_gains(r, f"{key}.gains") if "gains" in allowed and "watchdog_unit_s" in allowed else ()
    return replace(bus, ids=ids, watchdog_s=watchdog_s, watchdog_unit_s=watchdog_unit_s,
                   reply_timeout_s=reply_timeout_s, gains=gains)


BEAR_GAIN_REGISTERS = tuple(name for name in BEAR_CONFIG_REGISTERS if "_gain_" in name)


def _bear_gains(r: YamlReader, key: str) -> tuple[tuple[str, float], ...]:
    """Every PID gain register of the BEARs (the driver's config table), by name: what start-up writes."""
    node = r.mapping(key, set(BEAR_GAIN_REGISTERS))
    missing = [name for name in BEAR_GAIN_REGISTERS if name not in node]
    if missing:
        raise r.fail(f"{key}.{missing[0]}", f"a value for every BEAR gain register ({', '.join(BEAR_GAIN_REGISTERS)})",
                     show_got=False)
    return tuple((name, r.number(f"{key}.{name}")) for name in BEAR_GAIN_REGISTERS)


_CAN_KEYS = {"interface", "channel", "bitrate", "host_id", "timeout_s", "motor_type", "ranges", "motors"}
_CAN_MOTOR_KEYS = {"id", "channel", "gear", "sign", "offset", "ranges"}
_CAN_RANGE_KEYS = ("p", "v", "kp", "kd", "t")


def _can_ranges(r: YamlReader, key: str) -> MitRanges:
    r.mapping(key, set(_CAN_RANGE_KEYS))
    pairs = {}
    for name in _CAN_RANGE_KEYS:
        lo, hi = (float(x) for x in r.vector(f"{key}.{name}", 2))
        gain = name in ("kp", "kd")
        if not (lo < hi if gain else lo < 0.0 < hi):  # a motor moves and pushes both ways; gains are >= 0
            raise r.fail(f"{key}.{name}", "[min, max] with min < max" if gain else "[min, max] with min < 0 < max",
                         [lo, hi])
        pairs[name] = (lo, hi)
    return MitRanges(**pairs)


def _can_motor(r: YamlReader, key: str, slot: str, channel: str, default_ranges: MitRanges | None) -> CanMotor:
    node = r.mapping(key, _CAN_MOTOR_KEYS)
    if "ranges" in node:
        ranges = _can_ranges(r, f"{key}.ranges")
    elif default_ranges is None:
        raise ConfigError(f"{r.source}: {key}.ranges: missing key (and no buses.can.ranges default)")
    else:
        ranges = default_ranges
    return CanMotor(slot=slot, channel=str(node.get("channel", channel)), id=r.number(f"{key}.id"),
                    gear=r.number(f"{key}.gear") if "gear" in node else 1.0,
                    sign=r.number(f"{key}.sign") if "sign" in node else 1.0,
                    offset=r.number(f"{key}.offset") if "offset" in node else 0.0, ranges=ranges)


def _can(r: YamlReader, joints: tuple[str, ...]) -> CanBus:
    """buses.can: the interface and channel, and optionally the legs on MIT-mode CAN motors (`motors`)."""
    node = r.mapping("buses.can", _CAN_KEYS)
    channel = str(r.node("buses.can.channel"))
    host_id = r.number("buses.can.host_id") if "host_id" in node else 0
    motors: tuple[CanMotor, ...] = ()
    if "motors" in node:
        default_ranges = _can_ranges(r, "buses.can.ranges") if "ranges" in node else None
        r.check_keys("buses.can.motors", r.mapping("buses.can.motors"), joints, joints, what="joint",
                     missing=f" (every joint slot of {list(joints)} needs a motor)")
        motors = tuple(_can_motor(r, f"buses.can.motors.{name}", name, channel, default_ranges) for name in joints)
        first = {}  # motor ID -> the slot that has it
        for m in motors:
            clash = first.setdefault(m.id, m.slot)
            if clash != m.slot or m.id == host_id:
                also = f"buses.can.motors.{clash}.id" if clash != m.slot else "buses.can.host_id"
                raise r.fail(f"buses.can.motors.{m.slot}.id", f"unique motor IDs, other than buses.can.host_id "
                             f"({host_id}), got {m.id} (as {also})", show_got=False)
    elif "ranges" in node:
        _can_ranges(r, "buses.can.ranges")
    return CanBus(
        interface=r.string("buses.can.interface"),
        channel=channel,
        bitrate=r.number("buses.can.bitrate") if "bitrate" in node else None,
        host_id=host_id,
        timeout_s=r.number("buses.can.timeout_s") if "timeout_s" in node else None,
        motor_type=r.string("buses.can.motor_type") if "motor_type" in node else None,
        motors=motors,
    )


def _actuators(r: YamlReader, can: CanBus) -> tuple[float, float]:
    """actuators.torque_limit inside the rating of the leg bus's actuators, and torque_per_amp."""
    r.mapping("actuators", {"torque_limit", "torque_per_amp"})
    torque_per_amp = r.number("actuators.torque_per_amp")
    if can.motors:  # the torque a motor's frames can carry, at the actuator: gear x the smaller end of ranges.t
        ratings = [m.gear * min(-m.ranges.t[0], m.ranges.t[1]) for m in can.motors]
        weakest = int(np.argmin(ratings))
        rating, key = ratings[weakest], f"buses.can.motors.{can.motors[weakest].slot}"
        ranges = f"{key}.ranges" if "ranges" in r.node(key) else "buses.can.ranges"
        why = f"CAN motor rating: {key}.gear x |{ranges}.t|"
    else:  # the current sent is torque / torque_per_amp: never beyond the BEAR's rated current
        rating = min(BEAR_RATED_TORQUE, RATED_CURRENT_A * torque_per_amp)
        why = f"Koala BEAR: {RATED_CURRENT_A:g} A x actuators.torque_per_amp, at most {BEAR_RATED_TORQUE:g}"
    bound = BOUNDS["actuators.torque_limit"].narrowed(why, high=rating)
    return r.number("actuators.torque_limit", bound=bound), torque_per_amp


# `transfer` is the runtime's section (runtime/transfer/stage.py reads it from RobotConfig.raw): allowed here, unread.
_TOP_KEYS = {"name", "mjcf", "rates", "joints", "gains", "actuators", "coupling", "arms", "safety", "policy", "pinn",
             "buses", "transfer", "estimator"}


def _estimator(r: YamlReader) -> EstimatorConfig:
    """The optional `estimator` section."""
    if "estimator" not in r.data:
        return EstimatorConfig()
    node = r.mapping("estimator", {"level_from_feet_s"})
    values = {}
    if "level_from_feet_s" in node:
        values["level_from_feet_s"] = r.number("estimator.level_from_feet_s")
    return EstimatorConfig(**values)

# The safety section's keys are its BOUNDS entries, each a SafetyConfig field of the same name.
_SAFETY_FIELDS = tuple(key.removeprefix("safety.") for key in BOUNDS if key.startswith("safety."))


def _safety(r: YamlReader, joints: tuple[str, ...], q_lower: np.ndarray, q_upper: np.ndarray,
            loop_hz: float) -> SafetyConfig:
    r.mapping("safety", set(_SAFETY_FIELDS))
    half = 0.5 * (q_upper - q_lower)
    narrowest = int(np.argmin(half))
    narrowed = {
        "position_margin": BOUNDS["safety.position_margin"].narrowed(
            f"less than half of joints.position_limits.{joints[narrowest]}", high=half[narrowest], high_open=True),
        "min_rate_hz": BOUNDS["safety.min_rate_hz"].narrowed("at most rates.loop_hz", high=loop_hz),
        # the floor counts whole ticks: a window must hold several
        "rate_window_s": BOUNDS["safety.rate_window_s"].narrowed("at least 5 ticks of rates.loop_hz",
                                                                 low=5.0 / loop_hz),
    }
    return SafetyConfig(**{name: r.number(f"safety.{name}", bound=narrowed.get(name)) for name in _SAFETY_FIELDS})


def _model_file(r: YamlReader, key: str) -> Path | None:
    """An optional model path (None when null), resolved beside the config; existence is checked at load time
    by the runtime, which names the file."""
    value = r.node(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise r.fail(key, "a model file path or null", value)
    path = Path(value)
    return path if path.is_absolute() else (r.source.parent / path)


def _gait_cadence(r: YamlReader) -> tuple[tuple[float, float], ...]:
    key = "policy.gait_period_s"
    value = r.node(key)
    if not isinstance(value, list):
        return ((0.0, r.number(key, also=" or a list of [vx (m/s), period (s)] pairs")),)
    if not value:
        raise r.fail(key, "a period (s) or a list of [vx (m/s), period (s)] pairs in increasing vx", value)
    points = []
    for i, point in enumerate(value):
        if not isinstance(point, list) or len(point) != 2:
            raise r.fail(f"{key}[{i}]", "a [vx (m/s), period (s)] pair", point)
        points.append((r.number(f"{key}[{i}][0]", point[0]), r.number(f"{key}[{i}][1]", point[1])))
    if any(b[0] <= a[0] for a, b in itertools.pairwise(points)):
        raise r.fail(key, "[vx, period] pairs in increasing vx", value)
    return tuple(points)


def _models(r: YamlReader, joints: tuple[str, ...]) -> ModelsConfig:
    policy = r.mapping("policy", {"model", "gait_period_s", "spec"})
    pinn = r.mapping("pinn", {"model", "lookahead_ticks", "residual_bias"})
    return ModelsConfig(policy=_model_file(r, "policy.model"),
                        gait_period_s=_gait_cadence(r),
                        pinn=_model_file(r, "pinn.model"),
                        pinn_lookahead_ticks=r.number("pinn.lookahead_ticks") if "lookahead_ticks" in pinn else 0,
                        pinn_residual_bias=r.per_joint("pinn.residual_bias", joints) if "residual_bias" in pinn
                        else None,
                        policy_spec=_model_file(r, "policy.spec") if "spec" in policy else None)


def parse_config(data: Any, path: Path) -> RobotConfig:
    r = YamlReader(path, data, ConfigError, bounds=bound_for)
    r.mapping("", _TOP_KEYS)

    rates = r.mapping("rates", {"loop_hz", "policy_hz", "policy_lag_ticks"}, required=("loop_hz", "policy_hz"))
    loop_hz, policy_hz = r.number("rates.loop_hz"), r.number("rates.policy_hz")
    if loop_hz % policy_hz:
        raise r.fail("rates.policy_hz", f"a divisor of rates.loop_hz ({loop_hz})", policy_hz)
    policy_lag = r.number("rates.policy_lag_ticks") if "policy_lag_ticks" in rates else 0
    if policy_lag >= loop_hz // policy_hz:  # the targets must be in force before the next policy tick asks again
        raise r.fail("rates.policy_lag_ticks", f"fewer ticks than one policy period ({loop_hz // policy_hz} ticks: "
                     "rates.loop_hz / rates.policy_hz)", policy_lag)

    r.mapping("joints", {"names", "position_limits", "torque_limits", "velocity_limits", "standing_pose"})
    joints = r.names("joints.names")
    q_lower, q_upper = _limits(r, "joints.position_limits", joints)
    matrix = _coupling(r, len(joints))

    r.mapping("arms", {"names", "position_limits", "hold_pose", "servo_signs"})
    arm_names = r.names("arms.names")
    clash = set(arm_names) & set(joints)
    if clash:
        raise r.fail("arms.names", "names distinct from joints.names", sorted(clash))
    arm_lower, arm_upper = _limits(r, "arms.position_limits", arm_names)
    hold = r.per_joint("arms.hold_pose", arm_names, bounds=_inside(
        "arms.hold_pose", arm_names, arm_lower, arm_upper, "inside arms.position_limits.{name}"))
    servo_signs = r.per_joint("arms.servo_signs", arm_names)
    if not np.all(np.abs(servo_signs) == 1.0):
        name = arm_names[int(np.flatnonzero(np.abs(servo_signs) != 1.0)[0])]
        raise r.fail(f"arms.servo_signs.{name}", "+1 or -1", float(servo_signs[arm_names.index(name)]))

    r.mapping("buses", {"bear", "dynamixel", "sense", "can"})
    buses = Buses(
        bear=_serial(r, "buses.bear", n_ids=len(joints), min_watchdog_s=2.0 / loop_hz),
        dynamixel=_serial(r, "buses.dynamixel", n_ids=len(arm_names), watchdog_unit_s=0.02),
        sense=_serial(r, "buses.sense"),
        can=_can(r, joints),
    )
    torque_limit, torque_per_amp = _actuators(r, buses.can)

    # What the actuators reach at each joint: tau_joint = A^T tau_m (A = B^-1), each |tau_m| <= torque_limit.
    reach = torque_limit * np.abs(np.linalg.inv(matrix)).sum(axis=0) * (1.0 + 1e-9)
    tau_limit = r.per_joint("joints.torque_limits", joints, bounds=_inside(
        "joints.torque_limits", joints, np.zeros(len(joints)), reach,
        "what actuators.torque_limit reaches at the joint through coupling.joint_from_actuator"))
    qd_limit = r.per_joint("joints.velocity_limits", joints)
    safety = _safety(r, joints, q_lower, q_upper, loop_hz)
    if buses.bear.reply_timeout_s >= safety.max_sensor_age_s:
        raise r.fail("buses.bear.reply_timeout_s", f"less than safety.max_sensor_age_s ({safety.max_sensor_age_s:g} "
                     "s): one cycle's wait must not make the data stale", buses.bear.reply_timeout_s)
    if not buses.can.motors and safety.host_stall_max_s >= buses.bear.watchdog_s:
        raise r.fail("safety.host_stall_max_s", f"less than buses.bear.watchdog_s ({buses.bear.watchdog_s:g} s): a "
                     "stall ridden through must end before the BEARs damp themselves", safety.host_stall_max_s)
    margin = safety.position_margin
    standing = r.per_joint("joints.standing_pose", joints, bounds=_inside(
        "joints.standing_pose", joints, q_lower + margin, q_upper - margin,
        "inside joints.position_limits.{name} less safety.position_margin"))

    r.mapping("gains", {"eq8", "eq9"})
    return RobotConfig(
        path=path,
        name=r.string("name"),
        mjcf=_resolve_mjcf(path, r.string("mjcf"), "mjcf"),
        loop_hz=loop_hz,
        policy_hz=policy_hz,
        policy_lag_ticks=policy_lag,
        joints=joints,
        q_lower=q_lower,
        q_upper=q_upper,
        tau_limit=tau_limit,
        qd_limit=qd_limit,
        standing_pose=standing,
        eq8=_gains(r, "gains.eq8", joints),
        eq9=_gains(r, "gains.eq9", joints),
        actuator_torque_limit=torque_limit,
        torque_per_amp=torque_per_amp,
        coupling=Coupling(matrix),
        arms=ArmConfig(names=arm_names, lower=arm_lower, upper=arm_upper, hold_pose=hold, servo_signs=servo_signs),
        safety=safety,
        models=_models(r, joints),
        buses=buses,
        raw=data,
        estimator=_estimator(r),
    )


def resolve_config_path(path: str | Path = DEFAULT_CONFIG) -> Path:
    """A config path as given; a relative `configs/robots/NAME.yaml` missing from the working directory falls
    back to the copy installed with the package, so the default works from any directory."""
    path = Path(path)
    if path.is_file():
        return path.resolve()
    if path.is_dir():
        raise ConfigError(f"{path}: a directory, not a robot config file")
    if not path.is_absolute() and path.parent.as_posix() == "configs/robots":
        packaged = resources.files("configs.robots") / path.name
        if packaged.is_file():
            return Path(str(packaged))
    raise ConfigError(f"{path}: robot config file not found")


def load_config(path: str | Path = DEFAULT_CONFIG, overrides: list[str] | None = None) -> RobotConfig:
    resolved = resolve_config_path(path)
    data = read_yaml(resolved, ConfigError, what="robot config")
    if overrides:
        data = apply_overrides(data, overrides, resolved, ConfigError)
    return parse_config(data, resolved)


def load_config_or_say(prog: str, path: str | Path = DEFAULT_CONFIG,
                       overrides: list[str] | None = None) -> RobotConfig | None:
    """For a command line: the config, or None after the one line that names the problem on stderr (exit 2)."""
    try:
        return load_config(path, overrides)
    except ConfigError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return None
