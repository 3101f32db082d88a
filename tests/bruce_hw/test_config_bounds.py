"""Physical bounds of every numeric setting (robot config, reality-gap profiles, scenarios): dangerous values are
refused with one line naming the key and the range, through the file and through `--set`; the tables and
docs/config_bounds.md agree. The config's `transfer` section is the runtime's (runtime/transfer/stage.py): its
keys are checked here too, through `runtime.robot_config.load_config` and the registry's bounds."""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.paths import REPO

from bruce_hw.config import BOUNDS, ConfigError, SafetyConfig, parse_config, resolve_config_path
from bruce_hw.config import bound_for as description_bound_for
from bruce_hw.reality_gap import GAP_BOUNDS, GapError, load_gap, profile_names
from bruce_hw.yaml_reader import Bound, apply_overrides
from runtime.control.commands import SCENARIO_BOUNDS, CommandSchedule
from runtime.robot_config import load_config
from runtime.transfer.stage import settings_for, transfer_bounds

TRANSFER_BOUNDS = transfer_bounds()


def bound_for(key: str) -> Bound:
    """The Bound of a concrete key of a robot config: the transfer section's from the registry, the rest bruce_hw's."""
    return TRANSFER_BOUNDS[key] if key.startswith("transfer.") else description_bound_for(key)

ROBOTS = ("configs/robots/bruce.yaml", "configs/robots/bruce_can.yaml")
CAN = ROBOTS[1]


def refused(overrides: list[str], *fragments: str, path: str = ROBOTS[0]) -> str:
    """The one-line ConfigError of the shipped config with `overrides`; it names the file and every fragment."""
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides=overrides)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{resolve_config_path(path)}: "), message
    for fragment in fragments:
        assert fragment in message, message
    return message


# -- the values an independent review found accepted ----------------------------------------------------------------
@pytest.mark.parametrize(("override", "fragments"), [
    ("actuators.torque_per_amp=1.0e-9", ("actuators.torque_per_amp: expected a number in [0.2, 0.5] N·m/A",
                                         "got 1e-09")),
    ("actuators.torque_per_amp=1e-3", ("actuators.torque_per_amp", "YAML reads 1e-3 as text: write 1.0e-3")),
    ("actuators.torque_limit=.nan", ("actuators.torque_limit: expected a number in (0, 10.5] N·m", "got nan")),
    ("actuators.torque_limit=20.0", ("actuators.torque_limit", "(0, 10.5] N·m", "Koala BEAR")),
])
def test_actuator_constants(override, fragments):
    refused([override], *fragments)


def test_bear_torque_limit_keeps_the_current_within_the_bears_rating():
    # 10.5 N·m at 0.25 N·m/A would be 42 A: the limit is 30 A x 0.25 = 7.5 N·m
    refused(["actuators.torque_per_amp=0.25"], "actuators.torque_limit: expected a number in (0, 7.5] N·m",
            "actuators.torque_per_amp", "got 10.5")
    assert load_config(overrides=["actuators.torque_per_amp=0.25", "actuators.torque_limit=7.5",
                                  *(f"joints.torque_limits.{j}=7.5" for j in load_config().joints)])


@pytest.mark.parametrize(("override", "fragments"), [
    ("safety.damping_kd=-5", ("safety.damping_kd: expected a number in (0, 5] N·m·s/rad", "got -5")),
    ("safety.damping_kd=.nan", ("safety.damping_kd: expected a number in (0, 5] N·m·s/rad", "got nan")),
    ("safety.damping_kd=0", ("safety.damping_kd", "(0, 5]", "got 0")),
    ("safety.max_sensor_age_s=1.0e+9", ("safety.max_sensor_age_s: expected a number in (0, 0.05] s",
                                        "got 1000000000.0")),
    ("safety.max_torque_rate=1.0e+12", ("safety.max_torque_rate: expected a number in (0, 100000] N·m/s",)),
    ("safety.position_margin=-1", ("safety.position_margin: expected a number in [0, 0.5] rad", "got -1")),
    ("safety.torque_ramp_s=-1", ("safety.torque_ramp_s: expected a number in [0, 5] s", "got -1")),
    ("safety.damping_hold_s=-1", ("safety.damping_hold_s: expected a number in (0, 60] s", "got -1")),
    ("safety.soft_start_s=.inf", ("safety.soft_start_s: expected a number in (0, 30] s", "got inf")),
    ("safety.tilt_limit_deg=720", ("safety.tilt_limit_deg: expected a number in (0, 90) deg", "got 720")),
    ("safety.tilt_ticks=0", ("safety.tilt_ticks: expected an integer in [1, 1000] ticks", "got 0")),
    ("safety.min_rate_hz=2000", ("safety.min_rate_hz: expected a number in [50, 1000] Hz", "got 2000")),
    ("safety.rate_window_s=0.001", ("safety.rate_window_s: expected a number in [0.01, 1] s", "got 0.001")),
    ("buses.bear.reply_timeout_s=0.01", ("buses.bear.reply_timeout_s", "less than safety.max_sensor_age_s")),
    ("safety.reply_loss_max=1.5", ("safety.reply_loss_max: expected a number in (0, 0.5]", "got 1.5")),
    ("safety.reply_loss_window_s=0", ("safety.reply_loss_window_s: expected a number in [0.05, 60] s",)),
])
def test_safety_settings(override, fragments):
    refused([override], *fragments)


