"""A live nominal twin of the robot (`NominalTwin`): the simulator's own closed loop, run beside the robot and
resynchronised to it.

The twin is the nominal MuJoCo model under a second instance of the nominal controller on the robot's command, its
torques through its own safety stage (the simulator's went through one). Every resync (`TwinInput.resync`) it is set
to the robot's state and its controller takes the robot's target and action memory; between resyncs it rolls on by
itself, in phase (the gait clock is a function of the command history). Without a gap the twin reproduces the robot;
with one, the posture offset between them over seconds is what no prediction over a few ticks sees
(docs/transfer.md, "The schemes" and "Running a scheme on the robot").

Two ways to resynchronise, one per kind of run:

- **From what the robot has** (an `EstimatorSnapshot`: the robot's kinematic estimator at that tick; every
  robot-faithful run, and `--backend hw`). Joints as measured; roll and pitch from the estimator's attitude, yaw and
  planar position the twin's own (nothing on the robot observes them); the base's angular and linear velocity from
  the estimator; the height set so that the lowest toe or heel keeps the twin's own contact depth, so the resync
  neither pushes a foot into the floor nor lifts the stance off it (noisy state injected into a simulator makes
  invalid contacts). The twin's controller sees its own `KinematicEstimator` on the twin's own clean sensors,
  continued from the robot's estimator state at each resync: it observes what the robot's policy observes, bias
  and all, which is what makes the two policies act alike.
- **From the simulator's truth** (a `GroundTruth`; diagnostic runs with `--estimator truth` only): the full base
  state, and the twin's controller sees its own ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from bruce_hw.config import RobotConfig
from bruce_hw.types import GroundTruth
from runtime.control.mixing import eq8_torque
from runtime.estimation import BaseEstimate, GroundTruthEstimator
from runtime.estimation.kinematic import EstimatorSnapshot, KinematicEstimator
from runtime.loop.safety import SafetyStage
from runtime.transfer.reference_models import foot_spheres, nominal_model, place_from_estimate


@dataclass(slots=True)
class TwinInput:
    """What the robot's tick `tick` gives its twin (the arrays are the twin's to keep)."""

    tick: int
    a: np.ndarray                 # the robot's controller target in force
    q: np.ndarray                 # measured joints
    qd: np.ndarray
    command: np.ndarray           # (vx, vy, yaw rate) in force
    sent: np.ndarray | None       # the torque the robot was sent last tick (the rate limit starts from it at a resync)
    resync: EstimatorSnapshot | GroundTruth | None = None  # set the twin to the robot at this tick
    velocity: np.ndarray | None = None  # the robot's estimated (vx, vy, yaw rate), body frame, on policy ticks


class NominalTwin:
    """The nominal model under the nominal controller, resynchronised to the robot whenever it is told to."""

    name = "nominal twin"  # for GroundTruthEstimator, which reads the twin's truth as a backend's

    def __init__(self, config: RobotConfig, controller):
        robot, self.data = nominal_model(config)
        self.robot, self.model = robot, robot.model  # `robot.measure(data)`: the twin's clean sensors
        self._qpos, self._dofs, self._acts = robot.qpos, robot.dofs, robot.acts
        self._spheres = foot_spheres(self.model)
        self.controller = controller
        self.estimator = KinematicEstimator(config)
        self.truth = GroundTruthEstimator(self)  # the twin's own truth (`ground_truth`), for truth-fed runs
        self.safety = SafetyStage(config)
        self.eq8 = config.eq8
        self.decimation = config.policy_decimation
        self.standing_pose = config.standing_pose
        self.differential = True  # resync the base by the estimates' difference (place_from_estimate's `own`)
        self.reset()

    def reset(self) -> None:
        # Standing on the floor, as the robot starts: the first resync keeps this contact depth.
        self.robot.place_standing(self.data, self.standing_pose)
        self.safety.reset()
        self.tick = -1
        self.from_truth = False   # the last resync was from the simulator's truth (diagnostic runs)
        self.a: np.ndarray | None = None
        self.q: np.ndarray | None = None  # the twin's joint posture at the robot's coming tick
        self.velocity: np.ndarray | None = None  # what its controller saw last: (vx, vy, yaw rate), body frame

    def advance(self, step: TwinInput) -> None:
        """One tick, after the robot's controller gave `step.a` from the measured joints: resync when told to, then
        the twin's own controller (on policy ticks), Eq. 8, its safety filter and one physics step."""
        data = self.data
        first = self.tick < 0
        self.tick = step.tick
        policy_tick = step.tick % self.decimation == 0
        resync = step.resync
        if resync is not None:
            if isinstance(resync, GroundTruth):
                self.robot.set_truth(data, resync, step.q, step.qd)
                mujoco.mj_forward(self.model, data)
            else:
                own = None
                if not first and not self.from_truth and self.differential:
                    self.estimator.update(self.robot.measure(data))  # the twin's own estimate at this tick
                    own = self.estimator.estimate()
                place_from_estimate(self.robot, data, resync.estimate, step.q, step.qd, self._spheres, own)
                self.estimator.restore(resync, float(data.time))
            self.from_truth = isinstance(resync, GroundTruth)
            if step.sent is not None:
                self.safety.previous = np.array(step.sent, dtype=float)
        state = self.robot.measure(data)
        if first:
            self.controller.reset(state.joints.q)
        if resync is None and not self.from_truth:  # a resync tick's measurement is in the robot's estimate already
            if first:
                self.estimator.reset(state)
            else:
                self.estimator.update(state)
        if policy_tick or self.a is None:
            base = self._base()
            self.velocity = np.array((base.linvel[0], base.linvel[1], base.angvel[2]))
            a = self.controller(state, base, step.command)  # also advances its gait clock
            if resync is not None:  # the robot's controller state: its target now is the action memory of both
                a = np.array(step.a, dtype=float)
                self.controller.last_action = a
            self.a = a
        tau = self.safety.filter(eq8_torque(self.a, state.joints.q, state.joints.qd, self.eq8), state)
        data.ctrl[self._acts] = tau
        mujoco.mj_step(self.model, data)
        self.q = data.qpos[self._qpos].copy()

    def ground_truth(self) -> GroundTruth:
        """The twin's own simulator truth (what `GroundTruthEstimator` reads of a backend)."""
        return self.robot.ground_truth(self.data)

    def _base(self) -> BaseEstimate:
        """What the twin's controller sees of its base: its own estimator, or (truth-fed runs) its own truth."""
        return self.truth.estimate() if self.from_truth else self.estimator.estimate()
