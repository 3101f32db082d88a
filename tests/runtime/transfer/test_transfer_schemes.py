"""The transfer stage's schemes (runtime/transfer/: direct.py, eq9.py, shadow.py, observer.py, twin.py, built by
name in schemes.py), their gains (runtime/transfer/gains.py), the perfect-model reference and the nominal twin
(runtime/transfer/: reference_models.py, nominal_twin.py)."""

import math

import numpy as np
import pytest

from bruce_hw.config import ConfigError, PdGains, parse_config
from bruce_hw.mock import MujocoBackend
from bruce_hw.types import JointCommand
from runtime.control.inference import ModelError
from runtime.control.mixing import eq8_torque
from runtime.estimation.kinematic import KinematicEstimator
from runtime.robot_config import load_config
from runtime.transfer.eq9 import Eq9Scheme
from runtime.transfer.gains import joint_inertia, observer_gain, pd_crossover, pd_gains, shortest_observer_time_constant
from runtime.transfer.interface import TransferScheme
from runtime.transfer.nominal_twin import TwinInput
from runtime.transfer.observer import ObserverScheme
from runtime.transfer.reference_models import NominalReference
from runtime.transfer.schemes import build_scheme
from runtime.transfer.shadow import ShadowScheme
from runtime.transfer.stage import settings_for
from runtime.transfer.twin import TwinScheme
from runtime.transfer.twin_runner import InlineTwinRunner, ThreadTwinRunner, TwinIntegral

DT = 1e-3


class RecordingModel:
    """A reference model that returns given predictions and records what it was fed."""

    name = "recording"

    def __init__(self, predictions):
        self.predictions = list(predictions)
        self.calls = []
        self.resets = 0

    def reset(self):
        self.resets += 1

    def step(self, q, qd, tau):
        self.calls.append((q.copy(), qd.copy(), tau.copy()))
        q_next, qd_next = self.predictions.pop(0)
        return np.array(q_next, float), np.array(qd_next, float)


class InertiaPlant:
    """Per joint an inertia I under tau + a constant torque d, semi-implicit Euler at 1 kHz: plant and model."""

    name = "inertia"

    def __init__(self, inertia, disturbance=0.0):
        self.inertia = np.asarray(inertia, float)
        self.disturbance = disturbance

    def reset(self):
        pass

    def step(self, q, qd, tau):
        qd_next = qd + DT * (tau + self.disturbance) / self.inertia
        return q + DT * qd_next, qd_next


def closed_loop(scheme, plant, target, eq8, ticks, q0=None):
    """Run Eq. 8 towards `target` through `scheme` on `plant`; returns (q, qd, tau*, tau) of the last tick."""
    n = len(target)
    q, qd = (np.zeros(n) if q0 is None else q0.copy()), np.zeros(n)
    scheme.reset()
    for _ in range(ticks):
        tau_star = eq8_torque(target, q, qd, eq8)
        scheme.predict(target, q, qd, tau_star)
        tau = scheme.torque(tau_star, q, qd)
        q, qd = plant.step(q, qd, tau)
    return q, qd, tau_star, tau


GAINS = PdGains(kp=np.array([10.0, 20.0]), kd=np.array([1.0, 2.0]))
EQ8 = PdGains(kp=np.array([20.0, 2.5]), kd=np.array([0.7, 0.35]))


def test_direct_scheme_sends_tau_star_and_predicts_nothing():
    scheme = TransferScheme()
    tau_star = np.array([1.0, -2.0])
    scheme.predict(np.zeros(2), np.zeros(2), np.zeros(2), tau_star)
    assert scheme.torque(tau_star, np.zeros(2), np.zeros(2)) is tau_star
    assert scheme.one_step is None and scheme.q_hat is None


def test_eq9_scheme_is_the_papers_law_on_the_models_prediction_under_tau_star():
    model = RecordingModel([([0.2, 0.2], [1.0, 0.0])])
    scheme = Eq9Scheme(model, GAINS)
    tau_star, q, qd = np.array([1.0, -1.0]), np.array([0.1, 0.2]), np.array([0.0, 1.0])
    scheme.predict(np.zeros(2), q, qd, tau_star)
    tau = scheme.torque(tau_star, q, qd)
    # tau* + Kp (q^ - q) + Kd (qd^ - qd): [1 + 10 * 0.1 + 1 * 1, -1 + 20 * 0 + 2 * -1]
    np.testing.assert_allclose(tau, [3.0, -3.0])
    np.testing.assert_array_equal(model.calls[0][2], tau_star)  # the PINN is fed tau*, not tau
    np.testing.assert_allclose(scheme.one_step[1], [1.0, 0.0])


def test_eq9_with_a_look_ahead_model_offers_no_one_step_prediction():
    scheme = Eq9Scheme(RecordingModel([([0.0, 0.0], [0.0, 0.0])]), GAINS, one_step=False)
    scheme.predict(np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2))
    assert scheme.one_step is None and scheme.q_hat is not None


