"""The real robot's base state estimator (`KinematicEstimator`): an IMU attitude filter and a leg-odometry Kalman
filter on the base velocity, fed only what a real BRUCE measures (joints, the IMU's gyro and specific force, four
toe/heel contact switches; the sense board gives no orientation).

- Attitude: `bruce_hw.attitude.MahonyAttitude` on gravity = the specific force less the velocity filter's own
  acceleration, whose slow part is the leg odometry's, so walking's accelerations do not bias the tilt; yaw starts
  at 0 and is never corrected (nothing on the robot observes heading). `estimate` carries it over the IMU's delay.
- Optionally (`estimator.level_from_feet_s`), levelled from the feet at start-up: the accelerometer's horizontal
  bias learned while both feet are flat, from the feet plane's normal (`_level`).
- Velocity, in the yaw-relative world frame: the accelerometer integrated, v += (R a - g) dt, and each toe or heel
  sphere whose switch is closed a measurement: its lowest point is at rest, so the base moves at v = -R (J(q) qd +
  w x r), from the robot's own MJCF with the base at the origin; a sphere that has just touched down counts less.
  Isotropic noise keeps the covariance a multiple of the identity: three scalar filters, in scalar math at 1 kHz.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from bruce_hw.attitude import MAX_IMU_GAP_S, MahonyAttitude
from bruce_hw.config import RobotConfig
from bruce_hw.quaternion import euler_of, rotate_to_body, rotation_entries
from bruce_hw.types import FOOT_CONTACT_NAMES, RobotState
from runtime.estimation import BaseEstimate

# -- velocity Kalman filter ------------------------------------------------------------------------------
# ODOMETRY_STD, m/s: one-sample (1 kHz) standard deviation of a leg-odometry velocity. Our assumption, not a
# measurement: encoder-differentiated joint velocities (~0.05 rad/s each over ~0.4 m of leg) plus the foot
# rolling and compressing.
ODOMETRY_STD = 0.1
# VELOCITY_RANDOM_WALK, (m/s)^2 per s: variance growth from integrating the accelerometer, whose errors are
# slow. It sets the filter's time constant tau (q = ODOMETRY_STD^2 dt / tau^2): a slow acceleration error b costs
# ~b tau, odometry noise ~ODOMETRY_STD sqrt(dt / 2 tau). The attitude is corrected with this filter's
# acceleration, which turns a horizontal accelerometer bias into tilt, so b is what is left: the vertical bias and
# the tilt's residual error (0.1 deg ~ 0.017 m/s^2), ~0.02 m/s^2; the sum is smallest near tau = 140 ms, q = 0.0005
# (one foot on the ground: 140 ms, both: 100 ms). The odometry's errors are not white either (a landing's tail, a
# stance foot creeping, a sole compressing: tens of ms each), and tau averages them. Other values tried:
# docs/results/walking.md.
VELOCITY_RANDOM_WALK = 0.0005
# A sphere whose switch has just closed is still moving: the foot lands with some speed, compresses, bounces and
# slides before it settles. Its odometry's error, added in quadrature to ODOMETRY_STD, is taken as
# TOUCHDOWN_SPEED e^(-t / TOUCHDOWN_TAU), t the time since that switch closed. Measured on the mock walking at
# 0.4 m/s (the point's own speed, which is the odometry's error, by time since the heel closed): 1.1 m/s over the
# first 10 ms, 0.38, 0.13, 0.045, 0.018 over the next 10 ms windows, and the toe sinks at ~0.2 m/s for ~20 ms after
# it closes behind the heel: an exponential decay, since a flat window lets the tail in at full weight.
TOUCHDOWN_SPEED = 2.0  # m/s
TOUCHDOWN_TAU = 0.01   # s
# m/s, standard deviation of the velocity at reset (the robot is at rest, up to sway).
RESET_VELOCITY_STD = 0.01
# -- attitude --------------------------------------------------------------------------------------------
# s, how old the IMU's motion is when the loop reads it: the estimate's attitude is carried forward over it at the
# measured rate. On the robot, the ISM330DHCX's 5-sample average at 1.66 kHz (~1.2 ms of group delay) and the bulk
# read's trip back through the FTDI latency timer (~1 ms; configs/gaps/default.yaml's sensor latency): ~2 ms. The
# nominal mock's IMU is 1 ms old (it computes its sensors before the physics step whose time they carry), the
# default gap's 2 ms. The walking policy is sensitive to this lag (docs/results/walking.md).
IMU_DELAY_S = 0.002
# -- levelling from the feet (config estimator.level_from_feet_s) -----------------------------------------------
# While all four toe and heel spheres have been on the ground for more than LEVEL_SETTLE_TICKS, the plane through
# their centres (equal radii) is parallel to the floor: its normal n is world-up in the base frame, from the joints
# alone. The accelerometer's horizontal bias b then follows from f = g n + R^T a + b (a: the filter's own base
# acceleration), low-passed with LEVEL_TIME_CONSTANT_S; every sample is used as f - b. Learned only in the first
# `level_from_feet_s` after start-up: during walking the four switches are rarely closed together, and the few
# double-support moments of a gapped robot's gait gave wrong values (docs/transfer.md, "Levelling from the feet").
LEVEL_SETTLE_TICKS = 3
LEVEL_TIME_CONSTANT_S = 0.1
# Steps of `plane_normal`'s refinement at most: four points with no plane to speak of (spread as much across
# as along) converge slowly, and their normal is arbitrary anyway.
PLANE_NORMAL_MAX_STEPS = 50
LEVEL_BIAS_LIMIT = 0.5  # m/s^2: a learned bias is clipped here (an accelerometer further off is broken, not biased)

FEET = (("r_toe", "r_heel"), ("l_toe", "l_heel"))  # per foot, its toe and heel contact/geom names


@dataclass(frozen=True, slots=True)
class EstimatorSnapshot:
    """A `KinematicEstimator`'s state at one tick, and its estimate then (what a robot knows of its base)."""

    quat: tuple[float, float, float, float]
    gyro_bias: tuple[float, float, float]
    angvel: tuple[float, float, float]
    velocity: tuple[float, float, float]      # m/s, the estimator's (yaw-relative) world frame
    acceleration: tuple[float, float, float]
    variance: float
    feet: tuple[tuple[int, int], ...]         # per foot, ticks since its toe and heel switches closed
    estimate: BaseEstimate                    # carried over the IMU's delay, as the controller sees it


