"""The transfer stage of the tick: after Eq. 8 (tau*), before safety. One interface, one scheme per `--transfer`
(docs/transfer.md, "The schemes").

A scheme (`build_scheme`) gets the policy's targets a_t, the measured joint state and tau*, asks its reference model
(a `reference_models.ReferenceModel`: the PINN, or the nominal MuJoCo model as the perfect-model control)
what the simulator would do (`predict`: the model work, timed as the loop's `pinn` section) and returns the torque
to send (`torque`: the mixing). Schemes: `direct` (`TransferScheme`), `eq9` / `pinn` (`Eq9Scheme`), `shadow`
(`ShadowScheme`), `observer` (`ObserverScheme`), `twin` and `shadow_twin` (`TwinScheme`). `one_step` is the model's
prediction of the next tick's (q, qd) from this tick's measured state (None when the scheme made none this tick):
the gap monitor's input (`runtime.transfer.gap_monitor`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bruce_hw.config import TRANSFER_SCHEMES as TRANSFERS  # the config validates transfer.scheme against them
from bruce_hw.config import PdGains, RobotConfig
from runtime.controllers import build_controller
from runtime.inference import ModelError
from runtime.mixing import eq8_torque, eq9_torque
from runtime.transfer.gains import joint_inertia, observer_gain, pd_gains
from runtime.transfer.nominal_twin import NominalTwin, TwinInput
from runtime.transfer.reference_models import ReferenceModel, build_reference
from runtime.transfer.twin_runner import MAX_BACKLOG_TICKS, InlineTwinRunner, ThreadTwinRunner, TwinIntegral

EQ9_ALIASES = ("pinn", "eq9")  # `--transfer pinn` has always meant the paper's Eq. 9
TWIN_SCHEMES = {"twin": "direct", "shadow_twin": "shadow"}  # each one's inner scheme


class TransferScheme:
    """Direct transfer (tau* unchanged), and the interface of every scheme."""

    name = "direct"

    def __init__(self, reference: ReferenceModel | None = None):
        self.reference = reference
        self.q_hat: np.ndarray | None = None   # the reference state shown beside the measured one (telemetry)
        self.qd_hat: np.ndarray | None = None
        self.one_step: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self.q_hat = self.qd_hat = None
        self.one_step = None
        if self.reference is not None:
            self.reference.reset()

    def predict(self, a: np.ndarray, q: np.ndarray, qd: np.ndarray, tau_star: np.ndarray,
                command: np.ndarray | None = None) -> None:
        """The model work of this tick (none for direct transfer); `command` is the (vx, vy, yaw rate) in force."""

    def torque(self, tau_star: np.ndarray, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        return tau_star

    def steer(self, command: np.ndarray) -> np.ndarray:
        """The velocity command the robot's controller gets on this policy tick, from the one in force (only the
        twin's command correction changes it)."""
        return command

    def close(self) -> None:
        """Release what the scheme started (the twin's thread); called on every exit path of a run."""

    def report(self) -> dict:
        """The scheme's own figures for the run's summary (the twin's: resyncs, how far behind it ran)."""
        return {}


class Eq9Scheme(TransferScheme):
    """The paper's Eq. 9 on the model's one-step (or look-ahead) prediction under tau*: tau* + Kp' (q^' - q) +
    Kd' (qd^' - qd), gains `gains.eq9`. Its feedback is nearly nothing: q^' - q ~ qd dt whatever the gap, so it
    mostly adds Kp' qd dt + Kd' (qd^' - qd)."""

    name = "eq9"

    def __init__(self, reference: ReferenceModel, gains: PdGains, one_step: bool = True):
        super().__init__(reference)
        self.gains = gains
        self._one_step = one_step  # False: the model rolls ahead (pinn.lookahead_ticks), not a one-step prediction

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.q_hat, self.qd_hat = self.reference.step(q, qd, tau_star)
        self.one_step = (self.q_hat, self.qd_hat) if self._one_step else None

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return eq9_torque(tau_star, self.q_hat, self.qd_hat, q, qd, self.gains)


