"""The model-based walking controller ("teacher", `WalkingTeacher`): DCM footstep planning, swing trajectories,
analytic leg IK (docs/walking.md).

It has the nominal controller's interface, a_t = teacher(state, base, command) at the policy rate, and the 1 kHz
Eq. 8 PD turns a_t into torques, exactly as for the learned policy it is distilled into. Each policy tick: kinematics
from the robot's own model; gait timing from the policy's clock (`gait.GaitClock`); the swing foot's landing point
from the divergent component of motion xi = c + c'/omega predicted to the end of the step, less the periodic gait's
offset at the commanded velocity (Khadiv et al., TRO 2020; BRUCE's line feet have no ankle roll, so this is the only
lateral balance there is); a minimum-jerk swing with the sole level; a stance leg that holds the base upright at
the nominal height and turns through the stance hip yaw. The Eq. 8 gains are low, so feed-forward torques (stance
support, swing gravity and inertia) are folded into a_t: a = q_des + (tau_ff + Kd qd_des) / Kp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import GRAVITY, RobotState
from runtime.control.heading import HeadingReference
from runtime.estimation import BaseEstimate
from runtime.walking.gait import GaitClock, GaitPhase, interpolate, lipm_omega, min_jerk, swing_height
from runtime.walking.leg_ik import SIDES, leg_geometry, leg_ik


@dataclass(frozen=True)
class TeacherParams:
    standing_height: float = 0.400   # m, base origin above the stance ankle
    com_height: float = 0.358        # m, CoM above the sole for the pendulum's omega
    step_width: float = 0.110        # m, nominal lateral distance between the ankles
    foot_centre: float = 0.0075      # m, middle of the toe/heel line ahead of the ankle
    # The swing apex, the reach and the stance stiffness are set for walking backwards, the least robust regime
    # under action noise (docs/results/walking.md).
    swing_apex: float = 0.042        # m, swing ankle height at mid-swing
    swing_landing: float = -0.004    # m, the swing ends this far below the ground, so the foot lands
    swing_horizontal_end: float = 0.771  # share of the swing by which the foot is over its landing point
    replan_until: float = 0.897       # share of the swing after which the landing point is frozen
    reach_forward: float = 0.28      # m, ankle ahead of / behind the stance ankle at most
    width_min: float = 0.09          # m, lateral ankle distance at least (no crossing)
    width_max: float = 0.26          # m, ... at most
    start_shift: float = 0.75        # share of the way the CoM moves toward the first stance foot at start-up
    ankle_position_gain: float = 2.0  # ankle torque per m of CoM offset, in units of m g (must exceed 1)
    ankle_velocity_gain: float = 0.3  # s
    cop_gain: float = 2.0            # centre-of-pressure shift per m of DCM error (single stance)
    cop_front: float = 0.008         # m ahead of the foot centre at most (the toe is 0.0425 ahead)
    cop_back: float = 0.008          # m behind it at most (the heel is 0.0425 behind)
    # Swing hip yaw at landing, relative to the base, at most: after a push has yawed the base, a foot landing square
    # to the heading swings the hip yaw far, and the reaction spins the stance foot on its contact points.
    swing_yaw_max: float = 0.10      # rad
    heading_correction_max: float = 0.02  # rad of stance hip yaw per tick: more twists the foot past its friction
    # Forward-speed offset that the footstep plan adds to the command, as (vx, offset) points, linear between them:
    # the steady state of the velocity integral below, measured over the acceptance grid. Fed forward, it leaves
    # the integral a small correction, so the footsteps are nearly a function of what a student observes.
    speed_feedforward: tuple[tuple[float, float], ...] = ((-0.5, -0.044), (-0.3, 0.004), (0.0, 0.194), (0.4, 0.402),
                                                          (0.8, 0.506))
    lateral_feedforward: float = 0.46  # lateral-speed offset per m/s of lateral command, likewise
    velocity_integral_gain: float = 0.3  # 1/s, on the error of the base's velocity in the heading frame
    velocity_bias_max: float = 0.2   # m/s: the integral corrects the feed-forward, it does not replace it
    # Extra stiffness, as a multiple of Eq. 8's Kp, added through a_t (a sampled 100 Hz loop around the 1 kHz PD):
    stance_stiffness_boost: float = 0.8  # stance hips and knee
    swing_stiffness_boost: float = 0.25  # swing hips and knee
    swing_inertia_gain: float = 0.332  # share of the swing leg's inertial torque M q''_des fed forward
    swing_ankle_boost: float = 0.45       # swing ankle: Eq. 8's ankle (2.5 Nm/rad, 0.35 Nm s/rad) is too slow to
                                         # level the foot before it lands


class WalkingTeacher:
    def __init__(self, config: RobotConfig, params: TeacherParams | None = None):
        self.config = config
        self.params = p = params or TeacherParams()
        self.dt = 1.0 / config.policy_hz
        # The gait's clock, the policy observation's (runtime.control.policy): the same phase for teacher and student.
        self.clock = GaitClock(config.models.gait_period_s, self.dt)
        self.model = mujoco.MjModel.from_xml_path(str(config.mjcf))
        self.kin = mujoco.MjData(self.model)
        self.kin.qpos[0:3] = 0.0  # positions come out relative to the base origin
        names = config.joints
        self.leg_joints = [np.array([names.index(f"{side}_{j}") for j in
                                     ("hip_yaw", "hip_pitch", "hip_roll", "knee", "ankle")]) for side in SIDES]
        self.qpos = np.array([self.model.jnt_qposadr[self.model.joint(n).id] for n in names])
        self.dofs = np.array([self.model.jnt_dofadr[self.model.joint(n).id] for n in names])
        self.geo = [leg_geometry(self.model, side) for side in SIDES]
        self.feet = [self.model.body(f"{side}_foot").id for side in SIDES]
        self.base = self.model.body("base").id
        self.mass = float(self.model.body_subtreemass[self.base])
        self.mg = self.mass * GRAVITY
        self.omega = lipm_omega(p.com_height)
        self.kp, self.kd = config.eq8.kp, config.eq8.kd
        self.jacp = np.zeros((3, self.model.nv))
        self.jacr = np.zeros((3, self.model.nv))
        self.gravity = np.zeros(self.model.nv)
        self.qacc = np.zeros(self.model.nv)
        self.inertial = np.zeros(self.model.nv)
        # Extra stiffness per joint, for both feet down (start-up) and for each stance leg.
        self.boost = {stance_legs: self._boost(stance_legs) for stance_legs in ((0, 1), (0,), (1,))}
        # Desired base yaw, the policy observation's (runtime.control.policy): a student sees the error the teacher
        # acts on.
        self.heading_reference = HeadingReference(self.dt)
        self.reset(config.standing_pose)

    # -- state -------------------------------------------------------------------------------------------
    def reset(self, q_measured: np.ndarray) -> None:
        self.clock.reset()
        self.step_index = -2
        self.liftoff = np.zeros(3)       # swing ankle at lift-off, relative to the stance ankle (world axes)
        self.swing_yaw0 = 0.0
        self.velocity_bias = [0.0, 0.0]
        self.heading_reference.reset()
        self.landing = np.zeros(3)
        self.start_offset = None

    def _boost(self, stance_legs: tuple[int, ...]) -> np.ndarray:
        p = self.params
        boost = np.zeros(self.config.n_joints)
        for leg in (0, 1):
            if leg in stance_legs:
                boost[self.leg_joints[leg][:4]] = p.stance_stiffness_boost
            else:
                boost[self.leg_joints[leg][:4]] = p.swing_stiffness_boost
                boost[self.leg_joints[leg][4]] = p.swing_ankle_boost
        return boost

    # -- kinematics --------------------------------------------------------------------------------------
    def _kinematics(self, q: np.ndarray, quat: np.ndarray) -> None:
        kin = self.kin
        kin.qpos[3:7] = quat
        kin.qpos[self.qpos] = q
        mujoco.mj_kinematics(self.model, kin)
        mujoco.mj_comPos(self.model, kin)
        mujoco.mj_rne(self.model, kin, 0, self.gravity)  # at rest: the fixed-base gravity load of every joint

    def _support_torque(self, leg: int, share: float, com: np.ndarray) -> np.ndarray:
        """Joint torques of `leg` (hips and knee; the ankle is left to balance) that hold the robot's posture
        while that foot carries `share` of its weight: the fixed-base gravity load of the leg's own links, minus
        J^T of the ground wrench (share of m g up, and its moment about the ankle)."""
        kin = self.kin
        mujoco.mj_jacBody(self.model, kin, self.jacp, self.jacr, self.feet[leg])
        cols = self.dofs[self.leg_joints[leg]]
        force = share * self.mg
        arm = com - kin.xpos[self.feet[leg]]
        moment = (arm[1] * force, -arm[0] * force)  # (c - a) x (0, 0, F): no z component
        tau = self.gravity[cols] - (force * self.jacp[2, cols] + moment[0] * self.jacr[0, cols]
                                    + moment[1] * self.jacr[1, cols])
        tau[4] = 0.0
        return tau

    # -- the controller ----------------------------------------------------------------------------------
    def __call__(self, state: RobotState, base: BaseEstimate, command: np.ndarray) -> np.ndarray:
        p = self.params
        q = state.joints.q
        phase = self.clock.phase(self.clock.tick(command))
        step_time = phase.step_time
        growth = math.exp(self.omega * step_time)  # e^(omega T)
        self._kinematics(q, base.quat)
        kin = self.kin
        rot = kin.xmat[self.base].reshape(3, 3)  # base -> world-aligned axes
        ankles = [kin.xpos[f].copy() for f in self.feet]  # relative to the base origin, world axes
        com = kin.subtree_com[self.base].copy()
        # The base's velocity stands for the CoM's: counting the swing leg's own motion would feed it back into
        # its own landing point.
        com_velocity = rot @ base.linvel
        yaw = float(base.euler[2])
        cy, sy = math.cos(yaw), math.sin(yaw)
        forward = np.array([cy, sy, 0.0])  # the heading frame's axes in world axes
        side = np.array([-sy, cy, 0.0])
        # The command is followed at a bounded acceleration (the clock's, which the policy observes).
        vx, vy, wz = (float(c) for c in self.clock.command)
        # Velocity integral: model errors (pendulum vs multibody, foot, PD sag) bias the mean speed, so the
        # footstep plan aims at the command plus the integrated error of the measured base velocity.
        v_heading = (cy * com_velocity[0] + sy * com_velocity[1], -sy * com_velocity[0] + cy * com_velocity[1])
        if not phase.starting:
            for i, (cmd, meas) in enumerate(((vx, v_heading[0]), (vy, v_heading[1]))):
                self.velocity_bias[i] = min(p.velocity_bias_max, max(-p.velocity_bias_max, self.velocity_bias[i]
                                            + p.velocity_integral_gain * self.dt * (cmd - meas)))
        vx += self.velocity_bias[0] + interpolate(p.speed_feedforward, vx)
        vy += self.velocity_bias[1] + p.lateral_feedforward * vy

        heading = self.heading_reference.update(yaw, wz)
        q_des = np.empty(self.config.n_joints)
        qd_des = np.zeros(self.config.n_joints)
        tau_ff = np.zeros(self.config.n_joints)
        ankle_torque = np.full(self.config.n_joints, np.nan)  # where set: the ankle is a torque source
        stance_legs = (0, 1) if phase.starting else (phase.stance,)
        if phase.starting:
            # Both feet down: move the CoM toward the right foot, the first stance foot, so that the DCM is
            # where a periodic gait has it when the left foot lifts.
            offset = com - 0.5 * (ankles[0] + ankles[1])  # from the middle of the feet
            inner = p.step_width / (1.0 + growth)
            if self.start_offset is None:
                self.start_offset = float(offset @ side)
            target_lateral = -(0.5 * p.step_width - inner) * p.start_shift
            blend = min_jerk(phase.start_share / (1.0 - self.dt / phase.step_time))
            lateral = self.start_offset + blend * (target_lateral - self.start_offset)
            shift = (offset @ side - lateral) * side
            right_share = min(1.0, max(0.0, 0.5 - (offset @ side) / p.step_width))
            for leg in (0, 1):
                target = ankles[leg] + shift
                target[2] = -p.standing_height
                q_des[self.leg_joints[leg]] = self._stance_ik(leg, target, yaw, float(q[self.leg_joints[leg][0]]))
                share = right_share if leg == 0 else 1.0 - right_share
                tau_ff[self.leg_joints[leg]] = self._support_torque(leg, share, com)
            # Sagittal balance on two line feet: the ankles, as torque sources, keep the CoM over the feet.
            ahead = offset @ forward - p.foot_centre
            tau_ankle = -0.5 * self.mg * (p.ankle_position_gain * ahead
                                          + p.ankle_velocity_gain * com_velocity @ forward)
            ankle_torque[[self.leg_joints[0][4], self.leg_joints[1][4]]] = tau_ankle
        else:
            stance, swing = phase.stance, 1 - phase.stance
            if phase.step != self.step_index:
                self.step_index = phase.step
                self.liftoff = ankles[swing] - ankles[stance]
                self.swing_yaw0 = float(q[self.leg_joints[swing][0]])
            tau_s = phase.t_in_step / step_time
            # Stance: hold the base upright at the nominal height above the stance ankle; turn at wz.
            target = ankles[stance].copy()
            target[2] = -p.standing_height
            # The stance foot is fixed in the world, so turning it by the heading error turns the base back.
            heading_error = math.remainder(yaw - heading, math.tau)
            heading_error = min(p.heading_correction_max, max(-p.heading_correction_max, heading_error))
            stance_yaw = float(q[self.leg_joints[stance][0]]) + heading_error
            q_des[self.leg_joints[stance]] = self._stance_ik(stance, target, yaw, stance_yaw)
            tau_ff[self.leg_joints[stance]] = self._support_torque(stance, 1.0, com)
            tau_ff[self.leg_joints[swing]] = self.gravity[self.dofs[self.leg_joints[swing]]]
            qd_des[self.leg_joints[stance][0]] = -wz
            # Ankle strategy: the stance ankle, as a torque source, moves the centre of pressure within the foot
            # ahead of (behind) the foot centre when the DCM runs ahead of (behind) a periodic gait's.
            centre = ankles[stance] + p.foot_centre * forward
            dcm = com + com_velocity / self.omega
            xi = (dcm - centre) @ forward
            xi_nominal = vx * step_time / (growth - 1.0) * math.exp(self.omega * phase.t_in_step)
            cop = min(p.cop_front, max(-p.cop_back, p.cop_gain * (xi - xi_nominal)))
            ankle_torque[self.leg_joints[stance][4]] = -self.mg * (cop + p.foot_centre)
            # Footstep from the DCM.
            if tau_s <= p.replan_until:
                self.landing = self._landing(ankles[stance], centre, dcm, heading, phase, growth, swing,
                                             vx, vy, wz)
            # Swing trajectory relative to the stance ankle, then into the base frame at the measured attitude.
            # Land turned by half a step's turn ahead of the heading, so the stance foot turns symmetrically, but
            # never further than swing_yaw_max from the base: after a push has yawed the base, a foot landing
            # square to the heading is a large hip-yaw swing whose reaction spins the stance foot on its two contacts.
            swing_yaw_end = math.remainder(heading + wz * (phase.t_remaining + 0.5 * step_time) - yaw,
                                           math.tau)
            swing_yaw_end = min(p.swing_yaw_max, max(-p.swing_yaw_max, swing_yaw_end))
            legs = self.leg_joints[swing]

            def swing_joints(dt: float) -> np.ndarray:
                """Swing-leg joint targets dt from now: the stance ankle moves by -v dt relative to the base."""
                s = tau_s + dt / step_time
                yaw_blend = min_jerk(s)
                target = ankles[stance] - com_velocity * dt + self._swing_point(s)
                return np.array(self._swing_ik(swing, rot, target, yaw,
                                               self.swing_yaw0 + yaw_blend * (swing_yaw_end - self.swing_yaw0)))

            # Joint targets, rates and accelerations by central differences over one policy period; the
            # accelerations give the inertial feed-forward M q'' that the low Eq. 8 gains cannot supply in time.
            h = self.dt
            q_sw, q_next, q_prev = swing_joints(0.0), swing_joints(h), swing_joints(-h)
            q_des[legs] = q_sw
            qd_des[legs] = (q_next - q_prev) / (2 * h)
            self.qacc[:] = 0.0
            self.qacc[self.dofs[legs]] = (q_next - 2 * q_sw + q_prev) / (h * h)
            mujoco.mj_crb(self.model, kin)  # the joint-space inertia M(q), only needed here
            mujoco.mj_mulM(self.model, kin, self.inertial, self.qacc)
            tau_ff[legs] += p.swing_inertia_gain * self.inertial[self.dofs[legs]]
        # Extra stiffness on top of Eq. 8's: a further Kp * boost * (q_des - q) through a_t.
        a = q_des + self.boost[stance_legs] * (q_des - q) + (tau_ff + self.kd * qd_des) / self.kp
        torque_source = ~np.isnan(ankle_torque)
        a[torque_source] = q[torque_source] + (ankle_torque[torque_source] + self.kd[torque_source]
                                               * state.joints.qd[torque_source]) / self.kp[torque_source]
        return a

    def _landing(self, stance_ankle, centre, dcm, yaw, phase: GaitPhase, e: float, swing, vx, vy, wz) -> np.ndarray:
        """Swing ankle landing point relative to the stance ankle (world axes, z = 0: flat ground), from the DCM
        and the stance foot's centre (both relative to the base, world axes), with e = e^(omega T) of the step."""
        p = self.params
        t_remaining = phase.t_remaining
        xi_end = centre[:2] + (dcm[:2] - centre[:2]) * math.exp(self.omega * t_remaining)
        sign = 1.0 if swing == 1 else -1.0  # the left foot lands on the left
        T = phase.step_time
        bx = vx * T / (e - 1.0)
        by = -sign * p.step_width / (1.0 + e) + vy * T / (e - 1.0)
        heading = yaw + wz * t_remaining
        ch, sh = math.cos(heading), math.sin(heading)
        land = xi_end - np.array([ch * bx - sh * by, sh * bx + ch * by]) - p.foot_centre * np.array([ch, sh])
        rel = land - stance_ankle[:2]
        # Reachability, in the landing heading: forward and lateral bounds around the stance ankle.
        fwd = ch * rel[0] + sh * rel[1]
        lat = -sh * rel[0] + ch * rel[1]
        fwd = min(p.reach_forward, max(-p.reach_forward, fwd))
        lat = sign * min(p.width_max, max(p.width_min, sign * lat))
        return np.array([ch * fwd - sh * lat, sh * fwd + ch * lat, 0.0])

    def _swing_point(self, s: float) -> np.ndarray:
        """Swing ankle relative to the stance ankle at swing share s."""
        p = self.params
        h = min_jerk(s / p.swing_horizontal_end)
        z = swing_height(s, p.swing_apex, p.swing_landing)
        rel = self.liftoff + h * (self.landing - self.liftoff)
        rel[2] = self.liftoff[2] * (1.0 - h) + z
        return rel

    def _stance_ik(self, leg: int, target_world, yaw: float, hip_yaw: float):
        """IK for a stance ankle target given relative to the base in world axes, for an upright base with the
        measured heading: the joint PD then rights the torso."""
        c, s = math.cos(yaw), math.sin(yaw)
        x, y, z = target_world
        return leg_ik(self.geo[leg], (c * x + s * y, -s * x + c * y, z), hip_yaw, 0.0)

    def _swing_ik(self, leg: int, rot: np.ndarray, target_world, yaw: float, hip_yaw: float):
        """IK for a swing ankle target given relative to the base in world axes, at the measured attitude, with
        the sole level in the world."""
        local = rot.T @ target_world
        heading = yaw + hip_yaw
        slope = rot[0, 2] * math.cos(heading) + rot[1, 2] * math.sin(heading)
        return leg_ik(self.geo[leg], (float(local[0]), float(local[1]), float(local[2])), hip_yaw, slope)
