"""The settings of one policy training (`bruce-train-policy --config FILE`, default training/rl/bruce_walk.yaml).

Sections: `train` (seed, iterations, checkpoints, the action and reward scales, the warm start), `env`
(`WalkEnvConfig`), `rewards` (weights by term name; left out: Table II's at the paper's weights, our added terms at
0) and `ppo` (rsl-rl-lib's train config, passed on after its keys and numbers are checked). Read through the
project's YAML reader, so a bad value is one line naming the file and the dotted key; `--set KEY=VALUE` overrides
any key.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bruce_hw.yaml_reader import Bound, YamlReader, apply_overrides, bound_lookup, read_yaml
from training.rl.env import WalkEnvConfig
from training.rl.rewards import TERMS

DEFAULT_TRAINING_CONFIG = Path(__file__).with_name("bruce_walk.yaml")


WARM_START_METHODS = ("auto", "transfer", "clone")


class TrainingConfigError(ValueError):
    """A training config that cannot be used; the message names the file and the key."""


_PPO_ALGORITHM_KEYS = {"class_name", "num_learning_epochs", "num_mini_batches", "clip_param", "gamma", "lam",
                       "value_loss_coef", "entropy_coef", "learning_rate", "max_grad_norm", "optimizer",
                       "use_clipped_value_loss", "schedule", "desired_kl", "normalize_advantage_per_mini_batch"}
_PPO_MODEL_KEYS = {"class_name", "hidden_dims", "activation", "obs_normalization", "distribution_cfg"}

BOUNDS: dict[str, Bound] = {
    "train.seed": Bound(0, 2**31 - 1, "", "torch and numpy seed", integer=True),
    "train.iterations": Bound(1, 10**7, "", "PPO iterations", integer=True),
    "train.checkpoint_every": Bound(1, 10**6, "", "iterations between checkpoints", integer=True),
    "train.snapshot_every": Bound(0, 10**6, "", "iterations between ONNX snapshots (0: none)", integer=True),
    "train.action_scale": Bound(0.01, 2.0, "rad", "PD target per unit of network output", low_open=True),
    "train.reward_scale": Bound(0.0, 1.0, "", "factor on every reward (0.01: x the policy period, as legged_gym)",
                                low_open=True),
    "train.warm_start.samples": Bound(1000, 10**8, "", "behaviour-cloning observations", integer=True),
    "train.warm_start.epochs": Bound(1, 1000, "", "behaviour-cloning passes", integer=True),
    "train.warm_start.critic_iterations": Bound(0, 10**5, "", "PPO iterations with the actor held", integer=True),
    "train.warm_start.action_std": Bound(0.0, 10.0, "", "PPO's initial action noise after cloning (network units)",
                                         low_open=True),
    "train.warm_start.learning_rate": Bound(1e-7, 1.0, "", "PPO's initial learning rate after cloning", low_open=True),
    "train.warm_start.entropy_coef": Bound(0.0, 1.0, "", "PPO's entropy bonus after cloning"),
    "train.warm_start.anchor_weight": Bound(0.0, 1e3, "", "pull toward the clone after each PPO update (0: none)"),
    "rewards.*": Bound(-1e3, 1e3, "", "a reward term's weight"),
    "ppo.num_steps_per_env": Bound(1, 10**4, "", "env steps per env per iteration", integer=True),
    "ppo.algorithm.num_learning_epochs": Bound(1, 100, "", "", integer=True),
    "ppo.algorithm.num_mini_batches": Bound(1, 1024, "", "", integer=True),
    "ppo.algorithm.clip_param": Bound(0.0, 1.0, "", "", low_open=True),
    "ppo.algorithm.gamma": Bound(0.0, 1.0, "", "discount per policy step"),
    "ppo.algorithm.lam": Bound(0.0, 1.0, "", "GAE lambda"),
    "ppo.algorithm.value_loss_coef": Bound(0.0, 100.0),
    "ppo.algorithm.entropy_coef": Bound(0.0, 1.0),
    "ppo.algorithm.learning_rate": Bound(1e-7, 1.0, "", "", low_open=True),
    "ppo.algorithm.max_grad_norm": Bound(0.0, 1e3, "", "", low_open=True),
    "ppo.algorithm.desired_kl": Bound(0.0, 1.0, "", "the adaptive schedule's KL target", low_open=True),
    "ppo.*.hidden_dims[*]": Bound(1, 4096, "", "layer width", integer=True),
    "ppo.actor.distribution_cfg.init_std": Bound(0.0, 10.0, "", "initial action noise (network units)",
                                                 low_open=True),
}
_bound = bound_lookup(BOUNDS, "training config BOUNDS")


@dataclass(frozen=True)
class WarmStart:
    policy: Path | None = None       # ONNX policy to clone (obs -> a_t, the runtime's interface); None: from scratch
    samples: int = 200_000           # observations labelled by it (visited by the cloned network after round 0)
    epochs: int = 20
    critic_iterations: int = 20      # PPO iterations with the actor held: the critic learns the clone's values
    # PPO settings that replace the `ppo` section's when a run starts from a clone: a scratch run's noise and step
    # size would undo the clone in a few iterations.
    action_std: float = 0.2
    learning_rate: float = 1e-4
    entropy_coef: float = 0.0
    anchor_weight: float = 0.0       # PolicyTrainer.set_anchor: hold the actor near the warm start through PPO
    method: str = "auto"             # transfer (exact weights), clone (DAgger) or auto (transfer where it fits)

    def ppo(self, cfg: dict) -> dict:
        """`cfg` (rsl-rl's train config) with the warm start's settings."""
        cfg = copy.deepcopy(cfg)
        cfg["actor"].setdefault("distribution_cfg", {"class_name": "GaussianDistribution"})["init_std"] = \
            self.action_std
        cfg["algorithm"]["learning_rate"] = self.learning_rate
        cfg["algorithm"]["entropy_coef"] = self.entropy_coef
        return cfg


@dataclass(frozen=True)
class TrainingConfig:
    path: Path
    seed: int
    iterations: int
    checkpoint_every: int
    snapshot_every: int
    action_scale: float
    reward_scale: float
    warm_start: WarmStart
    env: WalkEnvConfig
    reward_weights: dict[str, float]
    ppo: dict[str, Any]
    raw: dict


def load_training_config(path: str | Path = DEFAULT_TRAINING_CONFIG, overrides: list[str] | None = None
                         ) -> TrainingConfig:
    path = Path(path)
    if not path.is_file():
        raise TrainingConfigError(f"{path}: training config file not found")
    data = read_yaml(path, TrainingConfigError, "training config")
    if overrides:
        data = apply_overrides(data, overrides, path, TrainingConfigError)
    return parse_training_config(data, path)


def parse_training_config(data: Any, path: Path) -> TrainingConfig:
    r = YamlReader(path, data, TrainingConfigError, _bound)
    r.mapping("", {"train", "env", "rewards", "ppo"}, required={"train", "ppo"})
    train = r.mapping("train", {"seed", "iterations", "checkpoint_every", "snapshot_every", "action_scale",
                                "reward_scale", "warm_start"},
                      required={"seed", "iterations", "checkpoint_every", "action_scale"})
    warm = WarmStart()
    if "warm_start" in train:
        numbers = ("samples", "epochs", "critic_iterations", "action_std", "learning_rate", "entropy_coef",
                   "anchor_weight")
        node = r.mapping("train.warm_start", {"policy", "method", *numbers})
        policy = node.get("policy")
        method = node.get("method", "auto")
        if method not in WARM_START_METHODS:
            raise r.fail("train.warm_start.method", " or ".join(WARM_START_METHODS), method)
        if policy is not None and (not isinstance(policy, str) or not policy):
            raise r.fail("train.warm_start.policy", "an ONNX policy path or null", policy)
        warm = WarmStart(policy=_beside(path, policy) if policy else None, method=method,
                         **{k: r.number(f"train.warm_start.{k}") for k in numbers if k in node})
    try:
        env = WalkEnvConfig.from_dict(data.get("env", {}), str(path)) if "env" in data else \
            WalkEnvConfig(source=str(path))
    except ValueError as exc:
        raise TrainingConfigError(str(exc)) from None
    weights = {name: weight for name, (_, weight) in TERMS.items()}
    if "rewards" in data:
        for name in r.mapping("rewards", set(TERMS)):
            weights[name] = r.number(f"rewards.{name}")
    return TrainingConfig(path=path, seed=r.number("train.seed"), iterations=r.number("train.iterations"),
                          checkpoint_every=r.number("train.checkpoint_every"),
                          snapshot_every=r.number("train.snapshot_every") if "snapshot_every" in train else 0,
                          action_scale=r.number("train.action_scale"),
                          reward_scale=r.number("train.reward_scale") if "reward_scale" in train else 1.0,
                          warm_start=warm, env=env,
                          reward_weights=weights, ppo=_ppo(r), raw=copy.deepcopy(data))


def _beside(config_path: Path, name: str) -> Path:
    """A path from the config: absolute, else relative to the working directory if it exists there, else to the
    config file's directory."""
    path = Path(name)
    if path.is_absolute() or path.exists():
        return path
    return config_path.parent / path


def _ppo(r: YamlReader) -> dict[str, Any]:
    node = r.mapping("ppo", {"num_steps_per_env", "algorithm", "actor", "critic"},
                     required={"num_steps_per_env", "algorithm", "actor", "critic"})
    r.number("ppo.num_steps_per_env")
    algorithm = r.mapping("ppo.algorithm", _PPO_ALGORITHM_KEYS, required={"class_name"})
    for key in algorithm:
        if f"ppo.algorithm.{key}" in BOUNDS:
            r.number(f"ppo.algorithm.{key}")
    if algorithm.get("schedule", "adaptive") not in {"adaptive", "fixed"}:
        raise r.fail("ppo.algorithm.schedule", "adaptive or fixed", algorithm["schedule"])
    for model in ("actor", "critic"):
        m = r.mapping(f"ppo.{model}", _PPO_MODEL_KEYS, required={"class_name", "hidden_dims"})
        if not isinstance(m["hidden_dims"], list) or not m["hidden_dims"]:
            raise r.fail(f"ppo.{model}.hidden_dims", "a list of layer widths", m["hidden_dims"])
        for i, width in enumerate(m["hidden_dims"]):
            r.number(f"ppo.{model}.hidden_dims[{i}]", width)
    if "distribution_cfg" in node["actor"]:
        dist = r.mapping("ppo.actor.distribution_cfg", {"class_name", "init_std", "std_type"})
        if "init_std" in dist:
            r.number("ppo.actor.distribution_cfg.init_std")
    cfg = copy.deepcopy(node)
    cfg["obs_groups"] = {"actor": ["policy"], "critic": ["critic"]}
    return cfg