@pytest.mark.parametrize(("override", "fragments"), [
    ("gains.eq8.kp.r_knee=1.0e+6", ("gains.eq8.kp.r_knee: expected a number in [0, 500] N·m/rad", "got 1000000.0")),
    ("gains.eq9.kp.l_ankle=-1", ("gains.eq9.kp.l_ankle: expected a number in [0, 500] N·m/rad", "got -1")),
    ("gains.eq9.kd.r_hip_yaw=.nan", ("gains.eq9.kd.r_hip_yaw: expected a number in [0, 5] N·m·s/rad", "got nan")),
    ("gains.eq8.kd.l_knee=50", ("gains.eq8.kd.l_knee", "[0, 5]", "got 50")),
])
def test_gains(override, fragments):
    refused([override], *fragments)


@pytest.mark.parametrize(("override", "fragments"), [
    ("joints.standing_pose.r_knee=.nan", ("joints.standing_pose.r_knee: expected a number in [-2.45, -0.05] rad",
                                          "got nan")),
    ("joints.standing_pose.r_knee=-0.01", ("joints.standing_pose.r_knee", "safety.position_margin", "got -0.01")),
    ("joints.velocity_limits.r_knee=.inf", ("joints.velocity_limits.r_knee: expected a number in (0, 50] rad/s",
                                            "got inf")),
    ("joints.velocity_limits.l_ankle=0", ("joints.velocity_limits.l_ankle", "(0, 50]", "got 0")),
    ("joints.torque_limits.r_knee=.nan", ("joints.torque_limits.r_knee: expected a number in (0, 21] N·m", "got nan")),
    ("joints.torque_limits.r_hip_yaw=21.0", ("joints.torque_limits.r_hip_yaw: expected a number in (0, 10.5] N·m",
                                             "coupling.joint_from_actuator")),
    ("joints.position_limits.r_ankle=[-1.5, .inf]", ("joints.position_limits.r_ankle[1]", "[-6.28319, 6.28319] rad")),
    ("joints.position_limits.r_ankle=[1.0, -1.0]", ("joints.position_limits.r_ankle", "lower < upper")),
    ("arms.hold_pose.r_elbow=3.0", ("arms.hold_pose.r_elbow: expected a number in [-2.3, 2.3] rad",
                                    "arms.position_limits.r_elbow")),
])
def test_joint_settings(override, fragments):
    refused([override], *fragments)


def test_position_margin_must_leave_every_joint_a_range():
    refused(["safety.position_margin=0.45", "joints.position_limits.r_hip_roll=[-0.3, 0.3]"],
            "safety.position_margin: expected a number in [0, 0.3) rad",
            "half of joints.position_limits.r_hip_roll")


def test_nan_coupling_entry_and_singular_coupling():
    raw = yaml.safe_load(resolve_config_path(ROBOTS[0]).read_text())
    path = resolve_config_path(ROBOTS[0])
    bad = copy.deepcopy(raw)
    bad["coupling"]["joint_from_actuator"][3][2] = math.nan
    with pytest.raises(ConfigError, match=re.escape("coupling.joint_from_actuator[3][2]: expected a number in "
                                                    "[-10, 10]") + ".*got nan"):
        parse_config(bad, path)
    bad = copy.deepcopy(raw)
    bad["coupling"]["joint_from_actuator"][2] = bad["coupling"]["joint_from_actuator"][1]
    with pytest.raises(ConfigError, match=r"coupling\.joint_from_actuator: expected an invertible matrix"):
        parse_config(bad, path)


