"""Distil the walking teacher into a small MLP policy by DAgger, and export it to ONNX for the runtime.

    python -m training.distill --out configs/robots/policies/bruce_walk.onnx [--seed 0] [--rounds N] ...

The student sees the runtime policy's observation (Table I, `runtime.observation.builder.ObservationBuilder`), and
its action goes through the runtime's own loop (`runtime.loop.run.run_session`: Eq. 8, safety) at 1 kHz in the mock.
DAgger (Ross et al. 2011): round 0 rolls out the teacher; in round k the executed action is the teacher's with
probability beta_decay^k, else the student's; the teacher labels every visited state and the student is trained on
all rounds' data after each round. Sampled, ramped velocity commands, random pushes and action noise widen the states
visited. The exported graph maps obs to action in SI units (normalisation folded in). The observation and the
committed policy: docs/walking.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import logging
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from bruce_hw.backend import LifecycleState
from bruce_hw.config import RobotConfig, load_config
from bruce_hw.mock import MujocoBackend
from runtime.control.commands import COMMAND_LIMITS, CommandSchedule
from runtime.estimation import GroundTruthEstimator
from runtime.loop.exit import INTERRUPTS
from runtime.loop.observers import FallStop, TickObserver, TickView
from runtime.loop.recorder import portable_path
from runtime.loop.run import run_session
from runtime.observation.builder import ObservationBuilder
from runtime.walking.teacher import WalkingTeacher


@dataclass(frozen=True)
class DistillSettings:
    seed: int = 0
    rounds: int = 8                       # DAgger rounds after the teacher-only round 0
    episodes_per_round: int = 24
    episode_s: float = 10.0
    segment_s: tuple[float, float] = (2.0, 5.0)        # command segment length, uniform
    vx: tuple[float, float] = (-0.5, 0.8)               # m/s
    vy: tuple[float, float] = (-0.2, 0.2)               # m/s
    wz: tuple[float, float] = (-0.5, 0.5)               # rad/s
    single_axis_share: float = 0.5         # share of segments that command one axis only (as the test grid does)
    zero_share: float = 0.1                # share of segments that command standing still
    push_interval_s: tuple[float, float] = (2.0, 4.0)
    push_impulse_ns: tuple[float, float] = (0.2, 1.2)  # horizontal impulse on the base, random direction
    push_duration_s: float = 0.1
    action_noise_rad: float = 0.02         # Gaussian noise on the executed action
    beta_decay: float = 0.5
    hidden: tuple[int, ...] = (256, 256)
    epochs: int = 20                       # per round, over the aggregated dataset
    batch_size: int = 1024
    learning_rate: float = 1e-3
    fall_trim_s: float = 0.5               # s of samples dropped before a fall (runtime.loop.falls) or a safety trip
    # Where the student's base state comes from: "truth" (the simulator's) or "kinematic" (the robot-side
    # estimator on the same sensors, runtime.estimation.kinematic). The teacher always labels from the truth.
    observe: str = "truth"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


class StudentPolicy(nn.Module):
    """obs (SI) -> a_t (rad): an ELU MLP between a fixed input normalisation and output scaling."""

    def __init__(self, obs_mean: np.ndarray, obs_scale: np.ndarray, act_mean: np.ndarray, act_scale: np.ndarray,
                 hidden: tuple[int, ...]):
        super().__init__()
        self.register_buffer("obs_mean", torch.as_tensor(obs_mean, dtype=torch.float32))
        self.register_buffer("obs_scale", torch.as_tensor(obs_scale, dtype=torch.float32))
        self.register_buffer("act_mean", torch.as_tensor(act_mean, dtype=torch.float32))
        self.register_buffer("act_scale", torch.as_tensor(act_scale, dtype=torch.float32))
        layers: list[nn.Module] = []
        width = len(obs_mean)
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ELU()]
            width = h
        layers.append(nn.Linear(width, len(act_mean)))
        self.net = nn.Sequential(*layers)

    def normalised(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net((obs - self.obs_mean) * self.obs_scale)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.act_mean + self.act_scale * self.normalised(obs)


@dataclass
class Dataset:
    obs: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)

    def add(self, obs: np.ndarray, actions: np.ndarray) -> None:
        self.obs.append(obs)
        self.actions.append(actions)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.obs), np.concatenate(self.actions)


@dataclass
class EpisodeResult:
    obs: np.ndarray
    teacher_actions: np.ndarray
    seconds: float
    fell: bool
    stop_cause: str = ""


def sample_commands(settings: DistillSettings, rng: np.random.Generator) -> CommandSchedule:
    """Piecewise-constant commands for one episode, inside the runtime's command limits."""
    segments = []
    total = 0.0
    while total < settings.episode_s:
        duration = float(rng.uniform(*settings.segment_s))
        roll = rng.random()
        cmd = np.zeros(3)
        ranges = (settings.vx, settings.vy, settings.wz)
        if roll < settings.zero_share:
            pass
        elif roll < settings.zero_share + settings.single_axis_share:
            axis = int(rng.integers(3))
            cmd[axis] = rng.uniform(*ranges[axis])
        else:
            cmd = np.array([rng.uniform(*r) for r in ranges])
        for i, (low, high) in enumerate(COMMAND_LIMITS.values()):
            cmd[i] = min(high, max(low, cmd[i]))
        segments.append((duration, tuple(float(c) for c in cmd)))
        total += duration
    return CommandSchedule(segments, name="sampled commands")


