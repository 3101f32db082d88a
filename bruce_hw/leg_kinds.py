"""The kinds of leg bus the hw path knows (`LEG_KINDS`, one module each under bruce_hw/legs/; what a kind provides:
`bruce_hw.leg_kind`), and which one a robot config uses (`leg_kind_of`). The hw backend, the emulated plant,
bruce-hw-check and bruce-emulate look the kind up here instead of naming BEARs or CAN motors. Adding one:
docs/extending.md ("Adding a leg actuator").
"""

from __future__ import annotations

from bruce_hw.config import RobotConfig
from bruce_hw.leg_kind import LegKind
from bruce_hw.legs.bear import BearKind
from bruce_hw.legs.can import CanKind

LEG_KINDS: dict[str, LegKind] = {}


def register_leg_kind(kind: LegKind) -> LegKind:
    """Make `kind` known; it is asked before every kind registered earlier (`leg_kind_of`)."""
    if kind.name in LEG_KINDS:
        raise ValueError(f"a leg kind named {kind.name!r} is registered already")
    LEG_KINDS[kind.name] = kind
    return kind


def leg_kind_of(config: RobotConfig) -> LegKind:
    """The kind of the config's legs: the last registered one that `uses` it. Asking the newest first lets a kind
    claim configs that an earlier, broader one would take: the BEAR legs take every config (the default)."""
    for kind in reversed(LEG_KINDS.values()):
        if kind.uses(config):
            return kind
    raise ValueError(f"{config.path}: no leg kind uses this config (known: {', '.join(LEG_KINDS)})")


register_leg_kind(BearKind())  # first: the default
register_leg_kind(CanKind())
