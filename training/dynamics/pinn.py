"""The paper's physics-informed forward-dynamics step (§III-A), one module for training and for the 1 kHz tick.

    M^-1(q) = (L(q) + bI)^T (L(q) + bI)           Eq. 5, L lower-triangular from a ResNet on q
    (f_n, dq) = head(LSTM([q, qd, tau]))           f_n: the lumped term of Eq. 4, dq: the Euler correction
    qdd = M^-1 (tau + f_n)                         Eq. 4
    q' = q + qd dt + dq,   qd' = qd + qdd dt       Eq. 6, explicit Euler: q' uses the old qd
    q' in [lower, upper], qd' = 0 where q' stopped  the simulator's joint-range stops (`set_joint_stop`)

`PinnStep.forward(q, qd, tau, h, c) -> (q', qd', h', c')` is one control tick with the LSTM state explicit, so the
exported graph is called once per tick; training unrolls the same module over windows. The normalisation is held in
buffers, so torch and onnxruntime scale alike; `folded()` folds it into the weights for export. The joint-range stop
and the folding: docs/dynamics.md.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from training.dynamics.normalisation import OptionalArray, register_input_statistics, set_statistic_buffers

if TYPE_CHECKING:
    from training.dataset import DatasetStats


ACTIVATIONS = {"tanh": nn.Tanh, "elu": nn.ELU}

# rad beyond the joint range the simulator reaches where the PINN's stop sits.
JOINT_STOP_MARGIN = 0.1


def joint_stop_range(robot_config, q_seen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the PINN's joint-range stop: the config's joints.position_limits (which the MJCF's joint
    ranges equal), extended to every angle in `q_seen` [T, n] (the training data: MuJoCo's limits are soft, and
    walking pushed a straight knee 0.065-0.133 rad past 0 in our recordings), widened by JOINT_STOP_MARGIN. So the
    stop never acts on what the simulator was seen to do."""
    lower, upper = np.asarray(robot_config.q_lower, float), np.asarray(robot_config.q_upper, float)
    if q_seen is not None and len(q_seen):
        lower = np.minimum(lower, np.min(q_seen, axis=0))
        upper = np.maximum(upper, np.max(q_seen, axis=0))
    return lower - JOINT_STOP_MARGIN, upper + JOINT_STOP_MARGIN


