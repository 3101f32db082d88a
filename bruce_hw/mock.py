"""The MuJoCo `mock` backend: BRUCE's model stepped one loop period per tick.

It reports what the robot's own sensors would (joint encoders and torques, the IMU, the four foot contact
switches) and, separately, simulator ground truth for evaluation. Motors are emulated at the joint level:
the command's torque (including any motor-side PD) is evaluated every physics step, saturated per actuator
through the coupling, then by the joint box limits of the model's motors.

With a `RealityGap` (`bruce_hw.reality_gap`) the mock plays "the real robot": perturbed model, delayed and lagged
torques, noisy and delayed sensors; ground truth stays truth. Without one, the per-tick path is the nominal one.
"""

from __future__ import annotations

import mujoco
import numpy as np

from bruce_hw.backend import Backend, BackendError, LifecycleState
from bruce_hw.config import RobotConfig
from bruce_hw.model_binding import JointBinding, bind_joints
from bruce_hw.reality_gap import ActuatorGap, RealityGap, SensorGap, apply_to_model, latency_ticks
from bruce_hw.types import FootContacts, GroundTruth, ImuSample, JointCommand, JointState, RobotState

IMU_SENSORS = ("imu_gyro", "imu_accel", "imu_quat")
CONTACT_THRESHOLD_N = 1.0  # a toe/heel switch closes above this normal force
AMBIENT_TEMPERATURE_C = 30.0  # the mock has no thermal model; it reports a constant winding temperature
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
        self.binding: JointBinding | None = None  # where the config's joints are in the model (after configure)
        self._command: JointCommand | None = None
        self.estop_pressed = False  # the mock's emergency-stop input, reported in every RobotState
        self._push_force = np.zeros(3)
        self._push_until = -1.0

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _on_configure(self) -> None:
        cfg = self.config
        model_file = str(cfg.mjcf)
        try:
            model = mujoco.MjModel.from_xml_path(model_file)
        except Exception as exc:  # mujoco raises ValueError with the parser's message
            raise BackendError(f"{model_file}: cannot load the MuJoCo model: {exc}") from exc
        if abs(model.opt.timestep - cfg.dt) > 1e-12:
            raise BackendError(f"{model_file}: timestep {model.opt.timestep} s does not match the config's "
                               f"loop period 1/rates.loop_hz = {cfg.dt} s")
        self.binding = bind_joints(model, cfg.joints, model_file)  # shared with the models built on this one
        self._qpos, self._dofs, self._acts = self.binding.qpos, self.binding.dofs, self.binding.acts
        self._sensor = {}
        for name in (*IMU_SENSORS, "r_toe", "r_heel", "l_toe", "l_heel"):
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
            if sid < 0:
                raise BackendError(f"{model_file}: no sensor named {name!r} (the mock needs {IMU_SENSORS} and "
                                   "one touch sensor per toe and heel)")
            adr = int(model.sensor_adr[sid])
            self._sensor[name] = slice(adr, adr + int(model.sensor_dim[sid]))
        touch = [self._sensor[n].start for n in ("r_toe", "r_heel", "l_toe", "l_heel")]
        self._touch = np.array(touch)
        self._base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "base")
        if self._base < 0 or model.body_jntnum[self._base] != 1 or \
                model.jnt_type[model.body_jntadr[self._base]] != mujoco.mjtJoint.mjJNT_FREE:
            raise BackendError(f"{model_file}: the mock needs a body 'base' with a free joint")
        self._soles = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in ("r_sole", "l_sole")]
        if min(self._soles) < 0:
            raise BackendError(f"{model_file}: the mock needs sites 'r_sole' and 'l_sole' on the soles")
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
        self.data = mujoco.MjData(model)
        self._damping_kd = np.full(cfg.n_joints, cfg.safety.damping_kd)
        self._zero = np.zeros(cfg.n_joints)
        self._temperature = np.full(cfg.n_joints, AMBIENT_TEMPERATURE_C)
        self.nominal_base_height = self._standing_height(cfg.standing_pose)
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
    def _standing_height(self, q: np.ndarray) -> float:
        """Base height at which the lower sole touches the floor with the base level and legs at q."""
        data = mujoco.MjData(self.model)
        data.qpos[0:7] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        data.qpos[self._qpos] = q
        mujoco.mj_kinematics(self.model, data)
        return float(-min(data.site_xpos[s][2] for s in self._soles))

    def place(self, q: np.ndarray) -> None:
        """Reset the simulation: legs at q, base level and at rest, soles on the floor."""
        data = self.data
        mujoco.mj_resetData(self.model, data)
        data.qpos[0:3] = (0.0, 0.0, self._standing_height(q))
        data.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        data.qpos[self._qpos] = q
        mujoco.mj_forward(self.model, data)
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
        data = self.data
        t = data.time
        s = data.sensordata
        return RobotState(
            joints=JointState(q=data.qpos[self._qpos].copy(), qd=data.qvel[self._dofs].copy(),
                              tau=data.actuator_force[self._acts].copy(), temperature=self._temperature.copy(),
                              stamp=t),
            imu=ImuSample(gyro=s[self._sensor["imu_gyro"]].copy(), accel=s[self._sensor["imu_accel"]].copy(),
                          orientation=s[self._sensor["imu_quat"]].copy(), stamp=t),
            contacts=FootContacts(contact=s[self._touch] > CONTACT_THRESHOLD_N, stamp=t),
            estop=self.estop_pressed,
        )

    def _write(self, command: JointCommand) -> None:
        self._command = command

    def clock(self) -> float:
        return float(self.data.time)  # stamps are simulated time

    def body_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions (nbody, 3) and orientations (nbody, 4; w, x, y, z) of every body, for display."""
        return self.data.xpos.copy(), self.data.xquat.copy()

    def _ground_truth(self) -> GroundTruth:
        data = self.data
        return GroundTruth(sim_time=float(data.time), base_pos=data.qpos[0:3].copy(),
                           base_quat=data.qpos[3:7].copy(), base_linvel=data.qvel[0:3].copy(),
                           base_angvel=data.qvel[3:6].copy(), joint_q=data.qpos[self._qpos].copy(),
                           joint_qd=data.qvel[self._dofs].copy())
