"""BRUCE's MuJoCo model bound to a robot config (`BruceModel`), as MuJoCo Playground's `<robot>_constants.py` and
`base.py`: the MJCF loaded and checked against the config once, the names the code looks up (the joints' slices,
the base body, the soles, the IMU and the contact switches), and what every user of the model does the same way:
the standing placement and height, setting a state, reading the model's clean sensors and its truth.

The mock backend (`bruce_hw.mock.MujocoBackend`) steps one of these as "the robot"; the transfer stage's nominal
models (`runtime/transfer/`) and the gains build their own, and the RL environment's training model
(`training/rl/sim_model.py`) is checked and measured by one. Each user keeps its own `MjData` (`new_data`).
"""

from __future__ import annotations

import mujoco
import numpy as np

from bruce_hw.backend import BackendError
from bruce_hw.config import RobotConfig
from bruce_hw.model_binding import JointBinding, bind_joints
from bruce_hw.types import FootContacts, GroundTruth, ImuSample, JointState, RobotState

IMU_SENSORS = ("imu_gyro", "imu_accel", "imu_quat")
TOUCH_SENSORS = ("r_toe", "r_heel", "l_toe", "l_heel")  # the foot contact switches, in `FootContacts` order
SOLE_SITES = ("r_sole", "l_sole")  # where each foot meets the floor: the standing placement
BASE_BODY = "base"  # the floating base (a free joint)
CONTACT_THRESHOLD_N = 1.0  # a toe/heel switch closes above this normal force
AMBIENT_TEMPERATURE_C = 30.0  # the model has no thermal model; it reports a constant winding temperature


def standing_height(model: mujoco.MjModel, data: mujoco.MjData, qpos: slice, soles, q: np.ndarray) -> float:
    """Base height at which the lower sole (`soles`: site ids) touches the floor with the base level and the joints
    (`qpos`: their slice in qpos) at q. `data`: a scratch MjData of `model` (its qpos and kinematics are overwritten);
    any compiled model of BRUCE's MJCF, the training model's included."""
    data.qpos[:] = model.qpos0
    data.qpos[0:7] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    data.qpos[qpos] = q
    mujoco.mj_kinematics(model, data)
    return float(-min(data.site_xpos[s][2] for s in soles))


