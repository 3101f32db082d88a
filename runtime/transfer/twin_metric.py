"""The twin metric: how far the robot moves from what the simulator would do, over one policy period at a time.

Every `window_ticks` (10: one policy period at 1 kHz) a nominal MuJoCo model (the mock without a reality gap) is
set to the robot's full simulator state (base pose and velocity, joints: the mock's ground truth), then stepped
once per tick as the simulator's own tick would on the targets a_t the robot got: Eq. 8 on the twin's state
through the safety stage's command filter (running: the rate limit continued from the torque the robot was sent
last, the clamps), saturated per actuator as the mock's motors do. At the end of each window the per-joint error
is the twin's q minus the robot's true q. The summary is the per-joint RMS over the windows that end after
TRACKING_SKIP_S and its mean over joints (`twin_rmse`).

The twin restarts from the robot every window, so the metric scores the transfer (robot against simulator under
the same targets) without the drift of two free runs apart, and it is zero when the robot is the simulator and
runs Eq. 8 alone. Mock only (it needs the simulator's state); an observer, never fed back.
"""

from __future__ import annotations

from types import SimpleNamespace

import mujoco
import numpy as np

from bruce_hw.backend import Backend
from bruce_hw.config import RobotConfig
from runtime.control.mixing import eq8_torque
from runtime.loop.observers import TRACKING_SKIP_S, TickObserver, TickView
from runtime.loop.safety import SafetyStage, SafetyState
from runtime.transfer.reference_models import nominal_model_on_truth


class TwinMetric(TickObserver):
    def __init__(self, window_ticks: int | None = None, skip_s: float = TRACKING_SKIP_S):
        self.window_ticks = window_ticks  # None: one policy period
        self.skip_s = skip_s
        self.windows = 0
        self.squared_error_sum: np.ndarray | None = None

    def on_start(self, backend: Backend, config: RobotConfig) -> None:
        robot, self.data = nominal_model_on_truth(
            config, backend.ground_truth, f"twin metric: needs the simulator's state, which the {backend.name} "
            "backend does not have (mock only)")
        self.robot, self.model = robot, robot.model
        self._qpos, self._dofs, self._acts = robot.qpos, robot.dofs, robot.acts
        self.eq8, self.coupling, self.torque_limit = config.eq8, config.coupling, config.actuator_torque_limit
        if self.window_ticks is None:
            self.window_ticks = config.policy_decimation
        self.windows = 0
        self.squared_error_sum = np.zeros(config.n_joints)
        # The twin's own command filter, past its soft start (the scored windows come after it); it reads the
        # twin's joint state through `_joints` (what SafetyStage.filter reads of a RobotState).
        self.safety = SafetyStage(config)
        self.safety.state = SafetyState.RUNNING
        self._joints = SimpleNamespace(q=None, qd=None)
        self._twin_state = SimpleNamespace(joints=self._joints)
        self._last_sent = np.zeros(config.n_joints)  # the torque the robot was sent at the previous tick
        self._synced = False

    def on_tick(self, view: TickView) -> None:
        data = self.data
        if view.tick % self.window_ticks == 0:
            truth = view.truth
            if self._synced and view.elapsed >= self.skip_s:
                error = data.qpos[self._qpos] - truth.joint_q
                self.squared_error_sum += error * error
                self.windows += 1
            self.robot.set_truth(data, truth, truth.joint_q, truth.joint_qd)
            self.safety.previous = self._last_sent.copy()
            self._synced = True
        np.copyto(self._last_sent, view.tau)
        if not self._synced:
            return None
        q, qd = data.qpos[self._qpos], data.qvel[self._dofs]
        self._joints.q, self._joints.qd = q, qd
        tau = self.safety.filter(eq8_torque(view.a, q, qd, self.eq8), self._twin_state)
        data.ctrl[self._acts] = self.coupling.saturate(tau, self.torque_limit)
        mujoco.mj_step(self.model, data)
        return None

    @property
    def rmse_per_joint(self) -> np.ndarray:
        """Per joint, the RMS of the end-of-window error over the scored windows (NaN before the first)."""
        if not self.windows:
            return np.full(len(self.squared_error_sum), np.nan)
        return np.sqrt(self.squared_error_sum / self.windows)

    @property
    def rmse(self) -> float:
        """`twin_rmse`: the mean over joints of `rmse_per_joint`."""
        return float(np.mean(self.rmse_per_joint))
