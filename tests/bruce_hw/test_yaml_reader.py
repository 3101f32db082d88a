"""The shared YAML reader (bruce_hw/yaml_reader.py): every failure is one line of the caller's error class naming the
source and the dotted key, whatever file it reads."""

from __future__ import annotations

import re

import numpy as np
import pytest

from bruce_hw.yaml_reader import Bound, YamlReader, apply_overrides, bound_lookup, read_yaml


class SettingsError(ValueError):
    """A caller's own error class: the reader raises it, never ValueError itself."""


TABLE = {
    "rate_hz": Bound(1, 1000, "Hz", "loop rate", integer=True),
    "legs.*.gain": Bound(0.0, 5.0, "N·m/rad", "a gain"),
    "segments[*].cmd.vx": Bound(-0.5, 1.0, "m/s", "the walking range"),
    "segments[*].duration": Bound(0.0, 10.0, "s", "a segment", low_open=True),
    "pose[*]": Bound(-1.0, 1.0, "rad"),
    "per_joint.*": Bound(0.0, 10.0, "N·m"),
}
TREE = {
    "rate_hz": 500,
    "name": "bruce",
    "legs": {"left": {"gain": 1.0}, "right": {"gain": 2.0}},
    "segments": [{"duration": 1.0, "cmd": [0.4, 0.0]}, {"duration": 2.0, "cmd": [0.1, 0.2]}],
    "pose": [0.1, -0.2, 0.3],
    "per_joint": {"a": 1.0, "b": 2.0},
}


def reader(tree=TREE) -> YamlReader:
    return YamlReader("robot.yaml", tree, SettingsError, bounds=bound_lookup(TABLE, "TABLE"))


def refused(call, message: str) -> None:
    """`call` raises exactly SettingsError("robot.yaml: {message}"), one line."""
    with pytest.raises(SettingsError) as info:
        call()
    assert type(info.value) is SettingsError
    assert str(info.value) == f"robot.yaml: {message}"