def test_shadow_rolls_on_its_own_state_under_the_simulators_eq8_and_resynchronises():
    a = np.array([0.5, -0.5])
    predictions = [([0.01, 0.02], [0.1, 0.2]), ([0.03, 0.05], [0.3, 0.4]), ([9.0, 9.0], [9.0, 9.0])]
    model = RecordingModel(predictions)
    scheme = ShadowScheme(model, GAINS, EQ8, resync_ticks=2)
    scheme.reset()
    q0, qd0, tau0 = np.array([0.0, 0.0]), np.array([0.0, 0.0]), np.array([1.0, 1.0])
    scheme.predict(a, q0, qd0, tau0)  # tick 0: resynchronised, the shadow starts at the measured state
    np.testing.assert_array_equal(scheme.torque(tau0, q0, qd0), tau0)
    np.testing.assert_array_equal(model.calls[0][2], tau0)
    assert scheme.one_step is not None
    q1, qd1, tau1 = np.array([0.0, 0.0]), np.array([0.05, 0.1]), np.array([2.0, 2.0])
    scheme.predict(a, q1, qd1, tau1)  # tick 1: the shadow is the model's state from tick 0
    np.testing.assert_allclose(scheme.q_hat, [0.01, 0.02])
    # the shadow is rolled under Eq. 8 on its own state, not the robot's tau*
    np.testing.assert_allclose(model.calls[1][2], eq8_torque(a, np.array([0.01, 0.02]), np.array([0.1, 0.2]), EQ8))
    assert scheme.one_step is None  # no prediction from the measured state this tick
    # tau* + Kp (q_s - q) + Kd (qd_s - qd) = [2 + 10 * 0.01 + 1 * 0.05, 2 + 20 * 0.02 + 2 * 0.1]
    np.testing.assert_allclose(scheme.torque(tau1, q1, qd1), [2.15, 2.6])
    q2 = np.array([0.7, 0.7])
    scheme.predict(a, q2, np.zeros(2), tau1)  # tick 2: resynchronised again
    np.testing.assert_array_equal(scheme.q_hat, q2)
    np.testing.assert_array_equal(model.calls[2][0], q2)


def test_observer_integrates_the_velocity_residual_clips_and_resets():
    model = RecordingModel([([0.0, 0.0], [1.0, 1.0])] * 4)
    scheme = ObserverScheme(model, gain=np.array([0.5, 0.5]), clip=np.array([0.1, 1.0]))
    scheme.reset()
    tau_star = np.array([1.0, 1.0])
    scheme.predict(None, np.zeros(2), np.zeros(2), tau_star)  # no prediction yet: nothing to integrate
    np.testing.assert_array_equal(scheme.torque(tau_star, np.zeros(2), np.zeros(2)), tau_star)
    scheme.predict(None, np.zeros(2), np.array([0.6, 0.0]), tau_star)  # residual (predicted - measured) 0.4, 1.0
    np.testing.assert_allclose(scheme.u, [0.1, 0.5])  # 0.5 * 0.4 = 0.2 clipped to 0.1; 0.5 * 1.0
    np.testing.assert_allclose(scheme.torque(tau_star, np.zeros(2), np.zeros(2)), [1.1, 1.5])
    scheme.predict(None, np.zeros(2), np.array([1.0, 1.0]), tau_star)  # as predicted: u holds
    np.testing.assert_allclose(scheme.u, [0.1, 0.5])
    scheme.predict(None, np.zeros(2), np.array([3.0, 3.0]), tau_star)  # residual -2: down, clipped at -0.1
    np.testing.assert_allclose(scheme.u, [-0.1, -0.5])
    scheme.reset()
    assert not scheme.u.any() and scheme.one_step is None and model.resets == 2  # the model restarts too


def test_observer_holds_its_torque_during_the_torque_ramp():
    model = RecordingModel([([0.0], [1.0])] * 4)
    scheme = ObserverScheme(model, gain=np.array([1.0]), clip=np.array([10.0]), hold_ticks=3)
    scheme.reset()
    for _ in range(3):
        scheme.predict(None, np.zeros(1), np.zeros(1), np.zeros(1))
        assert scheme.u[0] == 0.0
    scheme.predict(None, np.zeros(1), np.zeros(1), np.zeros(1))
    assert scheme.u[0] == pytest.approx(1.0)


@pytest.mark.parametrize("kind", ["eq9", "shadow", "observer"])
def test_a_scheme_whose_model_is_the_plant_adds_no_torque_in_steady_state(kind):
    inertia = np.array([0.004, 0.002])
    plant = InertiaPlant(inertia, disturbance=np.array([0.3, -0.1]))
    model = InertiaPlant(inertia, disturbance=np.array([0.3, -0.1]))  # the same dynamics: the null case
    scheme = {"eq9": lambda: Eq9Scheme(model, GAINS),
              "shadow": lambda: ShadowScheme(model, GAINS, EQ8, resync_ticks=5),
              "observer": lambda: ObserverScheme(model, observer_gain(inertia, 0.05), np.array([5.0, 5.0]))}[kind]()
    q, qd, tau_star, tau = closed_loop(scheme, plant, np.array([0.3, -0.2]), EQ8, ticks=20_000)
    assert np.max(np.abs(qd)) < 1e-9  # at rest ...
    np.testing.assert_allclose(tau, tau_star, atol=1e-9)  # ... and the scheme adds nothing