class BruceModel:
    """BRUCE's MJCF (`config.mjcf`) loaded, checked against `config` (timestep, joints and their motors, sensors,
    base, soles; BackendError naming the file otherwise) and bound: `model`, `binding` (and its `qpos`, `dofs`,
    `acts`), `motors` (the joints' motor names, config order), `base_body`, `soles`, `sensors` (name -> sensordata
    slice), `touch` (sensordata index of each switch, `TOUCH_SENSORS` order)."""

    def __init__(self, config: RobotConfig):
        self.config = config
        self.source = source = str(config.mjcf)
        try:
            model = mujoco.MjModel.from_xml_path(source)
        except Exception as exc:  # mujoco raises ValueError with the parser's message
            raise BackendError(f"{source}: cannot load the MuJoCo model: {exc}") from exc
        if abs(model.opt.timestep - config.dt) > 1e-12:
            raise BackendError(f"{source}: timestep {model.opt.timestep} s does not match the config's "
                               f"loop period 1/rates.loop_hz = {config.dt} s")
        self.model = model
        self.binding: JointBinding = bind_joints(model, config.joints, source)
        self.qpos, self.dofs, self.acts = self.binding.qpos, self.binding.dofs, self.binding.acts
        self.motors = tuple(model.actuator(a).name for a in range(self.acts.start, self.acts.stop))
        self.sensors: dict[str, slice] = {}
        for name in (*IMU_SENSORS, *TOUCH_SENSORS):
            sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
            if sid < 0:
                raise BackendError(f"{source}: no sensor named {name!r} (BRUCE's model needs {IMU_SENSORS} and "
                                   "one touch sensor per toe and heel)")
            adr = int(model.sensor_adr[sid])
            self.sensors[name] = slice(adr, adr + int(model.sensor_dim[sid]))
        self.touch = np.array([self.sensors[n].start for n in TOUCH_SENSORS])
        self.base_body = base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, BASE_BODY)
        if base < 0 or model.body_jntnum[base] != 1 or \
                model.jnt_type[model.body_jntadr[base]] != mujoco.mjtJoint.mjJNT_FREE:
            raise BackendError(f"{source}: BRUCE's model needs a body {BASE_BODY!r} with a free joint")
        self.soles = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in SOLE_SITES]
        if min(self.soles) < 0:
            raise BackendError(f"{source}: BRUCE's model needs sites 'r_sole' and 'l_sole' on the soles")
        self._temperature = np.full(config.n_joints, AMBIENT_TEMPERATURE_C)

    def new_data(self) -> mujoco.MjData:
        """A fresh MjData of the model (at qpos0; `place_standing` puts it on the floor)."""
        return mujoco.MjData(self.model)

    def standing_height(self, q: np.ndarray | None = None) -> float:
        """Base height with the base level, the joints at q (default: the config's standing pose) and the lower sole
        on the floor (`nominal_base_height` at the standing pose)."""
        q = self.config.standing_pose if q is None else q
        return standing_height(self.model, mujoco.MjData(self.model), self.qpos, self.soles, q)

    def place_standing(self, data: mujoco.MjData, q: np.ndarray | None = None) -> None:
        """Reset `data`: joints at q (default: the config's standing pose), base level and at rest, soles on the
        floor; ends with mj_forward."""
        q = self.config.standing_pose if q is None else q
        model = self.model
        mujoco.mj_resetData(model, data)
        data.qpos[0:3] = (0.0, 0.0, self.standing_height(q))
        data.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        data.qpos[self.qpos] = q
        mujoco.mj_forward(model, data)

    def set_state(self, data: mujoco.MjData, q: np.ndarray, qd: np.ndarray, base_pos: np.ndarray,
                  base_quat: np.ndarray, base_linvel: np.ndarray, base_angvel: np.ndarray) -> None:
        """Put `data` at a full state: the base pose (world position, orientation w, x, y, z), its velocity (world
        linear, body angular: a free joint's) and the joints (config order). No kinematics."""
        data.qpos[0:3], data.qpos[3:7] = base_pos, base_quat
        data.qvel[0:3], data.qvel[3:6] = base_linvel, base_angvel
        data.qpos[self.qpos], data.qvel[self.dofs] = q, qd

    def set_truth(self, data: mujoco.MjData, truth: GroundTruth, q: np.ndarray, qd: np.ndarray) -> None:
        """`set_state` at the base state of `truth` (a simulator's `GroundTruth`) and the joint state (q, qd)."""
        self.set_state(data, q, qd, truth.base_pos, truth.base_quat, truth.base_linvel, truth.base_angvel)

    def measure(self, data: mujoco.MjData, estop: bool = False) -> RobotState:
        """What the model's sensors read in `data` now, noise-free (fresh arrays; no step): joint encoders and
        torques, the IMU, the contact switches, stamped with the simulated time."""
        t = data.time
        s = data.sensordata
        sensor = self.sensors
        return RobotState(
            joints=JointState(q=data.qpos[self.qpos].copy(), qd=data.qvel[self.dofs].copy(),
                              tau=data.actuator_force[self.acts].copy(), temperature=self._temperature.copy(),
                              stamp=t),
            imu=ImuSample(gyro=s[sensor["imu_gyro"]].copy(), accel=s[sensor["imu_accel"]].copy(),
                          orientation=s[sensor["imu_quat"]].copy(), stamp=t),
            contacts=FootContacts(contact=s[self.touch] > CONTACT_THRESHOLD_N, stamp=t),
            estop=estop,
        )

    def ground_truth(self, data: mujoco.MjData) -> GroundTruth:
        """The simulator's truth in `data` (fresh arrays)."""
        return GroundTruth(sim_time=float(data.time), base_pos=data.qpos[0:3].copy(),
                           base_quat=data.qpos[3:7].copy(), base_linvel=data.qvel[0:3].copy(),
                           base_angvel=data.qvel[3:6].copy(), joint_q=data.qpos[self.qpos].copy(),
                           joint_qd=data.qvel[self.dofs].copy())