@pytest.mark.parametrize(("override", "fragments"), [
    ("rates.loop_hz=50", ("rates.loop_hz: expected an integer in [100, 10000] Hz", "got 50")),
    ("rates.loop_hz=1000.0", ("rates.loop_hz: expected an integer", "got 1000.0")),
    ("policy.gait_period_s=.nan", ("policy.gait_period_s: expected a number in (0.1, 2] s", "got nan")),
    ("policy.gait_period_s=[[0.0, 5.0]]", ("policy.gait_period_s[0][1]: expected a number in (0.1, 2] s",)),
    ("buses.bear.baud=0", ("buses.bear.baud: expected an integer in [9600, 12000000] bit/s", "got 0")),
    ("buses.bear.ids=[1, 2, 3, 4, 5, 6, 7, 8, 9, 254]", ("buses.bear.ids[9]: expected an integer in [0, 253]",)),
    ("buses.bear.ids=[1, 2, 3, 4, 5, 6, 7, 8, 9, 9]", ("buses.bear.ids: expected unique IDs",)),
])
def test_rates_models_and_buses(override, fragments):
    refused([override], *fragments)


@pytest.mark.parametrize(("override", "fragments"), [
    ("buses.bear.watchdog_s=0", ("buses.bear.watchdog_s: expected a number in [0.005, 1] s", "got 0")),
    ("buses.bear.watchdog_s=5", ("buses.bear.watchdog_s", "[0.005, 1] s", "got 5")),
    ("buses.bear.watchdog_unit_s=0", ("buses.bear.watchdog_unit_s: expected a number in [1e-06, 0.05] s", "got 0")),
    ("buses.bear.watchdog_unit_s=0.1", ("buses.bear.watchdog_unit_s", "at most buses.bear.watchdog_s")),
    ("buses.dynamixel.watchdog_s=0.03", ("buses.dynamixel.watchdog_s: expected a number in [0.02, 2.54] s in steps of "
                                         "0.02", "got 0.03")),
    ("buses.dynamixel.watchdog_s=0", ("buses.dynamixel.watchdog_s", "got 0")),
])
def test_motor_watchdogs(override, fragments):
    refused([override], *fragments)


def test_pinn_lookahead_is_bounded(raw_config):
    raw_config["pinn"]["lookahead_ticks"] = 1000
    with pytest.raises(ConfigError, match=re.escape("pinn.lookahead_ticks: expected an integer in [0, 50] ticks")):
        parse_config(raw_config, resolve_config_path(ROBOTS[0]))


def test_bear_watchdog_is_required_and_longer_than_two_ticks(raw_config, write_config):
    assert load_config(overrides=["buses.dynamixel.watchdog_s=2.54"]).buses.dynamixel.watchdog_s == 2.54
    refused(["rates.loop_hz=100", "rates.policy_hz=50", "buses.bear.watchdog_s=0.01"],
            "buses.bear.watchdog_s: expected a number in [0.02, 1] s", "rates.loop_hz")
    raw_config["mjcf"] = str(load_config().mjcf)
    del raw_config["buses"]["bear"]["watchdog_s"]
    with pytest.raises(ConfigError, match=r"buses\.bear\.watchdog_s: missing key"):
        load_config(write_config(raw_config))


