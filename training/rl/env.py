"""The walking environment for PPO (`BruceWalkEnv`, its settings `WalkEnvConfig`): N simulated BRUCEs stepped together.

A policy step is 10 physics steps of 1 ms (`mujoco.rollout` over every env's own MjModel, on `nthread` threads; no
Python per physics step) with the policy's a_t as the target of the Eq. 8 PD actuators (`sim_model`). Each episode
draws a randomisation (`randomisation`), a command (resampled now and then) and pushes. The actor observation is the
one the policy spec `env.policy_spec` asks for (default Table I, configs/robots/policy_specs/table1.yaml), built by
the runtime's `ObservationBuilder` (batched) of the simulator's truth as `GroundTruthEstimator` reports it, plus the
episode's observation noise; the critic's adds Table I's privileged state. An env ends on the runtime's fall rule
(`runtime.loop.falls`) or at the time-out and restarts inside `step`.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout

from bruce_hw.config import ConfigError, RobotConfig
from bruce_hw.quaternion import euler_rows, quaternion_rows, rotation_entries
from bruce_hw.robot_model import CONTACT_THRESHOLD_N, standing_height
from bruce_hw.yaml_reader import Bound, YamlReader
from runtime.control.commands import COMMAND_LIMITS
from runtime.control.policy_spec import TABLE_ONE, PolicySpec, load_policy_spec
from runtime.loop.falls import fallen
from runtime.loop.run import target_bounds
from runtime.observation.builder import ObservationBuilder
from runtime.walking.gait import gait_phase, swing_height
from runtime.walking.teacher import TeacherParams
from training.rl import rewards
from training.rl.randomisation import Draws, RandomisationRanges, apply_draw, draw
from training.rl.rewards import DOUBLE_SUPPORT, RewardParams, WalkStep
from training.rl.sim_model import FOOT_SITES, build_sim_model

CONTROL_SPEC = mujoco.mjtState.mjSTATE_CTRL.value | mujoco.mjtState.mjSTATE_XFRC_APPLIED.value
# Table I's state beyond the observation, in the critic's order after the actor's observation: joint torques (N·m),
# base height (m), ground friction, mass scale, the push's horizontal force (N) and its torque (N·m), both in the
# heading (yaw-only) frame.
PRIVILEGED = ("tau", "base_height", "ground_friction", "mass_scale", "push_force", "push_torque")


def _setting(key: str, default: Any, bound: Bound, kind: str = "number") -> Any:
    """A setting: its key under the env's section, its default, its bound (of each end, for kind "range")."""
    return field(default=default, metadata={"key": key, "bound": bound, "kind": kind})


def _command_bound(axis: str, unit: str) -> Bound:
    low, high = COMMAND_LIMITS[axis]
    return Bound(low, high, unit, "the walking controllers' range (runtime.control.commands.COMMAND_LIMITS)")