class DaggerController:
    """The controller of a DAgger episode (anything `run_session` runs: reset(q), __call__(state, base, command)).

    On each policy tick it labels the state with the teacher's a_t (the teacher plans on the simulator's truth),
    then executes the teacher's a_t with probability beta, else the student's (which sees the loop's base estimate:
    the truth, or the kinematic estimator with `--observe kinematic`), plus Gaussian noise. `obs` and `labels`
    hold what the episode taught, from the last reset on."""

    def __init__(self, config: RobotConfig, settings: DistillSettings, rng: np.random.Generator, beta: float,
                 student: StudentPolicy | None, truth_of: MujocoBackend | None = None):
        self.teacher = WalkingTeacher(config)
        self.builder = ObservationBuilder(config)
        self.student, self.beta, self.rng = student, beta, rng
        self.noise_rad = settings.action_noise_rad
        self.truth_of = truth_of  # the mock whose truth the teacher plans on; None: the loop's estimate is the truth
        self.truth: GroundTruthEstimator | None = None
        self.reset(config.standing_pose)

    def reset(self, q: np.ndarray) -> None:
        """Before the episode (the mock is configured by then)."""
        if self.truth_of is not None and self.truth_of.state is not LifecycleState.UNCONFIGURED:
            self.truth = GroundTruthEstimator(self.truth_of)
        self.teacher.reset(q)
        self.builder.reset()
        self.last_action = np.array(q, dtype=float)  # as runtime.control.policy.PolicyController starts
        self.obs: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []

    def __call__(self, state, base, command: np.ndarray) -> np.ndarray:
        obs = self.builder.build(command, state, base, self.last_action)
        label = self.teacher(state, base if self.truth is None else self.truth.estimate(), command)
        self.obs.append(obs)
        self.labels.append(label)
        if self.student is not None and self.rng.random() >= self.beta:
            with torch.no_grad():
                a = self.student(torch.as_tensor(obs, dtype=torch.float32)[None])[0].double().numpy()
        else:
            a = label
        a = a + self.rng.normal(0.0, self.noise_rad, size=a.shape)
        self.last_action = a
        return a


