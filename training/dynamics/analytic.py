"""The analytic Euler–Lagrange baseline (issue #5, item 3): a rigid-body model of BRUCE's legs whose joint torques are
linear in its parameters, identified by least squares from the same (q, qd, tau) data as the PINN.

    tau = M(q) qdd + C(q, qd) qd + g(q) + armature qdd + viscous qd + coulomb tanh(qd / v_c) = Y(q, qd, qdd) pi

Each leg is a fixed-base serial chain read from the MJCF (`read_chain`); pi holds the 10 inertial parameters of
each leg body, then the armature, viscous and Coulomb coefficients of each joint; Y comes from a recursive
Newton–Euler pass (`regressor`). Contact and the floating base are not represented: that is the point of this
baseline. `identify` fits pi; `AnalyticModel.forward` integrates semi-implicit Euler, MuJoCo's update for hinges.
Stateless, and nothing is trained by gradient descent. The model and its identification: docs/dynamics.md.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import mujoco
import numpy as np
import torch
from torch import nn

from bruce_hw.config import find_mjcf
from training.episodes import transition_indices

if TYPE_CHECKING:
    from bruce_hw.config import RobotConfig
    from training.dataset import DatasetStats

BRUCE_JOINTS = ("r_hip_yaw", "r_hip_pitch", "r_hip_roll", "r_knee", "r_ankle",
                "l_hip_yaw", "l_hip_pitch", "l_hip_roll", "l_knee", "l_ankle")
INERTIAL_PARAMS = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")
JOINT_PARAMS = ("armature", "viscous", "coulomb")
N_INERTIAL = len(INERTIAL_PARAMS)
_UNEXCITED = 1e-10  # a regressor column whose norm is below this times the largest one is treated as zero


@dataclass(frozen=True)
class AnalyticConfig:
    """What the analytic model is built from and how it is identified."""

    mjcf: str = "bruce.xml"  # an existing path, else a file name in bruce_hw/models/
    joints: tuple[str, ...] = BRUCE_JOINTS  # model joint order = the robot config's joints.names
    base_body: str = "base"  # the body held fixed in the world
    dt: float = 1e-3  # s, one control tick
    coulomb_velocity: float = 0.01  # rad/s, v_c of the tanh(qd / v_c) Coulomb term
    rcond: float = 1e-9  # drop scaled singular directions below rcond * s_max (unidentifiable combinations)
    ridge: float = 1e-12  # Tikhonov weight relative to s_max^2, in unit-norm column coordinates
    min_mass_eigenvalue: float = 1e-4  # kg m^2, floor on lambda_min(M(q)) enforced after the fit

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", tuple(self.joints))
        if not self.joints:
            raise ValueError("AnalyticConfig.joints: expected at least one joint name")
        for name in ("dt", "coulomb_velocity"):
            if not getattr(self, name) > 0:
                raise ValueError(f"AnalyticConfig.{name}: expected a value > 0, got {getattr(self, name)!r}")
        for name in ("rcond", "ridge", "min_mass_eigenvalue"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"AnalyticConfig.{name}: expected a value >= 0, got {getattr(self, name)!r}")

    @classmethod
    def from_robot_config(cls, config: RobotConfig, **overrides) -> AnalyticConfig:
        """The robot config's model file, joint order and control period."""
        return cls(mjcf=str(config.mjcf), joints=tuple(config.joints), dt=config.dt, **overrides)

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def n_params(self) -> int:
        return (N_INERTIAL + len(JOINT_PARAMS)) * self.n_joints

    def param_names(self) -> list[str]:
        """Name of every entry of pi, e.g. 'r_thigh.mcz', 'r_knee.viscous'."""
        bodies = read_chain(self).bodies
        names = [f"{body}.{p}" for body in bodies for p in INERTIAL_PARAMS]
        return names + [f"{joint}.{p}" for p in JOINT_PARAMS for joint in self.joints]


def resolve_mjcf(name: str | Path) -> Path:
    path = find_mjcf(name)
    if path is None:
        raise FileNotFoundError(f"analytic model: MuJoCo model {str(name)!r} not found (nor in bruce_hw/models)")
    return path


