"""Bring-up of a real BRUCE on its stand, step by step (docs/bringup.md):
`pytest -m hardware tests/bruce_hw/test_bringup.py -s`.

The ports are the robot config's (`--bruce-config PATH`, `--bruce-set KEY=VALUE` as bruce-run's `--set`); with
`--bruce-emulate` the same steps run against `bruce-emulate --realtime --lockstep`, which also plays the person at
the E-stop and the cable (CI runs them so: tests/bruce_hw/test_bringup_emulated.py). Each step is safe on its own: it
starts from torque off and leaves every motor damping or off. A step that fails skips every step after it (a robot that
did not answer is not enabled). Each prints what a person at the robot should see.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from bruce_hw.backend import BackendError, LifecycleState
from bruce_hw.hw import make_hw_backend
from runtime.loop.exit import ExitCode
from runtime.loop.observers import TickObserver
from runtime.loop.run import run_session

pytestmark = pytest.mark.hardware

HOLD_TORQUE_NM = 1.5      # per actuator and joint in the low-current hold: enough to hold the legs, not to hurt
SINE_RAD, SINE_HZ, SINE_S = 0.08, 1.0, 2.0  # the one-joint sine: small, slow, two periods per joint


def say(text: str) -> None:
    print(f"\n[bring-up] {text}", flush=True)


@pytest.fixture(autouse=True)
def after_a_failed_step(request):
    """Skip every step after one that failed (the order is the file's)."""
    failed = getattr(request.module, "_failed_step", None)
    if failed is not None:
        pytest.skip(f"an earlier step failed ({failed}): fix it first")
    yield
    report = getattr(request.node, "rep_call", None)
    if report is not None and report.failed:
        request.module._failed_step = request.node.name


def _backend(config):
    return make_hw_backend(config, check_imu=False)


def _torque_enable(backend) -> list[int]:
    """Every BEAR's torque_enable, read over the bus (0 off, 1 on, 3 damping)."""
    bus = backend.legs.bus
    return [int(bus.read_status(i, ["torque_enable"]).values["torque_enable"]) for i in backend.legs.ids]


def test_01_every_device_answers_and_reports_its_identity(bringup_config):
    from bruce_hw.hw_check import check

    say("Power on, E-stop released, robot on its stand. Every bus is asked for every device.")
    reports = check(bringup_config)
    for report in reports:
        print(report.text())
    assert all(report.ok for report in reports), "; ".join(r.problem() for r in reports if not r.ok)
    arms = next(r for r in reports if r.name.startswith("Dynamixel"))
    assert len(arms.lines) == len(bringup_config.buses.dynamixel.ids)
    assert all(", firmware " in line for line in arms.lines), arms.lines  # each servo's identity: model, firmware
    say("Every device answered: the lines above are their IDs, models (and the servos' firmware), flags, temperatures "
        "and voltages.")


def test_02_configuration_and_limits_write_and_read_back(bringup_config):
    say("The legs' watchdog, mode and limits are written with torque off and read back; nothing moves.")
    backend = _backend(bringup_config)
    try:
        backend.configure()  # raises, naming the register, if a value does not read back
        assert backend.state is LifecycleState.INACTIVE
        assert backend.legs.watchdog_count > 0 or bringup_config.buses.can.motors
        assert set(_torque_enable(backend)) <= {0, 3}  # nothing is on
    finally:
        backend.shutdown()
    say("Configured and read back; every motor is off or damping.")


def test_03_the_bear_watchdog_unit_is_what_the_config_says(bringup_config):
    from bruce_hw.watchdog_probe import run_watchdog_probe

    if bringup_config.buses.can.motors:
        pytest.skip("CAN legs: the probe is for BEARs")
    say("One BEAR's watchdog is probed: its joint goes limp, then damps, a few times (keep the robot supported).")
    assert run_watchdog_probe(bringup_config, None, (50, 100)) == 0


def test_04_torque_enable_in_damping_only_and_back(bringup_config):
    say("Every BEAR is put in damping and back to off, one at a time; the joints resist being moved, then do not.")
    backend = _backend(bringup_config)
    try:
        backend.configure()
        backend.legs.damp()
        assert _torque_enable(backend) == [3] * len(backend.legs.ids)
        backend.legs.disable()
        assert _torque_enable(backend) == [0] * len(backend.legs.ids)
    finally:
        backend.shutdown()
    say("Damping and off both took on every BEAR. The shutdown leaves them damping.")


class PoseHold:
    """Joint targets only: from the measured pose to the standing pose over RAMP_S, then held (the standing
    controller balances on the feet, which on the stand are in the air)."""

    RAMP_S = 1.0

    def __init__(self, config):
        self.config, self.dt = config, 1.0 / config.policy_hz
        self.t, self.start = 0.0, config.standing_pose.copy()

    def reset(self, q):
        self.t, self.start = 0.0, np.array(q, dtype=float)

    def pose(self) -> np.ndarray:
        share = min(1.0, self.t / self.RAMP_S)
        return self.start + share * (self.config.standing_pose - self.start)

    def __call__(self, state, base, command):
        a = self.pose()
        self.t += self.dt
        return a


class Trace(TickObserver):
    """q and the commanded targets per tick (the run's own data, as a recording would keep them), and, given
    `phase`, what it returns at each tick."""

    def __init__(self, phase=None):
        self.q, self.a, self.phases, self._phase = [], [], [], phase

    def on_tick(self, view):
        self.q.append(view.robot.joints.q.copy())
        self.a.append(np.array(view.a, dtype=float))
        if self._phase is not None:
            self.phases.append(self._phase())


def test_05_a_low_current_hold_of_the_standing_pose(bringup_config, bringup_config_with):
    # every torque limit lowered (checked as bruce-run's --set would be)
    config = bringup_config_with(f"actuators.torque_limit={HOLD_TORQUE_NM}",
                                 *(f"joints.torque_limits.{name}={HOLD_TORQUE_NM}" for name in bringup_config.joints))
    say(f"The standing pose is held for 3 s with every torque limited to {HOLD_TORQUE_NM} N m: the legs move to the "
        "pose slowly and hold it softly; a gentle push gives way and comes back.")
    trace = Trace()
    summary = run_session(_backend(config), config, duration=3.0, realtime=True, controller=PoseHold(config),
                          observers=[trace])
    assert summary.exit_code == ExitCode.OK, summary.stop_cause
    q = np.array(trace.q[-500:])
    error = np.abs(q.mean(axis=0) - config.standing_pose)
    print("standing pose error per joint (rad): " + ", ".join(f"{n} {e:.3f}" for n, e in zip(config.joints, error,
                                                                                             strict=True)))
    assert error.max() < 0.2  # held near the pose, softly (the low limit leaves some sag)
    say("Held. The run ended through damping.")


class OneJointSine(PoseHold):
    """The standing pose (reached as `PoseHold` does), then a small sine on one joint at a time, SINE_S each, in
    joint order."""

    joint = -1  # the joint the last call moved (-1: none yet)

    def __call__(self, state, base, command):
        a, t = self.pose(), self.t - 1.0  # a second to reach the pose first
        self.t += self.dt
        if t >= 0.0:
            i = self.joint = min(int(t // SINE_S), self.config.n_joints - 1)
            a[i] += SINE_RAD * np.sin(2 * np.pi * SINE_HZ * (t - i * SINE_S))
        return a


def test_06_a_short_sine_on_one_joint_at_a_time(bringup_config):
    config = bringup_config
    say(f"Each joint in turn follows a {SINE_RAD} rad, {SINE_HZ:g} Hz sine for {SINE_S:g} s, in the order of "
        f"joints.names ({', '.join(config.joints)}): watch that the joint that moves is the one named.")
    controller = OneJointSine(config)
    trace = Trace(phase=lambda: controller.joint)
    duration = 1.0 + SINE_S * config.n_joints
    summary = run_session(_backend(config), config, duration=duration, realtime=True, controller=controller,
                          observers=[trace])
    assert summary.exit_code == ExitCode.OK, summary.stop_cause
    # Each joint's span: the ticks at which the controller was moving it. The controller is called once per policy
    # period of the robot's clock, so where a slow computer skips ticks, its schedule runs ahead of the tick count.
    q, a, moving = np.array(trace.q), np.array(trace.a), np.array(trace.phases)
    for i, name in enumerate(config.joints):
        span = np.flatnonzero(moving == i)
        assert span.size > SINE_S * config.loop_hz / 4, f"{name}: moved for {span.size} ticks only"
        commanded, moved = a[span, i] - a[span, i].mean(), q[span, i] - q[span, i].mean()
        follows = float(np.corrcoef(commanded, moved)[0, 1])
        print(f"{name}: moved {np.ptp(q[span, i]):.3f} rad peak to peak for {np.ptp(a[span, i]):.3f} commanded, "
              f"correlation {follows:.2f}")
        assert follows > 0.5, f"{name} did not follow its sine (correlation {follows:.2f}): wiring, ID or sign"
    say("Every joint followed its own sine.")


def test_07_the_estop_reaches_damping(bringup_config, operator):
    say("Now the E-stop: " + operator.asks("estop"))
    backend = _backend(bringup_config)
    summary = run_session(backend, bringup_config, duration=operator.wait_s, realtime=True,
                          controller=PoseHold(bringup_config), commands=operator.at(1.0, "estop"))
    assert summary.exit_code in (ExitCode.SAFETY_TRIP, ExitCode.BUS_FAULT), summary.stop_cause
    assert "E-stop" in summary.stop_cause or "e-stop" in summary.stop_cause, summary.stop_cause
    print(f"stop cause: {summary.stop_cause}")
    operator.undo("estop")
    say("Damping on the E-stop. Release it now.")


def test_08_a_pulled_leg_cable_reaches_damping(bringup_config, operator, tmp_path):
    say("Now the leg bus's cable: " + operator.asks("cable"))
    backend, stats = _backend(bringup_config), tmp_path / "stats.json"
    with pytest.raises(BackendError, match=r"no reply from ID\(s\)"):  # a lost device ends the session so
        run_session(backend, bringup_config, duration=operator.wait_s, realtime=True, stats_path=stats,
                    controller=PoseHold(bringup_config), commands=operator.at(1.0, "cable"))
    summary = json.loads(stats.read_text())
    assert summary["exit_code"] == ExitCode.BUS_FAULT and backend.state is not LifecycleState.ACTIVE
    print(f"stop cause: {summary['stop_cause']}")
    operator.undo("cable")
    say("Damping on the pulled cable (the BEARs' own watchdog damped them too). Plug it back in.")
