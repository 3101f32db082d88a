"""The transfer stage of the tick: after Eq. 8 (tau*), before safety. One interface, one scheme per `--transfer`
(docs/transfer.md, "The schemes").

A scheme (`build_scheme`) gets the policy's targets a_t, the measured joint state and tau*, asks its reference model
(a `runtime.reference_models.ReferenceModel`: the PINN, or the nominal MuJoCo model as the perfect-model control)
what the simulator would do (`predict`: the model work, timed as the loop's `pinn` section) and returns the torque
to send (`torque`: the mixing). Schemes: `direct` (`TransferScheme`), `eq9` / `pinn` (`Eq9Scheme`), `shadow`
(`ShadowScheme`), `observer` (`ObserverScheme`), `twin` and `shadow_twin` (`TwinScheme`). `one_step` is the model's
prediction of the next tick's (q, qd) from this tick's measured state (None when the scheme made none this tick):
the gap monitor's input (`runtime.gap_monitor`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bruce_hw.config import TRANSFER_SCHEMES as TRANSFERS  # the config validates transfer.scheme against them
from bruce_hw.config import PdGains, RobotConfig
from runtime.controllers import build_controller
from runtime.mixing import eq8_torque, eq9_torque
from runtime.nominal_twin import NominalTwin
from runtime.reference_models import ReferenceModel, build_reference
from runtime.transfer_gains import joint_inertia, observer_gain, pd_gains

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
    `runtime.transfer_gains.pd_gains`). The model rolls the shadow on from its own previous state under the
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
    live nominal twin (`runtime.nominal_twin`): u <- clip(u + Kp dt / T (q_twin - q), +- clip), Kp the Eq. 8
    stiffness, T = `transfer.twin.time_constant_s`. It sees the offsets that build over seconds (a static load, a
    turning gait's lean), which no prediction over a few ticks does; where the robot is the simulator, u stays 0.
    An offset above `transfer.twin.disturbance_rad` is a push the twin did not feel: not integrated, and the twin
    resynchronises. Mock only: the twin needs the full base state."""

    def __init__(self, inner: TransferScheme, twin: NominalTwin, gain: np.ndarray, clip: np.ndarray,
                 hold_ticks: int, disturbance: float = np.inf):
        super().__init__(inner.reference)
        self.name = "twin" if inner.name == "direct" else f"{inner.name}_twin"
        self.inner, self.twin = inner, twin
        self.gain, self.clip, self.hold_ticks = gain, clip, hold_ticks  # gain: N·m per rad of offset, per tick
        self.disturbance = disturbance  # rad: an offset this large is something the twin did not feel, not a gap
        self.u = np.zeros_like(gain)
        self._ticks = 0
        self._sent: np.ndarray | None = None  # the torque this scheme gave last tick

    def reset(self) -> None:
        self.inner.reset()
        self.twin.reset()
        self.q_hat = self.qd_hat = self.one_step = None
        self.u = np.zeros_like(self.gain)
        self._ticks = 0
        self._sent = None

    def predict(self, a, q, qd, tau_star, command=None) -> None:
        self.inner.predict(a, q, qd, tau_star, command)
        self.q_hat, self.qd_hat, self.one_step = self.inner.q_hat, self.inner.qd_hat, self.inner.one_step
        if self.twin.q is not None:
            offset = self.twin.q - q
            if np.abs(offset).max() > self.disturbance:
                self.twin.resync_requested = True  # integrated, a push would be pulled back along the twin's path
            elif self._ticks >= self.hold_ticks:
                self.u = np.clip(self.u + self.gain * offset, -self.clip, self.clip)
        self._ticks += 1
        self.twin.advance(a, q, qd, np.zeros(3) if command is None else command, self._sent)

    def torque(self, tau_star, q, qd) -> np.ndarray:
        self._sent = self.inner.torque(tau_star, q, qd) + self.u
        return self._sent


def build_scheme(config: RobotConfig, name: str, pinn_path: Path | None = None, base_state=None,
                 twin_controller=None) -> TransferScheme:
    """The scheme `name` (TRANSFERS) with its reference model (`transfer.reference_model`; `base_state` gives the
    nominal model its base state: the backend's ground truth) and its settings from `config.transfer`.
    `twin_controller()` makes the twin schemes' second instance of the robot's nominal controller (default: the
    configured walking policy)."""
    if name not in TRANSFERS:
        raise ValueError(f"unknown transfer {name!r} (expected one of {', '.join(TRANSFERS)})")
    if name == "direct":
        return TransferScheme()
    settings = config.transfer
    if name in TWIN_SCHEMES:
        inner = build_scheme(config, TWIN_SCHEMES[name], pinn_path, base_state)
        resync = max(1, round(settings.twin_resync_s * config.loop_hz))
        controller = twin_controller() if twin_controller is not None else build_controller(config, None, "policy")[0]
        twin = NominalTwin(config, base_state or (lambda: None), resync, controller)
        # The integral starts at the first resync after the torque ramp: the window before began from the pose at
        # activation with the torques still fading in.
        ramp = round(config.safety.torque_ramp_s * config.loop_hz)
        return TwinScheme(inner, twin, config.eq8.kp * config.dt / settings.twin_time_constant_s,
                          settings.twin_clip * config.tau_limit, hold_ticks=-(-(ramp + 1) // resync) * resync,
                          disturbance=settings.twin_disturbance_rad)
    lookahead = config.models.pinn_lookahead_ticks if name in EQ9_ALIASES else 0
    reference = build_reference(config, settings.reference_model, pinn_path, base_state or (lambda: None),
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
