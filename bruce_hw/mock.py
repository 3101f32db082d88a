"""The MuJoCo `mock` backend: BRUCE's model stepped one loop period per tick.

It reports what the robot's own sensors would (joint encoders and torques, the IMU, the four foot contact
switches) and, separately, simulator ground truth for evaluation. Motors are emulated at the joint level:
the command's torque (including any motor-side PD) is evaluated every physics step, saturated per actuator
through the coupling, then by the joint box limits of the model's motors.

The model, its named indices, the standing placement and the sensor read-out are BRUCE's model
(`bruce_hw.robot_model.BruceModel`, `self.robot`); the backend adds the lifecycle, the motors, pushes and the gap.

With a `RealityGap` (`bruce_hw.reality_gap`) the mock plays "the real robot": perturbed model, delayed and lagged
torques, noisy and delayed sensors; ground truth stays truth. Without one, the per-tick path is the nominal one.
"""

from __future__ import annotations

import mujoco
import numpy as np

from bruce_hw.backend import Backend, BackendError, LifecycleState
from bruce_hw.config import RobotConfig
from bruce_hw.model_binding import JointBinding
from bruce_hw.reality_gap import ActuatorGap, RealityGap, SensorGap, apply_to_model, latency_ticks
from bruce_hw.robot_model import CONTACT_THRESHOLD_N, IMU_SENSORS, BruceModel  # noqa: F401 (re-exported)
from bruce_hw.types import GroundTruth, JointCommand, RobotState

DAMPING = "damping"  # what a faulted backend sends its motors (through the bus latency of a reality gap)


class MujocoBackend(Backend):
    name = "mock"

    def __init__(self, config: RobotConfig, initial_q: np.ndarray | None = None, gap: RealityGap | None = None):
        super().__init__(config)
        self.initial_q = config.standing_pose.copy() if initial_q is None else np.asarray(initial_q, float)
        self.gap = gap
        self._actuator_gap: ActuatorGap | None = None
        self._sensor_gap: SensorGap | None = None
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.robot: BruceModel | None = None  # the model, its named indices and placement (after configure)
        self.binding: JointBinding | None = None  # where the config's joints are in the model (after configure)
        self._command: JointCommand | None = None
        self.estop_pressed = False  # the mock's emergency-stop input, reported in every RobotState
        self._push_force = np.zeros(3)
        self._push_until = -1.0

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _on_configure(self) -> None:
        cfg = self.config
        robot = BruceModel(cfg)  # loads and checks the MJCF; the joints', sensors' and bodies' indices
        model = robot.model
        self.robot = robot
        self.binding = robot.binding  # shared with the models built on this one
        self._qpos, self._dofs, self._acts = robot.qpos, robot.dofs, robot.acts
        self._base = robot.base_body
        self._torque_limit = cfg.actuator_torque_limit
        if self.gap is not None:
            apply_to_model(self.gap, model, self._dofs, self._acts, cfg.joints)
            self._torque_limit *= self.gap.torque_limit_scale
            self._actuator_gap = ActuatorGap(latency_ticks(self.gap.actuator_latency_s, cfg.dt),
                                             self.gap.actuator_time_constant_s, cfg.dt, cfg.n_joints,
                                             self.gap.per_joint("torque_scale", cfg.joints))
            self._sensor_gap = SensorGap(self.gap, cfg.joints, latency_ticks(self.gap.sensor_latency_s, cfg.dt),
                                         dt=cfg.dt)
        self.model = model
        self.data = robot.new_data()
        self._damping_kd = np.full(cfg.n_joints, cfg.safety.damping_kd)
        self._zero = np.zeros(cfg.n_joints)
        self.nominal_base_height = robot.standing_height(cfg.standing_pose)
        self.place(self.initial_q)

    def _on_activate(self) -> None:
        self._command = None  # motors enable with no stale goal: zero torque until the first write

    def _on_deactivate(self) -> None:
        self._command = None

    def _on_fault(self) -> None:
        self._command = None

    def _on_shutdown(self) -> None:
        self._command = None

    # -- helpers -----------------------------------------------------------------------------------------
    def place(self, q: np.ndarray) -> None:
        """Reset the simulation: legs at q, base level and at rest, soles on the floor (`BruceModel.place_standing`)."""
        self.robot.place_standing(self.data, q)
        self._command = None
        self._push_until = -1.0  # mj_resetData cleared the applied force
        if self._actuator_gap is not None:
            self._actuator_gap.reset()
            self._sensor_gap.reset(self.measure)

    def push(self, impulse: np.ndarray, duration: float = 0.1) -> None:
        """Push the base: a constant world-frame force impulse / duration (N) on the base's centre of mass for the
        next `duration` s of simulated time, as a disturbance for tests and training."""
        if duration <= 0.0:
            raise ValueError(f"mock backend: push duration must be > 0 s, got {duration}")
        self._push_force = np.asarray(impulse, dtype=float) / duration
        self._push_until = float(self.data.time) + duration

    # -- per tick ----------------------------------------------------------------------------------------
    def _motor_torque(self) -> np.ndarray:
        """The torque the motors apply this tick: the command (or, faulted, damping) evaluated on the present state
        and saturated per actuator; with a reality gap, what arrives after the bus latency, saturated at the gap's
        limit, then lagged by the motor."""
        sent = DAMPING if self._state is LifecycleState.FAULT else self._command
        gap = self._actuator_gap
        arrived = sent if gap is None else gap.delayed(sent)
        data = self.data
        qd = data.qvel[self._dofs]
        if arrived is None:
            tau = self._zero
        elif arrived is DAMPING:
            tau = -self._damping_kd * qd
        else:
            tau = arrived.torque(data.qpos[self._qpos], qd)
            if not np.all(np.isfinite(tau)):
                raise BackendError("mock backend: non-finite joint torque commanded")
            tau = self.config.coupling.saturate(tau, self._torque_limit)
        return tau if gap is None else gap.lag(tau)

    def _read(self) -> RobotState:
        data = self.data
        data.ctrl[self._acts] = self._motor_torque()  # the model's motors clamp to the joint box limits
        if self._push_until >= 0.0:
            pushing = data.time < self._push_until - 1e-9
            data.xfrc_applied[self._base, :3] = self._push_force if pushing else 0.0
            if not pushing:
                self._push_until = -1.0
        mujoco.mj_step(self.model, data)
        state = self.measure()
        return state if self._sensor_gap is None else self._sensor_gap.report(state)

    def measure(self) -> RobotState:
        """What the model's sensors read now, noise-free (fresh arrays; no step): a nominal model's own sensors, for
        the twin's estimator."""
        return self.robot.measure(self.data, self.estop_pressed)

    def _write(self, command: JointCommand) -> None:
        self._command = command

    def clock(self) -> float:
        return float(self.data.time)  # stamps are simulated time

    def body_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions (nbody, 3) and orientations (nbody, 4; w, x, y, z) of every body, for display."""
        return self.data.xpos.copy(), self.data.xquat.copy()

    def _ground_truth(self) -> GroundTruth:
        return self.robot.ground_truth(self.data)
