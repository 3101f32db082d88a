"""The robot config as the runtime's commands load it: bruce_hw's robot description (`bruce_hw.config.load_config`)
with the sections the runtime owns checked too (`transfer`: runtime/transfer/stage.py), so that a bad key of either
is one ConfigError at start-up, before anything moves."""

from __future__ import annotations

from pathlib import Path

from bruce_hw.config import DEFAULT_CONFIG, RobotConfig
from bruce_hw.config import load_config as load_description
from runtime.transfer.stage import settings_for


def load_config(path: str | Path = DEFAULT_CONFIG, overrides: list[str] | None = None) -> RobotConfig:
    config = load_description(path, overrides)
    settings_for(config)  # read once here, cached for the run
    return config
