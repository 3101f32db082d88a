"""Trajectories from another simulator (Isaac Gym, Isaac Lab, MuJoCo Playground, ...) as our dataset.

`read_external` reads the documented CSV or `.npz` (docs/byo_data.md); `convert` maps its joints to the config's
order by name, converts units to SI, checks it (finite values, episodes, time, rate, joint limits, plausible
velocities and torques) and, when asked, resamples it to the config's control rate; `load_training_data` is what
`bruce-train --data` calls: our own `.npz` as it is, anything else converted in memory. Every refusal is one
`ExternalDataError` line naming the file and the column (or array) at fault.
"""

from __future__ import annotations

import csv
import datetime
import difflib
import json
import math
import re
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata as package_metadata
from pathlib import Path

import numpy as np

from bruce_hw.config import RobotConfig
from runtime.loop.recorder import file_sha256, portable_path
from training.dataset import Dataset, DatasetError, config_hash, load_dataset
from training.episodes import episode_runs

QUANTITIES = ("q", "qd", "tau")
# Accepted units and their factor to SI; "" is a column without a unit suffix, which means SI.
UNITS: dict[str, dict[str, float]] = {
    "time": {"": 1.0, "s": 1.0, "ms": 1e-3},
    "q": {"": 1.0, "rad": 1.0, "deg": math.pi / 180},
    "qd": {"": 1.0, "rad/s": 1.0, "deg/s": math.pi / 180},
    "tau": {"": 1.0, "N*m": 1.0, "Nm": 1.0},
}
SI_UNITS = {"q": "rad", "qd": "rad/s", "tau": "N m"}
NPZ_ARRAYS = ("time", "episode", "q", "qd", "tau", "joint_names", "units")
NPZ_REQUIRED = ("time", "q", "qd", "tau", "joint_names")

Q_LIMIT_MARGIN = 0.05   # rad past the config's joint limits: a simulator's contact solver lets joints overshoot a bit
QD_BOUND = 50.0         # rad/s: above any BRUCE leg joint's speed (the config's velocity limits are bounded by it)
TAU_LIMIT_FACTOR = 2.0  # x the config's torque limit: a torque applied by the simulator stays within its clip
STEP_TOLERANCE = 0.01   # share of the mean time step a single step may differ by (timestamp rounding)
STEP_TOLERANCE_FLOOR_S = 1e-6
RATE_TOLERANCE = 1e-4   # relative: a mean step this close to 1 / loop_hz is the config's rate
MAX_UPSAMPLE = 20       # at most 20 ticks interpolated per source step (>= 50 Hz for a 1 kHz loop)


class ExternalDataError(DatasetError):
    """An external trajectory that cannot become a dataset for this robot config; the message names the file and
    the column or array."""


@dataclass(frozen=True)
class Column:
    """One joint quantity of the file, as written there (unit factor not applied yet)."""

    label: str      # how messages name it: "column 'q.r_knee[deg]'" or "array 'q' column 3 ('r_knee')"
    source: str     # the name in the file: "q.r_knee[deg]" or "q[:, 3]"
    quantity: str   # q | qd | tau
    joint: str
    unit: str       # as written; "" = SI
    values: np.ndarray


@dataclass(frozen=True)
class RawTrajectory:
    """A file as read, before mapping and checks."""

    path: Path
    kind: str                   # "csv" | "npz"
    time: np.ndarray            # [T] in `time_unit`
    time_unit: str
    episode: np.ndarray | None  # [T], None when the file has none (one episode)
    columns: tuple[Column, ...]
    time_label: str             # how messages name the time and episode columns or arrays
    episode_label: str

    def row(self, index: int) -> str:
        """Where sample `index` is in the file (a CSV's header is line 1)."""
        return f"line {index + 2}" if self.kind == "csv" else f"sample {index}"

    def unit_hint(self, quantity: str, joint: str, unit: str) -> str:
        if self.kind == "csv":
            return f"label it '{quantity}.{joint}[{unit}]'"
        return f'give the file units {{"{quantity}": "{unit}"}}'


