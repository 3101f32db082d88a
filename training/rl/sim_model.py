"""The training MjModel (`build_sim_model` -> `SimModel`): BRUCE's MJCF with the ten motors turned into MuJoCo PD
actuators running Eq. 8 at every 1 ms physics step, and the sensors the environment reads.

Each actuator computes force = clamp(kp (act - q) - kd qd, +-joint torque limit), where act follows the control (the
PD target a_t) through a first-order filter (`filterexact`, time constant 0: no lag) evaluated early (`actearly`), so
the force of a step already uses the filtered target of that step, as `bruce_hw.reality_gap.ActuatorGap.lag` does for
the torque. Without randomisation the model steps exactly as the mock does under the runtime's Eq. 8
(tests/training/rl/test_rl_env.py), except that the mock saturates per actuator through the coupling.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.model_binding import bind_joints
from bruce_hw.robot_model import BASE_BODY, IMU_SENSORS, SOLE_SITES, TOUCH_SENSORS, BruceModel
from runtime.walking.leg_ik import SIDES

FOOT_SITES = SOLE_SITES                                       # the soles: foot position and velocity
KNEE_JOINTS = tuple(f"{side}_knee" for side in SIDES)         # knee position: the origin of the knee joint's body
FLOOR_GEOM = "floor"
# The arrays of the model a randomisation draw changes; kept at their nominal values to start each draw from.
RANDOMISED_FIELDS = ("body_mass", "body_inertia", "dof_frictionloss", "dof_damping", "dof_armature", "geom_friction",
                     "actuator_gainprm", "actuator_biasprm", "actuator_forcerange", "actuator_dynprm")


@dataclass(frozen=True, eq=False)
class SimModel:
    model: mujoco.MjModel            # the nominal training model (copy it per environment)
    qpos: slice                      # the config's joints in qpos, in config order
    dofs: slice                      # ... in qvel
    acts: slice                      # their PD actuators (ctrl and act)
    base_body: int
    floor_geom: int
    foot_geoms: np.ndarray           # every collision geom of the feet (toe and heel spheres)
    foot_pos: slice                  # sensordata: soles' world positions, (right, left) x 3
    foot_vel: slice                  # ... soles' world linear velocities, (right, left) x 3
    knee_pos: slice                  # ... knees' world positions, (right, left) x 3
    touch: slice                     # ... normal force on the toe and heel switches (r_toe, r_heel, l_toe, l_heel)
    tau: slice                       # ... actuator forces (joint torques), config order
    kp: np.ndarray                   # Eq. 8 gains, config order
    kd: np.ndarray
    torque_limit: np.ndarray         # N·m, joints.torque_limits
    standing_pose: np.ndarray
    nominal_base_height: float       # the mock's (`BruceModel.standing_height`): legs standing, soles on the floor
    nominal: dict[str, np.ndarray]   # RANDOMISED_FIELDS at their nominal values

    @property
    def nstate(self) -> int:
        return mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_FULLPHYSICS.value)


def _pd_actuator(actuator: mujoco.MjsActuator, kp: float, kd: float, limit: float) -> None:
    actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
    actuator.gainprm[:3] = (kp, 0.0, 0.0)
    actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
    actuator.biasprm[:3] = (0.0, -kp, -kd)
    actuator.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
    actuator.dynprm[0] = 0.0
    actuator.actearly = True
    actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE  # ctrl is a target angle now, not a torque
    actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    actuator.forcerange[:] = (-limit, limit)


def _span(model: mujoco.MjModel, names: list[str]) -> slice:
    """The contiguous sensordata of the named sensors, in order."""
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, n) for n in names]
    adr = [int(model.sensor_adr[i]) for i in ids]
    dim = int(model.sensor_dim[ids[0]])
    if adr != list(range(adr[0], adr[0] + dim * len(ids), dim)):
        raise AssertionError(f"sensors {names} are not contiguous")
    return slice(adr[0], adr[0] + dim * len(ids))


def build_sim_model(config: RobotConfig) -> SimModel:
    """The training model for `config`; the joint, sensor and contact layout is checked by the robot's model
    (`BruceModel`, the mock's: the same MJCF)."""
    robot = BruceModel(config)  # checks the MJCF against the config; gives the joints' motors and the standing height
    spec = mujoco.MjSpec.from_file(str(config.mjcf))
    for sensor in list(spec.sensors):
        if sensor.name in IMU_SENSORS:  # the environment observes the truth, as GroundTruthEstimator does
            spec.delete(sensor)
    kp, kd, limit = config.eq8.kp, config.eq8.kd, config.tau_limit
    nominal = robot.model
    motors = robot.motors
    for i, name in enumerate(motors):
        _pd_actuator(spec.actuator(name), float(kp[i]), float(kd[i]), float(limit[i]))
    sens = mujoco.mjtSensor
    site, body = mujoco.mjtObj.mjOBJ_SITE, mujoco.mjtObj.mjOBJ_BODY
    knee_bodies = [nominal.body(int(nominal.jnt_bodyid[nominal.joint(j).id])).name for j in KNEE_JOINTS]
    for s in FOOT_SITES:
        spec.add_sensor(name=f"{s}_pos", type=sens.mjSENS_FRAMEPOS, objtype=site, objname=s)
    for s in FOOT_SITES:
        spec.add_sensor(name=f"{s}_vel", type=sens.mjSENS_FRAMELINVEL, objtype=site, objname=s)
    for b in knee_bodies:
        spec.add_sensor(name=f"{b}_pos", type=sens.mjSENS_FRAMEPOS, objtype=body, objname=b)
    for name in motors:
        spec.add_sensor(name=f"{name}_tau", type=sens.mjSENS_ACTUATORFRC, objtype=mujoco.mjtObj.mjOBJ_ACTUATOR,
                        objname=name)
    # Euler (with the joints' damping implicit, as MuJoCo's Euler does by default) leaves the PD's -kd qd explicit, as
    # the runtime computes it every tick; on the mock's torque motors implicitfast reduces to the same step.
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    model = spec.compile()
    foot_geoms = np.array([g for g in range(model.ngeom) if model.geom_contype[g]
                           and model.body(model.geom_bodyid[g]).name.endswith("_foot")])
    binding = bind_joints(model, config.joints, str(config.mjcf))  # the PD actuators are the joints' motors still
    return SimModel(
        model=model, qpos=binding.qpos, dofs=binding.dofs, acts=binding.acts,
        base_body=model.body(BASE_BODY).id, floor_geom=model.geom(FLOOR_GEOM).id, foot_geoms=foot_geoms,
        foot_pos=_span(model, [f"{s}_pos" for s in FOOT_SITES]),
        foot_vel=_span(model, [f"{s}_vel" for s in FOOT_SITES]),
        knee_pos=_span(model, [f"{b}_pos" for b in knee_bodies]),
        touch=_span(model, list(TOUCH_SENSORS)),
        tau=_span(model, [f"{name}_tau" for name in motors]),
        kp=kp.copy(), kd=kd.copy(), torque_limit=limit.copy(), standing_pose=config.standing_pose.copy(),
        nominal_base_height=robot.standing_height(),
        nominal={name: getattr(model, name).copy() for name in RANDOMISED_FIELDS})
