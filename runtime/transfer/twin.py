"""The twin schemes (`--transfer twin`, `shadow_twin`): an inner scheme (direct transfer, or the shadow) plus a slow
clipped integral of the robot's posture offset from its live nominal twin (`nominal_twin`, `twin_runner`). Their
settings: `transfer.twin`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bruce_hw.yaml_reader import Bound
from runtime.control.controllers import build_controller
from runtime.control.inference import ModelError
from runtime.transfer.interface import TransferScheme
from runtime.transfer.nominal_twin import NominalTwin, TwinInput
from runtime.transfer.registry import SchemeContext, register_scheme
from runtime.transfer.settings import setting
from runtime.transfer.twin_runner import MAX_BACKLOG_TICKS, InlineTwinRunner, ThreadTwinRunner, TwinIntegral


@dataclass(frozen=True)
class TwinSettings:
    """transfer.twin"""

    # the nominal twin rolls this long from the robot's state before a resync
    resync_s: float = setting(2.0, Bound(0.01, 10.0, "s", "twin horizon: from one policy period to a walk's length"))
    # the twin integral's time constant: gain Kp_eq8 / T per s of offset
    time_constant_s: float = setting(2.0, Bound(1.0, 60.0, "s", "twin integral settling; 0.5 s fell "
                                                "(docs/results/transfer_schemes.md)"))
    clip: float = setting(0.25, Bound(0.0, 1.0, "", "share of joints.torque_limits", low_open=True))
    # a larger offset from the twin is a push, not a gap: resync, not integrated
    disturbance_rad: float = setting(0.3, Bound(0.01, 3.0, "rad", "offset from the twin taken as a push"))
    # the integral acts on the twin's offset this many ticks old (its own thread)
    lag_ticks: int = setting(10, Bound(0, 200, "ticks", "the twin's answer may be this late: 0.2 s beside T >= 1 s",
                                       integer=True))
    # > 0: the twin's command correction settles this slowly; 0: off
    command_time_constant_s: float = setting(0.0, Bound(0.0, 60.0, "s", "command correction settling; 0: off"))
    # the integral acts past Eq. 8 Kp x this, the shadow's share fades in past it
    dead_band_rad: float = setting(0.0, Bound(0.0, 0.05, "rad", "dead band as a posture offset at Eq. 8 Kp; 0: off"))
    # ... and past this many of the joint's encoder steps seen (0: off)
    resolution_counts: float = setting(0.0, Bound(0.0, 100.0, "", "dead band of at least this many encoder steps; "
                                                  "0: off"))


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

    @property
    def one_step(self):
        return self.inner.one_step  # read when the loop asks: the inner scheme's step may run beside the loop

    def reset(self) -> None:
        self.inner.reset()
        self.runner.reset()
        # Before the loop, not on its first tick: the twin's thread starts and the resync's snapshot is taken once
        # (their first time in a process cost the first tick ~3 ms of the control thread's CPU).
        self.runner.start()
        self.resync_state()
        self._clear()

    def _clear(self) -> None:
        self.q_hat = self.qd_hat = None
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
        self.inner.close()
        self.runner.close()

    def report(self) -> dict:
        twin = {"resyncs": self.resyncs, "stepped": self.runner.done + 1, "backlog_max": self.backlog_max,
                "behind_ticks": self.behind_ticks, "lag_ticks": self.runner.lag,
                "thread": isinstance(self.runner, ThreadTwinRunner)}
        return {**self.inner.report(), "twin": twin}

    def steer(self, command: np.ndarray) -> np.ndarray:
        self._command = np.array(command, dtype=float)
        return self._command + self.command_offset if self.velocity is not None else command

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.inner.predict(a, q, qd, tau_star, command)
        self.q_hat, self.qd_hat = self.inner.q_hat, self.inner.qd_hat
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


def twin_builder(inner: str):
    """The builder of the twin scheme around the scheme `inner`."""

    def build(context: SchemeContext) -> TwinScheme:
        config, settings = context.config, context.settings
        inner_scheme = context.build(inner)
        resync = max(1, round(settings.resync_s * config.loop_hz))
        controller = context.twin_controller() if context.twin_controller is not None else \
            build_controller(config, None, "policy")[0]
        # The integral starts at the first resync after the torque ramp: the window before began from the pose at
        # activation with the torques still fading in.
        ramp = round(config.safety.torque_ramp_s * config.loop_hz)
        gain = config.eq8.kp * config.dt / settings.time_constant_s
        command_gain = 0.0 if not settings.command_time_constant_s else (
            1.0 / (config.policy_hz * settings.command_time_constant_s))
        integral = TwinIntegral(NominalTwin(config, controller), gain, settings.clip * config.tau_limit,
                                hold_ticks=-(-(ramp + 1) // resync) * resync, disturbance=settings.disturbance_rad,
                                command_gain=command_gain, dead_band=settings.dead_band_rad * config.eq8.kp,
                                resolution_counts=settings.resolution_counts, kp=config.eq8.kp)
        runner = (ThreadTwinRunner if context.paced else InlineTwinRunner)(integral, settings.lag_ticks)
        estimator = context.estimator
        return TwinScheme(inner_scheme, runner, _resync_state(context.name, context.base_state, estimator), resync,
                          config.policy_decimation, velocity=None if estimator is None else estimator.estimate)

    return build


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


register_scheme("twin", TwinSettings, twin_builder("direct"),
                help="direct transfer plus a slow integral of the offset from a live nominal twin")
register_scheme("shadow_twin", TwinSettings, twin_builder("shadow"), section="twin", uses_reference=True,
                help="the shadow plus the twin's integral")
