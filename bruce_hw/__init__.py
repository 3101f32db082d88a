"""BRUCE hardware abstraction layer: one joint-space backend contract, the robot config, and backends
(`mock`: MuJoCo, `echo`: kinematic, `hw`: the real buses)."""

from bruce_hw.backend import Backend, BackendError, LifecycleError, LifecycleState
from bruce_hw.backends import BACKENDS, make_backend
from bruce_hw.config import DEFAULT_CONFIG, ConfigError, RobotConfig, load_config
from bruce_hw.types import FootContacts, GroundTruth, ImuSample, JointCommand, JointState, RobotState

__all__ = [
    "BACKENDS", "Backend", "BackendError", "LifecycleError", "LifecycleState", "make_backend",
    "DEFAULT_CONFIG", "ConfigError", "RobotConfig", "load_config",
    "FootContacts", "GroundTruth", "ImuSample", "JointCommand", "JointState", "RobotState",
]