@dataclass(frozen=True)
class Chain:
    """The legs' kinematic tree in float64 numpy, in the config's joint order (joint i moves body i).

    parent[i] is the joint index of body i's parent body, -1 for the base. body_pos/body_rot: body i's origin and
    orientation in its parent's frame at q = 0; axis: joint i's unit axis in body i's frame; gravity: the gravity
    vector in the base frame (m/s^2); q_lower/q_upper: the joint ranges (rad).
    """

    bodies: tuple[str, ...]
    parent: tuple[int, ...]
    body_pos: np.ndarray
    body_rot: np.ndarray
    axis: np.ndarray
    gravity: np.ndarray
    q_lower: np.ndarray
    q_upper: np.ndarray
    model: mujoco.MjModel = field(repr=False, compare=False)
    body_ids: tuple[int, ...] = ()
    dof_ids: tuple[int, ...] = ()

    def roots(self) -> list[int]:
        """For every joint, the base child its leg hangs from (joints with the same root form one leg)."""
        roots = []
        for i in range(len(self.parent)):
            j = i
            while self.parent[j] >= 0:
                j = self.parent[j]
            roots.append(j)
        return roots


def read_chain(config: AnalyticConfig) -> Chain:
    """The legs' kinematics from the MJCF; fails naming the file and joint when the model is not a tree of hinges
    hanging from `base_body` with each joint at its body's origin."""
    path = resolve_mjcf(config.mjcf)
    try:
        model = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:  # mujoco raises ValueError with the parser's message
        raise ValueError(f"{path}: cannot load the MuJoCo model: {exc}") from exc
    base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, config.base_body)
    if base < 0:
        raise ValueError(f"{path}: no body named {config.base_body!r} (AnalyticConfig.base_body)")
    body_ids, dof_ids = [], []
    for name in config.joints:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise ValueError(f"{path}: no joint named {name!r} (AnalyticConfig.joints)")
        if model.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError(f"{path}: joint {name!r} is not a hinge; the analytic model handles hinges only")
        body = int(model.jnt_bodyid[jid])
        if model.body_jntnum[body] != 1:
            raise ValueError(f"{path}: body of joint {name!r} has {model.body_jntnum[body]} joints, expected 1")
        if np.any(model.jnt_pos[jid] != 0) or model.qpos0[model.jnt_qposadr[jid]] != 0:
            raise ValueError(f"{path}: joint {name!r} must sit at its body's origin with reference 0")
        body_ids.append(body)
        dof_ids.append(int(model.jnt_dofadr[jid]))
    index = {b: i for i, b in enumerate(body_ids)}
    parent = []
    for name, body in zip(config.joints, body_ids, strict=True):
        up = int(model.body_parentid[body])
        if up != base and up not in index:
            raise ValueError(f"{path}: joint {name!r}: its body's parent is neither {config.base_body!r} nor the "
                             f"body of another listed joint")
        parent.append(index.get(up, -1))
    for body in range(model.nbody):  # a fixed child body would carry mass the chain does not know about
        if body not in index and int(model.body_parentid[body]) in index:
            raise ValueError(f"{path}: body {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body)!r} hangs "
                             f"from a leg body without a listed joint; the analytic model does not handle it")

    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)  # at qpos0: the base's reference orientation
    base_rot = data.xmat[base].reshape(3, 3)
    rot = np.zeros((len(body_ids), 3, 3))
    for i, body in enumerate(body_ids):
        mujoco.mju_quat2Mat(rot[i].reshape(9), model.body_quat[body])
    jids = [int(model.body_jntadr[b]) for b in body_ids]
    axis = model.jnt_axis[jids] / np.linalg.norm(model.jnt_axis[jids], axis=1, keepdims=True)
    return Chain(
        bodies=tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in body_ids),
        parent=tuple(parent),
        body_pos=model.body_pos[body_ids].copy(), body_rot=rot, axis=axis,
        gravity=base_rot.T @ model.opt.gravity, q_lower=model.jnt_range[jids, 0].copy(),
        q_upper=model.jnt_range[jids, 1].copy(), model=model, body_ids=tuple(body_ids), dof_ids=tuple(dof_ids))