@dataclass(frozen=True)
class Conversion:
    """What converting a file did: for the summary line and the dataset's metadata."""

    source: Path
    source_hz: float
    target_hz: int
    samples_in: int
    samples_out: int
    episodes: int
    resampling: dict | None
    dropped_joints: tuple[str, ...]

    def describe(self) -> str:
        if self.resampling is None:
            how = "not resampled"
        elif self.resampling["method"] == "decimate":
            how = (f"resampled to {self.target_hz} Hz (decimated by {self.resampling['factor']}: q, qd every "
                   f"{self.resampling['factor']}th sample, tau the mean over each tick)")
        else:
            how = (f"resampled to {self.target_hz} Hz (q: cubic Hermite, qd: linear, tau: held over each source "
                   "step)")
        dropped = f"; dropped joints the config lacks: {list(self.dropped_joints)}" if self.dropped_joints else ""
        return (f"{self.samples_out} samples ({self.samples_out / self.target_hz:g} s at {self.target_hz} Hz), "
                f"{self.episodes} episode(s), from {self.source} at {self.source_hz:.6g} Hz ({self.samples_in} "
                f"samples), {how}{dropped}")


# -- reading ----------------------------------------------------------------------------------------------------
def read_external(path: str | Path) -> RawTrajectory:
    """The file as written: a `.csv` or an external `.npz` (docs/byo_data.md)."""
    path = Path(path)
    if not path.is_file():
        raise ExternalDataError(f"{path}: trajectory file not found")
    if path.suffix.lower() == ".csv":
        return _read_csv(path)
    if path.suffix.lower() == ".npz":
        return _read_npz(path)
    raise ExternalDataError(f"{path}: expected a .csv or .npz trajectory (docs/byo_data.md), got {path.suffix!r}")


_HEADER_CELL = re.compile(r"\s*(?P<name>[^\[\]]*?)\s*(?:\[(?P<unit>[^\[\]]*)\])?\s*")


def _read_csv(path: Path) -> RawTrajectory:
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            header = next(csv.reader(handle), None)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ExternalDataError(f"{path}: unreadable CSV ({exc})") from None
    if not header:
        raise ExternalDataError(f"{path}: empty file, expected a header row (docs/byo_data.md)")
    names: dict[str, int] = {}
    parsed = []
    for index, cell in enumerate(header):
        match = _HEADER_CELL.fullmatch(cell)
        if match is None or not match["name"]:
            raise ExternalDataError(f"{path}: header cell {index + 1} {cell!r} is not a column name "
                                    "(expected time, episode, q.<joint>, qd.<joint> or tau.<joint>, with an "
                                    "optional [unit])")
        name, unit = match["name"], (match["unit"] or "").strip()
        if name in names:
            raise ExternalDataError(f"{path}: column {cell!r} repeats column {header[names[name]]!r}")
        names[name] = index
        parsed.append((cell, name, unit, _column_kind(path, cell, name, unit)))
    if "time" not in names:
        raise ExternalDataError(f"{path}: no column 'time' (seconds; the header has {header})")
    body = _read_csv_body(path, header)
    columns = tuple(Column(f"column {cell!r}", cell, quantity, joint, unit, body[:, i])
                    for i, (cell, _, unit, (quantity, joint)) in enumerate(parsed) if quantity in QUANTITIES)
    episode = body[:, names["episode"]] if "episode" in names else None
    time_cell, _, time_unit, _ = parsed[names["time"]]
    return RawTrajectory(path, "csv", body[:, names["time"]], time_unit, episode, columns, f"column {time_cell!r}",
                         f"column {header[names['episode']]!r}" if "episode" in names else "")


def _column_kind(path: Path, cell: str, name: str, unit: str) -> tuple[str, str]:
    """(quantity, joint) of a header cell, its unit checked; ("time"|"episode", "") for those."""
    if name == "episode":
        if unit:
            raise ExternalDataError(f"{path}: column {cell!r}: an episode id has no unit, got [{unit}]")
        return "episode", ""
    quantity, _, joint = name.partition(".") if name != "time" else ("time", "", "")
    if quantity not in UNITS or bool(joint) == (quantity == "time"):
        raise ExternalDataError(f"{path}: unknown column {cell!r} (expected time, episode, q.<joint>, qd.<joint> "
                                "or tau.<joint>, <joint> a name of the config's joints.names)")
    _check_unit(path, f"column {cell!r}", quantity, unit)
    return quantity, joint


def _check_unit(path: Path, label: str, quantity: str, unit: str) -> None:
    if unit not in UNITS[quantity]:
        accepted = ", ".join(u for u in UNITS[quantity] if u)
        raise ExternalDataError(f"{path}: {label} has unit [{unit}], which is not one for {quantity} "
                                f"(accepted: {accepted}; none means SI)")


