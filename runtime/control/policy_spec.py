"""A walking policy's interface (`PolicySpec`, one YAML file): which observation terms in which order, with which
offsets, clips, scales and history; the policy's rate and joint order; how its output becomes joint targets; its
ONNX tensor names. It lets `bruce-run` run a policy trained elsewhere (docs/byo_policy.md is the format for users).

Where a run's spec comes from (`policy_spec_for`): the config's `policy.spec` (`bruce-run --policy-spec`), else a
`policy_spec` entry in the model's sidecar (`<model>.onnx.json`: a path relative to the sidecar, or the spec
inline), else the shipped Table I spec (`configs/robots/policy_specs/table1.yaml`). The terms a spec can name are
`runtime.observation.registry`'s. Every failure is one ConfigError naming the file and the dotted key.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from bruce_hw.config import ConfigError, RobotConfig
from bruce_hw.yaml_reader import Bound, YamlReader, bound_lookup, read_yaml
from runtime.observation import builtin_terms  # noqa: F401  (registers our terms before a spec names them)
from runtime.observation.registry import OBSERVATION_TERMS

SPECS_PACKAGE = "configs.robots"
SPECS_FOLDER = "policy_specs"
TABLE_ONE = "table1"  # the spec of a policy without one: the paper's Table I, as our policies are trained

HISTORY_ORDERS = ("oldest_first", "newest_first")
_TERM_KEYS = {"term", "offset", "clip", "scale", "history", "history_order"}
_TOP_KEYS = {"rate_hz", "joints", "observation", "obs_clip", "action", "onnx"}
_TURN = 2 * math.pi

SPEC_BOUNDS: dict[str, Bound] = {
    "rate_hz": Bound(1, 10_000, "Hz", "the policy's own rate; a divisor of rates.policy_hz", integer=True),
    "obs_clip": Bound(0.0, 1e6, "", "every observation value is clipped to +-obs_clip", low_open=True),
    "observation[*].clip": Bound(0.0, 1e6, "", "the term is clipped to +-clip before its scale", low_open=True),
    "observation[*].history": Bound(1, 100, "frames", "the last N frames of the term, stacked", integer=True),
    **{f"observation[*].scale{tail}": Bound(-1e4, 1e4, "", "multiplies the term") for tail in ("", "[*]", ".*")},
    **{f"observation[*].offset{tail}": Bound(-1e4, 1e4, "", "subtracted from the term, in its unit")
       for tail in ("", "[*]")},
    "observation[*].offset.*": Bound(-_TURN, _TURN, "rad", "a joint's default angle, a turn either way"),
    **{f"action.scale{tail}": Bound(-10.0, 10.0, "rad", "joint target per unit of network output")
       for tail in ("", "[*]", ".*")},
    **{f"action.offset{tail}": Bound(-_TURN, _TURN, "rad", "a joint's default angle, a turn either way")
       for tail in ("", "[*]", ".*")},
    "action.clip": Bound(0.0, 1e6, "", "the network output is clipped to +-clip", low_open=True),
}
_spec_bound = bound_lookup(SPEC_BOUNDS, "SPEC_BOUNDS")


@dataclass(frozen=True, slots=True)
class ObservationTerm:
    """One term: clip(x - offset, +-clip) * scale per frame (Isaac Lab's order: clip, then scale), `history`
    frames of it stacked; joint-space values in the spec's joint order."""

    term: str
    width: int                 # values per frame
    offset: np.ndarray         # (width,)
    clip: float | None
    scale: np.ndarray          # (width,)
    history: int = 1
    newest_first: bool = False

    @property
    def size(self) -> int:
        return self.width * self.history


@dataclass(frozen=True, slots=True)
class ActionMap:
    """Network output -> joint targets, in the spec's joint order: offset + scale * clip(output, +-clip)."""

    scale: np.ndarray          # (n_joints,)
    offset: np.ndarray         # (n_joints,), rad
    clip: float | None

    def output_of(self, targets: np.ndarray) -> np.ndarray:
        """The network output that gives `targets` (spec order, any leading axes), as far as the map inverts: 0
        where a joint's scale is 0."""
        return np.divide(targets - self.offset, self.scale, out=np.zeros(np.shape(targets)),
                         where=self.scale != 0.0)


@dataclass(frozen=True, slots=True)
class PolicySpec:
    source: str                # the file (or sidecar entry) it was read from, for messages
    rate_hz: int
    joints: tuple[str, ...]    # the policy's joint order
    order: np.ndarray          # the config index of each of the policy's joints
    terms: tuple[ObservationTerm, ...]
    obs_clip: float | None
    action: ActionMap
    input_name: str = "obs"
    output_name: str = "action"

    @property
    def name(self) -> str:
        return Path(self.source.split(": ")[0]).name

    @property
    def obs_size(self) -> int:
        return sum(term.size for term in self.terms)

    def layout_text(self) -> str:
        """The observation's terms and sizes, e.g. "clock 2 + command 3 + q 10 + ..."."""
        return " + ".join(f"{t.term} {t.size}" for t in self.terms)


def spec_file(name_or_path: str | Path) -> Path:
    """A spec file: an existing path, else a bare name (no suffix) of a shipped spec."""
    path = Path(name_or_path)
    if path.is_file():
        return path.resolve()
    if path.suffix:
        raise ConfigError(f"{path}: policy spec file not found")
    packaged = resources.files(SPECS_PACKAGE) / SPECS_FOLDER / f"{path.name}.yaml"
    if packaged.is_file():
        return Path(str(packaged))
    shipped = sorted(p.name.removesuffix(".yaml") for p in (resources.files(SPECS_PACKAGE) / SPECS_FOLDER).iterdir()
                     if p.name.endswith(".yaml"))
    raise ConfigError(f"{name_or_path}: no such policy spec file, nor a shipped one (expected a YAML path or one of "
                      f"{shipped}, configs/robots/policy_specs/)")


def load_policy_spec(name_or_path: str | Path, config: RobotConfig) -> PolicySpec:
    path = spec_file(name_or_path)
    return parse_policy_spec(read_yaml(path, ConfigError, "policy spec"), str(path), config)


def trained_commands(model: Path) -> dict[str, tuple[float, float]] | None:
    """The command ranges (vx, vy, wz: low, high) the policy `model` was trained on, from its sidecar's "commands"
    (written by training.distill and bruce-train-policy); None when the sidecar does not say."""
    sidecar = Path(f"{model}.json")
    if not sidecar.is_file():
        return None
    try:
        entry = json.loads(sidecar.read_text(encoding="utf-8")).get("commands")
    except (OSError, UnicodeDecodeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"{sidecar}: not a readable JSON sidecar ({exc})") from None
    if entry is None:
        return None
    try:
        ranges = {axis: (float(span[0]), float(span[1])) for axis, span in entry.items()}
    except (AttributeError, TypeError, ValueError, IndexError, KeyError):
        raise ConfigError(f"{sidecar}: commands: expected axis: [low, high] pairs, got {entry!r}") from None
    return ranges


def sidecar_spec(model: Path, config: RobotConfig) -> PolicySpec | None:
    """The `policy_spec` entry of the model's sidecar `<model>.json` (None when there is none)."""
    sidecar = Path(f"{model}.json")
    if not sidecar.is_file():
        return None
    try:
        data = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"{sidecar}: not a readable JSON sidecar ({exc})") from None
    entry = data.get("policy_spec") if isinstance(data, dict) else None
    if entry is None:
        return None
    if isinstance(entry, dict):
        return parse_policy_spec(entry, f"{sidecar}: policy_spec", config)
    if not isinstance(entry, str) or not entry:
        raise ConfigError(f"{sidecar}: policy_spec: expected a spec file path (relative to the sidecar) or a spec "
                          f"mapping, got {entry!r}")
    path = Path(entry)
    return load_policy_spec(path if path.is_absolute() else sidecar.parent / path, config)


