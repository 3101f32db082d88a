"""The observation terms a policy spec can name (`observation: [clock, q, ...]` in a spec file), each registered once
by name with its width and one function of a batch of robots' `ObservationInputs`.

A term's function returns (batch, width) in SI units and, for a joint-space term (width `PER_JOINT`), in the robot
config's joint order: a spec's offset, clip, scale, history and joint order are applied after it, by
`runtime.observation.spec_terms`, the same way for every term, so a term is written once for the runtime (batch 1)
and for training (batch N).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from runtime.observation.inputs import ObservationInputs

PER_JOINT = "per joint"  # a term's width: one value per joint of the robot config

TermFunction = Callable[["ObservationInputs"], np.ndarray]


@dataclass(frozen=True, slots=True)
class ObservationTermDefinition:
    name: str
    width: int | str           # values per frame, or PER_JOINT
    function: TermFunction     # ObservationInputs (batch N) -> (N, width)
    joint_angles: bool = False  # its values are joint angles: a spec may write `offset: standing`

    @property
    def per_joint(self) -> bool:
        return self.width == PER_JOINT

    def width_for(self, n_joints: int) -> int:
        return n_joints if self.per_joint else int(self.width)


# name -> definition, in registration order (the order a spec error lists the names in)
OBSERVATION_TERMS: dict[str, ObservationTermDefinition] = {}


def register_term(name: str, width: int | str, function: TermFunction, *, joint_angles: bool = False
                  ) -> ObservationTermDefinition:
    """Make `name` a term a spec can name. A name is registered once: a second registration is a mistake (two
    modules defining one term), not an update."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"observation term name: expected an identifier, got {name!r}")
    if name in OBSERVATION_TERMS:
        raise ValueError(f"observation term {name!r} is registered already (by {OBSERVATION_TERMS[name].function})")
    if width != PER_JOINT and (isinstance(width, bool) or not isinstance(width, int) or width < 1):
        raise ValueError(f"observation term {name!r}: width: expected an integer >= 1 or {PER_JOINT!r}, got "
                         f"{width!r}")
    if not callable(function):
        raise ValueError(f"observation term {name!r}: function: expected a callable, got {function!r}")
    definition = ObservationTermDefinition(name, width, function, joint_angles)
    OBSERVATION_TERMS[name] = definition
    return definition


def term_definition(name: str) -> ObservationTermDefinition:
    return OBSERVATION_TERMS[name]
