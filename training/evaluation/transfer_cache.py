"""The on-disk cache of `bruce-eval transfer` runs, so that an interrupted suite resumes where it stopped.

One entry per distinct run, named by a hash of its `RunSpec` (`spec_key`) under OUT/runs/:

- `<key>.json`: the run's metrics against its nominal reference (written once the run has finished, atomically);
- `<key>.npz`: the run's record, for the runs that are needed whole: the nominal references (every other run is
  scored against them) and the runs the figures draw (`trace` keeps only what `plot` reads: joint 0).

A gap without noise makes a deterministic run whatever its seed, so its seed is left out of the key: the seeds of a
noise-free profile share one run. The key also carries a fingerprint of the robot configuration's folder (the
config file and the models, policy specs and sidecars beside it, `config_fingerprint`): a changed setting or a
retrained model is a new run, not a cached one. And `CACHE_VERSION`: bump it when a metric or the code of a run
changes meaning, or delete OUT/runs.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path

import numpy as np

CACHE_VERSION = 2  # 2: robot-faithful runs (the twin resynchronised from the estimator, read lag_ticks late)
NOISE_FIELDS = ("q_noise", "qd_noise", "gyro_noise", "accel_noise", "orientation_noise",
                "contact_bounce_s")  # what the seed draws
RECORD_ARRAYS = ("t", "q", "qd", "tau", "xy", "yaw", "velocity")


def _noisy(gap) -> bool:
    return any(np.any(np.asarray(list(v.values()) if isinstance(v, dict) else v, float))
               for v in (getattr(gap, name) for name in NOISE_FIELDS))


def config_fingerprint(config: str | Path) -> str:
    """A hash of every file in the robot config's folder and below (the YAML, the ONNX models and their sidecars,
    the policy specs), by content; cached per (path, size, mtime) of each file."""
    from bruce_hw.config import resolve_config_path

    folder = resolve_config_path(config).parent  # the default config from any working directory
    files = tuple(sorted((f.relative_to(folder).as_posix(), f.stat().st_size, f.stat().st_mtime_ns)
                         for f in folder.rglob("*") if f.is_file() and "__pycache__" not in f.parts))
    return _fingerprint(str(folder), files)


@functools.lru_cache(maxsize=8)
def _fingerprint(folder: str, files: tuple) -> str:
    digest = hashlib.sha256()
    for name, _, _ in files:  # names relative to the folder: two checkouts of one commit share their runs
        digest.update(name.encode())
        digest.update((Path(folder) / name).read_bytes())
    return digest.hexdigest()[:16]


def spec_key(spec) -> str:
    """A stable name for the run `spec` describes: 16 hex digits of a hash of its fields (the gap's values, not
    where it was read from; no seed when the gap has no noise), its robot config named by file name and the
    content of its folder."""
    from bruce_hw.config import DEFAULT_CONFIG

    fields = dataclasses.asdict(spec)
    config = Path(spec.config or DEFAULT_CONFIG)
    fields["config"] = (config.name, config_fingerprint(config))  # what it holds, not where it lies
    if spec.gap is not None:
        gap = fields["gap"]
        gap.pop("source", None)
        if not _noisy(spec.gap):
            gap.pop("seed", None)
    text = json.dumps({"version": CACHE_VERSION, **fields}, sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def trace(record):
    """What the figures read of a record (joint 0's traces, the base path and velocity), as a record."""
    return dataclasses.replace(record, q=record.q[:, :1], qd=record.qd[:, :1], tau=record.tau[:, :1])


class RunCache:
    """Metrics (JSON) and records (npz) of finished runs under `root`."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str, suffix: str) -> Path:
        return self.root / f"{key}{suffix}"

    def metrics(self, key: str) -> dict | None:
        path = self._path(key, ".json")
        return json.loads(path.read_text())["metrics"] if path.is_file() else None

    def save_metrics(self, key: str, spec, metrics: dict) -> None:
        from training.evaluation.report import json_safe

        text = json.dumps(json_safe({"spec": dataclasses.asdict(spec), "metrics": metrics}), indent=1)
        self._atomic(self._path(key, ".json"), lambda tmp: tmp.write_text(text + "\n"))

    def record(self, key: str, spec, record_type):
        """The stored record of `spec` (a `record_type`, i.e. RunRecord), or None."""
        path = self._path(key, ".npz")
        if not path.is_file():
            return None
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in RECORD_ARRAYS}
            fall_time = float(data["fall_time"][0]) if data["fall_time"].size else None  # stored as [] or [t]
            return record_type(spec=spec, fell=bool(data["fell"]), stop_cause=str(data["stop_cause"]),
                               fall_time=fall_time, **arrays)

    def save_record(self, key: str, record) -> None:
        arrays = {name: getattr(record, name) for name in RECORD_ARRAYS}
        fall_time = np.array([] if record.fall_time is None else [record.fall_time])

        def write(tmp: Path) -> None:
            with tmp.open("wb") as f:
                np.savez_compressed(f, fell=record.fell, stop_cause=record.stop_cause, fall_time=fall_time,
                                    **arrays)
        self._atomic(self._path(key, ".npz"), write)

    @staticmethod
    def _atomic(path: Path, write) -> None:
        """Write through a temporary file, so that an interrupted write leaves no entry rather than a broken one."""
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        write(tmp)
        os.replace(tmp, path)