@pytest.mark.slow
def test_observer_makes_a_disturbed_plant_settle_where_the_model_does():
    inertia = np.array([0.004, 0.002])
    target = np.array([0.3, -0.2])
    model = InertiaPlant(inertia)
    _, _, _, _ = closed_loop(TransferScheme(), model, target, EQ8, ticks=20_000)
    disturbance = np.array([0.5, -0.1])  # e.g. unmodelled gravity load and friction
    q_direct, *_ = closed_loop(TransferScheme(), InertiaPlant(inertia, disturbance), target, EQ8, ticks=20_000)
    scheme = ObserverScheme(model, observer_gain(inertia, 0.05), clip=np.array([5.0, 5.0]))
    q_obs, *_ = closed_loop(scheme, InertiaPlant(inertia, disturbance), target, EQ8, ticks=20_000)
    np.testing.assert_allclose(scheme.u, -disturbance, atol=1e-6)
    np.testing.assert_allclose(q_obs, target, atol=1e-6)  # the model's steady state: Eq. 8 reaches its target
    assert np.all(np.abs(q_direct - target) > 0.01)  # without it the disturbance bends the posture
    clipped = ObserverScheme(model, observer_gain(inertia, 0.05), clip=np.array([0.2, 5.0]))
    closed_loop(clipped, InertiaPlant(inertia, disturbance), target, EQ8, ticks=20_000)
    assert clipped.u[0] == pytest.approx(-0.2)


class BiasedModel(InertiaPlant):
    """The plant's dynamics, but every predicted qd off by a constant: a model with a bias."""

    def __init__(self, inertia, bias):
        super().__init__(inertia)
        self.bias = bias

    def step(self, q, qd, tau):
        q_next, qd_next = super().step(q, qd, tau)
        return q_next, qd_next + self.bias


@pytest.mark.slow
def test_a_calibrated_model_bias_is_not_integrated_into_a_posture_offset():
    inertia, target = np.array([0.004, 0.002]), np.array([0.3, -0.2])
    bias = np.array([0.1, -0.05])  # rad/s per tick: what the gap monitor's mean residual measures on the simulator
    raw = ObserverScheme(BiasedModel(inertia, bias), observer_gain(inertia, 0.05), clip=np.array([5.0, 5.0]))
    q_raw, *_ = closed_loop(raw, InertiaPlant(inertia), target, EQ8, ticks=20_000)
    assert np.all(np.abs(q_raw - target) > 0.01)  # integrated, the bias bends the posture on a robot with no gap
    calibrated = ObserverScheme(BiasedModel(inertia, bias), observer_gain(inertia, 0.05),
                                clip=np.array([5.0, 5.0]), bias=bias)
    q_cal, _, tau_star, tau = closed_loop(calibrated, InertiaPlant(inertia), target, EQ8, ticks=20_000)
    np.testing.assert_allclose(q_cal, target, atol=1e-9)
    np.testing.assert_allclose(tau, tau_star, atol=1e-9)


def _loop_phase_margin(kp, kd, inertia, delay):
    """Phase margin (deg) of Kp + Kd s on 1 / (I s^2) with a pure delay, at the numerically found crossover."""
    w = np.geomspace(0.1, 1e4, 400_000)
    loop = (kp + 1j * w * kd) * np.exp(-1j * w * delay) / (-inertia * w * w)
    phase = np.unwrap(np.angle(loop))  # from -180 deg + the PD's small lead at the lowest frequency
    crossing = int(np.argmax(np.abs(loop) < 1.0))
    return 180.0 + math.degrees(phase[crossing])


@pytest.mark.parametrize("delay, margin", [(0.010, 45.0), (0.005, 30.0), (0.020, 60.0)])
def test_pd_gains_leave_the_stated_phase_margin_at_the_stated_delay(delay, margin):
    inertia = np.array([0.0046, 0.012, 0.0018])
    gains = pd_gains(inertia, delay, margin)
    for i in range(3):
        found = _loop_phase_margin(gains.kp[i], gains.kd[i], inertia[i], delay)
        assert margin - 3.0 < found < margin + 0.5  # the PD's own gain lifts the crossover ~3 % above wc
        assert _loop_phase_margin(gains.kp[i], gains.kd[i], inertia[i], 3 * delay) < found - 20
    with pytest.raises(ValueError, match="phase_margin_deg"):
        pd_crossover(0.01, 75.0)


def test_observer_time_constant_bound_is_the_integrators_phase_margin():
    delay, margin = 0.01, 45.0
    shortest = shortest_observer_time_constant(delay, margin)
    assert 90.0 - math.degrees(delay / shortest) == pytest.approx(margin)  # loop -90 deg - w D at w = 1 / T
    np.testing.assert_allclose(observer_gain(np.array([0.004]), 0.2), [0.02])


