"""OLNN baseline (Gupta et al. 2019, structured mechanical models): Lagrangian dynamics from three networks, RK4.

    M(q) = L'(q) L'(q)^T,  L' = S L               L lower-triangular from an MLP on q, positive diagonal: M is SPD
    g(q) = dV/dq                                  V(q) a scalar potential-energy MLP on q
    F(q, qd, tau)                                 non-conservative force (friction, actuator, contact), an MLP
    c(q, qd) = Mdot qd - 1/2 d(qd^T M qd)/dq      Coriolis/centrifugal terms
    qdd = M^-1 (tau + F - c - g),  (q', qd') = RK4 (3/8 rule) over dt with tau held

`derivatives="autograd"` is the reference (torch.autograd.grad); `"analytic"` (the default, for training and
export) writes the same derivatives out as plain, exportable ops. The derivation, the exported triangular inverse,
the scales and the sizes: docs/dynamics.md ("The OLNN baseline").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from training.dynamics.normalisation import OptionalArray, register_input_statistics, set_statistic_buffers
from training.dynamics.pinn import tril_placement
from training.onnx_export import ExportError, export_checked

if TYPE_CHECKING:
    from training.dataset import DatasetStats

Accel = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

ACTIVATIONS = ("tanh", "softplus")
DERIVATIVES = ("analytic", "autograd")
# softplus(x + SOFTPLUS_ONE) = 1 at x = 0: an untrained L has a unit diagonal, so M starts near m_scale.
SOFTPLUS_ONE = float(np.log(np.expm1(1.0)))


@dataclass(frozen=True)
class OlnnConfig:
    """Sizes and constants of the OLNN; the defaults are the baseline trained against the paper's PINN."""

    n_joints: int = 10
    dt: float = 1e-3
    mass_widths: tuple[int, ...] = (64, 64, 64)
    potential_widths: tuple[int, ...] = (64, 64, 64)
    force_widths: tuple[int, ...] = (192, 192, 192)
    # Smooth activations: M(q)'s derivatives enter the dynamics, so the mass MLP must be at least C^1 (ReLU's
    # piecewise-constant Jacobian would make the Coriolis terms jump).
    activation: str = "tanh"
    # Lower bound of L's diagonal (relative to sqrt(m_scale)): keeps M positive definite and its factor invertible.
    diag_eps: float = 1e-2

    def __post_init__(self) -> None:
        if not (isinstance(self.n_joints, int) and self.n_joints > 0):
            raise ValueError(f"OlnnConfig.n_joints: expected an integer > 0, got {self.n_joints!r}")
        if not self.dt > 0:
            raise ValueError(f"OlnnConfig.dt: expected a time step > 0 s, got {self.dt!r}")
        for name in ("mass_widths", "potential_widths", "force_widths"):
            widths = tuple(getattr(self, name))
            if not widths or not all(isinstance(w, int) and w > 0 for w in widths):
                raise ValueError(f"OlnnConfig.{name}: expected one or more positive integer widths, got {widths!r}")
            object.__setattr__(self, name, widths)
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"OlnnConfig.activation: expected one of {list(ACTIVATIONS)}, got {self.activation!r}")
        if not self.diag_eps > 0:
            raise ValueError(f"OlnnConfig.diag_eps: expected > 0 (positive diagonal of L), got {self.diag_eps!r}")

    @property
    def n_tril(self) -> int:
        return self.n_joints * (self.n_joints + 1) // 2