@dataclass(frozen=True)
class PinnConfig:
    """Sizes and constants of the PINN; the defaults are the paper's (§IV-B)."""

    n_joints: int = 10
    dt: float = 1e-3
    resnet_widths: tuple[int, ...] = (20, 32, 48, 55)
    b: float = 0.3
    lstm_hidden: int = 72
    lstm_layers: int = 3
    # ResNet activation. tanh, because M^-1(q) of a rigid-body chain is a smooth (trigonometric) function of the
    # joint angles: tanh is smooth and saturates outside the training range, ELU is only C^1 and grows linearly.
    # "elu" stays selectable for an ablation. (The LSTM's gates use their own fixed sigmoid/tanh.)
    activation: str = "tanh"

    def __post_init__(self) -> None:
        if not (isinstance(self.n_joints, int) and self.n_joints > 0):
            raise ValueError(f"PinnConfig.n_joints: expected an integer > 0, got {self.n_joints!r}")
        if not self.dt > 0:
            raise ValueError(f"PinnConfig.dt: expected a time step > 0 s, got {self.dt!r}")
        widths = tuple(self.resnet_widths)
        if not widths or not all(isinstance(w, int) and w > 0 for w in widths):
            raise ValueError(f"PinnConfig.resnet_widths: expected positive integer widths, got {widths!r}")
        n_tril = self.n_joints * (self.n_joints + 1) // 2
        if widths[-1] != n_tril:
            raise ValueError(f"PinnConfig.resnet_widths: the last width fills the lower triangle of L, so it must be "
                             f"n(n+1)/2 = {n_tril} for n_joints={self.n_joints}, got {widths[-1]}")
        if not self.b > 0:
            raise ValueError(f"PinnConfig.b: expected a diagonal bias > 0 (Eq. 5), got {self.b!r}")
        if not (isinstance(self.lstm_hidden, int) and self.lstm_hidden > 0):
            raise ValueError(f"PinnConfig.lstm_hidden: expected an integer > 0, got {self.lstm_hidden!r}")
        if not (isinstance(self.lstm_layers, int) and self.lstm_layers > 0):
            raise ValueError(f"PinnConfig.lstm_layers: expected an integer > 0, got {self.lstm_layers!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"PinnConfig.activation: expected one of {sorted(ACTIVATIONS)}, got {self.activation!r}")
        object.__setattr__(self, "resnet_widths", widths)

    @property
    def n_tril(self) -> int:
        return self.n_joints * (self.n_joints + 1) // 2


class ResidualLayer(nn.Module):
    """y = act(W x + b) + skip(x); the skip is the identity when the widths match and a bias-free linear
    projection otherwise (every layer of the paper's 10->20->32->48 changes width, so all of them project)."""

    def __init__(self, width_in: int, width_out: int, activation: str):
        super().__init__()
        self.linear = nn.Linear(width_in, width_out)
        self.act = ACTIVATIONS[activation]()
        self.skip = nn.Identity() if width_in == width_out else nn.Linear(width_in, width_out, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.linear(x)) + self.skip(x)


class TrilResNet(nn.Module):
    """Normalised q -> the n(n+1)/2 entries of L. Hidden layers are `ResidualLayer`s; the last layer is plain
    linear, because L's entries are signed and unbounded, and a linear skip around a linear layer adds nothing."""

    def __init__(self, n_in: int, widths: Sequence[int], activation: str):
        super().__init__()
        sizes = [n_in, *widths]
        pairs = zip(sizes[:-2], sizes[1:-1], strict=True)
        self.hidden = nn.Sequential(*(ResidualLayer(w_in, w_out, activation) for w_in, w_out in pairs))
        self.out = nn.Linear(sizes[-2], sizes[-1])

    def forward(self, q_norm: torch.Tensor) -> torch.Tensor:
        return self.out(self.hidden(q_norm))


def tril_placement(n: int) -> torch.Tensor:
    """[n(n+1)/2, n*n] 0/1 matrix: entries @ P is L row-major flattened, entry k going to the k-th lower-triangular
    position in row-major order (torch.tril_indices). A constant MatMul exports cleanly, unlike index_put/scatter."""
    rows, cols = torch.tril_indices(n, n)
    placement = torch.zeros(rows.numel(), n * n)
    placement[torch.arange(rows.numel()), rows * n + cols] = 1.0
    return placement


class PinnStep(nn.Module):
    """One Eq. 4-6 step: (q, qd, tau [B, n], h, c [layers, B, hidden]) -> (q', qd', h', c')."""

    def __init__(self, config: PinnConfig | None = None):
        super().__init__()
        self.config = config = config or PinnConfig()
        n = config.n_joints
        self.n_joints = n
        self.dt = config.dt

        register_input_statistics(self, n)
        # Denormalisation of the head: f_n in torque units, dq in radians. Training fits them (issue #5).
        self.register_buffer("fn_scale", torch.ones(n))
        self.register_buffer("dq_scale", torch.ones(n))
        # Joint-range stop (docs/dynamics.md), raw radians; unbounded until set_joint_stop.
        self.register_buffer("q_stop_lower", torch.full((n,), -math.inf))
        self.register_buffer("q_stop_upper", torch.full((n,), math.inf))

        self.resnet = TrilResNet(n, config.resnet_widths, config.activation)
        self.register_buffer("placement", tril_placement(n))
        # b I of Eq. 5, flattened like L, added after the placement MatMul.
        self.register_buffer("b_eye", (config.b * torch.eye(n)).reshape(n * n))
        self.sqrt_dt = math.sqrt(config.dt)
        # True only in the export copy made by folded(): the affine stages live in the weights there.
        self.is_folded = False

        # Sequence-first (batch_first=False): the ONNX LSTM op is [seq, batch, feature], so the exporter needs no
        # transposes; each call is one time step (seq = 1).
        self.lstm = nn.LSTM(input_size=3 * n, hidden_size=config.lstm_hidden, num_layers=config.lstm_layers)
        self.head = nn.Linear(config.lstm_hidden, 2 * n)
        # Zero head: an untrained model predicts f_n = 0 and dq = 0, i.e. q' = q + qd dt, qd' = qd + M^-1 tau dt.
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def set_normalisation(self, *, q_mean: OptionalArray = None, q_std: OptionalArray = None,
                          qd_mean: OptionalArray = None, qd_std: OptionalArray = None,
                          tau_mean: OptionalArray = None, tau_std: OptionalArray = None,
                          fn_scale: OptionalArray = None, dq_scale: OptionalArray = None) -> None:
        """Set the input statistics and output scales given (each [n_joints]); the others keep their values.

        Stds and scales must be > 0. Values are copied into the buffers, so they travel with state_dict and export.
        """
        set_statistic_buffers(self, {"q_mean": q_mean, "q_std": q_std, "qd_mean": qd_mean, "qd_std": qd_std,
                                     "tau_mean": tau_mean, "tau_std": tau_std, "fn_scale": fn_scale,
                                     "dq_scale": dq_scale}, "PinnStep.set_normalisation")

    def set_joint_stop(self, lower: OptionalArray, upper: OptionalArray) -> None:
        """Set the joint-range stop to [lower, upper] (each [n_joints], radians, lower < upper, finite)."""
        bounds = [torch.as_tensor(np.array(v, dtype=np.float64)) for v in (lower, upper)]
        for name, value in zip(("lower", "upper"), bounds, strict=True):
            if value.shape != (self.n_joints,):
                raise ValueError(f"PinnStep.set_joint_stop: {name} must have shape ({self.n_joints},), "
                                 f"got {tuple(value.shape)}")
            if not torch.isfinite(value).all():
                raise ValueError(f"PinnStep.set_joint_stop: {name} has non-finite entries")
        if not (bounds[0] < bounds[1]).all():
            raise ValueError(f"PinnStep.set_joint_stop: lower must be < upper for every joint, got "
                             f"{bounds[0].tolist()} and {bounds[1].tolist()}")
        with torch.no_grad():
            self.q_stop_lower.copy_(bounds[0].to(self.q_stop_lower.dtype))
            self.q_stop_upper.copy_(bounds[1].to(self.q_stop_upper.dtype))

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
        """Zero LSTM state (h, c), each [layers, batch, hidden], in the module's dtype and device."""
        shape = (self.config.lstm_layers, batch, self.config.lstm_hidden)
        like = self.b_eye
        return like.new_zeros(shape), like.new_zeros(shape)

    def fit_normalisation(self, stats: DatasetStats) -> None:
        """Input statistics and output scales from the training split: f_n is a torque, so its head output is
        scaled by the spread of tau; dq corrects the Euler step, so it is scaled by the spread of that residual."""
        self.set_normalisation(q_mean=stats.q_mean, q_std=stats.q_std, qd_mean=stats.qd_mean, qd_std=stats.qd_std,
                               tau_mean=stats.tau_mean, tau_std=stats.tau_std, fn_scale=stats.tau_std,
                               dq_scale=stats.q_inc_std)

    def _scaled_factor(self, q_in: torch.Tensor) -> torch.Tensor:
        """A = sqrt(dt) (L + bI) flattened row-major, [B, n*n], from the ResNet's input (normalised q; raw q once
        folded)."""
        flat = self.resnet(q_in)
        return flat if self.is_folded else (flat @ self.placement + self.b_eye) * self.sqrt_dt

    def _resnet_input(self, q: torch.Tensor) -> torch.Tensor:
        centred = q - self.q_mean
        return centred if self.is_folded else centred / self.q_std

    def minv(self, q: torch.Tensor) -> torch.Tensor:
        """M^-1(q) = (L + bI)^T (L + bI), [..., n, n] (Eq. 5), for raw joint angles q [..., n]."""
        n = self.n_joints
        factor = self._scaled_factor(self._resnet_input(q)).unflatten(-1, (n, n))
        return factor.transpose(-1, -2) @ factor / self.dt

    def forward(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor, h: torch.Tensor, c: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One tick for q, qd, tau [B, n]; or, for training, a teacher-forced window [W, B, n] (time first, like
        nn.LSTM): the same math at every step, the LSTM carrying its state through the window, which returns
        q', qd' [W, B, n] and the state after the last step."""
        n = self.n_joints
        window = q.dim() == 3
        if self.is_folded and not torch.jit.is_tracing() and (window or q.shape[0] != 1):  # export traces batch 1
            raise ValueError(f"a folded PinnStep is the exported tick and takes q [1, n], got {list(q.shape)}")
        q = torch.clamp(q, self.q_stop_lower, self.q_stop_upper)  # the network only sees postures the robot can take
        # Centred here in both forms (folding the mean into a bias would cancel large terms in float32); the
        # division by the std is folded into the weights that read the features.
        features = torch.cat([q, qd, tau], dim=-1) - torch.cat([self.q_mean, self.qd_mean, self.tau_mean])
        if not self.is_folded:
            features = features / torch.cat([self.q_std, self.qd_std, self.tau_std])
        q_in = features[..., :n]

        factor = self._scaled_factor(q_in)  # sqrt(dt) (L + bI), flattened

        lstm_out, (h_next, c_next) = self.lstm(features if window else features.unsqueeze(0), (h, c))
        head = self.head(lstm_out if window else h_next[-1])  # a tick's output is the last layer's new h
        if not self.is_folded:
            head = head * torch.cat([self.fn_scale, self.dq_scale])
        f_n, dq = head.split(n, dim=-1)

        # Eq. 4 times dt with row vectors: (A^T A v)^T = v^T A^T A, since M^-1 dt = A^T A. The tick (batch 1)
        # uses 2-D products, which export without the Unsqueeze/Squeeze that the batched form needs.
        v = tau + f_n
        if self.is_folded:
            factor = factor.reshape(n, n)
            qdd_dt = v @ factor.T @ factor
        else:  # broadcast products: batched 10x10 matmuls are slow on a CPU in training's large batches
            factor = factor.unflatten(-1, (n, n))
            a_v = (factor * v.unsqueeze(-2)).sum(-1)  # A v
            qdd_dt = (factor * a_v.unsqueeze(-1)).sum(-2)  # A^T (A v)
        q_free = q + qd * self.dt + dq  # Eq. 6, old qd
        q_next = torch.clamp(q_free, self.q_stop_lower, self.q_stop_upper)
        qd_next = torch.where(q_next == q_free, qd + qdd_dt, 0.0)  # a joint that hit its stop stops there
        return q_next, qd_next, h_next, c_next

    @torch.no_grad()
    def folded(self) -> PinnStep:
        """An inference copy with the scaling stages folded into the weights (docs/dynamics.md); same outputs to
        float32 rounding. Its stds and scales are reset to 1, so nothing is applied twice; the means stay."""
        if self.is_folded:
            return copy.deepcopy(self)
        out = copy.deepcopy(self).eval()
        n = self.n_joints
        # Input scaling x_norm = (x - m) / s: the 1 / s folded into every linear map that reads x_norm (the
        # centring stays in the graph, see forward).
        first = out.resnet.hidden[0] if len(out.resnet.hidden) else None
        readers = [first.linear, first.skip] if first is not None else [out.resnet.out]
        for i, layer in enumerate(readers):
            if isinstance(layer, nn.Identity):  # first layer with width n: the skip is x_norm itself
                layer = readers[i] = first.skip = nn.Linear(n, n, bias=False).to(self.b_eye.dtype)
                layer.weight.copy_(torch.eye(n))
            layer.weight.div_(self.q_std)
        out.lstm.weight_ih_l0.div_(torch.cat([self.q_std, self.qd_std, self.tau_std]))
        # Head denormalisation.
        scale = torch.cat([self.fn_scale, self.dq_scale])
        out.head.weight.mul_(scale[:, None])
        out.head.bias.mul_(scale)
        # Output layer -> sqrt(dt) (L + bI) flattened, directly: (W h + b) P + bI = (P^T W) h + (P^T b + bI).
        last = out.resnet.out
        tril = nn.Linear(last.in_features, n * n).to(self.b_eye.dtype)
        tril.weight.copy_(self.placement.T @ last.weight * self.sqrt_dt)
        tril.bias.copy_((last.bias @ self.placement + self.b_eye) * self.sqrt_dt)
        out.resnet.out = tril
        out.set_normalisation(q_std=np.ones(n), qd_std=np.ones(n), tau_std=np.ones(n), fn_scale=np.ones(n),
                              dq_scale=np.ones(n))
        out.is_folded = True
        return out


def make_random_pinn(config: PinnConfig | None = None, seed: int = 0) -> PinnStep:
    """A PinnStep with torch's default initialisation drawn from `seed` and a zero head; the global RNG is left
    untouched."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return PinnStep(config)
