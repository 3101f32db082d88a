import mujoco
import numpy as np
import pytest

LEG = ("hip_yaw", "hip_pitch", "hip_roll", "knee", "ankle")


@pytest.fixture(scope="module")
def model(config):
    return mujoco.MjModel.from_xml_path(str(config.mjcf))


def test_total_mass_is_bruces_published_mass(model):
    assert model.body_subtreemass[0] == pytest.approx(4.45, abs=0.1)


def test_simulation_options(model):
    assert model.opt.timestep == 0.001
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST


def test_hip_chain_is_yaw_pitch_roll_then_knee_and_ankle(model, config):
    for side in ("r", "l"):
        bodies = [model.jnt_bodyid[model.joint(f"{side}_{j}").id] for j in LEG]
        for parent, child in zip(bodies, bodies[1:], strict=False):
            assert model.body_parentid[child] == parent
    axes = {j: model.jnt_axis[model.joint(f"r_{j}").id] for j in LEG}
    np.testing.assert_allclose(axes["hip_yaw"], [0, 0, 1])
    np.testing.assert_allclose(axes["hip_pitch"], [0, -1, 0])
    np.testing.assert_allclose(axes["hip_roll"], [1, 0, 0])


def test_joints_limits_armature_and_motors_match_the_config(model, config):
    for i, name in enumerate(config.joints):
        jid = model.joint(name).id
        np.testing.assert_allclose(model.jnt_range[jid], [config.q_lower[i], config.q_upper[i]])
        assert model.dof_armature[model.jnt_dofadr[jid]] == pytest.approx(0.0018)
        np.testing.assert_allclose(model.actuator(name).ctrlrange, [-config.tau_limit[i], config.tau_limit[i]])


def test_only_the_feet_collide_and_only_with_the_floor(model):
    colliding = {model.geom(g).name for g in range(model.ngeom)
                 if model.geom_contype[g] or model.geom_conaffinity[g]}
    assert colliding == {"floor", "r_toe", "r_heel", "l_toe", "l_heel"}
    feet = [model.geom(n).id for n in ("r_toe", "r_heel", "l_toe", "l_heel")]
    for a in feet:
        for b in feet:  # feet never collide with each other
            assert not (model.geom_contype[a] & model.geom_conaffinity[b])


def test_standing_pose_puts_the_ankles_where_bruce_op_does(model, config):
    data = mujoco.MjData(model)
    data.qpos[3] = 1.0
    for i, name in enumerate(config.joints):
        data.qpos[model.jnt_qposadr[model.joint(name).id]] = config.standing_pose[i]
    mujoco.mj_kinematics(model, data)
    base = data.xpos[model.body("base").id]
    for side, y in (("r", -0.07), ("l", 0.07)):
        ankle = data.xpos[model.body(f"{side}_foot").id] - base
        np.testing.assert_allclose(ankle, [0.07, y, -0.40], atol=0.003)
        # feet flat: the toe and heel points sit at the same height
        toe, heel = data.site_xpos[model.site(f"{side}_toe").id], data.site_xpos[model.site(f"{side}_heel").id]
        assert toe[2] == pytest.approx(heel[2], abs=1e-3)
