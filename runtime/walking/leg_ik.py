"""Analytic inverse kinematics of BRUCE's 5-DoF leg: hip yaw -> hip pitch -> hip roll -> knee -> ankle.

All three hip axes meet at one point (the hip), the knee and ankle axes are parallel to the pitch axis after
the roll, and the leg is planar after the roll. So, in the hip-yaw frame, the hip-to-ankle distance fixes the
knee, the lateral component fixes the roll, the sagittal angle fixes the pitch, and the ankle sets the sole's
pitch. The sole's roll follows from the others (no ankle roll: BRUCE's line feet cannot choose it).

Geometry comes from the MJCF (bodies `<side>_hip_yaw_link`, `<side>_shank`, `<side>_foot`), so the IK and the
simulated robot cannot disagree. Joint sign conventions are the model's: pitch, knee and ankle turn about -y,
roll about +x, yaw about +z; the knee bends with a negative angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

SIDES = ("r", "l")


@dataclass(frozen=True, slots=True)
class LegGeometry:
    hip: tuple[float, float, float]  # hip centre in the base frame (m)
    thigh: float                     # hip to knee (m)
    shank: float                     # knee to ankle (m)

    @property
    def reach(self) -> float:
        return self.thigh + self.shank


def leg_geometry(model: mujoco.MjModel, side: str) -> LegGeometry:
    """The leg's dimensions from the model (all joints at their body origins, bodies base-aligned at q = 0)."""
    hip = model.body_pos[model.body(f"{side}_hip_yaw_link").id]
    thigh = -float(model.body_pos[model.body(f"{side}_shank").id][2])
    shank = -float(model.body_pos[model.body(f"{side}_foot").id][2])
    return LegGeometry(hip=(float(hip[0]), float(hip[1]), float(hip[2])), thigh=thigh, shank=shank)


def leg_ik(geo: LegGeometry, ankle: tuple[float, float, float], yaw: float, sole_slope: float = 0.0
           ) -> tuple[float, float, float, float, float]:
    """(hip_yaw, hip_pitch, hip_roll, knee, ankle) putting the ankle at `ankle` (base frame, m), with the leg
    turned by `yaw` about the base z axis and the sole's forward axis at `sole_slope` (its z component in the
    base frame: 0 = level with the base, positive = toe up). Out-of-reach targets are brought back onto the
    workspace boundary (the leg straightens toward them) instead of failing."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy, dz = ankle[0] - geo.hip[0], ankle[1] - geo.hip[1], ankle[2] - geo.hip[2]
    x, y, z = c * dx + s * dy, -s * dx + c * dy, dz  # in the hip-yaw frame
    a3, a4 = geo.thigh, geo.shank
    dist = math.sqrt(x * x + y * y + z * z)
    longest = 0.999 * (a3 + a4)
    shortest = 1.001 * abs(a3 - a4)
    if dist > longest or dist < shortest:
        k = (longest if dist > longest else shortest) / max(dist, 1e-9)
        x, y, z = x * k, y * k, z * k
        dist *= k
    cos_knee = (dist * dist - a3 * a3 - a4 * a4) / (2.0 * a3 * a4)
    knee = -math.acos(max(-1.0, min(1.0, cos_knee)))
    vx = a4 * math.sin(knee)             # the ankle in the thigh's (rolled) frame: (vx, 0, vz)
    vz = -a3 - a4 * math.cos(knee)
    roll = math.asin(max(-1.0, min(1.0, -y / vz)))
    w = vz * math.cos(roll)
    pitch = math.atan2(z, x) - math.atan2(w, vx)
    pitch = math.remainder(pitch, math.tau)
    # The sole's forward axis has z component sin(p) cos(b) + cos(p) cos(roll) sin(b) in the hip-yaw frame,
    # with b = knee + ankle: of the two solutions take the one nearest the planar leg's, asin(slope) - p.
    A, B = math.sin(pitch), math.cos(pitch) * math.cos(roll)
    delta = math.atan2(B, A)
    spread = math.acos(max(-1.0, min(1.0, sole_slope / math.hypot(A, B))))
    planar = math.asin(max(-1.0, min(1.0, sole_slope))) - pitch
    b = min((delta - spread, delta + spread), key=lambda v: abs(math.remainder(v - planar, math.tau)))
    ankle_angle = math.remainder(b - knee, math.tau)
    return yaw, pitch, roll, knee, ankle_angle


def leg_fk(geo: LegGeometry, joints) -> np.ndarray:
    """Ankle position in the base frame for (hip_yaw, hip_pitch, hip_roll, knee, ankle); the IK's inverse."""
    yaw, pitch, roll, knee, _ = joints
    vx = geo.shank * math.sin(knee)
    vz = -geo.thigh - geo.shank * math.cos(knee)
    w = vz * math.cos(roll)
    x = vx * math.cos(pitch) - w * math.sin(pitch)
    z = vx * math.sin(pitch) + w * math.cos(pitch)
    y = -vz * math.sin(roll)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([geo.hip[0] + c * x - s * y, geo.hip[1] + s * x + c * y, geo.hip[2] + z])