@pytest.mark.parametrize(("override", "fragments"), [
    ("actuators.torque_limit=18.0", ()),  # the AK80-9 frames carry 18 N·m
    ("actuators.torque_limit=18.5", ("actuators.torque_limit: expected a number in (0, 18] N·m", "buses.can.ranges.t")),
    ("buses.can.motors.r_knee.gear=0.5", ("actuators.torque_limit: expected a number in (0, 9] N·m",
                                          "buses.can.motors.r_knee.gear")),
    ("buses.can.ranges.t=[-18.0, .nan]", ("buses.can.ranges.t[1]: expected a number in [-200, 200] N·m",)),
    ("buses.can.ranges.t=[0.0, 18.0]", ("buses.can.ranges.t: expected [min, max] with min < 0 < max",)),
    ("buses.can.timeout_s=10", ("buses.can.timeout_s: expected a number in (0, 0.1] s",)),
    ("buses.can.motors.r_hip_yaw.offset=.inf", ("buses.can.motors.r_hip_yaw.offset",)),
    ("buses.can.host_id=4", ("buses.can.motors.r_knee.id", "buses.can.host_id")),
])
def test_can_legs_are_bounded_by_their_frames(override, fragments):
    if not fragments:
        assert load_config(CAN, overrides=[override]).actuator_torque_limit == 18.0
    else:
        refused([override], *fragments, path=CAN)


# -- files that are not configs -------------------------------------------------------------------------------------
def test_binary_files_and_directories_give_one_line(tmp_path):
    binary = tmp_path / "robot.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    for load, error in ((load_config, ConfigError), (load_gap, GapError), (CommandSchedule.from_yaml, ConfigError)):
        with pytest.raises(error) as info:
            load(binary)
        assert str(info.value) == f"{binary}: not a text file (byte 128 is not UTF-8)"
    with pytest.raises(ConfigError, match="a directory, not a robot config file") as info:
        load_config(tmp_path)
    control = tmp_path / "control.yaml"
    control.write_text("name: \x00\x01\n")
    with pytest.raises(ConfigError, match=f"{control}: not valid YAML: ") as info:
        load_config(control)
    assert "\n" not in str(info.value)
    refused(["safety.damping_kd=[1"], "--set safety.damping_kd: not a valid YAML value")


# -- the tables: every shipped number is inside, every leaf has one --------------------------------------------------
def numeric_leaves(tree, prefix: str = ""):
    """(dotted key, value) of every number in a YAML tree: mappings by ".name", lists by "[i]"."""
    if isinstance(tree, dict):
        for name, value in tree.items():
            yield from numeric_leaves(value, f"{prefix}.{name}" if prefix else str(name))
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            yield from numeric_leaves(value, f"{prefix}[{i}]")
    elif isinstance(tree, int | float) and not isinstance(tree, bool):
        yield prefix, tree


def raw(path: str) -> dict:
    return yaml.safe_load(resolve_config_path(path).read_text())


RAW = {path: raw(path) for path in ROBOTS}  # parsed once: set_leaf works on copies
LEAVES = {path: dict(numeric_leaves(RAW[path])) for path in ROBOTS}


@pytest.mark.parametrize("path", ROBOTS)
def test_every_shipped_number_has_a_bound_and_is_inside(path):
    config = load_config(path)
    assert config.buses.bear.watchdog_s == 0.05 and config.actuator_torque_limit == 10.5
    for key, value in LEAVES[path].items():
        assert bound_for(key).contains(value), (key, value, bound_for(key))


def test_shipped_gaps_and_scenarios_are_inside_their_tables():
    for name in profile_names():
        tree = yaml.safe_load((REPO / "configs" / "gaps" / f"{name}.yaml").read_text())
        for key, value in numeric_leaves(tree):
            if key != "seed":
                base = re.sub(r"\[\d+\]$", "", key)
                bound = GAP_BOUNDS.get(base) or GAP_BOUNDS[base.rsplit(".", 1)[0]]  # per joint: section.name.joint
                assert bound.contains(value), (name, key, value)
        load_gap(name)
    for path in sorted((REPO / "configs" / "scenarios").glob("*.yaml")):
        for key, value in numeric_leaves(yaml.safe_load(path.read_text())):
            pattern = re.sub(r"\[\d+\]", "[*]", key)
            if ".cmd[" in pattern:
                pattern = pattern.replace(".cmd[*]", ".cmd.") + "vx vy wz".split()[int(key[-2])]
            assert SCENARIO_BOUNDS[pattern].contains(value), (path, key, value)
        CommandSchedule.from_yaml(path)


def test_the_doc_lists_every_bound_with_its_range():
    doc = (REPO / "docs" / "config_bounds.md").read_text()
    for table in (BOUNDS, TRANSFER_BOUNDS, GAP_BOUNDS, SCENARIO_BOUNDS):
        for key, bound in table.items():
            row = f"| `{key}` | {bound.unit or '–'} | {bound.interval()}{' (integer)' if bound.integer else ''} |"
            assert row in doc, row


