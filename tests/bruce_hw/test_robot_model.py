"""BRUCE's model bound to the config (bruce_hw/robot_model.py, `BruceModel`): the names it finds, the standing
placement the mock starts from, a state set and read back, and the checks of the MJCF against the config."""

import dataclasses

import mujoco
import numpy as np
import pytest

from bruce_hw.backend import BackendError
from bruce_hw.mock import MujocoBackend
from bruce_hw.robot_model import SOLE_SITES, TOUCH_SENSORS, BruceModel


@pytest.fixture(scope="module")
def robot(config):
    return BruceModel(config)


def test_named_indices(robot, config):
    model = robot.model
    assert robot.motors == tuple(model.actuator(a).name for a in range(robot.acts.start, robot.acts.stop))
    assert [model.joint(j).qposadr[0] for j in config.joints] == list(range(robot.qpos.start, robot.qpos.stop))
    assert [model.joint(j).dofadr[0] for j in config.joints] == list(range(robot.dofs.start, robot.dofs.stop))
    assert model.body(robot.base_body).name == "base"
    assert [model.site(s).name for s in robot.soles] == list(SOLE_SITES)
    assert [robot.sensors[n].start for n in TOUCH_SENSORS] == list(robot.touch)


def test_standing_placement_is_the_mocks_start(robot, config):
    mock = MujocoBackend(config)
    mock.configure()
    data = robot.new_data()
    robot.place_standing(data)
    assert data.qpos.tobytes() == mock.data.qpos.tobytes() and data.qvel.tobytes() == mock.data.qvel.tobytes()
    assert data.sensordata.tobytes() == mock.data.sensordata.tobytes()
    assert robot.standing_height() == mock.nominal_base_height == pytest.approx(data.qpos[2])
    lowest_sole = min(data.site_xpos[s][2] for s in robot.soles)
    assert lowest_sole == pytest.approx(0.0, abs=1e-12)
    measured, reference = robot.measure(data), mock.measure()
    np.testing.assert_array_equal(measured.joints.q, reference.joints.q)
    np.testing.assert_array_equal(measured.imu.accel, reference.imu.accel)
    np.testing.assert_array_equal(measured.contacts.contact, reference.contacts.contact)


def test_set_state_reads_back_as_truth(robot, config):
    data = robot.new_data()
    rng = np.random.default_rng(0)
    q, qd = config.standing_pose + rng.normal(0.0, 0.1, config.n_joints), rng.normal(0.0, 1.0, config.n_joints)
    quat = np.array([0.9, 0.1, -0.2, 0.3]) / np.linalg.norm([0.9, 0.1, -0.2, 0.3])
    pos, linvel, angvel = np.array([0.1, -0.2, 0.5]), np.array([0.3, 0.0, -0.1]), np.array([0.0, 0.2, 0.4])
    robot.set_state(data, q, qd, pos, quat, linvel, angvel)
    truth = robot.ground_truth(data)
    for got, want in ((truth.joint_q, q), (truth.joint_qd, qd), (truth.base_pos, pos), (truth.base_quat, quat),
                      (truth.base_linvel, linvel), (truth.base_angvel, angvel)):
        np.testing.assert_array_equal(got, want)
    again = robot.new_data()
    robot.set_truth(again, truth, q, qd)
    assert again.qpos.tobytes() == data.qpos.tobytes() and again.qvel.tobytes() == data.qvel.tobytes()


def test_an_mjcf_without_the_needed_names_is_refused(config, tmp_path):
    spec = mujoco.MjSpec.from_file(str(config.mjcf))
    spec.delete(spec.site("l_sole"))
    path = tmp_path / "no_sole.xml"
    path.write_text(spec.to_xml())
    with pytest.raises(BackendError, match="r_sole' and 'l_sole"):
        BruceModel(dataclasses.replace(config, mjcf=path))