class RandomPushes(TickObserver):
    """A disturbance riding on the loop's observer hook: pushes the mock's base (`MujocoBackend.push`) in a random
    horizontal direction every `push_interval_s` (uniform), with an impulse drawn from `push_impulse_ns`."""

    def __init__(self, settings: DistillSettings, rng: np.random.Generator):
        self.settings, self.rng = settings, rng
        self.next_push = float(rng.uniform(*settings.push_interval_s))
        self.backend: MujocoBackend | None = None

    def on_start(self, backend: MujocoBackend, config: RobotConfig) -> None:
        self.backend = backend

    def on_tick(self, view: TickView) -> None:
        t = view.elapsed
        if t >= self.next_push:
            settings, rng = self.settings, self.rng
            angle = rng.uniform(0.0, 2.0 * math.pi)
            impulse = rng.uniform(*settings.push_impulse_ns)
            self.backend.push(np.array([impulse * math.cos(angle), impulse * math.sin(angle), 0.0]),
                              settings.push_duration_s)
            self.next_push = t + float(rng.uniform(*settings.push_interval_s))


def rollout(config: RobotConfig, settings: DistillSettings, rng: np.random.Generator, beta: float,
            student: StudentPolicy | None) -> EpisodeResult:
    """One episode in the mock through the runtime's loop (`runtime.loop.run.run_session`: Eq. 8 and the safety stage
    at 1 kHz, as every run): the DAgger controller executes teacher or student per policy tick and labels every
    one with the teacher's a_t; random pushes; the episode ends at a fall (`runtime.loop.falls`), a safety trip or its
    duration. The labels of its last `fall_trim_s` are dropped when it ends early."""
    backend = MujocoBackend(config)
    commands = sample_commands(settings, rng)
    pushes = RandomPushes(settings, rng)
    kinematic = settings.observe == "kinematic"
    controller = DaggerController(config, settings, rng, beta, student, truth_of=backend if kinematic else None)
    runtime_log = logging.getLogger("runtime")
    saved_level = runtime_log.level
    runtime_log.setLevel(logging.WARNING)  # a "torque ramp done" line per episode says nothing here
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # run_session's per-run banner and summary
            summary = run_session(backend, config, duration=settings.episode_s, realtime=False,
                                  controller=controller, estimator="kinematic" if kinematic else "truth",
                                  commands=commands, observers=[pushes, FallStop()],
                                  privileged=True)  # the teacher labels from the simulator's truth
    finally:
        runtime_log.setLevel(saved_level)
    if summary.stop_cause in INTERRUPTS:
        raise KeyboardInterrupt(summary.stop_cause)
    obs_log, label_log = controller.obs, controller.labels
    if summary.stop_cause != "duration reached":  # the teacher's labels while falling teach nothing worth copying
        keep = max(0, len(obs_log) - round(settings.fall_trim_s * config.policy_hz))
        obs_log, label_log = obs_log[:keep], label_log[:keep]
    return EpisodeResult(np.array(obs_log).reshape(-1, controller.builder.size),
                         np.array(label_log).reshape(-1, config.n_joints), summary.ticks * config.dt,
                         bool(summary.truth.fell), summary.stop_cause or "")


def make_student(config: RobotConfig, settings: DistillSettings, obs: np.ndarray,
                 actions: np.ndarray) -> StudentPolicy:
    obs_mean = obs.mean(axis=0)
    obs_scale = 1.0 / np.maximum(obs.std(axis=0), 1e-2)
    return StudentPolicy(obs_mean, obs_scale, actions.mean(axis=0), np.maximum(actions.std(axis=0), 1e-3),
                         settings.hidden)


def train(student: StudentPolicy, obs: np.ndarray, actions: np.ndarray, settings: DistillSettings,
          generator: torch.Generator) -> float:
    """Fit the student to the teacher's actions (MSE in the normalised action space); returns the last epoch's loss."""
    x = torch.as_tensor(obs, dtype=torch.float32)
    y = (torch.as_tensor(actions, dtype=torch.float32) - student.act_mean) / student.act_scale
    optimiser = torch.optim.Adam(student.net.parameters(), lr=settings.learning_rate)
    n = len(x)
    loss_value = math.nan
    for epoch in range(settings.epochs):
        for group in optimiser.param_groups:  # cosine decay within a round
            group["lr"] = settings.learning_rate * 0.5 * (1.0 + math.cos(math.pi * epoch / settings.epochs))
        order = torch.randperm(n, generator=generator)
        total = 0.0
        for start in range(0, n, settings.batch_size):
            batch = order[start:start + settings.batch_size]
            loss = torch.mean((student.normalised(x[batch]) - y[batch]) ** 2)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * len(batch)
        loss_value = total / n
    return loss_value


