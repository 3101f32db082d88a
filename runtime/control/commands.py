"""Velocity commands for the walking controllers: timed segments of (vx, vy, yaw rate), with linear ramps.

A `CommandSchedule` is a constant command (`CommandSchedule.constant(vx, vy, wz)`, held for ever) or a
scenario file (`CommandSchedule.from_yaml(path)`):

    segments:                     # run one after the other; the command is 0 after the last
      - {duration: 10.0, cmd: [0.4, 0.0, 0.0]}   # s; [vx m/s, vy m/s, yaw rate rad/s], base heading frame
      - {duration: 5.0, cmd: [0.0, 0.0, 0.5]}
    ramp_s: 0.5                   # optional (default 0.5): linear ramp from the command before (0 at the start)

A ramp starts at its segment's start and is cut short by a segment shorter than it. Every command must lie in
`COMMAND_LIMITS`, the range the walking controllers support; every number of a scenario in `SCENARIO_BOUNDS`.
The schedule is precomputed as a piecewise-linear curve, so `at(t)` (called at the policy rate in the control
loop) is a bisect and one interpolation.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bruce_hw.config import ConfigError
from bruce_hw.yaml_reader import Bound, YamlReader, bound_lookup, read_yaml

COMMAND_AXES = ("vx", "vy", "wz")
COMMAND_UNITS = ("m/s", "m/s", "rad/s")
COMMAND_LIMITS = {"vx": (-0.5, 1.0), "vy": (-0.3, 0.3), "wz": (-0.5, 0.5)}  # the walking controllers' range
DEFAULT_RAMP_S = 0.5
SCENARIO_BOUNDS = {  # docs/config_bounds.md
    "ramp_s": Bound(0.0, 10.0, "s", "ramp between commands; 0: steps"),
    "segments[*].duration": Bound(0.0, 3600.0, "s", "an hour outlasts a battery", low_open=True),
    **{f"segments[*].cmd.{axis}": Bound(*COMMAND_LIMITS[axis], unit, "the walking controllers' range")
       for axis, unit in zip(COMMAND_AXES, COMMAND_UNITS, strict=True)},
}
_scenario_bound = bound_lookup(SCENARIO_BOUNDS, "SCENARIO_BOUNDS")
_SCENARIO_KEYS = {"segments", "ramp_s"}
_SEGMENT_KEYS = {"duration", "cmd"}


def limit_violation(cmd: Sequence[float]) -> str | None:
    """What is out of `COMMAND_LIMITS` in a (vx, vy, wz) command, or None when it is in range."""
    for axis, unit, value in zip(COMMAND_AXES, COMMAND_UNITS, cmd, strict=True):
        low, high = COMMAND_LIMITS[axis]
        if not low <= value <= high:
            return f"{axis} = {value:g} {unit} is outside the supported range [{low:g}, {high:g}] {unit}"
    return None


class CommandSchedule:
    """Velocity command (vx, vy, yaw rate) as a function of the time since activation."""

    def __init__(self, segments: Sequence[tuple[float, Sequence[float]]], ramp_s: float = DEFAULT_RAMP_S,
                 name: str = "command schedule"):
        """`segments`: (duration s, (vx, vy, wz)) in order, already checked; the last may last for ever."""
        self.name = name
        self.duration = math.fsum(d for d, _ in segments)
        if math.isfinite(self.duration):
            segments = [*segments, (math.inf, (0.0, 0.0, 0.0))]  # stop (step in place) after the last segment
        times, values = [0.0], [np.zeros(3)]
        start, current = 0.0, np.zeros(3)
        for duration, cmd in segments:
            target = np.array(cmd, dtype=float)
            ramp = min(ramp_s, duration)
            reached = target if ramp >= ramp_s else current + (target - current) * (ramp / ramp_s)
            times.append(start + ramp)
            values.append(reached)
            if ramp < duration < math.inf:
                times.append(start + duration)
                values.append(reached)
            start, current = start + duration, reached
        self._times = times
        self._values = np.array(values)
        spans = np.diff(times)
        rises = np.diff(self._values, axis=0)
        # Zero-length spans (no ramp) are never interpolated in: bisect_right steps past them.
        self._slopes = np.divide(rises, spans[:, None], out=np.zeros_like(rises), where=spans[:, None] > 0)

    def outside(self, ranges: dict[str, Sequence[float]]) -> str | None:
        """What of this schedule leaves `ranges` (axis -> (low, high), e.g. the range a policy was trained on), or
        None. The schedule is piecewise linear: its corners are its extremes."""
        for i, (axis, unit) in enumerate(zip(COMMAND_AXES, COMMAND_UNITS, strict=True)):
            if axis not in ranges:
                continue
            low, high = ranges[axis]
            for value in (float(self._values[:, i].min()), float(self._values[:, i].max())):
                if not low - 1e-12 <= value <= high + 1e-12:
                    return f"{axis} = {value:g} {unit} is outside [{low:g}, {high:g}] {unit}"
        return None

    @classmethod
    def constant(cls, vx: float, vy: float, wz: float, ramp_s: float = DEFAULT_RAMP_S) -> CommandSchedule:
        """One command for ever (ramped up from 0); ValueError when it is out of `COMMAND_LIMITS`."""
        cmd = (float(vx), float(vy), float(wz))
        problem = limit_violation(cmd)
        if problem is not None:
            raise ValueError(f"command {problem}")
        return cls([(math.inf, cmd)], ramp_s, name=f"constant command ({vx:g}, {vy:g}, {wz:g})")

    @classmethod
    def from_yaml(cls, path: str | Path) -> CommandSchedule:
        """A scenario file; ConfigError naming the file, the segment and the problem when it is not usable."""
        path = Path(path)
        r = YamlReader(path, read_yaml(path, ConfigError, "scenario"), ConfigError, bounds=_scenario_bound)
        top = r.mapping("", _SCENARIO_KEYS, required={"segments"})
        ramp_s = r.number("ramp_s") if "ramp_s" in top else DEFAULT_RAMP_S
        segments = top["segments"]
        if not isinstance(segments, list) or not segments:
            raise r.fail("segments", "a non-empty list of {duration, cmd}", segments)
        return cls([_segment(r, f"segments[{i}]") for i in range(len(segments))], ramp_s, name=f"scenario {path}")

    def at(self, t: float) -> np.ndarray:
        """The command (vx, vy, wz) at t seconds since activation: 0 before 0 and after the schedule."""
        i = bisect_right(self._times, t)
        if i == 0:
            return self._values[0].copy()
        if i == len(self._times):
            return self._values[-1].copy()
        return self._values[i - 1] + self._slopes[i - 1] * (t - self._times[i - 1])


def _segment(r: YamlReader, key: str) -> tuple[float, tuple[float, float, float]]:
    r.mapping(key, _SEGMENT_KEYS, required=_SEGMENT_KEYS)
    duration = r.number(f"{key}.duration")
    cmd = r.vector(f"{key}.cmd", len(COMMAND_AXES), axes=COMMAND_AXES)  # each inside COMMAND_LIMITS
    return duration, tuple(float(v) for v in cmd)
