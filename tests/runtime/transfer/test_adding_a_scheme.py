"""A newcomer's transfer scheme (tests/support/example_scheme.py: one file, registering itself) is a scheme like
the shipped ones: bruce-run offers it, a run uses it, its settings come from the config and `--set`, and a bad value
is one ConfigError naming the key, refused before anything moves."""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest
import yaml

from bruce_hw.config import ConfigError, resolve_config_path
from bruce_hw.mock import MujocoBackend
from runtime.cli import main as bruce_run
from runtime.control.commands import CommandSchedule
from runtime.loop.run import run_session
from runtime.robot_config import load_config
from runtime.transfer.registry import scheme_names, unregister_scheme
from runtime.transfer.stage import settings_for, transfer_bounds


@pytest.fixture
def example():
    """support.example_scheme, registered for this test only (the registry is the process's)."""
    module = importlib.import_module("support.example_scheme")
    if "offset" not in scheme_names():
        module = importlib.reload(module)  # imported by an earlier test: registered again by running it again
    yield module
    unregister_scheme("offset")


@pytest.fixture
def config_path(tmp_path):
    """The shipped config with a `transfer.offset` section, beside nothing: its model paths made absolute."""
    shipped = load_config()
    tree = yaml.safe_load(resolve_config_path("configs/robots/bruce.yaml").read_text())
    tree["mjcf"], tree["policy"]["model"], tree["pinn"]["model"] = (
        str(shipped.mjcf), str(shipped.models.policy), str(shipped.models.pinn))
    tree["transfer"]["offset"] = {"share": 0.01}
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(tree))
    return path


def test_a_registered_scheme_runs_with_its_settings_from_the_config_and_set(example, config_path):
    assert "offset" in scheme_names() and transfer_bounds()["transfer.offset.share"].high == 0.05
    config = load_config(config_path, ["transfer.offset.share=-0.02"])
    assert settings_for(config).of("offset").share == -0.02
    summary = run_session(MujocoBackend(config), config, duration=0.2, realtime=False, transfer="offset",
                          controller_kind="standing", commands=CommandSchedule.constant(0.0, 0.0, 0.0))
    assert summary.ticks == 200 and summary.scheme_report["offset"]["ticks"] == 200
    np.testing.assert_allclose(summary.scheme_report["offset"]["torque"], -0.02 * config.tau_limit)
    # the shipped default, where the config leaves the key out
    assert settings_for(load_config()).of("offset").share == 0.0


def test_bruce_run_offers_the_scheme_and_reads_set(example, config_path, tmp_path):
    stats = tmp_path / "stats.json"
    assert bruce_run(["--config", str(config_path), "--set", "transfer.offset.share=0.03", "--transfer", "offset",
                      "--controller", "standing", "--duration", "0.1", "--rerun", "off", "--stats", str(stats)]) == 0
    data = json.loads(stats.read_text())
    assert data["transfer"] == "offset" and data["offset"]["ticks"] == data["ticks"] == 100
    np.testing.assert_allclose(data["offset"]["torque"], 0.03 * load_config().tau_limit)


def test_a_bad_value_of_its_setting_is_one_line_naming_the_key(example, config_path, capsys):
    with pytest.raises(ConfigError) as info:
        load_config(config_path, ["transfer.offset.share=0.5"])
    assert str(info.value) == (f"{config_path}: transfer.offset.share: expected a number in [-0.05, 0.05] (share of "
                               "joints.torque_limits added to tau*), got 0.5")
    with pytest.raises(ConfigError, match=r"transfer\.offset\.sahre: unknown key"):
        load_config(config_path, ["transfer.offset={sahre: 0.01}"])
    # bruce-run: refused at start-up, one line, before any backend is made
    assert bruce_run(["--config", str(config_path), "--set", "transfer.offset.share=.nan", "--transfer", "offset",
                      "--rerun", "off"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "transfer.offset.share: expected a number in [-0.05, 0.05]" in err[0], err


def test_unregistered_its_section_is_unknown_again(config_path):
    assert "offset" not in scheme_names()
    with pytest.raises(ConfigError, match=r"transfer\.offset: unknown key"):
        load_config(config_path)