def _read_csv_body(path: Path, header: list[str]) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": said below, in our words
            body = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64, comments=None,
                              quotechar='"', encoding="utf-8-sig")
    except ValueError as exc:  # name the cell: loadtxt's message counts neither lines nor columns our way
        _raise_bad_cell(path, header)
        raise ExternalDataError(f"{path}: unreadable CSV ({exc})") from None
    if body.shape[0] == 0:
        raise ExternalDataError(f"{path}: no data rows after the header")
    if body.shape[1] != len(header):
        raise ExternalDataError(f"{path}: the rows have {body.shape[1]} fields, the header has {len(header)}")
    return body


def _raise_bad_cell(path: Path, header: list[str]) -> None:
    with open(path, newline="", encoding="utf-8-sig") as handle:
        for line, row in enumerate(csv.reader(handle), start=1):
            if line == 1 or not row:
                continue
            if len(row) != len(header):
                raise ExternalDataError(f"{path}: line {line} has {len(row)} fields, the header has {len(header)}")
            for cell, name in zip(row, header, strict=True):
                try:
                    float(cell)
                except ValueError:
                    raise ExternalDataError(f"{path}: line {line}, column {name!r}: {cell!r} is not a "
                                            "number") from None


def _read_npz(path: Path) -> RawTrajectory:
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise ExternalDataError(f"{path}: not an .npz archive ({exc})") from None
    with archive:
        if not hasattr(archive, "files"):
            raise ExternalDataError(f"{path}: a single .npy array, expected an .npz with arrays {list(NPZ_ARRAYS)}")
        if "metadata" in archive.files:
            raise ExternalDataError(f"{path}: already a dataset of ours (it has 'metadata'): bruce-train --data reads "
                                    "it as it is")
        unknown = [name for name in archive.files if name not in NPZ_ARRAYS]
        if unknown:
            raise ExternalDataError(f"{path}: unknown array {unknown[0]!r} (an external .npz has "
                                    f"{list(NPZ_ARRAYS)}; docs/byo_data.md)")
        missing = [name for name in NPZ_REQUIRED if name not in archive.files]
        if missing:
            raise ExternalDataError(f"{path}: missing array {missing[0]!r} (neither our dataset, which has "
                                    f"'metadata', nor an external trajectory, which needs {list(NPZ_REQUIRED)})")
        try:
            arrays = {name: archive[name] for name in archive.files}
        except ValueError as exc:  # an object array, which would need pickle
            raise ExternalDataError(f"{path}: unreadable array ({exc})") from None

    q = arrays["q"]
    if q.ndim != 2 or q.shape[0] < 1:
        raise ExternalDataError(f"{path}: array 'q' has shape {list(q.shape)}, expected [T, n_joints]")
    for name in ("q", "qd", "tau", "time"):
        array = arrays[name]
        expected = list(q.shape) if name != "time" else [q.shape[0]]
        if list(array.shape) != expected:
            raise ExternalDataError(f"{path}: array {name!r} has shape {list(array.shape)}, expected {expected}")
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
            raise ExternalDataError(f"{path}: array {name!r} has dtype {array.dtype}, expected numbers")
    names = arrays["joint_names"]
    if names.dtype.kind == "S":
        names = names.astype(str)
    if names.dtype.kind != "U" or names.shape != (q.shape[1],):
        raise ExternalDataError(f"{path}: array 'joint_names' must be {q.shape[1]} strings (one per column of "
                                f"'q'), got dtype {names.dtype} shape {list(names.shape)}")
    repeated = [n for n in dict.fromkeys(names.tolist()) if names.tolist().count(n) > 1]
    if repeated:
        raise ExternalDataError(f"{path}: array 'joint_names' names {repeated[0]!r} twice")
    episode = arrays.get("episode")
    if episode is not None and (episode.shape != (q.shape[0],) or episode.dtype.kind not in "iuf"):
        raise ExternalDataError(f"{path}: array 'episode' must be [{q.shape[0]}] numbers (one id per sample), got "
                                f"dtype {episode.dtype} shape {list(episode.shape)}")
    units = _npz_units(path, arrays.get("units"))
    columns = tuple(Column(f"array {quantity!r} column {i} ({joint!r})", f"{quantity}[:, {i}]", quantity, joint,
                           units.get(quantity, ""), arrays[quantity][:, i].astype(np.float64))
                    for quantity in QUANTITIES for i, joint in enumerate(names.tolist()))
    return RawTrajectory(path, "npz", arrays["time"].astype(np.float64), units.get("time", ""),
                         None if episode is None else episode.astype(np.float64), columns, "array 'time'",
                         "array 'episode'")


