from pathlib import Path

import pytest
import yaml

from bruce_hw.config import DEFAULT_CONFIG, load_config, resolve_config_path


@pytest.fixture(scope="session")
def config():
    return load_config()


@pytest.fixture
def raw_config():
    """The default config as a YAML tree, to break on purpose."""
    return yaml.safe_load(resolve_config_path(DEFAULT_CONFIG).read_text())


@pytest.fixture
def write_config(tmp_path):
    """Write a YAML tree beside a copy of the model and return its path."""

    def write(tree, name="robot.yaml") -> Path:
        path = tmp_path / name
        path.write_text(yaml.safe_dump(tree))
        return path

    return write