class ShadowScheme(TransferScheme):
    """A PD towards the simulator's shadow at the same tick (gains from the delay margin,
    `runtime.transfer.gains.pd_gains`). The model rolls the shadow on from its own previous state under the
    simulator's own Eq. 8 torque on the same a_t, resynchronised to the measured state every
    `transfer.shadow.resync_ticks`."""

    name = "shadow"

    def __init__(self, reference: ReferenceModel, gains: PdGains, eq8: PdGains, resync_ticks: int):
        super().__init__(reference)
        self.gains, self.eq8, self.resync_ticks = gains, eq8, resync_ticks
        self._tick = 0
        self._next: tuple[np.ndarray, np.ndarray] | None = None  # the shadow's state at the coming tick

    def reset(self) -> None:
        super().reset()
        self._tick = 0
        self._next = None

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        resync = self._next is None or self._tick % self.resync_ticks == 0
        self._tick += 1
        if resync:
            self.q_hat, self.qd_hat = q.copy(), qd.copy()
            tau_shadow = tau_star
        else:
            self.q_hat, self.qd_hat = self._next
            tau_shadow = eq8_torque(a, self.q_hat, self.qd_hat, self.eq8)  # the simulator's own Eq. 8 torque
        self._next = self.reference.step(self.q_hat, self.qd_hat, tau_shadow)
        self.one_step = self._next if resync else None

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return eq9_torque(tau_star, self.q_hat, self.qd_hat, q, qd, self.gains)  # same PD form, margin-derived gains


class ObserverScheme(TransferScheme):
    """tau* + u, u a slow clipped integrator of the one-step velocity residual (model under tau* minus measured),
    gain I / T (T = `transfer.observer.time_constant_s`), clipped to `transfer.observer.clip` x the torque limit.
    It settles where the robot under tau* + u moves as the model does under tau*: a disturbance observer whose
    nominal plant is the reference model. Held at zero during the safety stage's torque ramp (the robot then gets
    less than tau*); the model's own mean residual on the simulator (`pinn.residual_bias`) is taken off, since
    integrated, a model's bias becomes a posture offset on any robot."""

    name = "observer"

    def __init__(self, reference: ReferenceModel, gain: np.ndarray, clip: np.ndarray, hold_ticks: int = 0,
                 bias: np.ndarray | None = None):
        super().__init__(reference)
        self.gain, self.clip, self.hold_ticks = gain, clip, hold_ticks
        # The model's own mean residual on the simulator (predicted minus simulated qd): not a gap, so not integrated.
        self.bias = np.zeros_like(gain) if bias is None else bias
        self.u = np.zeros_like(gain)
        self._ticks = 0

    def reset(self) -> None:
        super().reset()
        self.u = np.zeros_like(self.gain)
        self._ticks = 0

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        if self.one_step is not None and self._ticks >= self.hold_ticks:
            residual = self.one_step[1] - qd - self.bias  # > 0: the robot is slower than the model: push more
            self.u = np.clip(self.u + self.gain * residual, -self.clip, self.clip)
        self._ticks += 1
        self.one_step = self.reference.step(q, qd, tau_star)
        self.q_hat, self.qd_hat = self.one_step

    def torque(self, tau_star, q, qd) -> np.ndarray:
        return tau_star + self.u