def test_joint_inertia_is_the_models_smallest_and_gains_follow_it():
    config = load_config()
    inertia = joint_inertia(config)
    armature = 0.0018  # the MJCF's reflected rotor inertia: every joint shows at least that
    assert np.all(inertia >= armature) and np.all(inertia < 0.05)
    ankles, hips = config.joint_indices("ankle"), config.joint_indices("hip_pitch")
    assert np.all(inertia[hips] > 2 * inertia[ankles])  # the hip moves the whole leg, the ankle only the foot
    np.testing.assert_allclose(inertia[: 5], inertia[5:], rtol=0.01)  # the legs mirror each other


def test_build_scheme_reads_the_config_and_pinn_means_eq9():
    config = load_config()
    eq9 = build_scheme(config, "pinn")
    assert isinstance(eq9, Eq9Scheme) and eq9.gains is config.eq9
    observer = build_scheme(load_config(overrides=["transfer.observer.time_constant_s=0.5",
                                                   "transfer.observer.clip=0.5"]), "observer")
    np.testing.assert_allclose(observer.gain, joint_inertia(config) / 0.5)
    np.testing.assert_allclose(observer.clip, 0.5 * config.tau_limit)
    shadow = build_scheme(config, "shadow")
    settings = settings_for(config)
    assert shadow.resync_ticks == settings.of("shadow").resync_ticks
    np.testing.assert_allclose(shadow.gains.kd, pd_gains(joint_inertia(config), settings.delay_margin_s,
                                                         settings.phase_margin_deg).kd)
    with pytest.raises(ValueError, match="unknown transfer 'eq10'"):
        build_scheme(config, "eq10")


def test_the_perfect_model_needs_a_base_state_from_the_estimator_or_the_truth():
    config = load_config(overrides=["transfer.reference_model=nominal"])
    with pytest.raises(ModelError, match="needs the robot's base state, from the run's estimator"):
        build_scheme(config, "observer")
    scheme = build_scheme(config, "observer", estimator=KinematicEstimator(config))  # what a robot has: enough
    assert isinstance(scheme.reference, NominalReference)


def test_the_nominal_reference_predicts_the_nominal_mock_exactly():
    config = load_config()
    backend = MujocoBackend(config)
    backend.configure()
    backend.activate()
    reference = NominalReference(config, backend.ground_truth)
    rng = np.random.default_rng(0)
    state = backend.read()
    for _ in range(50):
        tau = rng.normal(0.0, 2.0, config.n_joints)
        q_hat, qd_hat = reference.step(state.joints.q, state.joints.qd, tau)
        backend.write(JointCommand(tau_ff=tau))
        state = backend.read()  # the mock applies the torque written over its next physics step
        np.testing.assert_allclose(q_hat, state.joints.q, atol=1e-9)
        np.testing.assert_allclose(qd_hat, state.joints.qd, atol=1e-7)


def test_a_nominal_shadow_rolls_the_whole_model_and_a_new_state_restarts_from_the_base_read_now():
    config = load_config()
    backend = MujocoBackend(config)
    backend.configure()
    backend.activate()
    state = backend.read()
    reference = NominalReference(config, backend.ground_truth)
    reference.reset()
    tau = np.full(config.n_joints, 0.5)
    q_hat, qd_hat = reference.step(state.joints.q, state.joints.qd, tau)
    for _ in range(9):
        q_hat, qd_hat = reference.step(q_hat, qd_hat, tau)  # its own output: the base rolls on with the joints
    for _ in range(10):
        backend.write(JointCommand(tau_ff=tau))
        state = backend.read()
    np.testing.assert_allclose(q_hat, state.joints.q, atol=1e-9)  # ten ticks of the simulator, base and all
    for _ in range(50):  # the robot moves on under other torques: its base leaves the shadow's
        backend.write(JointCommand(tau_ff=-tau))
        backend.read()
    rolled = reference.step(q_hat, qd_hat, tau)[1]  # its own output: from the shadow's base
    restarted = reference.step(q_hat.copy(), qd_hat.copy(), tau)[1]  # the same values, new arrays: the base read now
    assert np.abs(rolled - restarted).max() > 1e-6


def test_transfer_config_keys_are_bounded_and_related():
    config = load_config()
    assert settings_for(config).scheme == "direct" and settings_for(config).reference_model == "pinn"
    with pytest.raises(ConfigError, match=r"transfer\.scheme: expected one of direct, pinn, eq9, shadow, observer"):
        load_config(overrides=["transfer.scheme=eq10"])
    with pytest.raises(ConfigError, match=r"transfer\.observer\.clip: expected a number in \(0, 1\]"):
        load_config(overrides=["transfer.observer.clip=0"])
    with pytest.raises(ConfigError, match=r"transfer\.observer\.time_constant_s: .*delay_margin_s"):
        load_config(overrides=["transfer.observer.time_constant_s=0.01"])  # < 9 ms / (pi/2 - pi/4) = 11.5 ms
    load_config(overrides=["transfer.observer.time_constant_s=0.012"])
    assert config.models.pinn_residual_bias is None  # not measured: the observer takes nothing off


