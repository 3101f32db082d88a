"""The transfer section of the robot config (runtime/transfer/stage.py): its keys are the stage's own and each
registered scheme's settings fields, a value set there lands in that field, and bruce_hw leaves the section to the
runtime."""

from __future__ import annotations

import dataclasses

import pytest

from bruce_hw.config import ConfigError
from bruce_hw.config import load_config as load_description
from runtime.robot_config import load_config
from runtime.transfer.registry import scheme_entry, scheme_names
from runtime.transfer.stage import TransferSettings, sections, settings_for, transfer_bounds


def field_of(settings: TransferSettings, key: str):
    """The field a key "transfer.a" or "transfer.SECTION.a" lands in."""
    parts = key.removeprefix("transfer.").split(".")
    if len(parts) == 1:
        return getattr(settings, parts[0])
    holder = settings.gap_monitor if parts[0] == "gap_monitor" else settings.of(parts[0])
    return getattr(holder, parts[1])


def test_every_transfer_key_is_a_settings_field_and_a_value_set_there_lands_in_it(config):
    table = transfer_bounds()
    own = {f.name for f in dataclasses.fields(TransferSettings)} - {"scheme", "reference_model", "gap_monitor",
                                                                     "schemes"}
    expected = {f"transfer.{name}" for name in own} | {
        f"transfer.{section}.{f.name}" for section, cls in sections().items() for f in dataclasses.fields(cls)}
    assert set(table) == expected
    shipped_settings = settings_for(config)
    for key in table:
        shipped = field_of(shipped_settings, key)
        value = shipped + 1 if isinstance(shipped, int) else round(shipped * 1.01, 9)
        assert field_of(settings_for(load_config(overrides=[f"{key}={value}"])), key) == value, key


def test_the_shipped_schemes_and_their_sections():
    assert scheme_names() == ("direct", "pinn", "eq9", "shadow", "observer", "twin", "shadow_twin")
    assert scheme_entry("pinn") is scheme_entry("eq9")
    assert list(sections()) == ["gap_monitor", "shadow", "observer", "twin"]
    assert scheme_entry("shadow_twin").section == "twin"
    with pytest.raises(ValueError, match="unknown transfer 'eq10'"):
        scheme_entry("eq10")


def test_bruce_hw_keeps_the_section_unread_and_the_runtime_refuses_a_bad_key():
    description = load_description(overrides=["transfer.twin.clip=0"])  # the robot description alone: not its part
    assert description.raw["transfer"]["twin"]["clip"] == 0 and not hasattr(description, "transfer")
    with pytest.raises(ConfigError, match=r"transfer\.twin\.clip: expected a number in \(0, 1\]"):
        settings_for(description)
    with pytest.raises(ConfigError, match=r"transfer\.twin\.clip: expected a number in \(0, 1\]"):
        load_config(overrides=["transfer.twin.clip=0"])
    with pytest.raises(ConfigError, match=r"transfer\.twin\.clip: expected a number"):
        load_config(overrides=["transfer.twin={clip: 0}"])


def test_the_observer_time_constant_is_narrowed_by_the_stage_margins():
    with pytest.raises(ConfigError) as info:
        load_config(overrides=["transfer.delay_margin_s=0.05", "transfer.phase_margin_deg=70.0",
                               "transfer.observer.time_constant_s=0.1"])  # < 50 ms / (pi/2 - 70 deg) = 143 ms
    assert "transfer.observer.time_constant_s: expected a number in [0.143239, 10] s (at least " \
           "transfer.delay_margin_s / (pi/2 - transfer.phase_margin_deg)), got 0.1" in str(info.value)