def policy_spec_for(config: RobotConfig, model: Path) -> PolicySpec:
    """The spec a run uses with the policy `model`: policy.spec, else the model's sidecar's, else Table I."""
    if config.models.policy_spec is not None:
        return load_policy_spec(config.models.policy_spec, config)
    return sidecar_spec(Path(model), config) or load_policy_spec(TABLE_ONE, config)


def parse_policy_spec(data: Any, source: str, config: RobotConfig) -> PolicySpec:
    r = YamlReader(source, data, ConfigError, bounds=_spec_bound)
    top = r.mapping("", _TOP_KEYS, required={"observation"})
    rate_hz = config.policy_hz
    if "rate_hz" in top:
        rate_hz = r.number("rate_hz")
        if config.policy_hz % rate_hz:
            raise r.fail("rate_hz", f"a divisor of rates.policy_hz ({config.policy_hz} Hz in {config.path}): the loop "
                         "asks for targets at that rate and the policy's are held between its own ticks (a faster "
                         "policy needs a faster rates.policy_hz, a divisor of rates.loop_hz)", rate_hz)
    joints = _joints(r, config) if "joints" in top else config.joints
    order = np.array([config.joints.index(name) for name in joints], dtype=int)
    standing = config.standing_pose[order]
    observation = r.node("observation")
    if not isinstance(observation, list) or not observation:
        raise r.fail("observation", "a non-empty list of terms (a term name or a mapping with `term`)", observation)
    terms = tuple(_term(r, f"observation[{i}]", joints, standing) for i in range(len(observation)))
    action = _action(r, joints, standing) if "action" in top else ActionMap(np.ones(len(joints)),
                                                                           np.zeros(len(joints)), None)
    input_name, output_name = _tensor_names(r) if "onnx" in top else ("obs", "action")
    return PolicySpec(source=source, rate_hz=rate_hz, joints=tuple(joints), order=order, terms=terms,
                      obs_clip=r.number("obs_clip") if "obs_clip" in top else None, action=action,
                      input_name=input_name, output_name=output_name)