def _index(indices: list[int]) -> slice | np.ndarray:
    """The indices as a slice when they are contiguous: assigning through a slice costs a third of the time."""
    if indices == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return np.array(indices)


def plane_normal(a: list[float], b: list[float], c: list[float], d: list[float]) -> tuple[float, float, float]:
    """The unit normal of the least-squares plane through four points (sign arbitrary), in scalar math: the same
    normal as the SVD of the centred points (the right singular vector of the smallest singular value), to
    round-off. Newell's normal of the quadrilateral a b c d (half the cross product of its diagonals: exact when
    the four are coplanar) is refined by the adjugate of their scatter matrix S until it stops changing: adj(S) =
    det(S) S^-1 weighs S's eigenvectors by the product of the other two eigenvalues, so each step divides the error's
    angle by lambda_mid / lambda_min (the in-plane spread over the out-of-plane one, squared; BRUCE's feet standing on
    the mock, nominal to `harsh` gap: 2-5 steps to the last bit), and a rank-2 S (coplanar points) needs no inverse.
    Four collinear points have no plane (S of rank 1, adj(S) = 0): Newell's vector comes back as it is."""
    mx, my, mz = ((a[0] + b[0] + c[0] + d[0]) * 0.25, (a[1] + b[1] + c[1] + d[1]) * 0.25,
                  (a[2] + b[2] + c[2] + d[2]) * 0.25)
    sxx = sxy = sxz = syy = syz = szz = 0.0
    for px, py, pz in (a, b, c, d):
        px, py, pz = px - mx, py - my, pz - mz
        sxx += px * px
        sxy += px * py
        sxz += px * pz
        syy += py * py
        syz += py * pz
        szz += pz * pz
    # Newell's normal: (c - a) x (d - b)
    ux, uy, uz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    vx, vy, vz = d[0] - b[0], d[1] - b[1], d[2] - b[2]
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    # adj(S), symmetric and positive semi-definite (as S is): a step never flips the normal
    axx, ayy, azz = syy * szz - syz * syz, sxx * szz - sxz * sxz, sxx * syy - sxy * sxy
    axy, axz, ayz = sxz * syz - sxy * szz, sxy * syz - sxz * syy, sxy * sxz - sxx * syz
    for _ in range(PLANE_NORMAL_MAX_STEPS):
        x, y, z = axx * nx + axy * ny + axz * nz, axy * nx + ayy * ny + ayz * nz, axz * nx + ayz * ny + azz * nz
        norm = math.sqrt(x * x + y * y + z * z)
        if norm == 0.0:  # collinear points: no plane to refine to (feet never are)
            break
        x, y, z = x / norm, y / norm, z / norm
        change = (x - nx) ** 2 + (y - ny) ** 2 + (z - nz) ** 2
        nx, ny, nz = x, y, z
        if change < 1e-30:  # moved less than 1e-15 rad: converged to round-off
            break
    return nx, ny, nz


