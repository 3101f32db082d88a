"""The nominal controllers by name (`--controller`): every one has reset(q) and a_t = controller(state, base, command)
at the policy rate."""

from __future__ import annotations

from pathlib import Path

from bruce_hw.config import RobotConfig
from runtime.control.inference import OnnxPolicy
from runtime.control.policy import PolicyController
from runtime.control.policy_spec import policy_spec_for
from runtime.control.standing import StandingController

CONTROLLERS = ("policy", "teacher", "standing")


def build_controller(config: RobotConfig, policy_path: Path | None, kind: str = "policy"):
    """The nominal controller and its name. `policy`: the ONNX policy given (or configured), else the standing
    controller; `teacher`: the model-based walking controller; `standing`: the standing controller. A policy runs
    with its spec (`runtime.control.policy_spec.policy_spec_for`), and its ONNX sizes are checked against the spec's."""
    if kind not in CONTROLLERS:
        raise ValueError(f"unknown controller {kind!r} (expected one of {', '.join(CONTROLLERS)})")
    if policy_path is not None and kind != "policy":
        raise ValueError(f"a policy model ({policy_path}) is for the policy controller, not {kind!r}")
    if kind == "teacher":
        from runtime.walking.teacher import WalkingTeacher  # only runs that walk with it load its models

        return WalkingTeacher(config), "walking teacher"
    path = (policy_path or config.models.policy) if kind == "policy" else None
    if path is None:
        return StandingController(config), "standing controller"
    spec = policy_spec_for(config, path)
    n = len(spec.joints)
    policy = OnnxPolicy(path, spec.obs_size, n, names=(spec.input_name, spec.output_name),
                        sized_by=(f"spec {spec.name} builds {spec.obs_size} values ({spec.layout_text()})",
                                  f"spec {spec.name} maps {n} joints"))
    policy.warmup()
    return PolicyController(config, policy, spec), f"policy {path} (spec {spec.name}, {spec.rate_hz} Hz)"