def _joints(r: YamlReader, config: RobotConfig) -> tuple[str, ...]:
    """`config` (the robot config's joint order) or every config joint once, by name, in the policy's order."""
    if r.node("joints") == "config":
        return config.joints
    joints = r.names("joints")
    for i, name in enumerate(joints):
        if name not in config.joints:
            raise r.fail(f"joints[{i}]", f"a joint of {config.path} (one of {list(config.joints)})", name)
    missing = [name for name in config.joints if name not in joints]
    if missing:
        raise r.fail("joints", f"every joint of {config.path} once (missing {missing})", show_got=False)
    return joints


def _values(r: YamlReader, key: str, width: int, joints: tuple[str, ...] | None, standing: np.ndarray | None,
            default: float) -> np.ndarray:
    """Per-element numbers at `key`: absent (`default`), one number for all, a list of `width`; for joint-space
    terms also a mapping joint name -> number, or "standing" (the config's standing pose, with `standing`)."""
    parent, _, name = key.rpartition(".")
    if name not in r.node(parent):
        return np.full(width, default)
    value = r.node(key)
    if isinstance(value, list):
        return r.vector(key, width)
    if joints is not None and isinstance(value, dict):
        node = r.mapping(key)
        r.check_keys(key, node, joints, joints, what="joint", missing=f" (every joint of {list(joints)} needs a "
                     "value)")
        return np.array([r.number(f"{key}.{joint}") for joint in joints])
    if standing is not None and value == "standing":
        return standing.copy()
    forms = (", a mapping joint -> number" if joints is not None else "") + \
        (" or \"standing\" (joints.standing_pose)" if standing is not None else "")
    return np.full(width, r.number(key, also=f", a list of {width} numbers{forms}"))


def _term(r: YamlReader, key: str, joints: tuple[str, ...], standing: np.ndarray) -> ObservationTerm:
    """A term: its name alone (no offset, clip or scale) or a mapping with `term` and the optional keys."""
    if isinstance(r.node(key), str):
        width = OBSERVATION_TERMS[r.choice(key, tuple(OBSERVATION_TERMS))].width_for(len(joints))
        return ObservationTerm(term=r.node(key), width=width, offset=np.zeros(width), clip=None, scale=np.ones(width))
    node = r.mapping(key, _TERM_KEYS, required={"term"})
    definition = OBSERVATION_TERMS[r.choice(f"{key}.term", tuple(OBSERVATION_TERMS))]
    names = joints if definition.per_joint else None
    width = definition.width_for(len(joints))
    newest_first = "history_order" in node and r.choice(f"{key}.history_order", HISTORY_ORDERS) == "newest_first"
    return ObservationTerm(
        term=definition.name, width=width,
        offset=_values(r, f"{key}.offset", width, names, standing if definition.joint_angles else None, 0.0),
        clip=r.number(f"{key}.clip") if "clip" in node else None,
        scale=_values(r, f"{key}.scale", width, names, None, 1.0),
        history=r.number(f"{key}.history") if "history" in node else 1, newest_first=newest_first)


def _action(r: YamlReader, joints: tuple[str, ...], standing: np.ndarray) -> ActionMap:
    node = r.mapping("action", {"scale", "offset", "clip"})
    n = len(joints)
    return ActionMap(scale=_values(r, "action.scale", n, joints, None, 1.0),
                     offset=_values(r, "action.offset", n, joints, standing, 0.0),
                     clip=r.number("action.clip") if "clip" in node else None)


def _tensor_names(r: YamlReader) -> tuple[str, str]:
    node = r.mapping("onnx", {"input", "output"})
    return (r.string("onnx.input") if "input" in node else "obs",
            r.string("onnx.output") if "output" in node else "action")