class DerivativeMlp(nn.Module):
    """An MLP (activation on hidden layers, linear output) that can also push a tangent forward (JVP) or a
    cotangent back (VJP) through the activations of a forward pass, as plain differentiable, exportable ops."""

    def __init__(self, n_in: int, widths: Sequence[int], n_out: int, activation: str):
        super().__init__()
        sizes = [n_in, *widths, n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True))
        self.activation = activation

    def _act(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """act(z) and act'(z)."""
        if self.activation == "tanh":
            y = torch.tanh(z)
            return y, 1.0 - y * y
        return functional.softplus(z), torch.sigmoid(z)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers[:-1]:
            x = self._act(layer(x))[0]
        return self.layers[-1](x)

    def forward_with_slopes(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Output and act'(z) of every hidden layer, which `jvp` and `vjp` need."""
        slopes = []
        for layer in self.layers[:-1]:
            x, slope = self._act(layer(x))
            slopes.append(slope)
        return self.layers[-1](x), slopes

    def jvp(self, slopes: Sequence[torch.Tensor], tangent: torch.Tensor) -> torch.Tensor:
        """d(output) for an input perturbation `tangent` [B, n_in]: dz = W dx, dx' = act'(z) dz (bias-free)."""
        for layer, slope in zip(self.layers[:-1], slopes, strict=True):
            tangent = slope * (tangent @ layer.weight.T)
        return tangent @ self.layers[-1].weight.T

    def vjp(self, slopes: Sequence[torch.Tensor], cotangent: torch.Tensor) -> torch.Tensor:
        """cotangent^T d(output)/d(input) [B, n_in], for a cotangent [B, n_out]: back through W^T and act'(z)."""
        cotangent = cotangent @ self.layers[-1].weight
        for layer, slope in zip(reversed(self.layers[:-1]), reversed(slopes), strict=True):
            cotangent = (slope * cotangent) @ layer.weight
        return cotangent


def rk4_step(accel: Accel, q: torch.Tensor, qd: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One RK4 step, 3/8 rule (as mechamodlearn), of q' = qd, qd' = accel(q, qd): four evaluations of `accel`."""
    a1 = accel(q, qd)
    q2, qd2 = q + dt / 3 * qd, qd + dt / 3 * a1
    a2 = accel(q2, qd2)
    q3, qd3 = q + dt * (qd2 - qd / 3), qd + dt * (a2 - a1 / 3)
    a3 = accel(q3, qd3)
    q4, qd4 = q + dt * (qd - qd2 + qd3), qd + dt * (a1 - a2 + a3)
    a4 = accel(q4, qd4)
    q_next = q + dt / 8 * (qd + 3 * qd2 + 3 * qd3 + qd4)
    qd_next = qd + dt / 8 * (a1 + 3 * a2 + 3 * a3 + a4)
    return q_next, qd_next


def unit_lower_inverse_factors(n: int) -> int:
    """How many (I + (-N)^(2^k)) factors make (I + N)^-1 exact for a strictly lower n x n N (N^n = 0)."""
    return max(1, int(np.ceil(np.log2(n)))) if n > 1 else 0


class OlnnStep(nn.Module):
    """One OLNN step: (q, qd, tau [B, n]) -> (q', qd'); stateless (`initial_state` is ())."""

    def __init__(self, config: OlnnConfig | None = None, derivatives: str = "analytic"):
        super().__init__()
        self.config = config = config or OlnnConfig()
        if derivatives not in DERIVATIVES:
            raise ValueError(f"OlnnStep.derivatives: expected one of {list(DERIVATIVES)}, got {derivatives!r}")
        self.derivatives = derivatives
        n = config.n_joints
        self.n_joints = n
        self.dt = config.dt

        register_input_statistics(self, n)
        self.register_buffer("m_scale", torch.ones(n))  # inertia scale per joint (N m s^2 / rad)
        self.register_buffer("f_scale", torch.ones(n))  # force scale per joint (N m)
        self.register_buffer("v_scale", torch.ones(()))  # potential scale (J), one scalar: dV/dq stays a gradient

        self.mass_net = DerivativeMlp(n, config.mass_widths, config.n_tril, config.activation)
        self.potential_net = DerivativeMlp(n, config.potential_widths, 1, config.activation)
        self.force_net = DerivativeMlp(3 * n, config.force_widths, n, config.activation)
        for net in (self.potential_net, self.force_net):  # untrained: V = 0, F = 0
            nn.init.zeros_(net.layers[-1].weight)
            nn.init.zeros_(net.layers[-1].bias)

        self.register_buffer("placement", tril_placement(n))
        rows, cols = torch.tril_indices(n, n)
        self.register_buffer("diag_mask", (rows == cols).to(torch.float32))

    # --- normalisation ---------------------------------------------------------------------------------------------

    def set_normalisation(self, *, q_mean: OptionalArray = None, q_std: OptionalArray = None,
                          qd_mean: OptionalArray = None, qd_std: OptionalArray = None,
                          tau_mean: OptionalArray = None, tau_std: OptionalArray = None,
                          m_scale: OptionalArray = None, f_scale: OptionalArray = None,
                          v_scale: float | None = None) -> None:
        """Set the input statistics and scales given (each [n_joints], v_scale a scalar); the others keep their
        values. Stds and scales must be > 0. All or nothing: a bad value leaves every buffer as it was."""
        set_statistic_buffers(self, {"q_mean": q_mean, "q_std": q_std, "qd_mean": qd_mean, "qd_std": qd_std,
                                     "tau_mean": tau_mean, "tau_std": tau_std, "m_scale": m_scale, "f_scale": f_scale,
                                     "v_scale": v_scale}, "OlnnStep.set_normalisation")

    def fit_normalisation(self, stats: DatasetStats) -> None:
        """Input statistics and output scales from the training split (docs/dynamics.md, the OLNN's scales)."""
        qdd_std = np.asarray(stats.qd_inc_std, dtype=np.float64) / self.dt
        tau_std = np.asarray(stats.tau_std, dtype=np.float64)
        q_std = np.asarray(stats.q_std, dtype=np.float64)
        self.set_normalisation(q_mean=stats.q_mean, q_std=q_std, qd_mean=stats.qd_mean, qd_std=stats.qd_std,
                               tau_mean=stats.tau_mean, tau_std=tau_std, m_scale=tau_std / qdd_std,
                               f_scale=tau_std, v_scale=float(np.mean(tau_std * q_std)))

    def initial_state(self, batch: int = 1) -> tuple[()]:
        """Stateless: no recurrent state."""
        return ()

    # --- the three networks ----------------------------------------------------------------------------------------

    def _factor(self, q: torch.Tensor, with_slopes: bool = False):
        """L' = S L [B, n, n] for raw q, and (with_slopes) what the derivatives need: the mass MLP's slopes and
        d(entry)/d(raw output) of L's entries (1 off the diagonal, softplus' on it)."""
        n = self.n_joints
        q_norm = (q - self.q_mean) / self.q_std
        if with_slopes:
            raw, slopes = self.mass_net.forward_with_slopes(q_norm)
        else:
            raw, slopes = self.mass_net(q_norm), []
        shifted = raw + SOFTPLUS_ONE
        diag = functional.softplus(shifted) + self.config.diag_eps
        entries = raw + self.diag_mask * (diag - raw)
        factor = (entries @ self.placement).reshape(-1, n, n) * self.m_scale.sqrt().unsqueeze(1)
        gate = 1.0 + self.diag_mask * (torch.sigmoid(shifted) - 1.0) if with_slopes else None
        return factor, slopes, gate

    def mass_matrix(self, q: torch.Tensor) -> torch.Tensor:
        """M(q) = L' L'^T [B, n, n], symmetric positive definite by construction."""
        factor = self._factor(q)[0]
        return factor @ factor.transpose(1, 2)

    def potential(self, q: torch.Tensor) -> torch.Tensor:
        """V(q) [B] (J)."""
        return self.v_scale * self.potential_net((q - self.q_mean) / self.q_std).squeeze(1)

    def generalised_force(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """F(q, qd, tau) [B, n] (N m): friction, actuator and contact effects."""
        mean = torch.cat([self.q_mean, self.qd_mean, self.tau_mean])
        std = torch.cat([self.q_std, self.qd_std, self.tau_std])
        return self.f_scale * self.force_net((torch.cat([q, qd, tau], dim=1) - mean) / std)

    def energy(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Total energy 1/2 qd^T M qd + V [B] (J); conserved when tau + F = 0."""
        kinetic = 0.5 * (qd.unsqueeze(1) @ self.mass_matrix(q) @ qd.unsqueeze(2)).reshape(-1)
        return kinetic + self.potential(q)

    # --- accelerations ---------------------------------------------------------------------------------------------

    def _lower_inverse(self, factor: torch.Tensor) -> torch.Tensor:
        """L'^-1 for a lower-triangular L' with a positive diagonal: L' = D (I + N), N strictly lower (nilpotent),
        (I + N)^-1 = (I - N)(I + N^2)(I + N^4)..., exact after `unit_lower_inverse_factors(n)` factors."""
        n = self.n_joints
        eye = torch.eye(n, dtype=factor.dtype, device=factor.device)
        diag = (factor * eye).sum(2, keepdim=True)  # [B, n, 1]
        strict = factor / diag - eye  # N = D^-1 L' - I, strictly lower
        inverse = eye - strict
        power = strict
        for _ in range(unit_lower_inverse_factors(n) - 1):
            power = power @ power
            inverse = inverse @ (eye + power)
        return inverse / diag.transpose(1, 2)  # (I + N)^-1 D^-1: column j divided by d_j

    def accel_analytic(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """qdd [B, n] with derivatives written out (docs/dynamics.md); plain ops, exportable."""
        n = self.n_joints
        s = self.m_scale.sqrt()
        factor, slopes, gate = self._factor(q, with_slopes=True)
        # Mdot qd = Ldot' u + L' (Ldot'^T qd), u = L'^T qd, Ldot' = S dL/dq . qd (one tangent through the MLP).
        entries_dot = gate * self.mass_net.jvp(slopes, qd / self.q_std)
        factor_dot = (entries_dot @ self.placement).reshape(-1, n, n) * s.unsqueeze(1)
        u = (qd.unsqueeze(1) @ factor).squeeze(1)
        w = (qd.unsqueeze(1) @ factor_dot).squeeze(1)  # Ldot'^T qd
        mdot_qd = (factor_dot @ u.unsqueeze(2) + factor @ w.unsqueeze(2)).squeeze(2)
        # 1/2 d(qd^T M qd)/dq_k = sum_ij (s qd)_i u_j dL_ij/dq_k: one cotangent back through the MLP.
        outer = ((s * qd).unsqueeze(2) * u.unsqueeze(1)).reshape(-1, n * n)
        half_kinetic_grad = self.mass_net.vjp(slopes, gate * (outer @ self.placement.T)) / self.q_std
        coriolis = mdot_qd - half_kinetic_grad

        v_slopes = self.potential_net.forward_with_slopes((q - self.q_mean) / self.q_std)[1]
        ones = torch.ones_like(q[:, :1])
        gravity = self.v_scale * self.potential_net.vjp(v_slopes, ones) / self.q_std

        rhs = tau + self.generalised_force(q, qd, tau) - coriolis - gravity
        return self._solve(factor, rhs)

    def _solve(self, factor: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """M^-1 rhs = L'^-T L'^-1 rhs [B, n]: two triangular solves in torch (19 % faster per training step than the
        matmul inverse, measured), the exact matmul inverse when exporting (ONNX has no triangular solve)."""
        if torch.onnx.is_in_onnx_export():
            inverse = self._lower_inverse(factor)
            return (inverse.transpose(1, 2) @ (inverse @ rhs.unsqueeze(2))).squeeze(2)
        y = torch.linalg.solve_triangular(factor, rhs.unsqueeze(2), upper=False)
        return torch.linalg.solve_triangular(factor.transpose(1, 2), y, upper=True).squeeze(2)

    def accel_autograd(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """qdd [B, n], the reference: Coriolis and gravity by torch.autograd.grad, solved with cholesky_solve.

        Gradients are taken of batch sums, exact because the samples do not interact. The graph is kept
        (create_graph) when gradients are enabled by the caller, so this path can also be trained; under no_grad or
        inference_mode it runs with gradients locally and returns plain tensors.
        """
        create_graph = torch.is_grad_enabled() and not torch.is_inference_mode_enabled()
        with torch.inference_mode(False), torch.enable_grad():
            # Tensors made under inference_mode cannot enter an autograd graph; a clone made outside it can.
            q, qd, tau = (t.clone() if t.is_inference() else t for t in (q, qd, tau))
            if not q.requires_grad:
                q = q.detach().requires_grad_(True)
            factor = self._factor(q)[0]
            mass = factor @ factor.transpose(1, 2)
            m_qd = (mass @ qd.unsqueeze(2)).squeeze(2)
            rows = [torch.autograd.grad(m_qd[:, i].sum(), q, create_graph=True)[0] for i in range(self.n_joints)]
            mdot_qd = (torch.stack(rows, dim=1) @ qd.unsqueeze(2)).squeeze(2)  # (d(M qd)/dq) qd
            kinetic = 0.5 * (qd * m_qd).sum()
            kinetic_grad = torch.autograd.grad(kinetic, q, create_graph=True)[0]
            gravity = torch.autograd.grad(self.potential(q).sum(), q, create_graph=True)[0]
            rhs = tau + self.generalised_force(q, qd, tau) - (mdot_qd - kinetic_grad) - gravity
            qdd = torch.cholesky_solve(rhs.unsqueeze(2), factor).squeeze(2)
        return qdd if create_graph else qdd.detach()

    def accel(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor, derivatives: str | None = None
              ) -> torch.Tensor:
        """qdd = M^-1 (tau + F - c - g) [B, n] by `derivatives` (default: the module's)."""
        derivatives = derivatives or self.derivatives
        if derivatives == "analytic":
            return self.accel_analytic(q, qd, tau)
        if derivatives == "autograd":
            return self.accel_autograd(q, qd, tau)
        raise ValueError(f"OlnnStep.accel: derivatives must be one of {list(DERIVATIVES)}, got {derivatives!r}")

    def step(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor, derivatives: str | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """One RK4 step over dt with tau held (zero-order hold), by `derivatives` (default: the module's)."""
        return rk4_step(lambda q_, qd_: self.accel(q_, qd_, tau, derivatives), q, qd, self.dt)

    def forward(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.step(q, qd, tau)


def make_random_olnn(config: OlnnConfig | None = None, seed: int = 0, derivatives: str = "analytic") -> OlnnStep:
    """An OlnnStep with torch's default initialisation drawn from `seed` (F = 0, V = 0); the global RNG is left
    untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return OlnnStep(config, derivatives)


def export_olnn_onnx(model: OlnnStep, path: str | Path, *, opset: int = 17) -> Path:
    """Export one OLNN step (analytic derivatives, whatever `model.derivatives` is: same parameters, same math):
    q, qd, tau [1, n] -> q_next, qd_next."""
    config = model.config
    n = config.n_joints
    if model.m_scale.dtype != torch.float32:
        raise ExportError(f"the OLNN's parameters are {model.m_scale.dtype}; export a float32 model")
    example = (torch.zeros(1, n), torch.zeros(1, n), torch.zeros(1, n))
    saved = model.derivatives
    model.derivatives = "analytic"  # autograd.grad cannot be exported
    try:
        return export_checked(
            model, example, path, input_names=("q", "qd", "tau"), output_names=("q_next", "qd_next"), opset=opset,
            op_counts={},
            metadata={"kind": "olnn_step", "n_joints": n, "dt": config.dt, "integrator": "rk4_3/8",
                      "mass_widths": list(config.mass_widths), "potential_widths": list(config.potential_widths),
                      "force_widths": list(config.force_widths), "activation": config.activation,
                      "diag_eps": config.diag_eps, "derivatives": "analytic"},
        )
    finally:
        model.derivatives = saved
