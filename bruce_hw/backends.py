"""The backends by name: the one place that knows every implementation of `bruce_hw.backend.Backend` (kept apart
from the contract, which each implementation imports)."""

from __future__ import annotations

from bruce_hw.backend import Backend, BackendError
from bruce_hw.config import RobotConfig

BACKENDS = ("mock", "echo", "hw")


def make_backend(name: str, config: RobotConfig, **options) -> Backend:
    """The backend called `name`, built from the robot config (not yet configured)."""
    if name == "mock":
        from bruce_hw.mock import MujocoBackend

        return MujocoBackend(config, **options)
    if name == "echo":
        from bruce_hw.echo import EchoBackend

        return EchoBackend(config, **options)
    if name == "hw":
        from bruce_hw.hw import make_hw_backend

        return make_hw_backend(config, **options)
    raise BackendError(f"unknown backend {name!r} (expected one of {', '.join(BACKENDS)})")