def nominal_parameters(config: AnalyticConfig) -> np.ndarray:
    """pi of the MJCF itself (float64, [n_params]): link inertias about the body origin, armature, damping as the
    viscous term and frictionloss as the Coulomb coefficient (MuJoCo's frictionloss is a constraint, not a tanh, so
    only the zero case is exact). Joint springs are not in the model, so a stiff joint is refused."""
    chain = read_chain(config)
    model = chain.model
    n = len(chain.bodies)
    inertial = np.zeros((n, N_INERTIAL))
    for i, body in enumerate(chain.body_ids):
        jid = int(model.body_jntadr[body])
        if model.jnt_stiffness[jid] != 0:
            raise ValueError(f"{resolve_mjcf(config.mjcf)}: joint {config.joints[i]!r} has a spring, which the "
                             f"analytic model does not represent")
        mass, com = float(model.body_mass[body]), model.body_ipos[body]
        frame = np.zeros(9)
        mujoco.mju_quat2Mat(frame, model.body_iquat[body])
        frame = frame.reshape(3, 3)
        inertia_com = frame @ np.diag(model.body_inertia[body]) @ frame.T
        inertia = inertia_com + mass * (com @ com * np.eye(3) - np.outer(com, com))  # parallel-axis theorem
        inertial[i] = [mass, *(mass * com), inertia[0, 0], inertia[0, 1], inertia[1, 1], inertia[0, 2],
                       inertia[1, 2], inertia[2, 2]]
    dofs = list(chain.dof_ids)
    joint = np.concatenate([model.dof_armature[dofs], model.dof_damping[dofs], model.dof_frictionloss[dofs]])
    return np.concatenate([inertial.reshape(-1), joint])


# -- rigid-body algebra, batched over the leading dimension, any float dtype ----------------------------------
class ChainTensors(NamedTuple):
    body_pos: torch.Tensor  # [n, 3]
    body_rot: torch.Tensor  # [n, 3, 3]
    axis: torch.Tensor  # [n, 3]
    gravity: torch.Tensor  # [3]


