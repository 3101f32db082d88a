"""Joint-state datasets from the simulator: the `.npz` file (`save_dataset`, and `load_dataset`, which checks it
against the robot config), `config_hash`, the time split, statistics and windows for truncated back-propagation.

The arrays, the metadata and what `config_hash` covers: docs/dynamics.md ("The dataset file"). Sample t + 1 is the
state one tick after sample t under `tau[t]`, so a model learns (q, qd, tau)[t] -> (q, qd)[t + 1] for every t whose
successor is in the same episode (`training.episodes`). `split_by_time` is contiguous: the first `train_fraction`
of the samples train, the rest test, each a `Dataset` of its own, so no transition crosses the split.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bruce_hw.config import RobotConfig
from training.episodes import episode_runs, transition_indices

FORMAT_VERSION = 1
STATE_ARRAYS = ("q", "qd", "tau")
REQUIRED = (*STATE_ARRAYS, "episode", "dt", "metadata")
HASH_EXCLUDED_SECTIONS = ("buses", "policy", "pinn", "transfer")
# Floors the stds: it only keeps a channel that never changes from dividing by zero. Real channels are far above
# it (the smallest, the std of the 1 kHz Euler residual of q, is ~1e-5 rad).
STD_FLOOR = 1e-8
DT_TOLERANCE = 1e-9  # s


class DatasetError(ValueError):
    """A dataset that cannot be used with this robot config; the message names the file and the problem."""


def config_hash(config: RobotConfig) -> str:
    """The robot config's identity for datasets (docs/dynamics.md: what it covers and what it leaves out)."""
    tree = {key: value for key, value in config.raw.items() if key not in HASH_EXCLUDED_SECTIONS}
    digest = hashlib.sha256(json.dumps(tree, sort_keys=True, separators=(",", ":")).encode())
    digest.update(b"\0")
    digest.update(Path(config.mjcf).read_bytes())
    return digest.hexdigest()


def _check_state_arrays(where: str, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, episode: np.ndarray,
                        joint_names: tuple[str, ...] | None = None) -> None:
    """Shapes, dtypes, finiteness and episode order; DatasetError naming `where`, the array and the problem."""
    if q.ndim != 2 or q.shape[0] < 2:
        raise DatasetError(f"{where}: array 'q' has shape {list(q.shape)}, expected [T, n_joints] with T >= 2")
    for name, array in (("q", q), ("qd", qd), ("tau", tau)):
        if array.shape != q.shape:
            raise DatasetError(f"{where}: array {name!r} has shape {list(array.shape)}, expected {list(q.shape)} "
                               "(as 'q')")
        bad = np.argwhere(~np.isfinite(array))
        if len(bad):
            row, col = (int(i) for i in bad[0])
            joint = joint_names[col] if joint_names is not None and col < len(joint_names) else f"column {col}"
            raise DatasetError(f"{where}: array {name!r} has {len(bad)} non-finite value(s), the first at sample "
                               f"{row}, {joint}")
    if episode.shape != (q.shape[0],):
        raise DatasetError(f"{where}: array 'episode' has shape {list(episode.shape)}, expected [{q.shape[0]}] "
                           "(one id per sample)")
    if not np.issubdtype(episode.dtype, np.integer):
        raise DatasetError(f"{where}: array 'episode' has dtype {episode.dtype}, expected integers")
    backwards = np.flatnonzero(np.diff(episode) < 0)
    if len(backwards):
        i = int(backwards[0])
        raise DatasetError(f"{where}: array 'episode' must be non-decreasing (an episode is one contiguous run), "
                           f"but goes from {episode[i]} to {episode[i + 1]} at sample {i + 1}")


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _read_only(values, dtype) -> np.ndarray:
    """`values` as a read-only array: a view when it already is one (slices of a Dataset), else a copy, so the
    caller's own arrays are never frozen."""
    array = np.asarray(values, dtype=dtype)
    return _frozen(array.copy() if array.flags.writeable else array)


