"""A transfer scheme by name (`build_scheme`): the registered builder (runtime/transfer/registry.py), given the
config's transfer settings (runtime/transfer/stage.py) and the run's sources of the robot's base state. The
schemes themselves: direct.py, eq9.py (`pinn` = `eq9`), shadow.py, observer.py, twin.py (`twin`, `shadow_twin`);
docs/transfer.md, "The schemes".
"""

from __future__ import annotations

from pathlib import Path

from bruce_hw.config import RobotConfig
from runtime.transfer.interface import TransferScheme
from runtime.transfer.registry import SchemeContext, scheme_entry
from runtime.transfer.stage import settings_for


def build_scheme(config: RobotConfig, name: str, pinn_path: Path | None = None, base_state=None,
                 twin_controller=None, estimator=None, paced: bool = False) -> TransferScheme:
    """The scheme `name` (a registered name or alias) with its reference model (`transfer.reference_model`) and its
    settings from the config's `transfer.<section>`. Where the schemes' models get the robot's base from:
    `estimator` (the run's `KinematicEstimator`: a robot-faithful run, any backend) or, when `base_state` is given
    instead, the simulator's truth (a truth-fed diagnostic run on the mock). `twin_controller()` makes the twin
    schemes' second instance of the robot's nominal controller (default: the configured walking policy); `paced`:
    the twin runs on a thread of its own (`runtime.transfer.twin_runner`), the shadow's PINN steps beside the loop
    (`runtime.transfer.shadow_stepper`)."""
    entry = scheme_entry(name)
    transfer = settings_for(config)

    def inner(other: str) -> TransferScheme:  # an inner scheme: the same run's base state and pacing
        return build_scheme(config, other, pinn_path, base_state, estimator=estimator, paced=paced)

    context = SchemeContext(config=config, name=name, transfer=transfer,
                            settings=None if entry.settings is None else transfer.of(entry.section),
                            pinn_path=pinn_path, base_state=base_state, estimator=estimator,
                            twin_controller=twin_controller, paced=paced, build=inner)
    return entry.build(context)