def _skew(v: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> [..., 3, 3] with skew(a) @ b = a x b."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*v.shape, 3)


def _mv(matrix: torch.Tensor, vector: torch.Tensor) -> torch.Tensor:
    return (matrix @ vector.unsqueeze(-1)).squeeze(-1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def _body_rotations(kin: ChainTensors, q: torch.Tensor) -> torch.Tensor:
    """R_i = body_rot_i @ Rot(axis_i, q_i): body i's orientation in its parent's frame, [B, n, 3, 3] (Rodrigues)."""
    k = _skew(kin.axis)  # [n, 3, 3]
    s, c = torch.sin(q)[..., None, None], torch.cos(q)[..., None, None]
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    return kin.body_rot @ (eye + s * k + (1 - c) * (k @ k))


class Tree(NamedTuple):
    """The joint tree grouped by depth, so that RNEA runs one batch of ops per depth (both legs at once)."""

    parent: tuple[int, ...]  # parent joint of each joint, -1 for the base
    levels: tuple[torch.Tensor, ...]  # joint indices at depth 0 (hanging from the base), 1, ...
    parent_slot: tuple[torch.Tensor, ...]  # per level, each joint's parent's position in the level above
    joint_slot: torch.Tensor  # position of joint i in torch.cat(levels)


def make_tree(parent: Sequence[int]) -> Tree:
    depth = []
    for i in range(len(parent)):
        d, j = 0, i
        while parent[j] >= 0:
            d, j = d + 1, parent[j]
        depth.append(d)
    levels = [[i for i in range(len(parent)) if depth[i] == d] for d in range(max(depth) + 1)]
    slots = [[]] + [[levels[d - 1].index(parent[i]) for i in levels[d]] for d in range(1, len(levels))]
    flat = [i for level in levels for i in level]
    return Tree(tuple(parent), tuple(torch.tensor(level) for level in levels),
                tuple(torch.tensor(slot, dtype=torch.long) for slot in slots),
                torch.tensor([flat.index(i) for i in range(len(parent))]))


def _motion(kin: ChainTensors, tree: Tree, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor,
            base_accel: torch.Tensor):
    """Forward pass of RNEA: per body the rotation to its parent R [B, n, 3, 3] and, in body coordinates, the
    spatial velocity (w, u) and spatial acceleration (aw, au), each [B, n, 3]. base_accel [B, 3] is the base's
    linear acceleration (-gravity to include gravity, 0 to leave it out)."""
    rot = _body_rotations(kin, q)
    per_level = []
    for d, idx in enumerate(tree.levels):
        rt = rot[:, idx].transpose(-1, -2)  # parent coordinates -> body coordinates
        r, axis = kin.body_pos[idx], kin.axis[idx]
        s_qd = axis * qd[:, idx, None]
        s_qdd = axis * qdd[:, idx, None]
        if d == 0:  # the base: at rest, accelerating by base_accel
            w, aw = s_qd, s_qdd
            u = torch.zeros_like(s_qd)
            au = _mv(rt, base_accel[:, None, :].expand_as(s_qd))
        else:
            wp, up, awp, aup = (x[:, tree.parent_slot[d]] for x in per_level[-1])
            w = _mv(rt, wp) + s_qd
            u = _mv(rt, up + _cross(wp, r.expand_as(wp)))
            aw = _mv(rt, awp) + s_qdd + _cross(w, s_qd)
            au = _mv(rt, aup + _cross(awp, r.expand_as(awp))) + _cross(u, s_qd)
        per_level.append((w, u, aw, au))
    return rot, *(torch.cat([level[k] for level in per_level], dim=1)[:, tree.joint_slot] for k in range(4))


def _inertia_from_params(inertial: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """[n, 10] -> mass [n], first moment m*c [n, 3], rotational inertia about the origin [n, 3, 3]."""
    m, mc = inertial[:, 0], inertial[:, 1:4]
    xx, xy, yy, xz, yz, zz = inertial[:, 4:].unbind(-1)
    inertia = torch.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], dim=-1).reshape(-1, 3, 3)
    return m, mc, inertia


def _rnea(kin: ChainTensors, tree: Tree, inertial: torch.Tensor, q: torch.Tensor, qd: torch.Tensor,
          qdd: torch.Tensor, base_accel: torch.Tensor) -> torch.Tensor:
    """Rigid-body joint torques [B, n] (no armature, no friction) for link parameters inertial [n, 10]."""
    rot, w, u, aw, au = _motion(kin, tree, q, qd, qdd, base_accel)
    m, mc, inertia = _inertia_from_params(inertial)
    # f = I a + v x* I v with the spatial inertia built from (m, mc, I_o); n: moment, f: force, body coordinates.
    h_n = _mv(inertia, w) + _cross(mc.expand_as(u), u)
    h_f = m[:, None] * u + _cross(w, mc.expand_as(w))
    moment = _mv(inertia, aw) + _cross(mc.expand_as(au), au) + _cross(w, h_n) + _cross(u, h_f)
    force = m[:, None] * au + _cross(aw, mc.expand_as(aw)) + _cross(w, h_f)
    moments = [moment[:, idx] for idx in tree.levels]
    forces = [force[:, idx] for idx in tree.levels]
    taus = [None] * len(tree.levels)
    for d in reversed(range(len(tree.levels))):
        idx = tree.levels[d]
        taus[d] = (moments[d] * kin.axis[idx]).sum(-1)
        if d > 0:  # the children's wrenches, moved to their parents' origins and coordinates
            f_parent = _mv(rot[:, idx], forces[d])
            m_parent = _mv(rot[:, idx], moments[d]) + _cross(kin.body_pos[idx].expand_as(f_parent), f_parent)
            moments[d - 1] = moments[d - 1].index_add(1, tree.parent_slot[d], m_parent)
            forces[d - 1] = forces[d - 1].index_add(1, tree.parent_slot[d], f_parent)
    return torch.cat(taus, dim=1)[:, tree.joint_slot]


def _inertia_basis(x: torch.Tensor) -> torch.Tensor:
    """L(x) [..., 3, 6] with I x = L(x) (Ixx, Ixy, Iyy, Ixz, Iyz, Izz)."""
    zero = torch.zeros_like(x[..., 0])
    x0, x1, x2 = x.unbind(-1)
    rows = [x0, x1, zero, x2, zero, zero, zero, x0, x1, zero, x2, zero, zero, zero, zero, x0, x1, x2]
    return torch.stack(rows, dim=-1).reshape(*x.shape[:-1], 3, 6)


def regressor(kin: ChainTensors, tree: Tree, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor,
              coulomb_velocity: float, base_accel: torch.Tensor | None = None) -> torch.Tensor:
    """Y(q, qd, qdd) [B, n, 13 n] with tau = Y pi, in the layout of `AnalyticConfig.param_names`.

    base_accel [B, 3] defaults to -gravity (gravity on)."""
    batch, n = q.shape
    if base_accel is None:
        base_accel = (-kin.gravity).expand(batch, 3)
    rot, w, u, aw, au = _motion(kin, tree, q, qd, qdd, base_accel)
    parent = tree.parent
    # Body wrench = A(v, a) pi_body, A [B, n, 6, 10]: rows (moment, force), columns INERTIAL_PARAMS.
    sw, su, saw, sau = _skew(w), _skew(u), _skew(aw), _skew(au)
    zeros31 = torch.zeros_like(w[..., None])
    zeros36 = torch.zeros(*w.shape[:-1], 3, 6, dtype=q.dtype, device=q.device)
    moment_rows = torch.cat([zeros31, -sau - sw @ su + su @ sw, _inertia_basis(aw) + sw @ _inertia_basis(w)], -1)
    force_rows = torch.cat([(au + _cross(w, u))[..., None], saw + sw @ sw, zeros36], -1)
    wrench = torch.cat([moment_rows, force_rows], dim=-2)

    y = q.new_zeros(batch, n, (N_INERTIAL + len(JOINT_PARAMS)) * n)
    for k in range(n):  # body k's parameters load joint k and every joint above it
        block = wrench[:, k]
        j = k
        while j >= 0:
            y[:, j, N_INERTIAL * k:N_INERTIAL * (k + 1)] = (kin.axis[j][:, None] * block[:, :3]).sum(-2)
            if parent[j] >= 0:
                rot_j, r = rot[:, j], _skew(kin.body_pos[j])
                f_parent = rot_j @ block[:, 3:]
                block = torch.cat([rot_j @ block[:, :3] + r @ f_parent, f_parent], dim=-2)
            j = parent[j]
    joints = torch.arange(n)
    y[:, joints, N_INERTIAL * n + joints] = qdd
    y[:, joints, (N_INERTIAL + 1) * n + joints] = qd
    y[:, joints, (N_INERTIAL + 2) * n + joints] = torch.tanh(qd / coulomb_velocity)
    return y


# -- the model ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class IdentificationReport:
    """What `identify` did; `as_dict()` is JSON-ready."""

    n_samples: int  # transitions used
    n_params: int
    rank: dict[str, int]  # per leg (named by its root body): kept singular directions of the scaled regressor
    condition: dict[str, float]  # per leg: s_max / s_min over the kept directions
    relative_residual: dict[str, float]  # per leg: |tau - Y pi| / |tau| on the fit data
    min_mass_eigenvalue: float  # lambda_min(M) over the checked states after any armature shift
    armature_shift: float  # kg m^2 added to every armature to reach config.min_mass_eigenvalue (0: none needed)
    seconds: float

    def as_dict(self) -> dict:
        return asdict(self)


class AnalyticModel(nn.Module):
    """Fixed-base rigid-body legs with parameters pi; the shared dynamics-model interface (stateless).

    `AnalyticModel(config)` carries the MJCF's own parameters (`nominal_parameters`); `identify` returns one
    with identified parameters. Kinematics and pi are buffers, so a checkpoint's state_dict restores both. They are
    made in `dtype` from float64 values (a float32 model cast with .double() keeps float32-rounded kinematics).
    """

    def __init__(self, config: AnalyticConfig | None = None, params: np.ndarray | torch.Tensor | None = None,
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        self.config = config = config or AnalyticConfig()
        chain = read_chain(config)
        self.n_joints = config.n_joints
        self.dt = config.dt
        self.tree = make_tree(chain.parent)
        self.bodies = chain.bodies
        self.q_lower, self.q_upper = chain.q_lower, chain.q_upper
        self.identification: IdentificationReport | None = None
        params = nominal_parameters(config) if params is None else params
        params = torch.as_tensor(np.asarray(params, dtype=np.float64))
        if params.shape != (config.n_params,):
            raise ValueError(f"AnalyticModel: params must have shape ({config.n_params},), got {tuple(params.shape)}")
        if not torch.isfinite(params).all():
            raise ValueError("AnalyticModel: params has non-finite entries")
        self.register_buffer("params", params.to(dtype))
        self.register_buffer("body_pos", torch.as_tensor(chain.body_pos, dtype=dtype))
        self.register_buffer("body_rot", torch.as_tensor(chain.body_rot, dtype=dtype))
        self.register_buffer("axis", torch.as_tensor(chain.axis, dtype=dtype))
        self.register_buffer("gravity", torch.as_tensor(chain.gravity, dtype=dtype))

    def _kin(self) -> ChainTensors:
        return ChainTensors(self.body_pos, self.body_rot, self.axis, self.gravity)

    def _split_params(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        n = self.n_joints
        inertial = self.params[:N_INERTIAL * n].reshape(n, N_INERTIAL)
        armature, viscous, coulomb = self.params[N_INERTIAL * n:].reshape(len(JOINT_PARAMS), n)
        return inertial, armature, viscous, coulomb

    def initial_state(self, batch: int = 1) -> tuple[()]:
        return ()

    def fit_normalisation(self, stats: DatasetStats) -> None:
        """Nothing to fit: the model works in SI units and is identified by least squares (`identify`). Checks
        that the statistics are for this model's joints."""
        shape = np.shape(stats.q_std)
        if shape != (self.n_joints,):
            raise ValueError(f"AnalyticModel.fit_normalisation: stats.q_std has shape {shape}, expected "
                             f"({self.n_joints},)")

    def inverse_dynamics(self, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor) -> torch.Tensor:
        """tau = M(q) qdd + h(q, qd) + friction(qd), [B, n], by RNEA on the parameters (not through Y)."""
        inertial, armature, viscous, coulomb = self._split_params()
        base_accel = (-self.gravity).expand(q.shape[0], 3)
        tau = _rnea(self._kin(), self.tree, inertial, q, qd, qdd, base_accel)
        return tau + armature * qdd + viscous * qd + coulomb * torch.tanh(qd / self.config.coulomb_velocity)

    def mass_and_bias(self, q: torch.Tensor, qd: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """M(q) [B, n, n] (with armature) and h(q, qd) + friction(qd) [B, n], from one batched RNEA: row 0 with
        gravity and zero acceleration, rows 1..n with unit accelerations and neither velocity nor gravity."""
        batch, n = q.shape
        inertial, armature, viscous, coulomb = self._split_params()
        eye = torch.eye(n, dtype=q.dtype, device=q.device)
        qs = q.unsqueeze(1).expand(batch, n + 1, n).reshape(-1, n)
        qds = torch.cat([qd.unsqueeze(1), qd.new_zeros(batch, n, n)], dim=1).reshape(-1, n)
        qdds = torch.cat([q.new_zeros(batch, 1, n), eye.expand(batch, n, n)], dim=1).reshape(-1, n)
        gravity_on = torch.cat([q.new_ones(batch, 1), q.new_zeros(batch, n)], dim=1).reshape(-1, 1)
        tau = _rnea(self._kin(), self.tree, inertial, qs, qds, qdds, gravity_on * -self.gravity)
        tau = tau.reshape(batch, n + 1, n)
        mass = tau[:, 1:].transpose(1, 2) + torch.diag_embed(armature.expand(batch, n))
        mass = 0.5 * (mass + mass.transpose(1, 2))  # symmetric to rounding; exact in exact arithmetic
        bias = tau[:, 0] + viscous * qd + coulomb * torch.tanh(qd / self.config.coulomb_velocity)
        return mass, bias

    def mass_matrix(self, q: torch.Tensor) -> torch.Tensor:
        return self.mass_and_bias(q, torch.zeros_like(q))[0]

    def acceleration(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        mass, bias = self.mass_and_bias(q, qd)
        # solve_ex: a singular M (a rollout far outside the data) gives non-finite values, not an exception.
        return torch.linalg.solve_ex(mass, tau - bias).result

    def forward(self, q: torch.Tensor, qd: torch.Tensor, tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        qd_next = qd + self.acceleration(q, qd, tau) * self.dt  # semi-implicit Euler, as MuJoCo for hinges
        q_next = q + qd_next * self.dt
        return q_next, qd_next

    @torch.no_grad()
    def raise_armature_floor(self, q_samples: torch.Tensor, floor: float) -> tuple[float, float]:
        """Make lambda_min(M(q)) >= floor on q_samples [S, n] by adding the shortfall to every armature.

        Returns (shift added in kg m^2, lambda_min after). Adding c to every armature adds c*I to M, so every
        eigenvalue rises by exactly c."""
        eigenvalues = torch.cat([torch.linalg.eigvalsh(self.mass_matrix(chunk))
                                 for chunk in q_samples.to(self.params.dtype).split(1024)])
        lowest = float(eigenvalues.min())
        shift = max(0.0, floor - lowest)
        if shift > 0:
            n = self.n_joints
            self.params[N_INERTIAL * n:(N_INERTIAL + 1) * n] += shift
        return shift, lowest + shift


# -- identification -------------------------------------------------------------------------------------------
def _as_joint_array(name: str, value, n: int, length: int | None = None) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != n or (length is not None and array.shape[0] != length):
        expected = f"[{'T' if length is None else length}, {n}]"
        raise ValueError(f"identify: {name} has shape {list(array.shape)}, expected {expected}")
    if not np.isfinite(array).all():
        raise ValueError(f"identify: {name} has non-finite entries")
    return array


def _solve_scaled(r_aug: np.ndarray, rcond: float, ridge: float) -> tuple[np.ndarray, int, float, float]:
    """Least squares from the R factor of [Y | tau]: unit-norm columns, truncated SVD, ridge.

    Returns (pi, rank, condition number of the kept part, relative residual)."""
    p = r_aug.shape[1] - 1
    r, z = r_aug[:, :p], r_aug[:, p]
    scale = np.linalg.norm(r, axis=0)
    # A column at rounding level is structurally zero (e.g. a link's first moment along its own joint axis) or never
    # excited; scaled to unit norm it would pose as a real direction, so it is dropped and its pi stays 0.
    excited = scale > _UNEXCITED * scale.max()
    scale[~excited] = np.inf
    u, s, vt = np.linalg.svd(r / scale, full_matrices=False)
    keep = s > rcond * s[0]
    gain = s[keep] / (s[keep] ** 2 + ridge * s[0] ** 2)
    pi = (vt[keep].T @ (gain * (u[:, keep].T @ z))) / scale
    tau_norm2 = float(np.sum(r_aug[:, p] ** 2))  # |Q^T tau|^2 = |tau|^2
    residual2 = float(np.sum((r @ pi - z) ** 2))  # the part of tau outside span(Y) is in the last row of R
    return pi, int(keep.sum()), float(s[0] / s[keep][-1]), float(np.sqrt(residual2 / max(tau_norm2, 1e-300)))


@contextmanager
def _one_thread():
    """torch on one intra-op thread for the duration, restored after: identification is many small batched ops,
    where a second thread only spins, and on a loaded 2-core machine that was measured 10-40x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _leg_factors(chain: Chain, config: AnalyticConfig, q: np.ndarray, qd: np.ndarray, tau: np.ndarray,
                 index: np.ndarray, legs: dict[int, list[int]], leg_columns: dict[int, np.ndarray], chunk: int
                 ) -> dict[int, torch.Tensor]:
    """Per leg, the R factor of [Y | tau] over the transitions `index`, streamed through QR chunk by chunk."""
    kin = ChainTensors(*(torch.as_tensor(x, dtype=torch.float64) for x in (chain.body_pos, chain.body_rot,
                                                                          chain.axis, chain.gravity)))
    tree = make_tree(chain.parent)
    factors: dict[int, torch.Tensor] = {}
    for start in range(0, len(index), chunk):
        t = index[start:start + chunk]
        qdd = (qd[t + 1] - qd[t]) / config.dt  # forward difference: the acceleration the step applied (docs)
        y = regressor(kin, tree, torch.as_tensor(q[t]), torch.as_tensor(qd[t]), torch.as_tensor(qdd),
                      config.coulomb_velocity)
        for root, joints in legs.items():  # with a fixed base each leg is its own least-squares problem
            rows = y[:, joints][:, :, leg_columns[root]].reshape(-1, len(leg_columns[root]))
            block = torch.cat([rows, torch.as_tensor(tau[t][:, joints]).reshape(-1, 1)], dim=1)
            stacked = torch.cat([factors[root], block]) if root in factors else block
            # torch's QR, not numpy's: numpy's OpenBLAS threads spin badly on a loaded machine (8x slower here).
            factors[root] = torch.linalg.qr(stacked, mode="r").R
    return factors


def identify(q, qd, tau, dt: float, episode=None, *, config: AnalyticConfig | None = None, seed: int = 0,
             chunk: int = 1024, dtype: torch.dtype = torch.float32) -> AnalyticModel:
    """Identify pi by least squares on the transitions of (q, qd, tau) [T, n] sampled every dt seconds, in the
    config's joint order, tau[t] being the torque applied over [t, t+1]; episode [T] marks where recordings were
    cut (no transition crosses a change of value). Pass the training split only.

    `seed` draws the random joint-range states of the positive-definiteness check; `chunk` is the number of
    transitions per regressor block. Returns the model in `dtype` with its `identification` report.
    """
    started = time.perf_counter()
    config = config or AnalyticConfig()
    if abs(dt - config.dt) > 1e-12:
        raise ValueError(f"identify: data dt = {dt} s does not match AnalyticConfig.dt = {config.dt} s")
    n = config.n_joints
    q = _as_joint_array("q", q, n)
    qd = _as_joint_array("qd", qd, n, len(q))
    tau = _as_joint_array("tau", tau, n, len(q))
    episode = np.zeros(len(q), np.int64) if episode is None else np.asarray(episode)
    if episode.shape != (len(q),):
        raise ValueError(f"identify: episode has shape {list(episode.shape)}, expected [{len(q)}]")
    index = transition_indices(episode)
    if len(index) == 0:
        raise ValueError("identify: no transition t -> t+1 within one episode")

    chain = read_chain(config)
    roots = chain.roots()
    legs = {root: [j for j in range(n) if roots[j] == root] for root in sorted(set(roots))}
    leg_columns = {root: np.concatenate([np.arange(N_INERTIAL * j, N_INERTIAL * (j + 1)) for j in joints]
                                        + [N_INERTIAL * n + k * n + np.array(joints) for k in range(len(JOINT_PARAMS))])
                   for root, joints in legs.items()}
    with _one_thread():
        factors = _leg_factors(chain, config, q, qd, tau, index, legs, leg_columns, chunk)
        params = np.zeros(config.n_params)
        rank, condition, residual = {}, {}, {}
        for root, r_aug in factors.items():
            leg = chain.bodies[root]
            pi, rank[leg], condition[leg], residual[leg] = _solve_scaled(r_aug.numpy(), config.rcond, config.ridge)
            params[leg_columns[root]] = pi

        model = AnalyticModel(config, params, dtype=torch.float64)
        rng = np.random.default_rng(seed)
        visited = q[np.linspace(0, len(q) - 1, min(len(q), 2048)).astype(int)]
        spread = rng.uniform(chain.q_lower, chain.q_upper, size=(2048, n))
        shift, lowest = model.raise_armature_floor(torch.as_tensor(np.vstack([visited, spread])),
                                                   config.min_mass_eigenvalue)
    if dtype != torch.float64:
        model = AnalyticModel(config, model.params, dtype=dtype)  # rounded once, from the float64 values
    model.identification = IdentificationReport(
        n_samples=len(index), n_params=config.n_params, rank=rank, condition=condition, relative_residual=residual,
        min_mass_eigenvalue=lowest, armature_shift=shift, seconds=time.perf_counter() - started)
    return model


def identify_dataset(split, config: AnalyticConfig | None = None, **kwargs) -> AnalyticModel:
    """`identify` on a `training.dataset.Dataset` (its q, qd, tau, dt and episode): pass the training split."""
    return identify(split.q, split.qd, split.tau, split.dt, split.episode, config=config, **kwargs)
