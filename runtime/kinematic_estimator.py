"""The real robot's base state estimator: IMU attitude filter + leg-odometry Kalman filter on the base velocity.

A real BRUCE measures joint angles and velocities, the IMU's gyro and specific force, and four toe/heel
contact switches; the sense board gives no orientation, so none is used here.

- Attitude: `bruce_hw.attitude.MahonyAttitude` (gyro integrated, roll and pitch pulled towards the specific
  force while |accel| is near g, gyro bias learned; yaw starts at 0 on reset and is never corrected: nothing on
  the robot observes heading).
- Velocity: a Kalman filter on the base's linear velocity in the (yaw-relative) world frame. Prediction
  integrates the accelerometer, v += (R a - g) dt, whose errors (tilt error times g, biases, impacts) grow the
  variance; each foot with a contact switch closed is a measurement: a foot point touching the ground
  is at rest, so the base moves at v = -R (J(q) qd + w x r), with r that point relative to the base and
  J(q) qd its velocity relative to the base, both from the robot's own MJCF with the base held at the origin.
  The point is the lowest point of the toe and/or heel sphere whose switch is closed: a line foot rolls on
  them. A foot that has just touched down (impact, bounce, slip) is trusted less for 20 ms; a foot with
  both switches open is not used, so in the air the velocity comes from the IMU alone.
  The measurements and the accelerometer are taken isotropic, so the 3x3 covariance stays a multiple of the
  identity: the filter is three scalar filters sharing one variance, which keeps the 1 kHz update in scalar
  Python math.
"""

from __future__ import annotations

import mujoco
import numpy as np

from bruce_hw.attitude import MAX_IMU_GAP_S, MahonyAttitude
from bruce_hw.config import RobotConfig
from bruce_hw.types import FOOT_CONTACT_NAMES, RobotState
from runtime.estimation import BaseEstimate, euler_of, rotate_to_body

# -- velocity Kalman filter ------------------------------------------------------------------------------
# ODOMETRY_STD, m/s: one-sample (1 kHz) standard deviation of a leg-odometry velocity. Our assumption, not a
# measurement: encoder-differentiated joint velocities (~0.05 rad/s each over ~0.4 m of leg) plus the foot
# rolling and compressing.
ODOMETRY_STD = 0.1
# VELOCITY_RANDOM_WALK, (m/s)^2 per s: variance growth from integrating the accelerometer, whose errors are
# slow (tilt error times g, 1 deg ~ 0.17 m/s^2; biases ~0.1 m/s^2). It sets the filter's time constant tau
# (q = ODOMETRY_STD^2 dt / tau^2): a slow acceleration error b costs ~b tau, odometry noise ~ODOMETRY_STD
# sqrt(dt / 2 tau); with b ~ 0.2 m/s^2 their sum is smallest near tau = 30 ms, q ~ 0.01 (one foot on the
# ground: ~30 ms, both: ~20 ms).
VELOCITY_RANDOM_WALK = 0.01
# A foot that has just touched down bounces, compresses and may slip: its odometry's standard deviation is this
# many times ODOMETRY_STD (variance x100: practically ignored) for TOUCHDOWN_S after its first switch closes.
# 20 ms is our estimate of a gentle step's impact transient; the mock's soft contacts take ~60 ms to recover
# from a 2 m/s landing.
TOUCHDOWN_STD_SCALE = 10.0
TOUCHDOWN_S = 0.02
# m/s, standard deviation of the velocity at reset (the robot is at rest, up to sway).
RESET_VELOCITY_STD = 0.01

FEET = (("r_toe", "r_heel"), ("l_toe", "l_heel"))  # per foot, its toe and heel contact/geom names


def _index(indices: list[int]) -> slice | np.ndarray:
    """The indices as a slice when they are contiguous: assigning through a slice costs a third of the time."""
    if indices == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return np.array(indices)


class _Foot:
    """One foot's contact switches, the spheres they sit on, and how long it has been on the ground."""

    def __init__(self, model: mujoco.MjModel, toe: str, heel: str):
        self.toe_switch, self.heel_switch = FOOT_CONTACT_NAMES.index(toe), FOOT_CONTACT_NAMES.index(heel)
        self.toe_geom, self.heel_geom = model.geom(toe).id, model.geom(heel).id
        self.body = int(model.geom_bodyid[self.toe_geom])
        if int(model.geom_bodyid[self.heel_geom]) != self.body:
            raise ValueError(f"MJCF: geoms {toe!r} and {heel!r} must be on the same foot body")
        self.toe_radius = float(model.geom_size[self.toe_geom][0])
        self.heel_radius = float(model.geom_size[self.heel_geom][0])
        self.ticks_on_ground = 0


