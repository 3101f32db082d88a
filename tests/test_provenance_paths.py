"""Records made for another machine (sidecars, datasets, logs) name files in this repository by their place in it,
not by this checkout's absolute path (`runtime.loop.recorder.portable_path`)."""

from pathlib import Path

from bruce_hw.config import DEFAULT_CONFIG
from runtime.loop.recorder import REPOSITORY, portable_path


def test_a_file_in_the_repository_is_named_relative_to_it_wherever_the_caller_stands(tmp_path, monkeypatch):
    absolute = Path(DEFAULT_CONFIG).resolve()
    assert portable_path(absolute) == "configs/robots/bruce.yaml"
    monkeypatch.chdir(tmp_path)  # another working directory: the same name
    assert portable_path(absolute) == "configs/robots/bruce.yaml"
    assert portable_path(REPOSITORY / "configs" / ".." / "configs" / "gaps" / "default.yaml") == \
        "configs/gaps/default.yaml"


def test_a_file_outside_the_repository_is_named_as_given(tmp_path):
    outside = tmp_path / "robot.yaml"
    assert portable_path(outside) == str(outside)