def test_the_safety_keys_are_the_bounds_table_s(config):
    """BOUNDS lists the keys of the safety section once: "safety.a" is field a, and a value set there lands in it
    (the transfer section's: tests/runtime/transfer/test_transfer_settings.py)."""
    keys = [key for key in BOUNDS if key.startswith("safety.")]
    assert {key.removeprefix("safety.") for key in keys} == {f.name for f in dataclasses.fields(SafetyConfig)}
    for key in keys:
        field = key.removeprefix("safety.")
        shipped = getattr(config.safety, field)
        value = shipped + 1 if isinstance(shipped, int) else round(shipped * 1.01, 9)
        assert getattr(load_config(overrides=[f"{key}={value}"]).safety, field) == value, key


# -- property: whatever a leaf is set to, the loader refuses it by name or the config is inside every bound --------
def set_leaf(tree: dict, key: str, value, path: Path) -> dict:
    """`tree` with the leaf at `key` set: through `--set` for mapping keys, directly for list entries."""
    if "[" not in key:
        return apply_overrides(tree, [f"{key}={yaml.safe_dump(value)}"], path, ConfigError)
    tree = copy.deepcopy(tree)
    parts = re.findall(r"[^.\[\]]+|\[\d+\]", key)
    node = tree
    for part in parts[:-1]:
        node = node[int(part[1:-1])] if part.startswith("[") else node[part]
    last = parts[-1]
    node[int(last[1:-1]) if last.startswith("[") else last] = value
    return tree


def numbers_of(value, where: str = "config"):
    """Every number inside a parsed config (dataclasses, arrays, tuples), with where it sits."""
    if isinstance(value, bool | str | Path | type(None)):
        return
    if isinstance(value, int | float | np.ndarray):
        yield where, np.asarray(value, dtype=float)
    elif isinstance(value, tuple | list):
        for i, item in enumerate(value):
            yield from numbers_of(item, f"{where}[{i}]")
    elif isinstance(value, dict):  # the transfer settings' sections
        for name, item in value.items():
            yield from numbers_of(item, f"{where}.{name}")
    elif dataclasses.is_dataclass(value):
        for f in dataclasses.fields(value):
            if f.name != "raw":
                yield from numbers_of(getattr(value, f.name), f"{where}.{f.name}")
    elif hasattr(value, "joint_from_actuator"):  # Coupling
        yield f"{where}.joint_from_actuator", value.joint_from_actuator


def check_leaf(path_name: str, key: str, value) -> None:
    path = resolve_config_path(path_name)
    try:
        tree = set_leaf(RAW[path_name], key, value, path)
        config = parse_config(tree, path)
        transfer = settings_for(config)
    except ConfigError as exc:
        message = str(exc)
        named = key in message or re.sub(r"(\[\d+\])+$", "", key) in message
        assert "\n" not in message and named, (key, value, message)
        return
    for where, numbers in (*numbers_of(config), *numbers_of(transfer, "transfer")):
        assert np.all(np.isfinite(numbers)), (key, value, where)
    for leaf, number in numeric_leaves(tree):
        assert bound_for(leaf).contains(number), (key, value, leaf, number)


NASTY = (math.nan, math.inf, -math.inf, 0, -1, 1e308, -1e-308, 10**40, True)


@pytest.mark.parametrize("value", NASTY, ids=repr)
@pytest.mark.parametrize("path", ROBOTS)
def test_every_leaf_of_the_shipped_configs_against_nasty_values(path, value):
    for key in LEAVES[path]:
        check_leaf(path, key, value)


def in_bound(bound: Bound) -> st.SearchStrategy:
    if bound.integer:
        return st.integers(int(bound.low), int(bound.high))
    return st.floats(bound.low, bound.high)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_property_any_value_of_any_leaf_is_refused_by_name_or_inside_the_bounds(data):
    path = data.draw(st.sampled_from(ROBOTS), label="config")
    key = data.draw(st.sampled_from(sorted(LEAVES[path])), label="key")
    value = data.draw(st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(-(10**30), 10**30),
        in_bound(bound_for(key)),  # mostly accepted: exercises the relations between settings
        st.sampled_from(NASTY),
    ), label="value")
    check_leaf(path, key, value)