@dataclass(frozen=True, eq=False)
class Dataset:
    """Joint states at every control tick, config joint order. `span` is (first, stop) of these samples in the
    source file (a split is a Dataset too); `source` names it in messages. Arrays are read-only."""

    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    episode: np.ndarray
    dt: float
    metadata: dict = field(default_factory=dict)
    source: str = "dataset"
    span: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        arrays = {name: _read_only(getattr(self, name), np.float64) for name in STATE_ARRAYS}
        episode = np.asarray(self.episode)
        arrays["episode"] = _read_only(episode, np.int64 if np.issubdtype(episode.dtype, np.integer) else None)
        names = self.metadata.get("joint_names")
        _check_state_arrays(self.source, arrays["q"], arrays["qd"], arrays["tau"], arrays["episode"],
                            tuple(names) if names else None)
        if not (isinstance(self.dt, int | float) and math.isfinite(self.dt) and self.dt > 0):
            raise DatasetError(f"{self.source}: dt must be a time step > 0 s, got {self.dt!r}")
        for name, array in arrays.items():
            object.__setattr__(self, name, array)
        object.__setattr__(self, "dt", float(self.dt))
        if self.span is None:
            object.__setattr__(self, "span", (0, len(self)))

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def joint_names(self) -> tuple[str, ...] | None:
        names = self.metadata.get("joint_names")
        return tuple(names) if names else None

    def slice(self, start: int, stop: int, label: str) -> Dataset:
        """Samples [start, stop) as a Dataset of their own (no transition leaves it)."""
        first = self.span[0]
        return Dataset(self.q[start:stop], self.qd[start:stop], self.tau[start:stop], self.episode[start:stop],
                       self.dt, self.metadata, f"{self.source} [{label}: samples {first + start}..{first + stop}]",
                       (first + start, first + stop))


def split_by_time(dataset: Dataset, train_fraction: float = 0.8) -> tuple[Dataset, Dataset]:
    """(train, test): the first round(train_fraction T) samples and the rest, never shuffled (adjacent 1 kHz
    samples are near-duplicates: a shuffled split would test on the training data)."""
    if not 0.0 < train_fraction < 1.0:
        raise ValueError(f"split_by_time: train_fraction must be in (0, 1), got {train_fraction!r}")
    n_train = round(train_fraction * len(dataset))
    if not 2 <= n_train <= len(dataset) - 2:
        raise DatasetError(f"{dataset.source}: {len(dataset)} samples are too few to split {train_fraction:g} / "
                           f"{1 - train_fraction:g} with at least 2 samples per part")
    return dataset.slice(0, n_train, "train"), dataset.slice(n_train, len(dataset), "test")