class TwinScheme(TransferScheme):
    """An inner scheme (direct or the shadow) plus a slow clipped integral of the robot's posture offset from its
    live nominal twin (`nominal_twin`, `twin_runner.TwinIntegral`): u <- clip(u + Kp dt / T
    (q_twin - q), +- clip), Kp the Eq. 8 stiffness, T = `transfer.twin.time_constant_s`. It sees the offsets that
    build over seconds (a static load, a turning gait's lean), which no prediction over a few ticks does; where the
    robot is the simulator, u stays 0. The twin is resynchronised to the robot every `resync_ticks` (and at the next
    policy tick after an offset that looks like a push) from `resync_state()`: the robot's estimator snapshot in a
    robot-faithful run, the simulator's truth in a truth-fed one. It runs where `runner` puts it (inline, or on a
    thread of its own), and the torque uses the integral `transfer.twin.lag_ticks` old. With a command correction
    (`transfer.twin.command_time_constant_s` > 0; `velocity()`: the robot's estimated (vx, vy, yaw rate)), the
    robot's controller gets the command in force plus the correction (`steer`), the twin the command alone.

    With a dead band (`transfer.twin.dead_band_rad` > 0, `TwinIntegral`), the integral acts only past it, and the
    inner scheme's correction (the shadow's PD) is applied in the share `engaged` of each joint: the shadow's model
    has a floor of its own (its null-test error), which a robot that needs no correction should not get. Where the
    twin sees no offset beyond its noise, the scheme is direct transfer, torque for torque."""

    def __init__(self, inner: TransferScheme, runner, resync_state, resync_ticks: int, decimation: int,
                 velocity=None):
        super().__init__(inner.reference)
        self.name = "twin" if inner.name == "direct" else f"{inner.name}_twin"
        self.inner, self.runner = inner, runner
        self.resync_state, self.resync_ticks, self.decimation = resync_state, resync_ticks, decimation
        self.velocity = velocity if runner.integral.command_gain else None
        self.u = np.zeros_like(runner.integral.gain)
        self._clear()

    @property
    def twin(self):
        return self.runner.integral.twin

    def reset(self) -> None:
        self.inner.reset()
        self.runner.reset()
        # Before the loop, not on its first tick: the twin's thread starts and the resync's snapshot is taken once
        # (their first time in a process cost the first tick ~3 ms of the control thread's CPU).
        self.runner.start()
        self.resync_state()
        self._clear()

    def _clear(self) -> None:
        self.q_hat = self.qd_hat = self.one_step = None
        self.u = np.zeros_like(self.u)
        self.engaged = np.zeros_like(self.u) if self.runner.integral.banded else np.ones_like(self.u)
        self.command_offset = np.zeros(3)
        self._command: np.ndarray | None = None  # the command in force, as the twin gets it
        self._tick = 0
        self._sent: np.ndarray | None = None  # the torque this scheme gave last tick
        self._resynced = -1      # the tick of the last resync
        self._behind = False     # the twin fell behind and was not posted to: resync at the next policy tick
        self.behind_ticks = 0    # ticks not posted because the twin was behind (paced runs on a starved machine)
        self.resyncs = 0
        self.backlog_max = 0     # the most ticks posted and not yet stepped, seen at a post

    def close(self) -> None:
        self.runner.close()

    def report(self) -> dict:
        return {"twin": {"resyncs": self.resyncs, "stepped": self.runner.done + 1, "backlog_max": self.backlog_max,
                         "behind_ticks": self.behind_ticks, "lag_ticks": self.runner.lag,
                         "thread": isinstance(self.runner, ThreadTwinRunner)}}

    def steer(self, command: np.ndarray) -> np.ndarray:
        self._command = np.array(command, dtype=float)
        return self._command + self.command_offset if self.velocity is not None else command

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.inner.predict(a, q, qd, tau_star, command)
        self.q_hat, self.qd_hat, self.one_step = self.inner.q_hat, self.inner.qd_hat, self.inner.one_step
        tick = self._tick
        self._tick += 1
        runner = self.runner
        backlog = runner.backlog()
        self.backlog_max = max(self.backlog_max, backlog)
        if backlog > MAX_BACKLOG_TICKS:
            self._behind = True
            self.behind_ticks += 1
            return  # the integral holds
        policy_tick = tick % self.decimation == 0
        resync = tick % self.resync_ticks == 0 or (policy_tick and (
            self._behind or runner.resync_asked(self._resynced, tick)))
        if resync:
            self._resynced, self._behind = tick, False
            self.resyncs += 1
        elif self._behind:
            return
        if self._command is None:  # not steered (a caller outside the loop): the command given is the one in force
            self._command = np.zeros(3) if command is None else np.array(command, dtype=float)
        velocity = None
        if self.velocity is not None and policy_tick:
            base = self.velocity()
            velocity = np.array((base.linvel[0], base.linvel[1], base.angvel[2]))
        runner.post(TwinInput(tick, np.array(a, dtype=float), q.copy(), qd.copy(), self._command, self._sent,
                              self.resync_state() if resync else None, velocity))
        self.u, self.command_offset, self.engaged = runner.u_at(tick)

    def torque(self, tau_star, q, qd) -> np.ndarray:
        inner = self.inner.torque(tau_star, q, qd)
        self._sent = tau_star + self.engaged * (inner - tau_star) + self.u
        return self._sent


