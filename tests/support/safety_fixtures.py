"""Robot states and a safety stage past its soft start, for the safety stage's tests (runtime/loop/test_safety.py) and
the host witness's (bruce_hw/test_host_witness.py)."""

import numpy as np

from bruce_hw.types import FootContacts, ImuSample, JointState, RobotState
from runtime.loop.safety import SafetyStage, SafetyState


def robot(config, q=None, qd=None, stamp=0.0, orientation=(1.0, 0.0, 0.0, 0.0), estop=False, imu_stamp=None):
    n = config.n_joints
    q = config.standing_pose.copy() if q is None else q
    qd = np.zeros(n) if qd is None else qd
    return RobotState(
        joints=JointState(q=q, qd=qd, tau=np.zeros(n), temperature=np.full(n, 30.0), stamp=stamp),
        imu=ImuSample(gyro=np.zeros(3), accel=np.array([0.0, 0.0, 9.81]),
                      orientation=None if orientation is None else np.array(orientation),
                      stamp=stamp if imu_stamp is None else imu_stamp),
        contacts=FootContacts(contact=np.ones(4, bool), stamp=stamp), estop=estop)


def running_stage(config) -> SafetyStage:
    stage = SafetyStage(config)
    state = robot(config)
    for _ in range(stage.ramp_ticks):
        stage.filter(np.zeros(config.n_joints), state)
    assert stage.state is SafetyState.RUNNING
    return stage
