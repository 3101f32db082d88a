"""The base's attitude from a gyro and an accelerometer: a Mahony complementary filter.

The gyro is integrated; roll and pitch are pulled towards the measured up direction (the specific force's), and
the same error is integrated into a gyro bias. The pull fades as |a| leaves g, so landings and the motors'
reaction forces do not tilt it. A caller that estimates the base's own acceleration (the kinematic estimator, from
leg odometry) passes it to `update`, and the specific force less it is then taken in without the fade, which is
biased while walking. Heading comes from the gyro alone and drifts: gravity does not observe it.
One filter for every consumer: the hw backend (which fills `ImuSample.orientation` for a sense board that has
none) and the kinematic base estimator.
"""

from __future__ import annotations

import math

import numpy as np

from bruce_hw.quaternion import roll_pitch_quaternion, rotation_entries, world_z_in_body
from bruce_hw.types import GRAVITY

# rad/s of correction per rad of tilt error: a ~3 s time constant, long next to a step (0.1-0.3 s), so the
# horizontal accelerations of walking and pushes (which |a| barely shows) average out, short next to the
# drift of a gyro bias (minutes); a shorter one lets walking's sway leak into the roll estimate
# (docs/results/walking.md).
ATTITUDE_GAIN = 0.3
# 1/s^2, integral of the same error into the gyro bias: poles at -0.04 and -0.26 1/s with the gain above, so a
# bias is learned in ~30 s without overshoot, and the gait's periodic tilt error does not wind it up. A heading
# bias is not observable from gravity and stays.
GYRO_BIAS_GAIN = 0.01
# The accelerometer's weight falls linearly from 1 at |a| = g to 0 at |a| = g (1 +- ACCEL_TRUST_BAND). In the
# mock, standing stays within 1 % of g and 5 N pushes within 7 %; a landing reaches several g.
ACCEL_TRUST_BAND = 0.2
# s, the longest gap between IMU samples integrated as one step: a single sample says little about a longer
# stall, and integrating it over the whole gap would jolt the estimate.
MAX_IMU_GAP_S = 0.01


class MahonyAttitude:
    def __init__(self, gravity: float = GRAVITY):
        self.gravity = gravity
        self.quat = (1.0, 0.0, 0.0, 0.0)      # (w, x, y, z), IMU (base) -> world
        self.gyro_bias = (0.0, 0.0, 0.0)     # rad/s
        self.angvel = (0.0, 0.0, 0.0)        # rad/s, body frame, bias removed
        self.stamp: float | None = None

    def accel_trust(self, norm: float) -> float:
        """Weight of the accelerometer's direction as the up direction, for a specific force of magnitude `norm`
        (<= 0: not used)."""
        return 1.0 - abs(norm - self.gravity) / (ACCEL_TRUST_BAND * self.gravity)

    def reset(self, gyro: np.ndarray, accel: np.ndarray, stamp: float) -> None:
        """At rest: roll and pitch from the specific force, yaw 0, no gyro bias. A specific force far from g (the
        mock's first tick, while its contacts settle) says nothing about tilt: start level."""
        ax, ay, az = (float(v) for v in accel)
        roll = pitch = 0.0
        if self.accel_trust(math.sqrt(ax * ax + ay * ay + az * az)) > 0.0:
            roll = math.atan2(ay, az)
            pitch = math.atan2(-ax, math.hypot(ay, az))
        self.quat = roll_pitch_quaternion(roll, pitch)
        self.gyro_bias = (0.0, 0.0, 0.0)
        self.angvel = tuple(float(v) for v in gyro)
        self.stamp = stamp

    def update(self, gyro: np.ndarray, accel: np.ndarray, stamp: float,
               linear_accel: tuple[float, float, float] | None = None) -> tuple[float, float, float, float]:
        """Advance to this sample (a repeated or older sample integrates nothing); the orientation (w, x, y, z).

        `linear_accel`: the base's own acceleration (world frame, m/s^2) where another estimate has it (the
        kinematic estimator's, from leg odometry). The specific force minus it is then gravity alone, and it is
        taken in linearly, at every magnitude and without normalising: its mean over a gait is gravity's direction.
        Without it, the specific force's direction is faded by |a| (`accel_trust`), which is biased while walking:
        the fade keeps some phases of the step and drops others."""
        if self.stamp is None:
            self.reset(gyro, accel, stamp)
        dt = min(max(stamp - self.stamp, 0.0), MAX_IMU_GAP_S)
        self.stamp = max(stamp, self.stamp)
        bx, by, bz = self.gyro_bias
        gx, gy, gz = gyro.tolist()
        gx, gy, gz = gx - bx, gy - by, gz - bz
        self.angvel = (gx, gy, gz)
        if dt <= 0.0:
            return self.quat
        w, x, y, z = quat = self.quat
        ax, ay, az = accel.tolist()
        if linear_accel is None:
            vx, vy, vz = world_z_in_body(quat)  # the estimated up
            norm = math.sqrt(ax * ax + ay * ay + az * az)
            trust = self.accel_trust(norm)
            if trust > 0.0:
                ux, uy, uz = ax / norm, ay / norm, az / norm
        else:
            # The specific force less the base's acceleration (R^T of it), in g; R's last row is the estimated up.
            r00, r01, r02, r10, r11, r12, vx, vy, vz = rotation_entries(quat)
            lx, ly, lz = linear_accel
            k = 1.0 / self.gravity
            ux = k * (ax - (r00 * lx + r10 * ly + vx * lz))
            uy = k * (ay - (r01 * lx + r11 * ly + vy * lz))
            uz = k * (az - (r02 * lx + r12 * ly + vz * lz))
            trust = 1.0
        cx, cy, cz = gx, gy, gz
        if trust > 0.0:
            ex, ey, ez = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx  # u x v: turns v towards u
            k = GYRO_BIAS_GAIN * trust * dt
            self.gyro_bias = (bx - k * ex, by - k * ey, bz - k * ez)
            k = ATTITUDE_GAIN * trust
            cx, cy, cz = cx + k * ex, cy + k * ey, cz + k * ez
        h = 0.5 * dt
        w, x, y, z = (w - h * (x * cx + y * cy + z * cz), x + h * (w * cx + y * cz - z * cy),
                      y + h * (w * cy - x * cz + z * cx), z + h * (w * cz + x * cy - y * cx))
        n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
        self.quat = (w * n, x * n, y * n, z * n)
        return self.quat
