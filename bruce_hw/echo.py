"""The kinematic `echo` backend for controller unit tests: no physics, the state mirrors the command.

After ros2_control's GenericSystem: a command with q_ref moves the joints there at once (qd follows qd_ref,
else 0); a torque-only command leaves them where they are. The measured torque is what the command asked for
at the previous state. The IMU reports an upright robot at rest with both feet down.
"""

from __future__ import annotations

import numpy as np

from bruce_hw.backend import Backend
from bruce_hw.config import RobotConfig
from bruce_hw.types import GRAVITY, FootContacts, ImuSample, JointCommand, JointState, RobotState


class EchoBackend(Backend):
    name = "echo"

    def __init__(self, config: RobotConfig, initial_q: np.ndarray | None = None):
        super().__init__(config)
        self.initial_q = config.standing_pose.copy() if initial_q is None else np.asarray(initial_q, float)

    def _on_configure(self) -> None:
        n = self.config.n_joints
        self.q = self.initial_q.copy()
        self.qd = np.zeros(n)
        self.tau = np.zeros(n)
        self.time = 0.0

    def _on_fault(self) -> None:
        self.qd[:] = 0.0
        self.tau[:] = 0.0

    def clock(self) -> float:
        return self.time  # stamps are the echo's own tick time

    def _read(self) -> RobotState:
        self.time += self.config.dt
        t = self.time
        return RobotState(
            joints=JointState(q=self.q.copy(), qd=self.qd.copy(), tau=self.tau.copy(),
                              temperature=np.full(self.config.n_joints, 30.0), stamp=t),
            imu=ImuSample(gyro=np.zeros(3), accel=np.array([0.0, 0.0, GRAVITY]),
                          orientation=np.array([1.0, 0.0, 0.0, 0.0]), stamp=t),
            contacts=FootContacts(contact=np.ones(4, dtype=bool), stamp=t),
        )

    def _write(self, command: JointCommand) -> None:
        self.tau = np.asarray(command.torque(self.q, self.qd), dtype=float).copy()
        if command.q_ref is not None:
            self.q = np.clip(command.q_ref, self.config.q_lower, self.config.q_upper).astype(float)
            self.qd = np.zeros_like(self.q) if command.qd_ref is None else np.array(command.qd_ref, float)
