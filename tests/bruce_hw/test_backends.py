import numpy as np
import pytest

from bruce_hw import BackendError, JointCommand, LifecycleError, LifecycleState, make_backend


@pytest.fixture(params=["mock", "echo"])
def backend(request, config):
    b = make_backend(request.param, config)
    yield b
    b.shutdown()


def zero_command(config):
    return JointCommand(tau_ff=np.zeros(config.n_joints))


def test_lifecycle_refuses_commands_unless_active(backend, config):
    with pytest.raises(LifecycleError, match="unconfigured"):
        backend.write(zero_command(config))
    with pytest.raises(LifecycleError):
        backend.read()
    backend.configure()
    assert backend.state is LifecycleState.INACTIVE
    backend.read()  # inactive reads
    with pytest.raises(LifecycleError, match="command refused, the backend is inactive"):
        backend.write(zero_command(config))
    backend.activate()
    backend.write(zero_command(config))
    backend.deactivate()
    with pytest.raises(LifecycleError, match="inactive"):
        backend.write(zero_command(config))


def test_fault_is_left_only_by_an_explicit_reset(backend, config):
    backend.configure()
    backend.activate()
    backend.fault("test")
    assert backend.state is LifecycleState.FAULT and backend.fault_cause == "test"
    with pytest.raises(LifecycleError, match="fault"):
        backend.write(zero_command(config))
    with pytest.raises(LifecycleError):
        backend.activate()
    backend.read()  # the robot is still observed while damping
    backend.reset()
    assert backend.state is LifecycleState.INACTIVE and backend.fault_cause is None
    backend.activate()
    backend.write(zero_command(config))


def test_command_of_the_wrong_size_is_refused(backend, config):
    backend.configure()
    backend.activate()
    with pytest.raises(ValueError, match=r"expected \(10,\)"):
        backend.write(JointCommand(tau_ff=np.zeros(9)))


def test_state_arrays_are_in_config_order_and_not_aliased(backend, config):
    backend.configure()
    first = backend.read()
    assert first.joints.q.shape == (config.n_joints,)
    np.testing.assert_allclose(first.joints.q, config.standing_pose, atol=1e-3)
    first.joints.q[:] = 99.0
    assert not np.any(backend.read().joints.q == 99.0)


def test_mock_applies_no_torque_while_inactive(config):
    with make_backend("mock", config) as mock:
        mock.configure()
        for _ in range(5):
            state = mock.read()
        np.testing.assert_array_equal(state.joints.tau, 0.0)


def test_mock_runs_the_command_pd_on_the_motor_and_saturates_per_actuator(config):
    with make_backend("mock", config) as mock:
        mock.configure()
        mock.activate()
        q = mock.read().joints.q
        kp = np.full(10, 5.0)
        mock.write(JointCommand(tau_ff=np.zeros(10), q_ref=q + 0.1, kp=kp))
        tau = mock.read().joints.tau
        np.testing.assert_allclose(tau, 0.5, atol=0.05)  # kp * 0.1 at (about) the previous pose
        # hip pitch and roll both at +20 Nm ask ~40 Nm of one hip BEAR: the motors saturate
        big = np.zeros(10)
        big[1] = big[2] = 20.0
        mock.write(JointCommand(tau_ff=big))
        tau = mock.read().joints.tau
        assert np.all(np.abs(config.coupling.actuator_torques(tau)) <= config.actuator_torque_limit + 1e-9)


def test_mock_damps_in_fault(config):
    with make_backend("mock", config) as mock:
        mock.configure()
        mock.activate()
        for _ in range(50):  # let the robot start to sag so that joints move
            mock.read()
        mock.fault("test")
        before = mock.read()
        after = mock.read()
        # the torque applied over the last step was -kd * qd at its start
        np.testing.assert_allclose(after.joints.tau, -config.safety.damping_kd * before.joints.qd, atol=1e-12)
        assert np.any(after.joints.tau != 0.0)


def test_mock_senses_like_the_robot_and_exposes_ground_truth(config):
    with make_backend("mock", config) as mock:
        mock.configure()
        state = mock.read()
        truth = mock.ground_truth()
        assert state.contacts.contact.shape == (4,)
        assert truth.base_pos[2] == pytest.approx(mock.nominal_base_height, abs=0.002)
        assert state.imu.orientation is not None and state.imu.orientation[0] == pytest.approx(1.0, abs=1e-3)
        for _ in range(300):
            state = mock.read()
        assert state.contacts.contact.all()  # on its feet
        assert state.imu.accel[2] > 5.0  # specific force points up
        assert state.joints.stamp == pytest.approx(truth.sim_time + 0.3, abs=1e-9)


def test_echo_mirrors_position_commands(config):
    with make_backend("echo", config) as echo:
        echo.configure()
        echo.activate()
        target = config.standing_pose + 0.05
        echo.write(JointCommand(tau_ff=np.ones(10), q_ref=target, kp=np.full(10, 2.0)))
        state = echo.read()
        np.testing.assert_allclose(state.joints.q, target)
        np.testing.assert_allclose(state.joints.tau, 1.0 + 2.0 * 0.05)


def test_hw_backend_says_what_is_missing(config):
    with pytest.raises(BackendError) as info:
        make_backend("hw", config)
    message = str(info.value)
    assert "buses.bear.port" in message and "/dev/ttyUSB0" in message


def test_unknown_backend_is_named(config):
    with pytest.raises(BackendError, match="unknown backend 'robot'"):
        make_backend("robot", config)