def test_pinn_residual_bias_is_per_joint_bounded_and_reaches_the_observer():
    config = load_config()
    raw = config.raw
    biased = dict(raw, pinn={**raw["pinn"], "residual_bias": {name: 0.001 * i for i, name in enumerate(config.joints)}})
    parsed = parse_config(biased, config.path)
    np.testing.assert_allclose(parsed.models.pinn_residual_bias, 0.001 * np.arange(config.n_joints))
    np.testing.assert_allclose(build_scheme(parsed, "observer").bias, parsed.models.pinn_residual_bias)
    backend = MujocoBackend(config)
    backend.configure()
    perfect = parse_config(dict(biased, transfer={"reference_model": "nominal"}), config.path)
    assert not build_scheme(perfect, "observer", base_state=backend.ground_truth).bias.any()  # the PINN's, not its
    broken = dict(raw, pinn={**raw["pinn"], "residual_bias": {name: 2.0 for name in config.joints}})
    with pytest.raises(ConfigError, match=r"pinn\.residual_bias\.r_hip_yaw: expected a number in \[-1, 1\] rad/s"):
        parse_config(broken, config.path)


def test_transfer_pinn_and_eq9_are_the_same_run():
    from runtime.control.commands import CommandSchedule
    from runtime.loop.observers import EachTick
    from runtime.loop.run import run_session

    config = load_config()
    torques = {}
    for name in ("pinn", "eq9"):
        sent = []
        run_session(MujocoBackend(config), config, duration=0.3, realtime=False, transfer=name,
                    commands=CommandSchedule.constant(0.3, 0.0, 0.0),
                    observers=[EachTick(lambda view, sent=sent: sent.append(view.tau.copy()))])
        torques[name] = np.array(sent)
    np.testing.assert_array_equal(torques["pinn"], torques["eq9"])
    direct = []
    run_session(MujocoBackend(config), config, duration=0.3, realtime=False,
                commands=CommandSchedule.constant(0.3, 0.0, 0.0),
                observers=[EachTick(lambda view: direct.append(view.tau.copy()))])
    assert np.abs(np.array(direct) - torques["eq9"]).max() > 0.01  # Eq. 9 does act


class ScriptedTwin:
    """A nominal twin whose posture at each tick is given; records what the scheme hands it."""

    def __init__(self, postures):
        self.postures = [np.array(p, float) for p in postures]
        self.q = None
        self.advanced: list[TwinInput] = []
        self.resets = 0

    def reset(self):
        self.resets += 1
        self.q = None

    def advance(self, step: TwinInput):
        self.advanced.append(step)
        self.q = self.postures.pop(0)


RESYNC = object()  # what the scripted schemes resynchronise from


def scripted_scheme(inner, twin, gain, clip, hold_ticks, disturbance=np.inf, lag=0, resync_ticks=1000):
    integral = TwinIntegral(twin, np.array(gain, float), np.array(clip, float), hold_ticks, disturbance)
    return TwinScheme(inner, InlineTwinRunner(integral, lag), lambda: RESYNC, resync_ticks, decimation=1)


def test_twin_integrates_the_posture_offset_from_the_twin_clips_holds_and_resets():
    twin = ScriptedTwin([[0.1, 0.1], [0.3, -0.2], [0.5, -0.2], [0.0, 0.0], [0.0, 0.0]])
    scheme = scripted_scheme(TransferScheme(), twin, gain=[2.0, 2.0], clip=[0.5, 10.0], hold_ticks=1)
    tau_star, command = np.array([1.0, -1.0]), np.array([0.4, 0.0, 0.0])
    q = np.zeros(2)
    scheme.predict(np.zeros(2), q, q, tau_star, command)  # no twin posture yet: nothing to integrate
    assert twin.advanced[0].resync is RESYNC  # the first tick sets the twin to the robot
    np.testing.assert_array_equal(scheme.torque(tau_star, q, q), tau_star)
    scheme.predict(np.zeros(2), q, q, tau_star, command)  # offset 0.1, 0.1 from the twin: u = 2 * offset
    np.testing.assert_allclose(scheme.u, [0.2, 0.2])
    np.testing.assert_allclose(scheme.torque(tau_star, q, q), [1.2, -0.8])  # tau* + u
    scheme.predict(np.zeros(2), np.array([0.1, 0.0]), q, tau_star, command)  # offset 0.2, -0.2: adds 0.4, -0.4
    np.testing.assert_allclose(scheme.u, [0.5, -0.2])  # 0.6 clipped to 0.5
    np.testing.assert_allclose(twin.advanced[-1].sent, [1.2, -0.8])  # the twin's rate limit starts from what was sent
    np.testing.assert_array_equal(twin.advanced[-1].command, command)  # the twin runs on the robot's command
    assert all(step.resync is None for step in twin.advanced[1:])
    resets = twin.resets
    scheme.reset()
    assert not scheme.u.any() and twin.resets == resets + 1 and twin.q is None


class FixedCorrection(TransferScheme):
    """An inner scheme that adds a fixed correction to tau* (a stand-in for the shadow's PD)."""

    name = "shadow"

    def __init__(self, correction):
        super().__init__()
        self.correction = np.array(correction, float)

    def torque(self, tau_star, q, qd):
        return tau_star + self.correction