def _npz_units(path: Path, array: np.ndarray | None) -> dict[str, str]:
    if array is None:
        return {}
    try:
        units = json.loads(str(array)) if array.shape == () and array.dtype.kind == "U" else None
    except json.JSONDecodeError:
        units = None
    if not isinstance(units, dict) or not all(isinstance(v, str) for v in units.values()):
        raise ExternalDataError(f"{path}: array 'units' must be a JSON object string such as "
                                f"'{{\"q\": \"deg\", \"qd\": \"deg/s\"}}', got {array!r}")
    for key, unit in units.items():
        if key not in UNITS:
            raise ExternalDataError(f"{path}: array 'units' has key {key!r}, expected some of {list(UNITS)}")
        _check_unit(path, f"array {key!r}", key, unit)
    return units


# -- mapping and checks -----------------------------------------------------------------------------------------
def _map_joints(raw: RawTrajectory, config: RobotConfig, ignore_extra: bool
                ) -> tuple[dict[str, list[Column]], tuple[str, ...]]:
    """{quantity: [Column per config joint, config order]} and the file's joints that the config lacks."""
    by_joint: dict[str, dict[str, Column]] = {}
    for column in raw.columns:
        by_joint.setdefault(column.joint, {})[column.quantity] = column
    extra = tuple(joint for joint in by_joint if joint not in config.joints)
    missing = [joint for joint in config.joints if joint not in by_joint]
    if extra and not ignore_extra:
        first = next(iter(by_joint[extra[0]].values()))
        close = difflib.get_close_matches(extra[0], missing or config.joints, n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ExternalDataError(f"{raw.path}: {first.label}: joint {extra[0]!r} is not in joints.names of "
                                f"{config.path}{hint}; the file's joints the config lacks: {list(extra)} (rename "
                                "them, or pass --ignore-extra to drop them)")
    if missing:
        typo = difflib.get_close_matches(missing[0], extra, n=1, cutoff=0.6)
        hint = f"; the file has joint {typo[0]!r}: a typo?" if typo else ""
        raise ExternalDataError(f"{raw.path}: no data for joint(s) {missing} of {config.path} (expected "
                                f"{_expected_names(raw, missing[0])}){hint}")
    for joint in config.joints:
        absent = [quantity for quantity in QUANTITIES if quantity not in by_joint[joint]]
        if absent:
            raise ExternalDataError(f"{raw.path}: no column '{absent[0]}.{joint}' (every joint needs "
                                    f"{_expected_names(raw, joint)})")
    return {quantity: [by_joint[joint][quantity] for joint in config.joints] for quantity in QUANTITIES}, extra


def _expected_names(raw: RawTrajectory, joint: str) -> str:
    if raw.kind == "csv":
        return ", ".join(f"{quantity}.{joint}" for quantity in QUANTITIES)
    return f"{joint!r} in array 'joint_names'"


def _check_finite(raw: RawTrajectory, columns: dict[str, list[Column]]) -> None:
    named = [(raw.time_label, raw.time)] + ([(raw.episode_label, raw.episode)] if raw.episode is not None else [])
    named += [(column.label, column.values) for quantity in QUANTITIES for column in columns[quantity]]
    for label, values in named:
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            raise ExternalDataError(f"{raw.path}: {label} has {len(bad)} non-finite value(s), the first "
                                    f"{values[bad[0]]} at {raw.row(int(bad[0]))}")


def _episode_runs(raw: RawTrajectory, time: np.ndarray) -> tuple[np.ndarray, tuple[tuple[int, int], ...], list]:
    """(episode renumbered 0.. in file order, its runs, the file's ids); checks ids and time inside each run."""
    ids = np.zeros(len(time)) if raw.episode is None else raw.episode
    fractional = np.flatnonzero(ids != np.round(ids))
    if len(fractional):
        raise ExternalDataError(f"{raw.path}: {raw.episode_label}: {ids[fractional[0]]} at "
                                f"{raw.row(int(fractional[0]))} is not an integer id")
    runs = episode_runs(ids)
    seen: dict[float, int] = {}
    for begin, end in runs:
        number = ids[begin]
        if number in seen:
            raise ExternalDataError(f"{raw.path}: {raw.episode_label}: episode {number:g} comes back at "
                                    f"{raw.row(begin)} after other episodes (it ended at {raw.row(seen[number])});"
                                    " an episode must be one contiguous run of rows")
        seen[number] = end - 1
        if end - begin < 2:
            raise ExternalDataError(f"{raw.path}: {raw.episode_label}: episode {number:g} has one sample "
                                    f"({raw.row(begin)}); an episode needs at least 2")
        steps = np.diff(time[begin:end])
        back = np.flatnonzero(steps <= 0)
        if len(back):
            i = begin + int(back[0])
            unit = raw.time_unit or "s"
            raise ExternalDataError(f"{raw.path}: {raw.time_label} does not increase within episode {number:g}: "
                                    f"{raw.time[i]:.9g} {unit} at {raw.row(i)}, then {raw.time[i + 1]:.9g} {unit} "
                                    f"at {raw.row(i + 1)}")
    renumbered = np.repeat(np.arange(len(runs), dtype=np.int64), [end - begin for begin, end in runs])
    return renumbered, runs, [int(ids[begin]) for begin, _ in runs]


def _mean_step(raw: RawTrajectory, time: np.ndarray, runs: tuple[tuple[int, int], ...]) -> float:
    """The file's time step (s), after checking every step is within tolerance of it."""
    mean = sum(time[end - 1] - time[begin] for begin, end in runs) / sum(end - begin - 1 for begin, end in runs)
    rows = np.concatenate([np.arange(begin + 1, end) for begin, end in runs])
    steps = time[rows] - time[rows - 1]
    worst = int(np.argmax(np.abs(steps - mean)))
    tolerance = max(STEP_TOLERANCE * mean, STEP_TOLERANCE_FLOOR_S)
    if abs(steps[worst] - mean) > tolerance:
        raise ExternalDataError(f"{raw.path}: {raw.time_label}: time steps are not uniform: the step to "
                                f"{raw.row(int(rows[worst]))} is {steps[worst]:.6g} s, the mean step is "
                                f"{mean:.6g} s (deviation {abs(steps[worst] - mean):.3g} s, tolerance "
                                f"{tolerance:.3g} s): dropped or repeated frames?")
    return float(mean)


def _check_ranges(raw: RawTrajectory, config: RobotConfig, values: dict[str, np.ndarray],
                  columns: dict[str, list[Column]]) -> None:
    """Values a correctly labelled BRUCE trajectory cannot have; the message says what the label likely is."""
    low, high = config.q_lower - Q_LIMIT_MARGIN, config.q_upper + Q_LIMIT_MARGIN
    for j, column in enumerate(columns["q"]):
        q = values["q"][:, j]
        outside = np.flatnonzero((q < low[j]) | (q > high[j]))
        if len(outside):
            i = int(outside[np.argmax(np.abs(q[outside]))])
            why = (f"looks like degrees: {raw.unit_hint('q', column.joint, 'deg')}" if np.abs(q).max() > 2 * math.pi
                   else "another zero or sign convention for this joint than the config's model?")
            raise ExternalDataError(f"{raw.path}: {column.label} leaves the joint limits [{config.q_lower[j]:g}, "
                                    f"{config.q_upper[j]:g}] rad of {config.path} by more than {Q_LIMIT_MARGIN} "
                                    f"rad ({q[i]:.6g} rad at {raw.row(i)}): {why}")
    for j, column in enumerate(columns["qd"]):
        qd = np.abs(values["qd"][:, j])
        if qd.max() > QD_BOUND:
            i = int(np.argmax(qd))
            why = (f": deg/s labelled as rad/s? {raw.unit_hint('qd', column.joint, 'deg/s')}" if column.unit != "deg/s"
                   else "")
            raise ExternalDataError(f"{raw.path}: {column.label} reaches {values['qd'][i, j]:.6g} rad/s at "
                                    f"{raw.row(i)}, beyond a plausible {QD_BOUND:g} rad/s{why}")
    for j, column in enumerate(columns["tau"]):
        tau = np.abs(values["tau"][:, j])
        bound = TAU_LIMIT_FACTOR * config.tau_limit[j]
        if tau.max() > bound:
            i = int(np.argmax(tau))
            raise ExternalDataError(f"{raw.path}: {column.label} reaches {values['tau'][i, j]:.6g} N m at "
                                    f"{raw.row(i)}, beyond {TAU_LIMIT_FACTOR:g}x the torque limit "
                                    f"{config.tau_limit[j]:g} N m of {config.path}: log the torque the simulator "
                                    "applied (after its clipping), in N m")


# -- resampling -------------------------------------------------------------------------------------------------
def _interpolate(time: np.ndarray, q: np.ndarray, qd: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q and qd at times `at` (inside [time[0], time[-1]]). q: the cubic Hermite spline through the samples with qd
    as its derivative. qd: linear between samples, the constant acceleration a torque held over the step gives. Kept
    every 2nd sample of a 1 kHz walk of the mock, linear qd misses the samples in between by 13 % of a tick's change
    of qd (RMS), the spline's own derivative (which bends to fit q's discrete-time increments) by 71 %; kept every
    5th, the two are alike (docs/byo_data.md)."""
    i = np.clip(np.searchsorted(time, at, side="right") - 1, 0, len(time) - 2)
    h = (time[i + 1] - time[i])[:, None]
    s = ((at - time[i])[:, None]) / h
    s2, s3 = s * s, s * s * s
    q_at = ((2 * s3 - 3 * s2 + 1) * q[i] + (s3 - 2 * s2 + s) * h * qd[i] + (3 * s2 - 2 * s3) * q[i + 1]
            + (s3 - s2) * h * qd[i + 1])
    return q_at, (1 - s) * qd[i] + s * qd[i + 1]


def _resample_run(time: np.ndarray, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, dt: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One episode on the grid time[0] + k dt up to its last sample."""
    step = (time[-1] - time[0]) / (len(time) - 1)
    at = time[0] + np.arange(int(math.floor((time[-1] - time[0]) / dt + 1e-6)) + 1) * dt
    q_at, qd_at = _interpolate(time, q, qd, np.minimum(at, time[-1]))
    # Zero-order hold: a simulator applies the torque it computed at a step unchanged until its next step (Isaac
    # Gym's actuation tensor and MuJoCo's ctrl are held over the physics step), so every tick inside a source step
    # saw that torque; interpolating it would invent torques the simulator never applied. A grid instant within
    # 0.1 % of a step before a sample is that sample's instant (rounding), and takes its torque.
    held = np.clip(np.searchsorted(time, at + 1e-3 * step, side="right") - 1, 0, len(time) - 1)
    return q_at, qd_at, tau[held]


def _decimate_run(q: np.ndarray, qd: np.ndarray, tau: np.ndarray, factor: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every `factor`th sample; tau the mean of the `factor` torques held over the tick, the constant torque with
    the same impulse over it (the last sample's mean covers what is left)."""
    kept = np.arange(0, len(q), factor)
    sums = np.add.reduceat(tau, kept, axis=0)
    counts = np.diff(np.append(kept, len(q)))[:, None]
    return q[kept], qd[kept], sums / counts


def _rate_plan(raw: RawTrajectory, config: RobotConfig, step: float, resample: bool) -> dict | None:
    """None when the file is at the config's rate; else how to resample it (or a refusal)."""
    hz, rate = config.loop_hz, 1.0 / step
    if abs(step * hz - 1.0) <= RATE_TOLERANCE:
        return None
    if not resample:
        raise ExternalDataError(f"{raw.path}: the samples are {rate:.6g} Hz (mean time step {step:.6g} s), "
                                f"{config.path} runs at rates.loop_hz = {hz} Hz: pass --resample to resample to "
                                f"{hz} Hz (docs/byo_data.md)")
    if rate < hz:
        if hz / rate > MAX_UPSAMPLE:
            raise ExternalDataError(f"{raw.path}: {rate:.6g} Hz is too coarse to resample to {hz} Hz (at most "
                                    f"{MAX_UPSAMPLE}x: >= {hz / MAX_UPSAMPLE:g} Hz): log every physics step, not "
                                    "every policy step")
        return {"method": "interpolate", "from_hz": rate, "to_hz": hz, "q": "cubic Hermite spline, qd as its "
                "derivative", "qd": "linear", "tau": "zero-order hold over each source step"}
    factor = round(rate / hz)
    if abs(rate / (factor * hz) - 1.0) > RATE_TOLERANCE:
        raise ExternalDataError(f"{raw.path}: {rate:.6g} Hz is faster than rates.loop_hz = {hz} Hz and not an "
                                f"integer multiple of it: only an integer multiple is decimated (the torques over "
                                "a tick would otherwise be interpolated)")
    return {"method": "decimate", "factor": factor, "from_hz": rate, "to_hz": hz, "q": f"every {factor}th sample",
            "qd": f"every {factor}th sample", "tau": f"mean of the {factor} torques over each tick"}


# -- the conversion ---------------------------------------------------------------------------------------------
def convert(raw: RawTrajectory, config: RobotConfig, *, resample: bool = False, ignore_extra: bool = False,
            source_name: str | None = None, command: str | None = None) -> tuple[Dataset, Conversion]:
    """The file as our dataset for `config` (config joint order, SI units, 1 / loop_hz apart)."""
    columns, dropped = _map_joints(raw, config, ignore_extra)
    _check_finite(raw, columns)
    values = {quantity: np.stack([c.values * UNITS[quantity][c.unit] for c in columns[quantity]], axis=1)
              for quantity in QUANTITIES}
    time = raw.time * UNITS["time"][raw.time_unit]
    episode, runs, file_ids = _episode_runs(raw, time)
    step = _mean_step(raw, time, runs)
    _check_ranges(raw, config, values, columns)
    plan = _rate_plan(raw, config, step, resample)
    if plan is not None:
        parts = [(_resample_run(time[a:b], values["q"][a:b], values["qd"][a:b], values["tau"][a:b], config.dt)
                  if plan["method"] == "interpolate" else
                  _decimate_run(values["q"][a:b], values["qd"][a:b], values["tau"][a:b], plan["factor"]))
                 for a, b in runs]
        values = {quantity: np.concatenate([part[k] for part in parts]) for k, quantity in enumerate(QUANTITIES)}
        episode = np.concatenate([np.full(len(part[0]), n, dtype=np.int64) for n, part in enumerate(parts)])
    conversion = Conversion(raw.path, 1.0 / step, config.loop_hz, len(time), len(episode), len(runs), plan,
                            dropped)
    metadata = {
        "joint_names": list(config.joints),
        "config_hash": config_hash(config),
        "config": portable_path(config.path),
        "robot": config.name,
        "samples": len(episode),
        "dt": config.dt,
        "units": SI_UNITS,
        "tau": "as the source logged it: the torque applied from each sample to the next (docs/byo_data.md)",
        "source": {"path": str(raw.path), "sha256": file_sha256(raw.path), "format": raw.kind, "name": source_name,
                   "rate_hz": 1.0 / step, "samples": len(time), "episode_ids": file_ids,
                   "columns": {joint: {c.quantity: {"from": c.source, "unit": c.unit or "SI"}
                                       for c in (columns[quantity][j] for quantity in QUANTITIES)}
                               for j, joint in enumerate(config.joints)},
                   "dropped_joints": list(dropped)},
        "resampling": plan,
        "package_version": package_metadata.version("bruce-sim2real"),
        "command": command,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    dataset = Dataset(values["q"], values["qd"], values["tau"], episode, config.dt, metadata, str(raw.path))
    return dataset, conversion


def is_our_dataset(path: str | Path) -> bool:
    """An `.npz` with our `metadata` array (bruce-collect, bruce-import-data); anything else is external."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return path.suffix.lower() != ".csv"  # a missing or other file: load_dataset says what is wrong with it
    try:
        with np.load(path, allow_pickle=False) as archive:
            return "metadata" in getattr(archive, "files", ())
    except (OSError, ValueError, zipfile.BadZipFile):
        return True


def load_training_data(path: str | Path, config: RobotConfig, *, resample: bool = False, ignore_extra: bool = False,
                       say: Callable[[str], None] = print) -> Dataset:
    """Our dataset as it is; an external trajectory converted in memory (with the same checks and rate rule as
    bruce-import-data), which `say` reports on one line."""
    if is_our_dataset(path):
        return load_dataset(path, config)
    dataset, conversion = convert(read_external(path), config, resample=resample, ignore_extra=ignore_extra)
    say(f"{path} is an external trajectory, converted in memory (docs/byo_data.md): {conversion.describe()}")
    return dataset
