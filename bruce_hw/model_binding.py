"""Where the robot config's joints live in a MuJoCo model (`JointBinding`): one lookup, by name, held by BRUCE's
model (`bruce_hw.robot_model.BruceModel`) that the mock, the transfer stage's nominal models and the training model
build, instead of each reading another's private indices.

A joint named in `joints.names` must be a joint of the model with exactly one joint-transmission actuator (its
motor), and the config's joints must be contiguous in qpos, qvel and the actuators, in the config's order, so that
one slice addresses them all: `data.qpos[binding.qpos]` is q in config order.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco

from bruce_hw.backend import BackendError


@dataclass(frozen=True)
class JointBinding:
    qpos: slice   # the config's joints in qpos, in config order
    dofs: slice   # ... in qvel (and qfrc, dof_* arrays)
    acts: slice   # their motors (ctrl, actuator_force, actuator_* arrays)


def _contiguous(indices: list[int], what: str, source: str) -> slice:
    if indices != list(range(indices[0], indices[0] + len(indices))):
        raise BackendError(f"{source}: {what} of the config's joints are not contiguous in the model: {indices}")
    return slice(indices[0], indices[0] + len(indices))


def bind_joints(model: mujoco.MjModel, joints: tuple[str, ...], source: str) -> JointBinding:
    """The binding of `joints` in `model`; BackendError naming `source` (the model file) and the joint otherwise."""
    qpos, dofs, acts = [], [], []
    for name in joints:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise BackendError(f"{source}: no joint named {name!r} (from joints.names)")
        act = [a for a in range(model.nu)
               if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and model.actuator_trnid[a, 0] == jid]
        if len(act) != 1:
            raise BackendError(f"{source}: joint {name!r} needs exactly one motor, found {len(act)}")
        qpos.append(int(model.jnt_qposadr[jid]))
        dofs.append(int(model.jnt_dofadr[jid]))
        acts.append(act[0])
    return JointBinding(_contiguous(qpos, "qpos addresses", source), _contiguous(dofs, "dof addresses", source),
                        _contiguous(acts, "motors", source))