@dataclass(frozen=True)
class WalkEnvConfig:
    """The environment's settings, checked on construction (errors name `source` and the key under `key`)."""

    source: str = field(default="WalkEnvConfig", compare=False)
    key: str = field(default="env", compare=False)
    num_envs: int = _setting("num_envs", 64, Bound(1, 65536, "", "simulations stepped together", integer=True))
    nthread: int = _setting("nthread", 2, Bound(0, 256, "", "rollout threads; 0: the calling thread",
                                                integer=True))
    # num_envs / shards simulations per shard, shard i seeded train.seed + i; with --executor ray one Ray actor each
    # (training/rl/env_shards.py). 1: the plain environment.
    shards: int = _setting("shards", 1, Bound(1, 4096, "", "batches of simulations stepped apart", integer=True))
    episode_s: float = _setting("episode_s", 20.0, Bound(0.01, 3600.0, "s", "time-out"))
    reset_joint_noise_rad: float = _setting("reset_joint_noise_rad", 0.05,
                                            Bound(0.0, 0.3, "rad", "uniform, around the standing pose"))
    # The paper's (-0.3, 0.8) x (-0.5, 0.5) x (-0.5, 0.5), with vx and vy set to the acceptance grid's.
    command_vx: tuple[float, float] = _setting("commands.vx", (-0.5, 0.8), _command_bound("vx", "m/s"), "range")
    command_vy: tuple[float, float] = _setting("commands.vy", (-0.3, 0.3), _command_bound("vy", "m/s"), "range")
    command_wz: tuple[float, float] = _setting("commands.wz", (-0.5, 0.5), _command_bound("wz", "rad/s"), "range")
    command_zero_share: float = _setting("commands.zero_share", 0.1, Bound(0.0, 1.0, "", "commands to stand still"))
    command_resample_s: tuple[float, float] = _setting("commands.resample_s", (4.0, 8.0),
                                                       Bound(0.01, 3600.0, "s", "a new command after"), "range")
    push_interval_s: tuple[float, float] = _setting("pushes.interval_s", (2.0, 4.0),
                                                    Bound(0.01, 3600.0, "s", "between pushes"), "range")
    push_impulse_ns: tuple[float, float] = _setting("pushes.impulse_ns", (0.2, 1.2),
                                                    Bound(0.0, 20.0, "N·s", "horizontal, random direction"), "range")
    push_angular_impulse_nms: tuple[float, float] = _setting(
        "pushes.angular_impulse_nms", (0.0, 0.05), Bound(0.0, 2.0, "N·m·s", "random axis"), "range")
    push_duration_s: float = _setting("pushes.duration_s", 0.1, Bound(0.01, 1.0, "s", "whole policy periods"))
    randomisation: RandomisationRanges = field(default_factory=RandomisationRanges)
    # The actor's observation (and how the exported policy's output becomes targets): a spec file, or the name of
    # a shipped one (configs/robots/policy_specs/); runtime/control/policy_spec.py, docs/byo_policy.md.
    policy_spec: str = TABLE_ONE

    def __post_init__(self) -> None:
        r = YamlReader(self.source, None, ValueError)
        if not isinstance(self.policy_spec, str) or not self.policy_spec:
            raise r.fail(_join(self.key, "policy_spec"), "a policy spec file or the name of a shipped one",
                         self.policy_spec)
        for f in _SETTINGS:
            key = f"{self.key}.{f.metadata['key']}" if self.key else f.metadata["key"]
            value, bound = getattr(self, f.name), f.metadata["bound"]
            if f.metadata["kind"] == "range":
                if not isinstance(value, list | tuple) or len(value) != 2:
                    raise r.fail(key, "[low, high] (a list of 2 numbers)", value)
                value = tuple(r.number(f"{key}[{i}]", v, bound) for i, v in enumerate(value))
                if value[0] > value[1]:
                    raise r.fail(key, "[low, high] with low <= high", list(value))
            else:
                value = r.number(key, value, bound)
            object.__setattr__(self, f.name, value)

    @classmethod
    def from_dict(cls, d: Any, source: str, key: str = "env") -> WalkEnvConfig:
        """The settings in `d`, the parsed YAML mapping found under the top-level `key` of the file `source` ("": the
        whole file); every setting is optional (the defaults fill in), an unknown one is an error naming the file
        and the dotted key."""
        r = YamlReader(source, {key: d} if key else d, ValueError)
        keys = [f.metadata["key"] for f in _SETTINGS]
        sections = {k.split(".")[0] for k in keys}
        node = r.mapping(key, sections | {"randomisation", "policy_spec"})
        values: dict[str, Any] = {}
        for section in sections & set(node):
            names = {k.partition(".")[2] for k in keys if k.startswith(f"{section}.")}
            if names:
                r.mapping(_join(key, section), names)
        for f, k in zip(_SETTINGS, keys, strict=True):
            section, _, name = k.partition(".")
            if section in node and (not name or name in node[section]):
                values[f.name] = node[section][name] if name else node[section]
        ranges_key = _join(key, "randomisation")
        values["randomisation"] = (RandomisationRanges.read(r, ranges_key) if "randomisation" in node
                                   else RandomisationRanges(source=str(source), key=ranges_key))
        if "policy_spec" in node:
            values["policy_spec"] = _spec_beside(source, r.string(_join(key, "policy_spec")))
        return cls(source=str(source), key=key, **values)


_SETTINGS = tuple(f for f in fields(WalkEnvConfig) if "key" in f.metadata)


def _join(key: str, name: str) -> str:
    return f"{key}.{name}" if key else name


def _spec_beside(source: str, name: str) -> str:
    """A spec named in the settings file `source`: a shipped spec's bare name as it is; a path absolute, else
    relative to the working directory if it exists there, else to the settings file's folder."""
    path = Path(name)
    if not path.suffix and len(path.parts) == 1 or path.is_absolute() or path.exists():
        return name
    return str(Path(source).parent / path)