def test_values_are_read_by_dotted_key_with_list_indexes():
    r = reader()
    assert r.number("rate_hz") == 500 and isinstance(r.number("rate_hz"), int)
    assert r.number("legs.right.gain") == 2.0
    assert r.number("segments[1].duration") == 2.0
    assert r.node("segments[1].cmd") == [0.1, 0.2]
    assert r.string("name") == "bruce"
    np.testing.assert_array_equal(r.vector("pose", 3), [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(r.per_joint("per_joint", ("b", "a")), [2.0, 1.0])  # in the order asked


def test_unknown_key_names_the_dotted_key_and_what_is_allowed():
    refused(lambda: reader().mapping("legs.left", {"kp", "kd"}), "legs.left.gain: unknown key (expected one of "
                                                                  "['kd', 'kp'])")
    refused(lambda: reader().mapping("", {"rate_hz"}), "name: unknown key (expected one of ['rate_hz'])")


def test_missing_key_names_the_dotted_key_and_where_it_belongs():
    refused(lambda: reader().number("legs.left.kd"), "legs.left.kd: missing key (expected under 'legs.left')")
    refused(lambda: reader().mapping("segments[0]", {"duration", "cmd", "ramp"}, required={"ramp"}),
            "segments[0].ramp: missing key (expected under 'segments[0]')")
    refused(lambda: reader().per_joint("per_joint", ("a", "b", "c")),
            "per_joint.c: missing joint (every joint of ['a', 'b', 'c'] needs a value)")
    refused(lambda: reader().per_joint("per_joint", ("a",)), "per_joint.b: unknown joint (expected one of ['a'])")


def test_wrong_type_names_the_key_the_expectation_and_the_value():
    refused(lambda: reader().mapping("name"), "name: expected a mapping, got 'bruce'")
    refused(lambda: reader([1, 2]).mapping("", {"rate_hz"}), "<top>: expected a mapping with keys among "
                                                              "['rate_hz'], got [1, 2]")
    refused(lambda: reader().number("name", bound=TABLE["rate_hz"]),
            "name: expected an integer in [1, 1000] Hz (loop rate), got 'bruce'")
    refused(lambda: reader().number("legs.left", bound=TABLE["pose[*]"]),
            "legs.left: expected a number in [-1, 1] rad, got {'gain': 1.0}")
    refused(lambda: reader().string("rate_hz"), "rate_hz: expected a non-empty string, got 500")
    refused(lambda: reader().node("name.first"), "name: expected a mapping, got 'bruce'")
    refused(lambda: reader().node("legs[0]"), "legs: expected a list, got {'left': {'gain': 1.0}, 'right': "
                                              "{'gain': 2.0}}")
    refused(lambda: reader().node("segments[2].cmd"), "segments: expected a list of more than 2 entries, got 2")
    refused(lambda: reader({"x": True}).number("x", bound=TABLE["pose[*]"]),
            "x: expected a number in [-1, 1] rad, got True")  # a YAML boolean is no number


def test_out_of_bound_names_the_concrete_key_of_the_pattern():
    tree = {**TREE, "legs": {"left": {"gain": 9.0}}, "segments": [{"duration": 1.0, "cmd": [0.4, 0.0]},
                                                                   {"duration": 0.0, "cmd": [2.0, 0.0]}]}
    refused(lambda: reader(tree).number("legs.left.gain"),
            "legs.left.gain: expected a number in [0, 5] N·m/rad (a gain), got 9.0")
    refused(lambda: reader(tree).number("segments[1].duration"),
            "segments[1].duration: expected a number in (0, 10] s (a segment), got 0.0")
    refused(lambda: reader(tree).vector("segments[1].cmd", 2, bound=TABLE["segments[*].cmd.vx"]),
            "segments[1].cmd[0]: expected a number in [-0.5, 1] m/s (the walking range), got 2.0")
    refused(lambda: reader({"per_joint": {"a": 11.0}}).per_joint("per_joint", ("a",)),
            "per_joint.a: expected a number in [0, 10] N·m, got 11.0")
    refused(lambda: reader({"pose": [0.0, float("nan")]}).vector("pose", 2),
            "pose[1]: expected a number in [-1, 1] rad, got nan")
    refused(lambda: reader({"pose": "1e-3"}).number("pose", bound=TABLE["pose[*]"]),
            "pose: expected a number in [-1, 1] rad, got '1e-3' (YAML reads 1e-3 as text: write 1.0e-3)")


def test_vector_with_axes_names_each_entry_by_its_axis():
    r = reader({"segments": [{"cmd": [2.0, 0.0]}]})
    refused(lambda: r.vector("segments[0].cmd", 2, axes=("vx", "vy")),
            "segments[0].cmd.vx: expected a number in [-0.5, 1] m/s (the walking range), got 2.0")
    refused(lambda: r.vector("segments[0].cmd", 3, axes=("vx", "vy", "wz")),
            "segments[0].cmd: expected [vx, vy, wz] (3 numbers), got 2 entries")
    refused(lambda: reader().vector("name", 3), "name: expected a list of 3 numbers, got 'bruce'")


def test_choice_and_names():
    refused(lambda: reader().choice("name", ("direct", "pinn")), "name: expected one of direct, pinn, got 'bruce'")
    refused(lambda: reader({"n": ["a", "a"]}).names("n"), "n: expected unique names, got ['a', 'a']")
    refused(lambda: reader({"n": ["a"]}).names("n", 2), "n: expected a list of 2 names, got 1")


def test_a_key_without_a_bound_is_a_programming_error():
    with pytest.raises(LookupError, match=re.escape("no TABLE entry for name")):
        reader().number("name")
    with pytest.raises(LookupError, match="no bound for x"):
        YamlReader("robot.yaml", {"x": 1}, SettingsError).number("x")


def test_bound_lookup_matches_one_name_per_star_and_one_index_per_list_star():
    lookup = bound_lookup(TABLE, "TABLE")
    assert lookup("legs.left.gain") is TABLE["legs.*.gain"]
    assert lookup("segments[12].cmd.vx") is TABLE["segments[*].cmd.vx"]
    for key in ("legs.left.right.gain", "legs..gain", "segments[x].duration", "pose"):
        with pytest.raises(LookupError):
            lookup(key)


def test_set_overrides_existing_keys_only_with_the_callers_error(tmp_path):
    tree = {"legs": {"left": {"gain": 1.0}}}
    assert apply_overrides(tree, ["legs.left.gain=2.5"], "robot.yaml", SettingsError) == {"legs": {"left":
                                                                                                     {"gain": 2.5}}}
    assert tree["legs"]["left"]["gain"] == 1.0  # the tree given is left alone
    refused(lambda: apply_overrides(tree, ["legs.left.kd=1"], "robot.yaml", SettingsError),
            "legs.left.kd: no such key to --set (nothing named 'kd' under legs.left)")
    refused(lambda: apply_overrides(tree, ["legs.right.gain=1"], "robot.yaml", SettingsError),
            "legs.right.gain: no such key to --set (nothing named 'right' under legs)")
    refused(lambda: apply_overrides(tree, ["legs.left.gain"], "robot.yaml", SettingsError),
            "--set 'legs.left.gain': expected KEY=VALUE with a dotted key path")
    with pytest.raises(SettingsError, match=r"^robot\.yaml: --set legs\.left\.gain: not a valid YAML value: "):
        apply_overrides(tree, ["legs.left.gain=[1"], "robot.yaml", SettingsError)


def test_read_yaml_raises_the_callers_error_naming_the_file(tmp_path):
    path = tmp_path / "x.yaml"
    with pytest.raises(SettingsError, match=re.escape(f"{path}: cannot read the scenario: ")):
        read_yaml(path, SettingsError, "scenario")
    path.write_text("a: [1\n")
    with pytest.raises(SettingsError, match=re.escape(f"{path}: not valid YAML: ") + r".*\(line \d+, column \d+\)$"):
        read_yaml(path, SettingsError)
    path.write_text("a: {b: [1, 2]}\n")
    assert read_yaml(path, SettingsError) == {"a": {"b": [1, 2]}}


def test_long_values_are_cut_in_the_message():
    with pytest.raises(SettingsError) as info:
        reader({"x": list(range(100))}).string("x")
    message = str(info.value)
    assert message.startswith("robot.yaml: x: expected a non-empty string, got [0, 1, 2,") and message.endswith("...")
    assert len(message) < 140