def distill(config: RobotConfig, settings: DistillSettings, log=print) -> tuple[StudentPolicy, list[dict]]:
    rng = np.random.default_rng(settings.seed)
    torch.manual_seed(settings.seed)
    generator = torch.Generator().manual_seed(settings.seed)
    data = Dataset()
    student: StudentPolicy | None = None
    history = []
    for round_index in range(settings.rounds + 1):
        beta = settings.beta_decay ** round_index
        started = time.perf_counter()
        falls, seconds = 0, 0.0
        for _ in range(settings.episodes_per_round):
            episode = rollout(config, settings, rng, beta, student)
            data.add(episode.obs, episode.teacher_actions)
            falls += episode.fell
            seconds += episode.seconds
        obs, actions = data.arrays()
        if student is None:
            student = make_student(config, settings, obs, actions)
        loss = train(student, obs, actions, settings, generator)
        record = {"round": round_index, "beta": beta, "episodes": settings.episodes_per_round, "falls": falls,
                  "sim_s": round(seconds, 1), "samples": len(obs), "loss": round(loss, 5),
                  "wall_s": round(time.perf_counter() - started, 1)}
        history.append(record)
        log(f"distill: round {round_index}: beta {beta:.3f}, {falls}/{settings.episodes_per_round} episodes fell, "
            f"{len(obs)} samples, loss {loss:.5f}, {record['wall_s']} s")
    assert student is not None
    return student, history


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.distill", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="ONNX file to write (a .json sidecar goes beside)")
    parser.add_argument("--config", type=Path, default=None, help="robot config (default: BRUCE's)")
    defaults = DistillSettings()
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--rounds", type=int, default=defaults.rounds)
    parser.add_argument("--episodes", type=int, default=defaults.episodes_per_round, help="episodes per round")
    parser.add_argument("--episode-s", type=float, default=defaults.episode_s)
    parser.add_argument("--epochs", type=int, default=defaults.epochs)
    parser.add_argument("--hidden", type=int, nargs="+", default=list(defaults.hidden), help="MLP layer widths")
    parser.add_argument("--vx", type=float, nargs=2, default=list(defaults.vx), help="vx command range, m/s")
    parser.add_argument("--observe", choices=("truth", "kinematic"), default=defaults.observe,
                        help="the student's base state: simulator truth or the robot-side kinematic estimator")
    parser.add_argument("--push", type=float, nargs=2, default=list(defaults.push_impulse_ns),
                        help="push impulse range, N s")
    args = parser.parse_args(argv)
    config = load_config(args.config) if args.config else load_config()
    settings = dataclasses.replace(defaults, seed=args.seed, rounds=args.rounds, episodes_per_round=args.episodes,
                                   episode_s=args.episode_s, epochs=args.epochs, hidden=tuple(args.hidden),
                                   vx=tuple(args.vx), push_impulse_ns=tuple(args.push),
                                   observe=args.observe)
    torch.set_num_threads(1)
    student, history = distill(config, settings)
    from training.onnx_export import export_mlp_policy_onnx, sidecar_path

    student.eval()
    path = export_mlp_policy_onnx(student, args.out, ObservationBuilder(config).size, config.n_joints)
    sidecar = sidecar_path(path)
    record = json.loads(sidecar.read_text())
    record["commands"] = {"vx": list(settings.vx), "vy": list(settings.vy), "wz": list(settings.wz)}  # trained on
    record["distill"] = {"command": "python -m training.distill " + " ".join(sys.argv[1:] if argv is None else argv),
                         "config": portable_path(config.path), "settings": settings.to_json(), "history": history}
    sidecar.write_text(json.dumps(record, indent=2) + "\n")
    print(f"distill: wrote {path} ({path.stat().st_size / 1024:.0f} kB) and {sidecar}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