def test_the_dead_band_gives_out_the_integral_past_it_and_fades_the_inner_correction_in():
    # offsets 0.1 rad per tick on joint 0, none on joint 1; gain 1, band 0.25 N·m: u = 0.1, 0.2, ... on joint 0
    twin = ScriptedTwin([[0.1, 0.0]] * 8)
    integral = TwinIntegral(twin, np.array([1.0, 1.0]), np.array([10.0, 10.0]), hold_ticks=0,
                            dead_band=np.array([0.25, 0.25]))
    scheme = TwinScheme(FixedCorrection([0.5, -0.5]), InlineTwinRunner(integral, 0), lambda: RESYNC, 1000,
                        decimation=1)
    tau_star, zero = np.array([1.0, 2.0]), np.zeros(2)
    sent = []
    for _ in range(8):
        scheme.predict(zero, zero, zero, tau_star)
        sent.append(scheme.torque(tau_star, zero, zero))
    # tick k integrates 0.1 k on joint 0 (none at tick 0: no twin posture yet)
    u0 = [max(0.0, 0.1 * k - 0.25) for k in range(8)]
    share = [min(1.0, max(0.0, 0.1 * k - 0.25) / 0.25) for k in range(8)]
    np.testing.assert_allclose([s[0] for s in sent], [1.0 + share[k] * 0.5 + u0[k] for k in range(8)], atol=1e-12)
    # joint 1: no offset, so no torque of the twin's and none of the inner scheme's: tau* exactly (direct transfer)
    assert all(s[1] == 2.0 for s in sent)
    # the band costs no steady-state accuracy: the integral itself runs on from zero, not from the band
    assert integral.u[0] == pytest.approx(0.7)


def test_the_band_grows_to_the_encoder_steps_seen_and_not_for_a_continuous_reading():
    # joint 0 read in counts of 0.01 rad, joint 1 continuous (noise); Kp 10, band 0.001 rad (0.01 N·m), 2 counts
    twin = ScriptedTwin([[0.0, 0.0]] * 6)
    integral = TwinIntegral(twin, np.array([1.0, 1.0]), np.array([10.0, 10.0]), hold_ticks=0,
                            dead_band=np.array([0.01, 0.01]), resolution_counts=2.0, kp=np.array([10.0, 10.0]))
    scheme = TwinScheme(FixedCorrection([0.5, 0.5]), InlineTwinRunner(integral, 0), lambda: RESYNC, 1000,
                        decimation=1)
    readings = [[0.0, 0.0], [0.0, 1e-4], [0.01, 3e-5], [0.03, 2e-5], [0.02, 1e-5], [0.02, 1.5e-5]]
    for q in readings:
        scheme.predict(np.zeros(2), np.array(q), np.zeros(2), np.zeros(2))
    np.testing.assert_allclose(integral.resolution, [0.01, 5e-6])
    np.testing.assert_allclose(integral.band, [2 * 10.0 * 0.01, 0.01])  # 2 counts at Kp; the set band stands
    assert not scheme.engaged.any()  # before any offset: direct transfer


def test_without_a_dead_band_the_inner_correction_is_applied_whole():
    twin = ScriptedTwin([[0.0]] * 3)
    scheme = scripted_scheme(FixedCorrection([0.5]), twin, gain=[1.0], clip=[10.0], hold_ticks=0)
    for _ in range(3):
        scheme.predict(np.zeros(1), np.zeros(1), np.zeros(1), np.ones(1))
        assert scheme.torque(np.ones(1), np.zeros(1), np.zeros(1))[0] == 1.5


