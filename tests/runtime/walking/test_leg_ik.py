import math

import mujoco
import numpy as np
import pytest

from bruce_hw.config import load_config
from runtime.walking.gait import COMMAND_ACCELERATION, GaitClock, gait_period, gait_phase, min_jerk, swing_height
from runtime.walking.leg_ik import SIDES, leg_fk, leg_geometry, leg_ik


@pytest.fixture(scope="module")
def model():
    return mujoco.MjModel.from_xml_path(str(load_config().mjcf))


@pytest.mark.parametrize("side", SIDES)
def test_ik_inverts_the_models_forward_kinematics(model, side):
    """Random leg poses (sole within 0.6 rad of level): MuJoCo's ankle position and sole slope -> IK -> the pose."""
    data = mujoco.MjData(model)
    geo = leg_geometry(model, side)
    adr = model.jnt_qposadr[model.joint(f"{side}_hip_yaw").id]
    foot = model.body(f"{side}_foot").id
    rng = np.random.default_rng(7)
    for _ in range(300):
        joints = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 1.2), rng.uniform(-0.4, 0.4),
                           rng.uniform(-2.0, -0.2), 0.0])
        joints[4] = -(joints[1] + joints[3]) + rng.uniform(-0.6, 0.6)
        data.qpos[:] = 0.0
        data.qpos[3] = 1.0
        data.qpos[adr:adr + 5] = joints
        mujoco.mj_kinematics(model, data)
        ankle = data.xpos[foot]
        np.testing.assert_allclose(leg_fk(geo, joints), ankle, atol=1e-9)
        slope = data.xmat[foot].reshape(3, 3)[2, 0]  # z of the sole's forward axis
        np.testing.assert_allclose(leg_ik(geo, tuple(ankle), joints[0], slope), joints, atol=1e-7)


def test_ik_of_the_standing_pose_matches_the_config(model, config):
    geo = leg_geometry(model, "r")
    stand = config.standing_pose[:5]
    ankle = leg_fk(geo, stand)
    np.testing.assert_allclose(leg_ik(geo, tuple(ankle), stand[0], 0.0)[1:4], stand[1:4], atol=1e-3)


def test_out_of_reach_targets_straighten_the_leg_toward_them(model):
    geo = leg_geometry(model, "l")
    far = (geo.hip[0] + 0.1, geo.hip[1], geo.hip[2] - 1.0)
    joints = leg_ik(geo, far, 0.0, 0.0)
    assert all(math.isfinite(j) for j in joints)
    assert joints[3] == pytest.approx(0.0, abs=0.1)  # knee nearly straight
    reached = leg_fk(geo, joints) - np.array(geo.hip)
    direction = np.subtract(far, geo.hip)
    cos = reached @ direction / np.linalg.norm(reached) / np.linalg.norm(direction)
    assert cos > 0.999


def test_gait_phase_alternates_steps_after_one_start_up_period():
    period = 0.4
    assert gait_phase(0.25, period).starting and gait_phase(0.25, period).start_share == 0.25
    first = gait_phase(1.0 + 0.01 / period, period)
    second = gait_phase(1.5 + 0.01 / period, period)
    assert (first.step, first.stance) == (0, 0) and (second.step, second.stance) == (1, 1)
    assert first.t_in_step == pytest.approx(0.01) and first.step_time == pytest.approx(0.5 * period)
    assert first.t_in_step + first.t_remaining == pytest.approx(0.5 * period)


def test_gait_clock_cadence_interpolates_the_table_and_holds_beyond_it():
    cadence = ((-0.5, 0.44), (0.0, 0.36), (0.8, 0.26))
    assert gait_period(cadence, 0.4) == pytest.approx(0.31)
    assert gait_period(cadence, -1.0) == 0.44 and gait_period(cadence, 1.0) == 0.26
    clock = GaitClock(cadence, 0.01)
    command = np.array([0.8, -0.2, 0.5])
    ticks = [clock.tick(command)]
    # the followed command moves toward the command at the bounded acceleration (policy ticks of 0.01 s)...
    np.testing.assert_allclose(clock.command, 0.01 * COMMAND_ACCELERATION * np.sign(command), rtol=1e-12)
    ticks += [clock.tick(command) for _ in range(299)]
    np.testing.assert_allclose(clock.command, command)  # ... and holds it once reached
    assert ticks[0] == 0.0 and clock.period == pytest.approx(0.26)  # 0.8 m/s reached after 1.6 s
    assert ticks[-1] - ticks[-2] == pytest.approx(0.01 / 0.26)
    assert clock.phase(ticks[-1]).step_time == pytest.approx(0.13)


def test_swing_profiles_start_and_end_at_rest():
    h = 1e-6
    for s in (h, 1.0 - h):  # one-sided slopes at the ends, inside the clamp
        assert (min_jerk(s + h) - min_jerk(s - h)) / (2 * h) == pytest.approx(0.0, abs=1e-5)
        assert (swing_height(s + h, 0.04, -0.004) - swing_height(s - h, 0.04, -0.004)) / (2 * h) == \
            pytest.approx(0.0, abs=1e-5)
    assert swing_height(0.5, 0.04, 0.0) == pytest.approx(0.04)
    assert swing_height(1.0, 0.04, -0.004) == pytest.approx(-0.004)