def training_spec(robot: RobotConfig, config: WalkEnvConfig) -> PolicySpec:
    """The spec the environment observes with; a ConfigError naming the file and key if it cannot be trained on."""
    spec = load_policy_spec(config.policy_spec, robot)
    if spec.rate_hz != robot.policy_hz:
        raise ConfigError(f"{config.source}: {_join(config.key, 'policy_spec')}: {spec.name} runs at {spec.rate_hz} "
                          f"Hz; training steps the policy at rates.policy_hz ({robot.policy_hz} Hz in {robot.path})")
    return spec


# The env's arrays that carry over from one policy step to the next (with the draws, the observation builder's clock,
# heading reference and history, and the random generator): what a checkpoint must hold.
_CONTINUED = ("state", "_late", "_noise_std", "_sensor_bias", "command", "_command_left", "_push_countdown",
              "_push_left", "push_wrench", "last_action", "last_action2", "last_raw_action", "_qd_prev", "_linvel_prev",
              "_angvel_prev", "tau", "episode_length", "mean_velocity")
MEAN_VELOCITY_S = 0.5  # s, time constant of the averaged velocity the added tracking term scores: about a step cycle


@dataclass
class BaseTruth:
    """The simulator's truth of every env's base and joints (arrays over the envs)."""

    pos: np.ndarray          # (N, 3) world
    linvel: np.ndarray       # (N, 3) base frame
    angvel: np.ndarray       # (N, 3) base frame
    euler: np.ndarray        # (N, 3) roll, pitch, yaw (ZYX)
    heading_linvel: np.ndarray  # (N, 3) linear velocity in the heading (yaw-only) frame
    fallen: np.ndarray       # (N,) runtime.loop.falls' rule
    q: np.ndarray            # (N, n_joints)
    qd: np.ndarray