class _Foot:
    """One foot's contact switches, the spheres they sit on, and how long each has been on the ground."""

    def __init__(self, model: mujoco.MjModel, toe: str, heel: str):
        self.toe_switch, self.heel_switch = FOOT_CONTACT_NAMES.index(toe), FOOT_CONTACT_NAMES.index(heel)
        self.toe_geom, self.heel_geom = model.geom(toe).id, model.geom(heel).id
        self.body = int(model.geom_bodyid[self.toe_geom])
        if int(model.geom_bodyid[self.heel_geom]) != self.body:
            raise ValueError(f"MJCF: geoms {toe!r} and {heel!r} must be on the same foot body")
        self.toe_radius = float(model.geom_size[self.toe_geom][0])
        self.heel_radius = float(model.geom_size[self.heel_geom][0])
        self.toe_ticks = self.heel_ticks = 0  # ticks since that switch closed; 0: open


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
        self.level_geoms = tuple((foot.toe_geom, foot.heel_geom) for foot in self.feet)
        self.gravity = float(-model.opt.gravity[2])
        # Odometry variance by ticks since a switch closed (1: just closed), up to where the touchdown's share has
        # fallen below 1 % of ODOMETRY_STD^2; settled beyond.
        tau = TOUCHDOWN_TAU * config.loop_hz
        self.settle_ticks = max(1, math.ceil(tau * math.log(10.0 * TOUCHDOWN_SPEED / ODOMETRY_STD)))
        self.odometry_variance = ODOMETRY_STD ** 2
        self.touchdown_variance = [0.0] + [ODOMETRY_STD ** 2 + (TOUCHDOWN_SPEED * math.exp(-(k - 1) / tau)) ** 2
                                           for k in range(1, self.settle_ticks + 1)]
        self.attitude = MahonyAttitude(self.gravity)
        self.level_ticks = round(config.estimator.level_from_feet_s * config.loop_hz)
        self.level_gain = 1.0 / (LEVEL_TIME_CONSTANT_S * config.loop_hz)
        self.accel_bias = (0.0, 0.0)  # m/s^2, x and y in the IMU frame (learned by levelling from the feet)
        self.ticks = 0                # updates since reset
        self.stamp = 0.0
        self.velocity = (0.0, 0.0, 0.0)        # m/s, world frame
        self.acceleration = (0.0, 0.0, 0.0)    # m/s^2, world frame: the estimated velocity's last change per s
        self.variance = RESET_VELOCITY_STD ** 2  # (m/s)^2, per axis

    def reset(self, state: RobotState) -> None:
        """At rest: zero velocity, attitude levelled from the specific force (`MahonyAttitude.reset`)."""
        self.attitude.reset(state.imu.gyro, state.imu.accel, state.imu.stamp)
        self.stamp = state.imu.stamp
        self.velocity = (0.0, 0.0, 0.0)
        self.acceleration = (0.0, 0.0, 0.0)
        self.variance = RESET_VELOCITY_STD ** 2
        self.accel_bias = (0.0, 0.0)
        self.ticks = 0
        contact = state.contacts.contact.tolist()
        settled = self.settle_ticks + 1
        for foot in self.feet:  # spheres already down at reset are settled, not touching down
            foot.toe_ticks = settled if contact[foot.toe_switch] else 0
            foot.heel_ticks = settled if contact[foot.heel_switch] else 0

    def update(self, state: RobotState) -> None:
        """One tick: attitude from the gyro and accelerometer, velocity predicted from the accelerometer, then
        corrected by the odometry of each foot on the ground."""
        imu = state.imu
        dt = min(max(imu.stamp - self.stamp, 0.0), MAX_IMU_GAP_S)
        self.stamp = imu.stamp
        self.ticks += 1
        accel = imu.accel
        bx, by = self.accel_bias
        if bx or by:
            accel = accel - np.array((bx, by, 0.0))
        # The attitude's gravity measurement is the specific force less the base's acceleration, the last tick's
        # change of the velocity estimate (whose slow part is the leg odometry's, free of the attitude's error).
        quat = self.attitude.update(imu.gyro, accel, imu.stamp, self.acceleration)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation_entries(quat)
        gx, gy, gz = self.attitude.angvel  # bias removed
        ax, ay, az = accel.tolist()

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
        settle_ticks, touchdown_variance = self.settle_ticks, self.touchdown_variance
        for foot in self.feet:
            toe, heel = contact[foot.toe_switch], contact[foot.heel_switch]
            foot.toe_ticks = foot.toe_ticks + 1 if toe else 0
            foot.heel_ticks = foot.heel_ticks + 1 if heel else 0
            if not (toe or heel):
                continue
            if not kinematics_done:
                kin.qpos[self.leg_qpos] = state.joints.q
                mujoco.mj_kinematics(self.model, kin)
                mujoco.mj_comPos(self.model, kin)  # mj_jac needs the dof axes it computes
                self.qvel[self.leg_dofs] = state.joints.qd
                kinematics_done = True
            # The point at rest: the lowest point of the sphere on the ground, its centre plus its radius along
            # "down" in the base frame (minus row 2 of R). Both spheres on the ground: their points averaged with
            # weights 1 / variance (a sphere that has just landed counts little next to a settled one), and the
            # smaller variance: the two share the joints' errors, so together they are no better than the better.
            if toe:
                toe_variance = touchdown_variance[foot.toe_ticks] if foot.toe_ticks <= settle_ticks \
                    else self.odometry_variance
            if heel:
                heel_variance = touchdown_variance[foot.heel_ticks] if foot.heel_ticks <= settle_ticks \
                    else self.odometry_variance
            if toe and heel:
                tx, ty, tz = kin.geom_xpos[foot.toe_geom].tolist()
                hx, hy, hz = kin.geom_xpos[foot.heel_geom].tolist()
                share = heel_variance / (toe_variance + heel_variance)  # the toe's weight
                radius = foot.heel_radius + share * (foot.toe_radius - foot.heel_radius)
                fx, fy, fz = hx + share * (tx - hx), hy + share * (ty - hy), hz + share * (tz - hz)
                measurement_variance = min(toe_variance, heel_variance)
            elif toe:
                fx, fy, fz = kin.geom_xpos[foot.toe_geom].tolist()
                radius, measurement_variance = foot.toe_radius, toe_variance
            else:
                fx, fy, fz = kin.geom_xpos[foot.heel_geom].tolist()
                radius, measurement_variance = foot.heel_radius, heel_variance
            fx, fy, fz = fx - radius * r20, fy - radius * r21, fz - radius * r22
            point = self.point
            point[0], point[1], point[2] = fx, fy, fz
            mujoco.mj_jac(self.model, kin, self.jacp, None, point, foot.body)
            jx, jy, jz = (self.jacp @ self.qvel).tolist()  # the point's velocity relative to the base
            # Base velocity in the base frame: -(J qd + w x r); then rotated to the world.
            mx, my, mz = -(jx + gy * fz - gz * fy), -(jy + gz * fx - gx * fz), -(jz + gx * fy - gy * fx)
            gain = variance / (variance + measurement_variance)
            px += gain * (r00 * mx + r01 * my + r02 * mz - px)
            py += gain * (r10 * mx + r11 * my + r12 * mz - py)
            pz += gain * (r20 * mx + r21 * my + r22 * mz - pz)
            variance *= 1.0 - gain
        if dt > 0.0:
            vx, vy, vz = self.velocity
            self.acceleration = ((px - vx) / dt, (py - vy) / dt, (pz - vz) / dt)
        self.velocity = (px, py, pz)
        self.variance = variance
        if self.ticks <= self.level_ticks and all(
                foot.toe_ticks > LEVEL_SETTLE_TICKS and foot.heel_ticks > LEVEL_SETTLE_TICKS for foot in self.feet):
            self._level(imu.accel.tolist(), (r00, r01, r10, r11, r20, r21))

    def _level(self, specific_force: list[float], rotation: tuple[float, ...]) -> None:
        """One levelling step (both feet flat; the kinematics at this tick's joints are in `kin`). `rotation`: the
        entries r00, r01, r10, r11, r20, r21 of the attitude's rotation (base to world), those the horizontal
        components of R^T a need. Scalar math: on the robot's first second every tick runs it, and numpy's calls
        (an SVD, two clips) cost ~27 µs warm and several times that on the control thread's cold caches."""
        xpos = self.kin.geom_xpos
        (right_toe, right_heel), (left_toe, left_heel) = self.level_geoms
        nx, ny, nz = plane_normal(xpos[right_toe].tolist(), xpos[right_heel].tolist(), xpos[left_heel].tolist(),
                                  xpos[left_toe].tolist())
        if nz < 0.0:
            nx, ny = -nx, -ny
        r00, r01, r10, r11, r20, r21 = rotation
        ax, ay, az = self.acceleration
        g = self.gravity
        seen_x = specific_force[0] - g * nx - (r00 * ax + r10 * ay + r20 * az)
        seen_y = specific_force[1] - g * ny - (r01 * ax + r11 * ay + r21 * az)
        bx, by = self.accel_bias
        k = self.level_gain
        self.accel_bias = (min(max(bx + k * (seen_x - bx), -LEVEL_BIAS_LIMIT), LEVEL_BIAS_LIMIT),
                           min(max(by + k * (seen_y - by), -LEVEL_BIAS_LIMIT), LEVEL_BIAS_LIMIT))

    def snapshot(self) -> EstimatorSnapshot:
        """The filter's whole state (a few numbers: cheap enough for the control thread at a resync)."""
        attitude = self.attitude
        return EstimatorSnapshot(attitude.quat, attitude.gyro_bias, attitude.angvel, self.velocity,
                                 self.acceleration, self.variance,
                                 tuple((foot.toe_ticks, foot.heel_ticks) for foot in self.feet), self.estimate())

    def restore(self, snapshot: EstimatorSnapshot, stamp: float) -> None:
        """Continue from `snapshot` (another estimator's, e.g. the robot's for its twin), on a clock whose last
        sample was at `stamp`."""
        attitude = self.attitude
        attitude.quat, attitude.gyro_bias, attitude.angvel = snapshot.quat, snapshot.gyro_bias, snapshot.angvel
        attitude.stamp = self.stamp = stamp
        self.velocity, self.acceleration, self.variance = snapshot.velocity, snapshot.acceleration, snapshot.variance
        for foot, (toe, heel) in zip(self.feet, snapshot.feet, strict=True):
            foot.toe_ticks, foot.heel_ticks = toe, heel

    def estimate(self) -> BaseEstimate:
        quat = np.array(self.attitude.quat)
        angvel = np.array(self.attitude.angvel)
        mujoco.mju_quatIntegrate(quat, angvel, IMU_DELAY_S)  # to the time the state was read (body-frame rate)
        return BaseEstimate(quat=quat, linvel=rotate_to_body(quat, np.array(self.velocity)), angvel=angvel,
                            euler=euler_of(quat))