def test_twin_holds_its_torque_until_the_hold_ends():
    twin = ScriptedTwin([[1.0]] * 5)
    scheme = scripted_scheme(TransferScheme(), twin, gain=[1.0], clip=[10.0], hold_ticks=3)
    for _ in range(3):
        scheme.predict(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
        assert scheme.u[0] == 0.0
    scheme.predict(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    assert scheme.u[0] == pytest.approx(1.0)


def test_the_torque_uses_the_integral_lag_ticks_old():
    twin = ScriptedTwin([[1.0]] * 8)
    scheme = scripted_scheme(TransferScheme(), twin, gain=[1.0], clip=[10.0], hold_ticks=0, lag=3)
    u = []
    for _ in range(8):
        scheme.predict(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
        u.append(scheme.u[0])
    # the integral after tick t is t (offset 1 per tick from tick 1 on); the torque at tick t uses the one at t - 3
    assert u == [0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0]


class VelocityTwin(ScriptedTwin):
    """A scripted twin whose estimated velocity is given too."""

    def __init__(self, postures, velocity):
        super().__init__(postures)
        self.velocity = np.array(velocity, float)


def test_the_command_correction_holds_the_robots_velocity_to_the_twins_and_only_the_robot_is_steered():
    from runtime.estimation import BaseEstimate
    from runtime.transfer.twin_runner import COMMAND_CLIP

    twin = VelocityTwin([[0.0]] * 6, velocity=[0.4, -0.03, 0.4])
    robot = BaseEstimate(quat=np.array([1.0, 0, 0, 0]), linvel=np.array([0.37, -0.07, 0.0]),
                         angvel=np.array([0.0, 0.0, 0.38]), euler=np.zeros(3))
    integral = TwinIntegral(twin, np.array([1.0]), np.array([10.0]), hold_ticks=0, command_gain=0.5)
    scheme = TwinScheme(TransferScheme(), InlineTwinRunner(integral, 0), lambda: RESYNC, 1000, decimation=1,
                        velocity=lambda: robot)
    command = np.array([0.4, 0.0, 0.4])
    steered = []
    for _ in range(6):
        steered.append(scheme.steer(command))
        scheme.predict(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), steered[-1])
    np.testing.assert_array_equal(steered[0], command)  # nothing to correct before the twin has a velocity
    # per policy tick 0.5 x (twin - robot) = (0.015, 0.02, 0.01), vx and wz until their clip
    np.testing.assert_allclose(steered[2] - command, [0.015, 0.02, 0.01])
    np.testing.assert_allclose(steered[5] - command, np.minimum(4 * np.array([0.015, 0.02, 0.01]), COMMAND_CLIP))
    assert all(np.array_equal(step.command, command) for step in twin.advanced)  # the twin walks the command alone
    off = scripted_scheme(TransferScheme(), VelocityTwin([[0.0]] * 2, [1.0, 1.0, 1.0]), [1.0], [10.0], 0)
    assert off.steer(command) is command  # no command correction configured: the command passes unchanged


def test_an_offset_beyond_the_disturbance_bound_is_not_integrated_and_resyncs_the_twin():
    twin = ScriptedTwin([[0.05], [0.5], [0.05], [0.05]])
    scheme = scripted_scheme(TransferScheme(), twin, gain=[1.0], clip=[10.0], hold_ticks=0, disturbance=0.3)
    zero = np.zeros(1)
    scheme.predict(zero, zero, zero, zero)
    scheme.predict(zero, zero, zero, zero)  # offset 0.05: a gap, integrated
    assert scheme.u[0] == pytest.approx(0.05) and twin.advanced[-1].resync is None
    scheme.predict(zero, zero, zero, zero)  # offset 0.5: a push the twin did not feel
    assert scheme.u[0] == pytest.approx(0.05)
    scheme.predict(zero, zero, zero, zero)  # the next policy tick resynchronises the twin
    assert twin.advanced[-1].resync is RESYNC and scheme.u[0] == pytest.approx(0.10)


def test_shadow_twin_adds_the_integral_to_the_shadows_pd():
    model = RecordingModel([([0.01, 0.02], [0.1, 0.2]), ([0.0, 0.0], [0.0, 0.0])])
    shadow = ShadowScheme(model, GAINS, EQ8, resync_ticks=5)
    twin = ScriptedTwin([[0.1, 0.0], [0.0, 0.0]])
    scheme = scripted_scheme(shadow, twin, gain=[1.0, 1.0], clip=[5.0, 5.0], hold_ticks=0)
    a, q, qd, tau_star = np.array([0.5, -0.5]), np.zeros(2), np.zeros(2), np.array([2.0, 2.0])
    scheme.predict(a, q, qd, tau_star)
    scheme.torque(tau_star, q, qd)
    scheme.predict(a, q, np.array([0.05, 0.1]), tau_star)  # shadow PD [0.15, 0.6] (as above), twin offset 0.1, 0
    np.testing.assert_allclose(scheme.torque(tau_star, q, np.array([0.05, 0.1])), [2.0 + 0.15 + 0.1, 2.0 + 0.6])
    assert scheme.q_hat is shadow.q_hat and scheme.name == "shadow_twin"


def run_with_twin(config, gap, ticks, faithful=False, differential=True):
    """The run loop's stages by hand (read, policy every 10th tick, Eq. 8, the scheme, safety, write) with the `twin`
    scheme, its twin resynchronised from the simulator's truth or (`faithful`) from the robot's kinematic estimator;
    per tick the twin's posture error and the integral."""
    from runtime.control.controllers import build_controller
    from runtime.estimation import GroundTruthEstimator
    from runtime.loop.safety import SafetyStage

    backend = MujocoBackend(config, gap=gap)
    backend.configure()
    controller, _ = build_controller(config, None, "policy")
    estimator = KinematicEstimator(config) if faithful else GroundTruthEstimator(backend)
    safety = SafetyStage(config)
    scheme = build_scheme(config, "twin", base_state=None if faithful else backend.ground_truth, estimator=estimator)
    scheme.twin.differential = differential
    backend.activate()
    state = backend.read()
    controller.reset(state.joints.q)
    estimator.reset(state)
    scheme.reset()
    command = np.array([0.3, 0.0, 0.0])
    offsets, integral = [], []
    for tick in range(ticks):
        state = backend.read()
        q, qd = state.joints.q, state.joints.qd
        estimator.update(state)
        if tick % config.policy_decimation == 0:
            a = controller(state, estimator.estimate(), command)
        if scheme.twin.q is not None:
            offsets.append(np.abs(scheme.twin.q - q).max())
        tau_star = eq8_torque(a, q, qd, config.eq8)
        scheme.predict(a, q, qd, tau_star, command)
        backend.write(JointCommand(tau_ff=safety.filter(scheme.torque(tau_star, q, qd), state)))
        integral.append(np.abs(scheme.u).max())
    return np.array(offsets), np.array(integral), scheme


def test_where_the_robot_is_the_simulator_the_twin_is_the_robot_and_adds_no_torque():
    config = load_config(overrides=["transfer.twin.resync_s=0.1"])
    offsets, integral, scheme = run_with_twin(config, None, 400)
    assert scheme.twin.tick == 399 and scheme.runner.integral.hold_ticks == 100  # resyncs after the hold ran
    assert scheme.resyncs == 4
    assert offsets.max() < 1e-9  # the twin reproduces the nominal mock, torque ramp and rate limit included
    assert integral.max() < 1e-12  # N·m: rounding


@pytest.mark.slow
def test_a_twin_resynchronised_from_the_estimator_stays_with_the_simulator():
    """Robot-faithful: the twin is set from the robot's estimate, not its truth (the base's height, yaw and position
    are the twin's own; its attitude and velocities its own moved by the difference between the robot's estimate
    and its own estimator's). Where the robot is the simulator it stays within a few mrad of it over 2 s of walking
    with 0.5 s between resyncs; with the gap, the offsets it shows are several times that. Set to the robot's
    estimate alone (no difference taken), the estimator's lag behind the gait's velocity swings makes the twin drift
    on its own."""
    config = load_config(overrides=["transfer.twin.resync_s=0.5"])
    offsets, integral, scheme = run_with_twin(config, None, 2000, faithful=True)
    assert scheme.resyncs == 4 and not scheme.twin.from_truth and scheme.twin.differential
    assert 0.0 < offsets.max() < 0.008
    from bruce_hw.reality_gap import load_gap

    gapped, _, _ = run_with_twin(config, load_gap("default"), 2000, faithful=True)
    assert gapped.max() > 5 * offsets.max()
    plain, _, _ = run_with_twin(config, None, 2000, faithful=True, differential=False)
    assert plain[500:].mean() > 3 * offsets[500:].mean()


def test_with_a_gap_the_twin_sees_an_offset_and_the_integral_acts_within_its_clip():
    from bruce_hw.reality_gap import load_gap

    # the integral itself, given out whole (the dead band is tested on its own)
    config = load_config(overrides=["transfer.twin.resync_s=0.1", "transfer.twin.time_constant_s=1",
                                    "transfer.twin.dead_band_rad=0"])
    offsets, integral, scheme = run_with_twin(config, load_gap("default"), 400)
    lag = settings_for(config).of("twin").lag_ticks
    assert offsets.max() > 1e-3
    # held until the first resync after the torque ramp, and read lag_ticks late
    assert not integral[:100 + lag].any() and integral[-1] > 0.0
    assert np.all(np.abs(scheme.u) <= scheme.runner.integral.clip)


def test_build_twin_schemes_read_the_config_and_resync_from_the_estimator_or_the_truth():
    config = load_config(overrides=["transfer.twin.resync_s=0.5", "transfer.twin.time_constant_s=4",
                                    "transfer.twin.clip=0.1", "transfer.twin.lag_ticks=7"])
    backend = MujocoBackend(config)
    backend.configure()
    estimator = KinematicEstimator(config)
    twin = build_scheme(config, "twin", estimator=estimator)
    assert isinstance(twin, TwinScheme) and type(twin.inner) is TransferScheme and twin.name == "twin"
    assert twin.resync_ticks == 500 and twin.runner.integral.hold_ticks == 500 and twin.runner.lag == 7
    assert twin.resync_state == estimator.snapshot  # what a robot has
    assert isinstance(twin.runner, InlineTwinRunner) and not isinstance(twin.runner, ThreadTwinRunner)
    np.testing.assert_allclose(twin.runner.integral.gain, config.eq8.kp * config.dt / 4.0)
    np.testing.assert_allclose(twin.runner.integral.clip, 0.1 * config.tau_limit)
    dead_band = settings_for(config).of("twin").dead_band_rad
    np.testing.assert_allclose(twin.runner.integral.dead_band, config.eq8.kp * dead_band)
    paced = build_scheme(config, "shadow_twin", estimator=estimator, paced=True)
    assert isinstance(paced.inner, ShadowScheme) and isinstance(paced.runner, ThreadTwinRunner)
    assert build_scheme(config, "twin", base_state=backend.ground_truth).resync_state == backend.ground_truth
    with pytest.raises(ModelError, match="resynchronised from the kinematic estimator's state"):
        build_scheme(config, "twin", estimator=object())
    with pytest.raises(ConfigError, match=r"transfer\.twin\.time_constant_s: expected a number in \[1, 60\] s"):
        load_config(overrides=["transfer.twin.time_constant_s=0.5"])
    with pytest.raises(ConfigError, match=r"transfer\.twin\.clip: expected a number in \(0, 1\]"):
        load_config(overrides=["transfer.twin.clip=0"])