class BruceWalkEnv:
    """N BRUCE simulations: `reset()` -> obs, `step(actions)` -> obs, reward, terminated, time_out, info.

    obs is {"policy": (N, spec.obs_size) the runtime's observation of `config.policy_spec` (Table I: 44), "critic":
    (N, obs_size + 18) with Table I's privileged state}; actions are (N, 10) PD targets a_t (rad, config joint
    order), clipped to the runtime's `target_bounds`.
    `episode_length` (N,) policy steps, may be written (rsl-rl starts at random lengths).
    """

    def __init__(self, robot: RobotConfig, config: WalkEnvConfig | None = None, seed: int = 0,
                 reward_weights: Mapping[str, float] | None = None, reward_params: RewardParams | None = None):
        self.robot = robot
        self.config = config = config or WalkEnvConfig()
        self.sim = sim = build_sim_model(robot)
        self.num_envs = n = config.num_envs
        self.num_actions = robot.n_joints
        self.decimation = robot.policy_decimation
        self.dt = 1.0 / robot.policy_hz
        if config.randomisation.latency_ticks[1] >= self.decimation:
            raise ValueError(f"{config.source}: {config.randomisation.key}.latency_ticks: expected at most "
                             f"{self.decimation - 1} ticks (inside one policy period), got "
                             f"{config.randomisation.latency_ticks[1]}")
        self.max_episode_length = round(config.episode_s * robot.policy_hz)
        self.push_steps = max(1, round(config.push_duration_s * robot.policy_hz))
        self.reward_weights = reward_weights
        self.reward_params = reward_params
        self.rng = np.random.default_rng(seed)
        m = sim.model
        if sim.nstate != 1 + m.nq + m.nv + m.na:
            raise ValueError("training model: the state holds more than time, qpos, qvel and act")
        self._qpos = slice(1, 1 + m.nq)
        self._qvel = slice(1 + m.nq, 1 + m.nq + m.nv)
        self._act = slice(1 + m.nq + m.nv, sim.nstate)
        self._wrench = slice(m.nu + 6 * sim.base_body, m.nu + 6 * sim.base_body + 6)  # base's xfrc_applied
        self._soles = [m.site(s).id for s in FOOT_SITES]
        self.models = [copy.deepcopy(m) for _ in range(n)]
        self._rollout = rollout.Rollout(nthread=config.nthread)
        self._scratch = [mujoco.MjData(m) for _ in range(max(1, config.nthread))]
        self._kin = mujoco.MjData(m)
        self.state = np.zeros((n, sim.nstate))
        self._control = np.zeros((n, self.decimation, mujoco.mj_stateSize(m, CONTROL_SPEC)))
        # The last policy step's physics steps: the state after each, and the sensors MuJoCo evaluated in each (before
        # it integrated: sensordata[:, k] belongs to physics_states[:, k - 1]).
        self.physics_states = np.zeros((n, self.decimation, sim.nstate))
        self.sensordata = np.zeros((n, self.decimation, m.nsensordata))
        self.spec = training_spec(robot, config)
        self.builder = ObservationBuilder(robot, self.spec, n)
        self.a_low, self.a_high = target_bounds(robot)
        teacher = TeacherParams()
        self._swing_apex, self._swing_landing = teacher.swing_apex, teacher.swing_landing
        j = robot.n_joints
        self.draws: Draws = draw(config.randomisation, self.rng, n, j)
        self._late = np.zeros((n, self.decimation), dtype=bool)  # physics steps still on the previous target
        self._noise_std = np.zeros((n, 2 * j + 9))                # q, qd, linvel, angvel, euler
        self._sensor_bias = np.zeros((n, 2 * j + 9))              # ... their constant offsets this episode
        self.command = np.zeros((n, 3))
        self._command_left = np.zeros(n, dtype=int)
        self._push_countdown = np.zeros(n, dtype=int)
        self._push_left = np.zeros(n, dtype=int)
        self.push_wrench = np.zeros((n, 6))                       # world force, torque on the base's centre of mass
        self.last_action = np.zeros((n, j))
        self.last_action2 = np.zeros((n, j))
        self.last_raw_action = np.zeros((n, j))  # the network output the spec's action map makes a_{t-1} of
        self._qd_prev = np.zeros((n, j))
        self._linvel_prev = np.zeros((n, 3))
        self._angvel_prev = np.zeros((n, 3))
        self.tau = np.zeros((n, j))
        self.mean_velocity = np.zeros((n, 3))  # vx, vy (heading frame), yaw rate, low-passed over MEAN_VELOCITY_S
        self.episode_length = np.zeros(n, dtype=int)
        self.obs: dict[str, np.ndarray] = {}
        self.reset()

    # -- the interface ------------------------------------------------------------------------------------------
    def reset(self) -> dict[str, np.ndarray]:
        """Every env starts a new episode; the observations."""
        self._reset(np.arange(self.num_envs))
        self.obs = self._observe(self.truth())
        return self.obs

    def get_observations(self) -> dict[str, np.ndarray]:
        return self.obs

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict]:
        """One policy step of every env. Returns the observations (of the new episode where one ended), the reward
        (N,), terminated (N,: fell), time_out (N,: the episode's time is up and it did not fall) and info:
        "reward_terms" (name -> (N,), weighted, summing to the reward), "episode_length" (N,: at this step's end,
        before the restarts) and "walk_step" (the rewards' input)."""
        a = np.asarray(actions, dtype=float)
        if a.shape != (self.num_envs, self.num_actions) or not np.all(np.isfinite(a)):
            raise ValueError(f"actions: expected finite values of shape {(self.num_envs, self.num_actions)}, "
                             f"got shape {a.shape}")
        a = np.clip(a, self.a_low, self.a_high)
        self._start_pushes()
        self._physics(a)
        truth = self.truth()
        self.episode_length += 1
        time_out = (self.episode_length >= self.max_episode_length) & ~truth.fallen
        velocity = np.concatenate([truth.heading_linvel[:, :2],
                                   rewards.world_yaw_rate(truth.euler, truth.angvel)[:, None]], axis=1)
        self.mean_velocity += min(1.0, self.dt / MEAN_VELOCITY_S) * (velocity - self.mean_velocity)
        walk_step = self._walk_step(a, truth)
        reward, terms = rewards.compute(walk_step, self.reward_weights, self.reward_params)
        self.last_action2, self.last_action = self.last_action, a
        self.last_raw_action = self._output_of(a)
        self._qd_prev, self._linvel_prev, self._angvel_prev = truth.qd.copy(), truth.linvel.copy(), truth.angvel.copy()
        self._advance_schedules()
        info = {"reward_terms": terms, "episode_length": self.episode_length.copy(), "walk_step": walk_step}
        fell = truth.fallen
        done = np.flatnonzero(fell | time_out)
        if len(done):
            self._reset(done)
            truth = self.truth()
        self.obs = self._observe(truth)
        return self.obs, reward, fell, time_out, info

    def close(self) -> None:
        self._rollout.close()

    def get_state(self) -> dict[str, Any]:
        """Everything that decides how the envs go on (arrays, and the random generator's state), for a checkpoint:
        `set_state` on an env of the same robot and settings continues exactly as this one would."""
        clock, heading = self.builder.clock, self.builder.heading_reference
        return {**{name: np.array(getattr(self, name)) for name in _CONTINUED},
                "draws": {f.name: getattr(self.draws, f.name).copy() for f in fields(self.draws)},
                "obs": {k: v.copy() for k, v in self.obs.items()},
                "clock": {"cycles": np.array(clock.cycles), "command": clock.command.copy(),
                          "period": np.array(clock.period)},
                "heading": {"heading": heading.heading.copy(), "started": heading.started.copy()},
                "observation_history": self.builder.terms.get_state(), "rng": self.rng.bit_generator.state}

    def set_state(self, saved: Mapping[str, Any]) -> None:
        if np.shape(saved["state"]) != self.state.shape:
            raise ValueError(f"saved environment state: {np.shape(saved['state'])[0]} envs of state size "
                             f"{np.shape(saved['state'])[1]}, this environment has {self.state.shape}")
        for name in _CONTINUED:
            setattr(self, name, np.array(saved[name], dtype=getattr(self, name).dtype))
        self.draws = Draws(**{k: np.array(v) for k, v in saved["draws"].items()})
        for i, model in enumerate(self.models):
            apply_draw(self.sim, model, self.robot.joints, self.draws.row(i), self._kin)
        self.obs = {k: np.array(v) for k, v in saved["obs"].items()}
        clock, heading = self.builder.clock, self.builder.heading_reference
        clock.cycles, clock.command, clock.period = (np.array(saved["clock"][k]) for k in ("cycles", "command",
                                                                                           "period"))
        heading.heading, heading.started = np.array(saved["heading"]["heading"]), np.array(saved["heading"]["started"])
        self.builder.terms.set_state(saved["observation_history"])
        self.rng.bit_generator.state = saved["rng"]

    # -- one policy step ----------------------------------------------------------------------------------------
    def _physics(self, a: np.ndarray) -> None:
        """`decimation` physics steps: the PD target switches from a_{t-1} to a_t after each env's latency."""
        ctrl = self._control[:, :, self.sim.acts]
        np.copyto(ctrl, np.where(self._late[:, :, None], self.last_action[:, None, :], a[:, None, :]))
        self._control[:, :, self._wrench] = self.push_wrench[:, None, :]
        self._rollout.rollout(self.models, self._scratch, self.state, self._control, control_spec=CONTROL_SPEC,
                              skip_checks=True, nstep=self.decimation, state=self.physics_states,
                              sensordata=self.sensordata)
        self.state[:] = self.physics_states[:, -1]
        self.tau = self.sensordata[:, -1, self.sim.tau].copy()

    def truth(self) -> BaseTruth:
        """The simulator's truth of every env now (copies)."""
        qpos, qvel = self.state[:, self._qpos], self.state[:, self._qvel]
        pos, (w, x, y, z) = qpos[:, :3], qpos[:, 3:7].T
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation_entries((w, x, y, z))
        vx, vy, vz = qvel[:, 0], qvel[:, 1], qvel[:, 2]
        linvel = np.stack([r00 * vx + r10 * vy + r20 * vz, r01 * vx + r11 * vy + r21 * vz,
                           r02 * vx + r12 * vy + r22 * vz], axis=1)
        euler = euler_rows(qpos[:, 3:7])
        yaw = euler[:, 2]
        c, s = np.cos(yaw), np.sin(yaw)
        heading_linvel = np.stack([c * vx + s * vy, -s * vx + c * vy, vz], axis=1)
        fell = fallen(pos[:, 2], np.arccos(np.clip(r22, -1.0, 1.0)), self.sim.nominal_base_height)
        return BaseTruth(pos=pos.copy(), linvel=linvel, angvel=qvel[:, 3:6].copy(), euler=euler,
                         heading_linvel=heading_linvel, fallen=fell, q=qpos[:, self.sim.qpos].copy(),
                         qd=qvel[:, self.sim.dofs].copy())

    def _walk_step(self, a: np.ndarray, truth: BaseTruth) -> WalkStep:
        """The rewards' input, of arrays no later step or restart changes."""
        sim, n = self.sim, self.num_envs
        last = self.sensordata[:, -1]  # MuJoCo evaluates sensors before it integrates: 1 ms before the state
        touch = last[:, sim.touch].reshape(n, 2, 2) > CONTACT_THRESHOLD_N  # (right, left) x (toe, heel)
        clock = self.builder.clock
        phase = gait_phase(clock.cycles, clock.period)  # the gait at the state reached, the next observation's
        swing = swing_height(phase.t_in_step / phase.step_time, self._swing_apex, self._swing_landing)
        return WalkStep(
            dt=self.dt, alive=~truth.fallen, base_pos=truth.pos, base_euler=truth.euler, base_linvel=truth.linvel,
            base_angvel=truth.angvel, base_linvel_prev=self._linvel_prev.copy(),
            base_angvel_prev=self._angvel_prev.copy(), command=clock.command.copy(),
            heading_linvel=truth.heading_linvel,
            foot_pos=last[:, sim.foot_pos].reshape(n, 2, 3), foot_vel=last[:, sim.foot_vel].reshape(n, 2, 3),
            foot_contact=touch.any(axis=2), knee_pos=last[:, sim.knee_pos].reshape(n, 2, 3),
            stance_desired=np.where(phase.starting, DOUBLE_SUPPORT, phase.stance),
            swing_height_desired=np.where(phase.starting, 0.0, swing), q=truth.q, qd=truth.qd,
            qd_prev=self._qd_prev.copy(), tau=self.tau.copy(), action=a.copy(), action_prev=self.last_action.copy(),
            action_prev2=self.last_action2.copy(), joint_names=self.robot.joints,
            heading_error=np.asarray(self.builder.heading_reference.error(truth.euler[:, 2]), dtype=float),
            mean_velocity=self.mean_velocity.copy())

    def _observe(self, truth: BaseTruth) -> dict[str, np.ndarray]:
        j = self.num_actions
        noise = self.rng.standard_normal(self._noise_std.shape) * self._noise_std + self._sensor_bias
        euler = truth.euler + noise[:, 2 * j + 6:]
        # the orientation as the noisy Euler angles say, so a term of the quaternion sees the same sensor error
        policy = self.builder.observe(self.command, truth.q + noise[:, :j], truth.qd + noise[:, j:2 * j],
                                      truth.linvel + noise[:, 2 * j:2 * j + 3],
                                      truth.angvel + noise[:, 2 * j + 3:2 * j + 6], euler, quaternion_rows(euler),
                                      self.last_action, self.last_raw_action)
        c, s = np.cos(truth.euler[:, 2]), np.sin(truth.euler[:, 2])
        f, t = self.push_wrench[:, :3], self.push_wrench[:, 3:]
        privileged = {
            "tau": self.tau, "base_height": truth.pos[:, 2:3], "ground_friction": self.draws.ground_friction[:, None],
            "mass_scale": self.draws.mass_scale[:, None],
            "push_force": np.stack([c * f[:, 0] + s * f[:, 1], -s * f[:, 0] + c * f[:, 1]], axis=1),
            "push_torque": np.stack([c * t[:, 0] + s * t[:, 1], -s * t[:, 0] + c * t[:, 1], t[:, 2]], axis=1)}
        return {"policy": policy, "critic": np.concatenate([policy, *(privileged[k] for k in PRIVILEGED)], axis=1)}

    def _output_of(self, targets: np.ndarray) -> np.ndarray:
        """The network output (config joint order) that the spec's action map makes `targets` of: what a policy
        observes as its last raw action."""
        order = self.spec.order
        raw = np.empty_like(targets)
        raw[:, order] = self.spec.action.output_of(targets[:, order])
        return raw

    # -- schedules: commands and pushes -------------------------------------------------------------------------
    def _steps(self, seconds_range: tuple[float, float], n: int) -> np.ndarray:
        return np.maximum(1, np.round(self.rng.uniform(*seconds_range, size=n) / self.dt)).astype(int)

    def _sample_commands(self, envs: np.ndarray) -> None:
        cfg, n = self.config, len(envs)
        command = np.stack([self.rng.uniform(*r, size=n) for r in (cfg.command_vx, cfg.command_vy, cfg.command_wz)],
                           axis=1)
        command[self.rng.random(n) < cfg.command_zero_share] = 0.0
        self.command[envs] = command
        self._command_left[envs] = self._steps(cfg.command_resample_s, n)

    def _start_pushes(self) -> None:
        envs = np.flatnonzero(self._push_countdown <= 0)
        if len(envs):
            cfg, n = self.config, len(envs)
            heading = self.rng.uniform(-math.pi, math.pi, size=n)
            force = self.rng.uniform(*cfg.push_impulse_ns, size=n) / cfg.push_duration_s
            axis = self.rng.standard_normal((n, 3))
            axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
            torque = self.rng.uniform(*cfg.push_angular_impulse_nms, size=n)[:, None] / cfg.push_duration_s * axis
            self.push_wrench[envs] = np.concatenate(
                [np.stack([force * np.cos(heading), force * np.sin(heading), np.zeros(n)], axis=1), torque], axis=1)
            self._push_left[envs] = self.push_steps
            self._push_countdown[envs] = self._steps(cfg.push_interval_s, n)
        self._push_countdown -= 1

    def _advance_schedules(self) -> None:
        self._push_left = np.maximum(self._push_left - 1, 0)
        self.push_wrench[self._push_left == 0] = 0.0
        self._command_left -= 1
        envs = np.flatnonzero(self._command_left <= 0)
        if len(envs):
            self._sample_commands(envs)

    # -- episodes -----------------------------------------------------------------------------------------------
    def _reset(self, envs: np.ndarray) -> None:
        """New episodes for `envs` (indices): randomisation, pose, command, push schedule, the observation's state."""
        sim, cfg, n, j = self.sim, self.config, len(envs), self.num_actions
        draws = draw(cfg.randomisation, self.rng, n, j)
        self.draws.assign(envs, draws)
        for k, i in enumerate(envs):
            apply_draw(sim, self.models[i], self.robot.joints, draws.row(k), self._kin)
        self._late[envs] = np.arange(self.decimation)[None, :] < draws.latency_ticks[:, None]
        stds = (draws.noise_q_rad, draws.noise_qd_rads, draws.noise_linvel_ms, draws.noise_angvel_rads,
                draws.noise_euler_rad)
        self._noise_std[envs] = np.repeat(np.stack(stds, axis=1), (j, j, 3, 3, 3), axis=1)
        self._sensor_bias[envs] = np.concatenate([draws.bias_q_rad, np.zeros((n, j + 3)), draws.bias_angvel_rads,
                                                  draws.bias_euler_rad], axis=1)
        q = np.clip(sim.standing_pose + self.rng.uniform(-1.0, 1.0, size=(n, j)) * cfg.reset_joint_noise_rad,
                    self.robot.q_lower, self.robot.q_upper)
        yaw = self.rng.uniform(-math.pi, math.pi, size=n)
        state = np.zeros((n, sim.nstate))
        state[:, self._qpos] = sim.model.qpos0
        qpos = state[:, self._qpos]
        qpos[:, 2] = [self._standing_height(row) for row in q]
        qpos[:, 3:7] = np.stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)], axis=1)
        qpos[:, sim.qpos] = q
        state[:, self._act] = q  # the target filter starts settled at the pose
        self.state[envs] = state
        self.builder.reset(envs)
        self.last_action[envs] = q  # as runtime.control.policy.PolicyController starts
        self.last_action2[envs] = q
        self.last_raw_action[envs] = 0.0  # as PolicyController starts: no action yet (legged_gym, Isaac Lab)
        self._qd_prev[envs] = 0.0
        self._linvel_prev[envs] = 0.0
        self._angvel_prev[envs] = 0.0
        self.tau[envs] = 0.0
        self.mean_velocity[envs] = 0.0
        self.episode_length[envs] = 0
        self._sample_commands(envs)
        self._push_countdown[envs] = self._steps(cfg.push_interval_s, n)
        self._push_left[envs] = 0
        self.push_wrench[envs] = 0.0

    def _standing_height(self, q: np.ndarray) -> float:
        """Base height at which the lower sole touches the floor with the base level and the legs at q (the mock's
        placement, `bruce_hw.robot_model.standing_height`, on the training model)."""
        return standing_height(self.sim.model, self._kin, self.sim.qpos, self._soles, q)
