"""The standing controller: the nominal controller of `bruce-run` until a walking policy exists.

It outputs joint targets a_t at the policy rate, like the paper's policy, and leaves torques to the Eq. 8 PD:
- soft start: a_t ramps (smoothstep) from the measured pose to the standing pose over `safety.soft_start_s`;
- balance: BRUCE's line feet and the Eq. 8 ankle gain (Kp 2.5 against m g h ~ 15 Nm/rad of toppling
  stiffness) cannot hold the body up as a stiff pendulum, so the ankles act as torque sources that keep the
  centre of mass over the middle of the feet: tau = -m g (K_x dx + K_v dx'), with dx the CoM's offset from
  the support centre along the heading, from the robot's own model, the joint angles and the IMU tilt.
  The torque is folded into a_t (a = q + tau / Kp), so the interface stays a_t;
- sag: a slow, bounded integral on the hip-pitch and knee tracking errors removes the droop of the
  low-gain PD under the robot's weight.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import ImuSample, RobotState
from runtime.estimation import BaseEstimate, world_up_in_body

COM_POSITION_GAIN = 2.0     # K_x, in units of the toppling stiffness m g (must exceed 1)
COM_VELOCITY_GAIN = 0.3     # K_v, s
COM_VELOCITY_FILTER = 0.5   # first-order smoothing of the finite-difference CoM velocity (0 = none)
LATERAL_POSITION_GAIN = 1.0 # rad of hip roll per m of lateral CoM offset
LATERAL_VELOCITY_GAIN = 0.5 # rad of hip roll per m/s of lateral CoM velocity
SAG_INTEGRAL_GAIN = 1.0     # 1/s
SAG_INTEGRAL_LIMIT = 0.15   # rad
SUPPORT_SITES = ("r_toe", "r_heel", "l_toe", "l_heel")


def tilt_quaternion(imu: ImuSample) -> np.ndarray:
    """The base's roll and pitch as a quaternion (w, x, y, z), heading removed: the shortest rotation taking the
    body's z axis onto the world's. Scalar math: numpy's cross/norm on 3-vectors cost ~15 µs per call."""
    ux, uy, uz = (float(v) for v in world_up_in_body(imu))
    s = math.hypot(ux, uy)  # |up x e_z|; the rotation axis is (uy, -ux, 0) / s
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    half = 0.5 * math.atan2(s, uz)
    k = math.sin(half) / s
    return np.array([math.cos(half), k * uy, -k * ux, 0.0])


class StandingController:
    def __init__(self, config: RobotConfig):
        self.config = config
        self.dt = 1.0 / config.policy_hz
        self.ramp_steps = max(1, round(config.safety.soft_start_s * config.policy_hz))
        self.ankles = config.joint_indices("ankle")
        self.rolls = config.joint_indices("hip_roll")
        # Gravity loads the sagittal joints; an integral on yaw/roll only feeds the lateral sway mode.
        self.sagittal = config.joint_indices("hip_pitch", "knee")
        self.model = mujoco.MjModel.from_xml_path(str(config.mjcf))
        self.kin = mujoco.MjData(self.model)
        self.legs = np.array([self.model.jnt_qposadr[self.model.joint(n).id] for n in config.joints])
        self.support = [self.model.site(n).id for n in SUPPORT_SITES]
        self.base = self.model.body("base").id
        self.mg = float(self.model.body_subtreemass[self.base]) * float(-self.model.opt.gravity[2])
        self.reset(config.standing_pose)

    def reset(self, q_measured: np.ndarray) -> None:
        """Start the soft start from the pose the robot is in now."""
        self.start = np.array(q_measured, dtype=float)
        self.step = 0
        self.sag = np.zeros(len(self.sagittal))
        self.com_offset: np.ndarray | None = None
        self.com_velocity = np.zeros(2)

    def com_offset_xy(self, state: RobotState) -> np.ndarray:
        """Centre of mass minus centre of the toe/heel points, along and across the heading (m)."""
        kin = self.kin
        kin.qpos[3:7] = tilt_quaternion(state.imu)
        kin.qpos[self.legs] = state.joints.q
        mujoco.mj_kinematics(self.model, kin)
        mujoco.mj_comPos(self.model, kin)
        support = kin.site_xpos[self.support, :2].mean(axis=0)
        return kin.subtree_com[self.base][:2] - support

    def __call__(self, state: RobotState, base: BaseEstimate | None = None, command: np.ndarray | None = None
                 ) -> np.ndarray:
        """a_t for this policy step (it stands still: the base estimate and the velocity command are unused)."""
        stand, q = self.config.standing_pose, state.joints.q
        s = min(1.0, self.step / self.ramp_steps)
        s = s * s * (3.0 - 2.0 * s)  # smoothstep: no jump in target velocity at either end
        a = self.start + s * (stand - self.start)

        offset = self.com_offset_xy(state)
        if self.com_offset is not None:
            raw = (offset - self.com_offset) / self.dt
            self.com_velocity += (1.0 - COM_VELOCITY_FILTER) * (raw - self.com_velocity)
        self.com_offset = offset
        (dx, dy), (vx, vy) = offset, self.com_velocity
        # Positive ankle torque pushes the shank forward (joint axis -y), moving the CoM forward.
        tau_each = -0.5 * self.mg * (COM_POSITION_GAIN * dx + COM_VELOCITY_GAIN * vx)
        a[self.ankles] = q[self.ankles] + tau_each / self.config.eq8.kp[self.ankles]
        # Line feet have no ankle roll: across the heading, both hip rolls shift the pelvis over the feet.
        a[self.rolls] += LATERAL_POSITION_GAIN * dy + LATERAL_VELOCITY_GAIN * vy

        if self.step >= self.ramp_steps:
            err = stand[self.sagittal] - q[self.sagittal]
            self.sag = np.clip(self.sag + SAG_INTEGRAL_GAIN * self.dt * err, -SAG_INTEGRAL_LIMIT, SAG_INTEGRAL_LIMIT)
        a[self.sagittal] += self.sag
        self.step += 1
        return a
