"""The one backend contract, in joint space, that everything above the HAL uses.

Lifecycle (after ros2_control): UNCONFIGURED -> configure() -> INACTIVE (reads, never commands)
-> activate() -> ACTIVE (commands) ; any fault -> FAULT (damping), left only by an explicit reset().
A tick is read() -> controller -> write(). Time passes between reads: on a robot by itself, in the mock
because read() advances the physics by one loop period with what the motors were last told to do.
"""

from __future__ import annotations

import enum
import logging
import time
from abc import ABC, abstractmethod

from bruce_hw.config import RobotConfig
from bruce_hw.types import GroundTruth, JointCommand, RobotState

log = logging.getLogger("bruce_hw")


class LifecycleState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FAULT = "fault"


class LifecycleError(RuntimeError):
    """An operation the backend's current lifecycle state does not allow."""


class TruthSealed(RuntimeError):
    """The simulator's truth was read where a robot-faithful run allows only what a robot measures."""


class BackendError(RuntimeError):
    """A backend could not be built, started, read or written."""


class Backend(ABC):
    name: str = "backend"

    def __init__(self, config: RobotConfig):
        self.config = config
        self._state = LifecycleState.UNCONFIGURED
        self.fault_cause: str | None = None

    @property
    def state(self) -> LifecycleState:
        return self._state

    def _require(self, operation: str, *allowed: LifecycleState) -> None:
        if self._state not in allowed:
            names = " or ".join(s.value for s in allowed)
            raise LifecycleError(f"{self.name} backend: {operation} needs state {names}, "
                                 f"but the backend is {self._state.value}")

    # -- transitions -------------------------------------------------------------------------------------
    def configure(self) -> None:
        self._require("configure", LifecycleState.UNCONFIGURED)
        self._on_configure()
        self._state = LifecycleState.INACTIVE

    def activate(self) -> None:
        self._require("activate", LifecycleState.INACTIVE)
        self._on_activate()
        self._state = LifecycleState.ACTIVE

    def deactivate(self) -> None:
        self._require("deactivate", LifecycleState.ACTIVE)
        self._on_deactivate()
        self._state = LifecycleState.INACTIVE

    def fault(self, cause: str) -> None:
        """Enter the damping state now. Idempotent: the first cause is kept."""
        self._require("fault", LifecycleState.INACTIVE, LifecycleState.ACTIVE, LifecycleState.FAULT)
        if self._state is LifecycleState.FAULT:
            return
        self._on_fault()
        self._state = LifecycleState.FAULT
        self.fault_cause = cause
        log.warning("%s backend: damping (%s)", self.name, cause)

    def reset(self) -> None:
        """Leave FAULT for INACTIVE; never automatic."""
        self._require("reset", LifecycleState.FAULT)
        self._on_reset()
        self.fault_cause = None
        self._state = LifecycleState.INACTIVE

    def shutdown(self) -> None:
        """From any state back to UNCONFIGURED; an active robot goes through damping first."""
        if self._state is LifecycleState.UNCONFIGURED:
            return
        if self._state is LifecycleState.ACTIVE:
            self._on_fault()
        self._on_shutdown()
        self._state = LifecycleState.UNCONFIGURED

    # -- per tick ----------------------------------------------------------------------------------------
    def read(self) -> RobotState:
        self._require("read", LifecycleState.INACTIVE, LifecycleState.ACTIVE, LifecycleState.FAULT)
        return self._read()

    def write(self, command: JointCommand) -> None:
        if self._state is not LifecycleState.ACTIVE:
            raise LifecycleError(f"{self.name} backend: command refused, the backend is {self._state.value} "
                                 "(only an active backend takes commands)")
        if command.tau_ff.shape != (self.config.n_joints,):
            raise ValueError(f"{self.name} backend: JointCommand.tau_ff has shape {command.tau_ff.shape}, "
                             f"expected ({self.config.n_joints},) in the order of joints.names")
        self._write(command)

    def clock(self) -> float:
        """Now, on the clock of the stamps this backend puts on its data (for the sensor-age check)."""
        return time.monotonic()

    # The robot's MuJoCo model where the backend has one (the mock: telemetry draws the robot with it), else None.
    model = None

    def body_poses(self):
        """(positions, quaternions) of every body for the 3D view, where the backend simulates them; else None."""
        return None

    def link_report(self) -> dict | None:
        """The backend's bus figures for the run's stats (hw: cycles, lost replies per ID, host stalls), or None."""
        return None

    # Whether `stalled_between` comes from a witness of the host (hw); without one a paced run's late ticks are not
    # attributed to the machine or the loop.
    host_witness = False

    def stalled_between(self, t0: float, t1: float) -> float:
        """Seconds of [t0, t1] (on `clock()`) in which this process was not run: a host stall, not device silence
        (`bruce_hw.host_witness`). 0 where the backend's clock is the simulation's own (the mock, echo)."""
        return 0.0

    def joint_stalled_between(self, t0: float, t1: float) -> float:
        """Seconds of [t0, t1] in which the host held the joint readings back: its stalls, and on hw the leg bus's
        port calls the host held (a request not sent is not a silent actuator). The joint data's age is judged on
        the rest."""
        return self.stalled_between(t0, t1)

    # A robot-faithful run seals the truth while anything but its observers runs (`runtime.loop.run`): the control path
    # must work on what a robot measures, and a read of the truth then raises instead of going unnoticed.
    truth_sealed = False

    def ground_truth(self) -> GroundTruth | None:
        """Simulator truth for evaluation; None on a real robot. Raises TruthSealed while `truth_sealed`."""
        if self.truth_sealed:
            raise TruthSealed(f"{self.name} backend: the simulator's truth was read in the control path of a "
                              "robot-faithful run (only observers may read it)")
        return self._ground_truth()

    def _ground_truth(self) -> GroundTruth | None:
        return None

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()

    # -- what a backend implements -----------------------------------------------------------------------
    @abstractmethod
    def _on_configure(self) -> None: ...

    def _on_activate(self) -> None:
        """Enable the motors."""

    def _on_deactivate(self) -> None:
        """Disable the motors (no torque)."""

    @abstractmethod
    def _on_fault(self) -> None:
        """Put every motor into damping."""

    def _on_reset(self) -> None:
        """Clear device errors before INACTIVE."""

    def _on_shutdown(self) -> None:
        """Release devices."""

    @abstractmethod
    def _read(self) -> RobotState: ...

    @abstractmethod
    def _write(self, command: JointCommand) -> None: ...