def build_scheme(config: RobotConfig, name: str, pinn_path: Path | None = None, base_state=None,
                 twin_controller=None, estimator=None, paced: bool = False) -> TransferScheme:
    """The scheme `name` (TRANSFERS) with its reference model (`transfer.reference_model`) and its settings from
    `config.transfer`. Where the schemes' nominal models get the robot's base from: `estimator` (the run's
    `KinematicEstimator`: a robot-faithful run, any backend) or, when `base_state` is given instead, the simulator's
    truth (a truth-fed diagnostic run on the mock). `twin_controller()` makes the twin schemes' second instance of
    the robot's nominal controller (default: the configured walking policy); `paced`: the twin runs on a thread of
    its own (`runtime.transfer.twin_runner`)."""
    if name not in TRANSFERS:
        raise ValueError(f"unknown transfer {name!r} (expected one of {', '.join(TRANSFERS)})")
    if name == "direct":
        return TransferScheme()
    settings = config.transfer
    if name in TWIN_SCHEMES:
        inner = build_scheme(config, TWIN_SCHEMES[name], pinn_path, base_state, estimator=estimator)
        resync = max(1, round(settings.twin_resync_s * config.loop_hz))
        controller = twin_controller() if twin_controller is not None else build_controller(config, None, "policy")[0]
        # The integral starts at the first resync after the torque ramp: the window before began from the pose at
        # activation with the torques still fading in.
        ramp = round(config.safety.torque_ramp_s * config.loop_hz)
        gain = config.eq8.kp * config.dt / settings.twin_time_constant_s
        command_gain = 0.0 if not settings.twin_command_time_constant_s else (
            1.0 / (config.policy_hz * settings.twin_command_time_constant_s))
        integral = TwinIntegral(NominalTwin(config, controller), gain, settings.twin_clip * config.tau_limit,
                                hold_ticks=-(-(ramp + 1) // resync) * resync, disturbance=settings.twin_disturbance_rad,
                                command_gain=command_gain, dead_band=settings.twin_dead_band_rad * config.eq8.kp,
                                resolution_counts=settings.twin_resolution_counts, kp=config.eq8.kp)
        runner = (ThreadTwinRunner if paced else InlineTwinRunner)(integral, settings.twin_lag_ticks)
        return TwinScheme(inner, runner, _resync_state(name, base_state, estimator), resync,
                          config.policy_decimation, velocity=None if estimator is None else estimator.estimate)
    lookahead = config.models.pinn_lookahead_ticks if name in EQ9_ALIASES else 0
    reference_base = base_state if base_state is not None else (
        None if estimator is None else estimator.estimate)
    if settings.reference_model == "nominal" and reference_base is None:
        raise ModelError(f"--transfer {name} with transfer.reference_model nominal: the nominal model needs the "
                         "robot's base state, from the run's estimator (or, in a diagnostic, the simulator's truth)")
    reference = build_reference(config, settings.reference_model, pinn_path, reference_base or (lambda: None),
                                lookahead=lookahead, scheme=name)
    if name in EQ9_ALIASES:
        return Eq9Scheme(reference, config.eq9, one_step=lookahead == 0)
    inertia = joint_inertia(config)
    if name == "shadow":
        gains = pd_gains(inertia, settings.delay_margin_s, settings.phase_margin_deg)
        return ShadowScheme(reference, gains, config.eq8, settings.shadow_resync_ticks)
    bias = config.models.pinn_residual_bias if settings.reference_model == "pinn" else None
    return ObserverScheme(reference, observer_gain(inertia, settings.observer_time_constant_s),
                          settings.observer_clip * config.tau_limit,
                          hold_ticks=round(config.safety.torque_ramp_s * config.loop_hz), bias=bias)


def _resync_state(name: str, base_state, estimator):
    """What the twin is resynchronised from: the simulator's truth where the run is truth-fed, else the robot's
    estimator (its state and estimate, `KinematicEstimator.snapshot`)."""
    if base_state is not None:
        return base_state
    snapshot = getattr(estimator, "snapshot", None)
    if snapshot is None:
        raise ModelError(f"--transfer {name}: the nominal twin is resynchronised from the kinematic estimator's "
                         f"state; this run's estimator ({type(estimator).__name__}) has none")
    return snapshot