class KinematicEstimator:
    """Base orientation, linear and angular velocity from the gyro, accelerometer, joints and foot contacts."""

    def __init__(self, config: RobotConfig):
        model = mujoco.MjModel.from_xml_path(str(config.mjcf))
        self.model = model
        # Kinematics only, base held at the origin with identity orientation: world quantities are base-frame.
        self.kin = mujoco.MjData(model)
        self.kin.qpos[0:7] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        joints = [model.joint(name).id for name in config.joints]
        self.leg_qpos = _index([int(model.jnt_qposadr[j]) for j in joints])
        self.leg_dofs = _index([int(model.jnt_dofadr[j]) for j in joints])
        self.qvel = np.zeros(model.nv)  # leg joint velocities at their dofs, the base's at zero
        self.jacp = np.zeros((3, model.nv))
        self.point = np.zeros(3)
        self.feet = [_Foot(model, toe, heel) for toe, heel in FEET]
        self.gravity = float(-model.opt.gravity[2])
        self.touchdown_ticks = max(1, round(TOUCHDOWN_S * config.loop_hz))
        self.odometry_variance = ODOMETRY_STD ** 2
        self.touchdown_variance = (TOUCHDOWN_STD_SCALE * ODOMETRY_STD) ** 2
        self.attitude = MahonyAttitude(self.gravity)
        self.stamp = 0.0
        self.velocity = (0.0, 0.0, 0.0)        # m/s, world frame
        self.variance = RESET_VELOCITY_STD ** 2  # (m/s)^2, per axis

    def reset(self, state: RobotState) -> None:
        """At rest: zero velocity, attitude levelled from the specific force (`MahonyAttitude.reset`)."""
        self.attitude.reset(state.imu.gyro, state.imu.accel, state.imu.stamp)
        self.stamp = state.imu.stamp
        self.velocity = (0.0, 0.0, 0.0)
        self.variance = RESET_VELOCITY_STD ** 2
        contact = state.contacts.contact.tolist()
        for foot in self.feet:  # feet already down at reset are settled, not touching down
            on_ground = contact[foot.toe_switch] or contact[foot.heel_switch]
            foot.ticks_on_ground = self.touchdown_ticks if on_ground else 0

    def update(self, state: RobotState) -> None:
        """One tick: attitude from the gyro and accelerometer, velocity predicted from the accelerometer, then
        corrected by the odometry of each foot on the ground."""
        imu = state.imu
        dt = min(max(imu.stamp - self.stamp, 0.0), MAX_IMU_GAP_S)
        self.stamp = imu.stamp
        w, x, y, z = self.attitude.update(imu.gyro, imu.accel, imu.stamp)
        gx, gy, gz = self.attitude.angvel  # bias removed
        ax, ay, az = imu.accel.tolist()
        r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)

        # Velocity prediction from the specific force rotated to the world, gravity removed.
        px, py, pz = self.velocity
        px += (r00 * ax + r01 * ay + r02 * az) * dt
        py += (r10 * ax + r11 * ay + r12 * az) * dt
        pz += (r20 * ax + r21 * ay + r22 * az - self.gravity) * dt
        variance = self.variance + VELOCITY_RANDOM_WALK * dt

        # Leg odometry from every foot on the ground.
        contact = state.contacts.contact.tolist()
        kin = self.kin
        kinematics_done = False
        for foot in self.feet:
            toe, heel = contact[foot.toe_switch], contact[foot.heel_switch]
            if not (toe or heel):
                foot.ticks_on_ground = 0
                continue
            foot.ticks_on_ground += 1
            if not kinematics_done:
                kin.qpos[self.leg_qpos] = state.joints.q
                mujoco.mj_kinematics(self.model, kin)
                mujoco.mj_comPos(self.model, kin)  # mj_jac needs the dof axes it computes
                self.qvel[self.leg_dofs] = state.joints.qd
                kinematics_done = True
            # The point at rest: the lowest point of the sphere on the ground, its centre plus its radius along
            # "down" in the base frame (minus row 2 of R); both spheres on the ground: their midpoint.
            if toe and heel:
                tx, ty, tz = kin.geom_xpos[foot.toe_geom].tolist()
                hx, hy, hz = kin.geom_xpos[foot.heel_geom].tolist()
                radius = 0.5 * (foot.toe_radius + foot.heel_radius)
                fx, fy, fz = 0.5 * (tx + hx), 0.5 * (ty + hy), 0.5 * (tz + hz)
            else:
                geom, radius = (foot.toe_geom, foot.toe_radius) if toe else (foot.heel_geom, foot.heel_radius)
                fx, fy, fz = kin.geom_xpos[geom].tolist()
            fx, fy, fz = fx - radius * r20, fy - radius * r21, fz - radius * r22
            point = self.point
            point[0], point[1], point[2] = fx, fy, fz
            mujoco.mj_jac(self.model, kin, self.jacp, None, point, foot.body)
            jx, jy, jz = (self.jacp @ self.qvel).tolist()  # the point's velocity relative to the base
            # Base velocity in the base frame: -(J qd + w x r); then rotated to the world.
            mx, my, mz = -(jx + gy * fz - gz * fy), -(jy + gz * fx - gx * fz), -(jz + gx * fy - gy * fx)
            measurement_variance = self.odometry_variance if foot.ticks_on_ground > self.touchdown_ticks \
                else self.touchdown_variance
            gain = variance / (variance + measurement_variance)
            px += gain * (r00 * mx + r01 * my + r02 * mz - px)
            py += gain * (r10 * mx + r11 * my + r12 * mz - py)
            pz += gain * (r20 * mx + r21 * my + r22 * mz - pz)
            variance *= 1.0 - gain
        self.velocity = (px, py, pz)
        self.variance = variance

    def estimate(self) -> BaseEstimate:
        quat = np.array(self.attitude.quat)
        return BaseEstimate(quat=quat, linvel=rotate_to_body(quat, np.array(self.velocity)),
                            angvel=np.array(self.attitude.angvel), euler=euler_of(quat))
