"""`bruce-collect`: record the simulator's joint dynamics under the walking policy, as the PINN's training data.

    bruce-collect --seconds 90 --seed 0 --out data/walk_90s.npz [--config PATH] [--segment-s 3.0] [--policy PATH]

The walking policy walks the nominal mock through the runtime's own session loop (`runtime.loop.run.run_session`, the
ticks of `bruce-run --backend mock`: Eq. 8, safety, transfer direct, ground-truth base state, unpaced) under sampled
velocity commands, and an observer of that loop (`EpisodeRecorder`) keeps q, qd and the written torque of every
tick. An episode starts standing after an unrecorded warm-up and ends at a fall, whose last `fall_trim_s` is
dropped. The same seed gives the same arrays and metadata. The commands, episodes and file: docs/dynamics.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import io
import logging
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata as package_metadata
from pathlib import Path

import numpy as np

from bruce_hw.backend import BackendError
from bruce_hw.config import DEFAULT_CONFIG, ConfigError, RobotConfig
from bruce_hw.mock import MujocoBackend
from runtime.cli import positive_seconds
from runtime.control.commands import COMMAND_AXES, COMMAND_LIMITS, CommandSchedule
from runtime.control.controllers import build_controller
from runtime.control.inference import ModelError
from runtime.loop.exit import INTERRUPTS
from runtime.loop.falls import fall_rule
from runtime.loop.observers import FallStop, TickObserver, TickView
from runtime.loop.recorder import file_sha256, portable_path
from runtime.loop.run import run_session
from runtime.robot_config import load_config
from training.dataset import Dataset, DatasetError, config_hash, save_dataset
from training.executor import Executor, ExecutorError, add_executor_arguments, job_files, make_executor

SAMPLE_BOX = {"vx": (-0.5, 1.0), "vy": (-0.5, 0.5), "wz": (-0.5, 0.5)}   # the paper's §IV-B command box
# What the committed policy supports: the ranges it was distilled on (training.distill.DistillSettings; the test
# checks them against the policy's sidecar), inside the runtime's COMMAND_LIMITS.
POLICY_CLIP = {"vx": (-0.5, 0.8), "vy": (-0.2, 0.2), "wz": (-0.5, 0.5)}
COMMAND_RAMP_S = 0.5
FALL_TRIM_S = 0.5
PROGRESS_TICKS = 100  # the progress bar moves every 0.1 s of simulated time
MAX_EMPTY_EPISODES = 20  # in a row: a controller that falls before anything is kept would never finish


class CollectError(RuntimeError):
    """A collection that cannot finish (the controller falls before anything is kept)."""


@dataclass(frozen=True)
class CollectSettings:
    seconds: float = 90.0     # recorded (kept) simulated seconds
    seed: int = 0
    segment_s: float = 3.0    # each sampled command is held this long
    fall_trim_s: float = FALL_TRIM_S
    ramp_s: float = COMMAND_RAMP_S

    def __post_init__(self) -> None:
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise ValueError(f"seconds: expected a duration > 0 s, got {self.seconds!r}")
        if not (math.isfinite(self.segment_s) and self.segment_s > 0):
            raise ValueError(f"segment_s: expected a duration > 0 s, got {self.segment_s!r}")
        if not self.fall_trim_s >= 0 or not self.ramp_s >= 0:
            raise ValueError(f"fall_trim_s and ramp_s must be >= 0 s, got {self.fall_trim_s!r}, {self.ramp_s!r}")
        for axis, (low, high) in POLICY_CLIP.items():  # a clip outside the runtime's limits is a programming error
            assert COMMAND_LIMITS[axis][0] <= low < high <= COMMAND_LIMITS[axis][1], axis


def sample_command(rng: np.random.Generator) -> tuple[list[float], list[float]]:
    """(sampled, clipped): one draw from SAMPLE_BOX and the command the policy gets, clipped to POLICY_CLIP."""
    sampled = [float(rng.uniform(*SAMPLE_BOX[axis])) for axis in COMMAND_AXES]
    clipped = [min(max(v, POLICY_CLIP[axis][0]), POLICY_CLIP[axis][1]) for axis, v in zip(COMMAND_AXES, sampled,
                                                                                            strict=True)]
    return sampled, clipped


class EpisodeRecorder(TickObserver):
    """An observer of the session's loop: copies q, qd, the written torque and the true base position of every
    tick into preallocated arrays (a `runtime.loop.observers.FallStop` after it ends the session at a fall)."""

    def __init__(self, n_ticks: int, n_joints: int, on_progress: Callable[[int], None]):
        self.q = np.empty((n_ticks, n_joints))
        self.qd = np.empty((n_ticks, n_joints))
        self.tau = np.empty((n_ticks, n_joints))
        self.base_xy = np.empty((n_ticks, 2))
        self.ticks = 0
        self.on_progress = on_progress  # called with the tick every PROGRESS_TICKS

    def on_tick(self, view: TickView) -> None:
        tick = view.tick
        self.q[tick] = view.q
        self.qd[tick] = view.qd
        self.tau[tick] = view.tau
        self.base_xy[tick] = view.truth.base_pos[:2]
        self.ticks = tick + 1
        if tick % PROGRESS_TICKS == 0:
            self.on_progress(tick)


class Progress:
    """A tqdm bar over the kept simulated seconds, on stderr."""

    def __init__(self, ticks: int, dt: float, enabled: bool):
        self.bar = None
        if enabled:
            from tqdm import tqdm

            # Counts ticks (integers: no float drift past the total), shown in seconds through unit_scale.
            self.bar = tqdm(total=ticks, unit="s", unit_scale=dt, desc="bruce-collect", file=sys.stderr,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s simulated "
                                       "[{elapsed}<{remaining}, {rate_fmt}]{postfix}")

    def show(self, kept_ticks: int) -> None:
        """Kept ticks so far; it moves back when a fall's tail is dropped."""
        if self.bar is not None:
            self.bar.update(kept_ticks - self.bar.n)

    def episode(self, episodes: int, falls: int) -> None:
        if self.bar is not None:
            self.bar.set_postfix(episodes=episodes, falls=falls)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def collect(config: RobotConfig, settings: CollectSettings, *, policy: Path | None = None,
            backend_factory: Callable[[RobotConfig], MujocoBackend] = MujocoBackend, progress: bool = False,
            command_line: str | None = None) -> Dataset:
    """Roll the walking policy out in the mock until `settings.seconds` of samples are kept (docs/dynamics.md).

    `backend_factory(config)` makes each episode's mock (tests pass one that pushes or spies)."""
    policy_path = policy or config.models.policy
    if policy_path is None:
        raise ConfigError(f"{config.path}: policy.model: collection needs the walking policy (null runs the "
                          "standing controller); set it or pass --policy")
    controller, _ = build_controller(config, Path(policy_path), "policy")
    hz, dt = config.loop_hz, config.dt
    target = round(settings.seconds * hz)
    warmup = round(config.safety.soft_start_s * hz)
    trim = round(settings.fall_trim_s * hz)
    rng = np.random.default_rng(settings.seed)
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    episodes: list[dict] = []
    segments: list[dict] = []
    kept, falls, empty_in_a_row = 0, 0, 0
    bar = Progress(target, dt, progress)
    runtime_log = logging.getLogger("runtime")
    saved_level = runtime_log.level
    runtime_log.setLevel(logging.WARNING)  # one "torque ramp done" line per episode would bury the progress bar
    try:
        while kept < target:
            n_ticks = warmup + target - kept
            schedule, drawn = _episode_commands(rng, n_ticks * dt, config.safety.soft_start_s, settings)
            backend = backend_factory(config)
            recorder = EpisodeRecorder(n_ticks, config.n_joints,
                                       lambda tick, base=kept: bar.show(base + max(0, tick - warmup)))
            fall = FallStop()
            with contextlib.redirect_stdout(io.StringIO()):  # run_session's per-run banner and summary
                summary = run_session(backend, config, duration=n_ticks / hz, realtime=False, controller=controller,
                                      commands=schedule, observers=[recorder, fall])
            if summary.stop_cause in INTERRUPTS:
                raise KeyboardInterrupt(summary.stop_cause)
            ended_early = summary.stop_cause != "duration reached"
            # A fall is the recorder's last tick; a safety trip stops the loop before the tick is recorded.
            end = fall.fell_at if fall.fell_at is not None else recorder.ticks
            stop = max(warmup, end - trim) if ended_early else recorder.ticks
            falls += ended_early
            if stop - warmup < 2:  # no transition left to learn from
                empty_in_a_row += 1
                if empty_in_a_row >= MAX_EMPTY_EPISODES:
                    raise CollectError(f"{empty_in_a_row} episodes in a row ended before "
                                       f"{(warmup + trim + 2) / hz:g} s (last: {summary.stop_cause}); the "
                                       "controller does not walk in this mock")
                continue
            empty_in_a_row = 0
            index = len(episodes)
            parts.append((recorder.q[warmup:stop], recorder.qd[warmup:stop], recorder.tau[warmup:stop]))
            episodes.append({"episode": index, "first_index": kept, "samples": stop - warmup,
                             "end": "duration" if not ended_early else summary.stop_cause,
                             "simulated_s": round(recorder.ticks / hz, 6),
                             "base_xy_start": recorder.base_xy[warmup].tolist(),
                             "base_xy_end": recorder.base_xy[stop - 1].tolist()})
            for start_s, sampled, clipped in drawn:
                first = round(start_s * hz)
                if first < stop:
                    segments.append({"episode": index, "first_index": kept + first - warmup,
                                     "t_s": round((first - warmup) / hz, 6), "sampled": sampled, "cmd": clipped})
            kept += stop - warmup
            bar.show(kept)
            bar.episode(len(episodes), falls)
    finally:
        runtime_log.setLevel(saved_level)
        bar.close()

    ids = np.concatenate([np.full(len(q), i, dtype=np.int64) for i, (q, _, _) in enumerate(parts)])
    meta = {
        "joint_names": list(config.joints),
        "config_hash": config_hash(config),
        "config": portable_path(config.path),
        "robot": config.name,
        "seed": settings.seed,
        "seconds": settings.seconds,
        "samples": kept,
        "dt": dt,
        "units": {"q": "rad", "qd": "rad/s", "tau": "N m"},
        "tau": "applied: the safety stage's output written to the mock each tick (Eq. 8 only, transfer direct)",
        "policy": str(policy_path),
        "policy_sha256": file_sha256(policy_path),
        "commands": {"axes": list(COMMAND_AXES), "units": ["m/s", "m/s", "rad/s"],
                     "sampled_uniform": {k: list(v) for k, v in SAMPLE_BOX.items()},
                     "clipped_to": {k: list(v) for k, v in POLICY_CLIP.items()},
                     "segment_s": settings.segment_s, "ramp_s": settings.ramp_s},
        "warmup_s": config.safety.soft_start_s,
        "fall": {**fall_rule(), "trim_s": settings.fall_trim_s},
        "episodes": episodes,
        "segments": segments,
        "package_version": package_metadata.version("bruce-sim2real"),
        "command": command_line,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    return Dataset(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                   np.concatenate([p[2] for p in parts]), ids, dt, meta, "bruce-collect")


def collect_seed(config_path: str, settings: CollectSettings, policy: str | None) -> Dataset:
    """One seed's collection, as an executor's worker runs it (`--seeds`): no progress bar, its own log level."""
    return collect(load_config(config_path), settings, policy=Path(policy) if policy else None)


def merge(parts: list[Dataset], command_line: str | None = None) -> Dataset:
    """The seeds' datasets as one, in the order given: episodes numbered on, each episode and command segment
    naming its seed, `seeds` listing them; the same parts give the same file wherever they were collected."""
    first = parts[0].metadata
    offsets = np.cumsum([0] + [len(part) for part in parts[:-1]])
    episode_offsets = np.cumsum([0] + [len(part.metadata["episodes"]) for part in parts[:-1]])
    episodes, segments = [], []
    for part, offset, episode_offset in zip(parts, offsets, episode_offsets, strict=True):
        seed = part.metadata["seed"]
        episodes += [{**e, "seed": seed, "episode": e["episode"] + int(episode_offset),
                      "first_index": e["first_index"] + int(offset)} for e in part.metadata["episodes"]]
        segments += [{**g, "seed": seed, "episode": g["episode"] + int(episode_offset),
                      "first_index": g["first_index"] + int(offset)} for g in part.metadata["segments"]]
    meta = {**first, "seed": None, "seeds": [part.metadata["seed"] for part in parts],
            "seconds": float(sum(part.metadata["seconds"] for part in parts)), "samples": int(sum(map(len, parts))),
            "episodes": episodes, "segments": segments, "command": command_line or first.get("command")}
    return Dataset(np.concatenate([p.q for p in parts]), np.concatenate([p.qd for p in parts]),
                   np.concatenate([p.tau for p in parts]),
                   np.concatenate([p.episode + o for p, o in zip(parts, episode_offsets, strict=True)]),
                   parts[0].dt, meta, "bruce-collect")


def collect_seeds(config: RobotConfig, settings: CollectSettings, seeds: list[int], executor: Executor,
                  policy: Path | None = None, command_line: str | None = None, progress: bool = False) -> Dataset:
    """`settings.seconds` of samples per seed, each seed a run on `executor` (shipping `job_files(config.path,
    files=[policy])`), merged in the order of `seeds`."""
    calls = [(executor.where(config.path), dataclasses.replace(settings, seed=seed),
              executor.where(policy) if policy else None) for seed in seeds]
    parts: list[Dataset | None] = [None] * len(calls)
    per_seed = round(settings.seconds * config.loop_hz)
    bar = Progress(per_seed * len(calls), config.dt, progress)  # one bar over every seed, wherever it runs
    try:
        for done, (index, part) in enumerate(executor.map(collect_seed, calls), start=1):
            parts[index] = part
            bar.show(done * per_seed)
    finally:
        bar.close()
    merged = merge(parts, command_line)
    merged.metadata["config"] = portable_path(config.path)  # named as here, not as a worker read it
    merged.metadata["policy"] = str(policy or config.models.policy)
    return merged


def _episode_commands(rng: np.random.Generator, seconds: float, warmup_s: float, settings: CollectSettings
                      ) -> tuple[CommandSchedule, list[tuple[float, list[float], list[float]]]]:
    """A standstill for the warm-up, then sampled segments to cover `seconds`; and (start s, sampled, clipped)
    of each sampled segment."""
    timed: list[tuple[float, tuple[float, ...]]] = [(warmup_s, (0.0, 0.0, 0.0))]
    drawn = []
    start = warmup_s
    while start < seconds:
        sampled, clipped = sample_command(rng)
        drawn.append((start, sampled, clipped))
        timed.append((settings.segment_s, tuple(clipped)))
        start += settings.segment_s
    return CommandSchedule(timed, settings.ramp_s, name="sampled commands"), drawn


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bruce-collect", description=__doc__.split("\n\n")[0],
                                epilog="Commands, episodes and the file's format: docs/dynamics.md")
    defaults = CollectSettings()
    p.add_argument("--seconds", type=positive_seconds, default=defaults.seconds, metavar="S",
                   help="simulated seconds of samples to keep (default: %(default)g, as the paper)")
    p.add_argument("--seed", type=int, default=defaults.seed, help="command sampling seed (default: %(default)s)")
    p.add_argument("--seeds", default=None, metavar="S,S,...",
                   help="several seeds, --seconds each, collected in parallel (--executor) into one dataset; "
                        "instead of --seed")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="with --seeds and --executor local: parallel seeds (default: CPU count)")
    add_executor_arguments(p)
    p.add_argument("--out", type=Path, required=True, metavar="PATH", help="the .npz file to write")
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--segment-s", type=positive_seconds, default=defaults.segment_s, metavar="S",
                   help="how long each sampled velocity command is held (default: %(default)g s)")
    p.add_argument("--policy", type=Path, default=None, metavar="PATH",
                   help="ONNX walking policy (default: policy.model in the config)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _seeds(text: str) -> list[int]:
    try:
        seeds = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--seeds: expected comma-separated integers, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds: expected distinct integers, got {text!r}")
    return seeds


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command_line = "bruce-collect " + " ".join(sys.argv[1:] if argv is None else argv)
    try:
        config = load_config(args.config)
        settings = CollectSettings(seconds=args.seconds, seed=args.seed, segment_s=args.segment_s)
        if args.policy is not None and not args.policy.is_file():
            raise ConfigError(f"{args.policy}: --policy file not found")
        if args.seeds is None:
            dataset = collect(config, settings, policy=args.policy, progress=not args.no_progress,
                              command_line=command_line)
        else:
            seeds = _seeds(args.seeds)
            ship = job_files(config.path, files=[args.policy] if args.policy else [])
            with make_executor(args, args.jobs, ship=ship) as executor:
                dataset = collect_seeds(config, settings, seeds, executor, policy=args.policy,
                                        command_line=command_line, progress=not args.no_progress)
        path = save_dataset(args.out, dataset)
    except (ConfigError, BackendError, ModelError, DatasetError, CollectError, ExecutorError) as exc:
        print(f"bruce-collect: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("bruce-collect: interrupted, nothing written", file=sys.stderr)
        return 130
    meta = dataset.metadata
    falls = sum(e["end"] != "duration" for e in meta["episodes"])
    print(f"bruce-collect: wrote {path}: {len(dataset)} samples ({len(dataset) * dataset.dt:g} s at "
          f"{1 / dataset.dt:g} Hz), {len(meta['episodes'])} episode(s), {falls} ended by a fall, "
          f"{'seed ' + str(args.seed) if args.seeds is None else 'seeds ' + args.seeds}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