@dataclass(frozen=True, eq=False)
class DatasetStats:
    """Per-joint statistics ([n_joints] float64 each) that models fit their input scaling and output scales to.

    q/qd/tau mean and std are over the inputs of the valid transitions; `q_inc_std` is the std of the Euler
    residual q[t+1] - q[t] - qd[t] dt and `qd_inc_std` that of qd[t+1] - qd[t]. Stds are population stds
    (ddof 0) floored at STD_FLOOR."""

    q_mean: np.ndarray
    q_std: np.ndarray
    qd_mean: np.ndarray
    qd_std: np.ndarray
    tau_mean: np.ndarray
    tau_std: np.ndarray
    q_inc_std: np.ndarray
    qd_inc_std: np.ndarray

    def __post_init__(self) -> None:
        n = np.shape(self.q_mean)[0] if np.ndim(self.q_mean) == 1 else None
        for name in self.field_names():
            value = np.array(getattr(self, name), dtype=np.float64)
            if n is None or value.shape != (n,):
                raise ValueError(f"DatasetStats.{name}: expected shape [{n}] (n_joints), got {list(value.shape)}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"DatasetStats.{name}: non-finite entries {value.tolist()}")
            if name.endswith("_std") and not np.all(value > 0):
                raise ValueError(f"DatasetStats.{name}: a std must be > 0, got {value.tolist()}")
            object.__setattr__(self, name, _frozen(value))

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return ("q_mean", "q_std", "qd_mean", "qd_std", "tau_mean", "tau_std", "q_inc_std", "qd_inc_std")

    @property
    def n_joints(self) -> int:
        return self.q_mean.shape[0]

    def to_json(self) -> dict[str, list[float]]:
        return {name: getattr(self, name).tolist() for name in self.field_names()}

    @classmethod
    def from_json(cls, data: dict) -> DatasetStats:
        return cls(**{name: data[name] for name in cls.field_names()})


def compute_stats(train: Dataset) -> DatasetStats:
    """Statistics of `train`'s valid transitions (pass the training split only: test data must not leak in)."""
    t = transition_indices(train.episode)
    if len(t) == 0:
        raise DatasetError(f"{train.source}: no transition inside an episode to compute statistics from")

    def std(values: np.ndarray) -> np.ndarray:
        return np.maximum(values.std(axis=0), STD_FLOOR)

    q, qd, tau = train.q[t], train.qd[t], train.tau[t]
    return DatasetStats(q_mean=q.mean(axis=0), q_std=std(q), qd_mean=qd.mean(axis=0), qd_std=std(qd),
                        tau_mean=tau.mean(axis=0), tau_std=std(tau),
                        q_inc_std=std(train.q[t + 1] - q - qd * train.dt), qd_inc_std=std(train.qd[t + 1] - qd))


@dataclass(frozen=True, eq=False)
class Windows:
    """Windows of `length` transitions (length + 1 samples) for truncated back-propagation through time.

    Window i covers samples start[i] .. start[i] + length of its dataset: inputs at the first `length`, targets
    at the last `length`. `continues[i]` is the window whose last sample is window i's first (same episode), so
    a model's recurrent state at the end of that window is the right initial state for window i; -1 where a
    window starts an episode's stream (start the state fresh, or warm it up). Windows are in time order."""

    start: np.ndarray      # [N] int64, first sample of each window
    episode: np.ndarray    # [N] int64, the episode id it lies in
    continues: np.ndarray  # [N] int64, index of the window it continues, -1 for none
    length: int

    def __len__(self) -> int:
        return len(self.start)

    def gather(self, dataset: Dataset, which: np.ndarray | slice | None = None,
               dtype: np.dtype | type = np.float64) -> dict[str, np.ndarray]:
        """{"q", "qd", "tau"} -> [B, length + 1, n_joints] for the windows `which` (default: all), in that order."""
        starts = self.start if which is None else self.start[which]
        index = np.asarray(starts)[:, None] + np.arange(self.length + 1)
        return {name: getattr(dataset, name)[index].astype(dtype, copy=False) for name in STATE_ARRAYS}

    def streams(self, n_streams: int) -> tuple[np.ndarray, np.ndarray]:
        """Lay the windows out as `n_streams` parallel streams for batches with carried state.

        Returns (index, fresh), each [steps, n_streams]: column b is windows b * steps .. (b + 1) * steps - 1 in
        time order (steps = len // n_streams; the last len % n_streams windows are left out). At step k the batch
        is `gather(dataset, index[k])`; the state of column b carries from step k - 1 to step k except where
        fresh[k, b], where window index[k, b] does not continue index[k - 1, b] (step 0, or a new episode)."""
        if not (isinstance(n_streams, int) and 0 < n_streams <= len(self)):
            raise ValueError(f"Windows.streams: n_streams must be an integer in 1..{len(self)} (the number of "
                             f"windows), got {n_streams!r}")
        steps = len(self) // n_streams
        index = np.arange(steps * n_streams).reshape(n_streams, steps).T
        fresh = np.ones_like(index, dtype=bool)
        fresh[1:] = self.continues[index[1:]] != index[:-1]
        return index, fresh


def windows(dataset: Dataset, length: int, stride: int | None = None, offset: int = 0) -> Windows:
    """Windows of `length` transitions inside each episode of `dataset`, never across a boundary.

    In each episode the first window starts `offset` samples in (0 <= offset < length; vary it between epochs to
    move the cuts) and the next ones every `stride` samples (default `length`: consecutive windows share their
    boundary sample and each continues the one before); a tail shorter than a window is left out. With a stride
    other than `length`, no window continues another."""
    if not (isinstance(length, int) and length > 0):
        raise ValueError(f"windows: length must be an integer > 0 (transitions per window), got {length!r}")
    stride = length if stride is None else stride
    if not (isinstance(stride, int) and stride > 0):
        raise ValueError(f"windows: stride must be an integer > 0, got {stride!r}")
    if not (isinstance(offset, int) and 0 <= offset < max(length, stride)):
        raise ValueError(f"windows: offset must be an integer in [0, {max(length, stride)}), got {offset!r}")
    starts, episodes, continues = [], [], []
    for begin, end in episode_runs(dataset.episode):
        first = np.arange(begin + offset, end - length, stride)  # the last sample, start + length, is < end
        if len(first) == 0:
            continue
        base = sum(len(s) for s in starts)
        chained = np.arange(base - 1, base + len(first) - 1) if stride == length else np.full(len(first), -1)
        chained[0] = -1
        starts.append(first)
        episodes.append(np.full(len(first), dataset.episode[begin]))
        continues.append(chained)
    if not starts:
        empty = np.zeros(0, dtype=np.int64)
        return Windows(empty, empty.copy(), empty.copy(), length)
    return Windows(np.concatenate(starts).astype(np.int64), np.concatenate(episodes).astype(np.int64),
                   np.concatenate(continues).astype(np.int64), length)


# -- the file -------------------------------------------------------------------------------------------------
def save_dataset(path: str | Path, dataset: Dataset) -> Path:
    """Write `dataset` in the documented format (docs/dynamics.md), atomically: a crash leaves no half file."""
    path = Path(path)
    for key in ("joint_names", "config_hash"):
        if key not in dataset.metadata:
            raise DatasetError(f"{path}: metadata needs {key!r} (the loader checks it against the robot config)")
    metadata = {"format_version": FORMAT_VERSION, **dataset.metadata}
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as f:  # a file object: np.savez would append ".npz" to a path without it
        np.savez(f, q=dataset.q, qd=dataset.qd, tau=dataset.tau, episode=dataset.episode.astype(np.int64),
                            dt=np.float64(dataset.dt), metadata=np.array(json.dumps(metadata)))
    os.replace(partial, path)
    return path


def load_dataset(path: str | Path, config: RobotConfig) -> Dataset:
    """Read a dataset and check it against `config`; DatasetError naming the file and what does not match."""
    path = Path(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DatasetError(f"{path}: dataset file not found") from None
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise DatasetError(f"{path}: not a dataset .npz ({exc})") from None
    with archive:
        if not hasattr(archive, "files"):
            raise DatasetError(f"{path}: not a dataset .npz (a single .npy array, expected arrays {list(REQUIRED)})")
        missing = [name for name in REQUIRED if name not in archive.files]
        if missing:
            raise DatasetError(f"{path}: missing array {missing[0]!r} (a dataset has {list(REQUIRED)}, this file "
                               f"has {sorted(archive.files)})")
        try:
            arrays = {name: archive[name] for name in REQUIRED}
        except ValueError as exc:  # an object array, which would need pickle
            raise DatasetError(f"{path}: unreadable array ({exc})") from None

    metadata = _metadata(path, arrays["metadata"])
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise DatasetError(f"{path}: metadata format_version is {version!r}, expected {FORMAT_VERSION}")
    for name in STATE_ARRAYS:
        array = arrays[name]
        if not np.issubdtype(array.dtype, np.floating):
            raise DatasetError(f"{path}: array {name!r} has dtype {array.dtype}, expected floating point")
        if array.ndim != 2 or array.shape[1] != config.n_joints:
            raise DatasetError(f"{path}: array {name!r} has shape {list(array.shape)}, expected [T, "
                               f"{config.n_joints}] (n_joints of {config.path})")
    names = metadata.get("joint_names")
    if names != list(config.joints):
        raise DatasetError(f"{path}: joint_names {names} do not match joints.names of {config.path}: "
                           f"{list(config.joints)}")
    expected_hash = config_hash(config)
    if metadata.get("config_hash") != expected_hash:
        raise DatasetError(f"{path}: config_hash {metadata.get('config_hash')!r} does not match {config.path} "
                           f"({expected_hash}): the data was recorded with a different robot config or model "
                           f"(the hash covers the config without {list(HASH_EXCLUDED_SECTIONS)}, and the MJCF)")
    dt = arrays["dt"]
    if dt.shape != () or not np.issubdtype(dt.dtype, np.floating) or not math.isfinite(float(dt)):
        raise DatasetError(f"{path}: array 'dt' must be a finite float scalar, got {dt!r}")
    if abs(float(dt) - config.dt) > DT_TOLERANCE:
        raise DatasetError(f"{path}: dt = {float(dt):g} s does not match the control period of {config.path} "
                           f"(1 / rates.loop_hz = {config.dt:g} s)")
    return Dataset(arrays["q"], arrays["qd"], arrays["tau"], arrays["episode"], config.dt, metadata, str(path))


def _metadata(path: Path, array: np.ndarray) -> dict:
    if array.shape != () or array.dtype.kind != "U":
        raise DatasetError(f"{path}: array 'metadata' must be a JSON string scalar, got dtype {array.dtype} "
                           f"shape {list(array.shape)}")
    try:
        metadata = json.loads(str(array))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: array 'metadata' is not valid JSON ({exc})") from None
    if not isinstance(metadata, dict):
        raise DatasetError(f"{path}: array 'metadata' must hold a JSON object, got {type(metadata).__name__}")
    return metadata
