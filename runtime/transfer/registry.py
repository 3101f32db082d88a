"""The transfer schemes by name: each scheme's module registers itself (`register_scheme`), and everything that
lists or builds schemes asks here: bruce-run's `--transfer`, the config's `transfer.scheme`, `bruce-eval transfer
--schemes`, the bench, docs/config_bounds.md (through `runtime.transfer.stage.transfer_bounds`).

A registration is the scheme's name (and older aliases), its settings class (the keys of `transfer.<section>`,
runtime/transfer/settings.py; None: it has none) and its builder: a function of a `SchemeContext` that returns the
scheme (a `runtime.transfer.interface.TransferScheme`). Adding one, step by step: docs/extending.md ("Adding a
transfer scheme").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bruce_hw.config import RobotConfig
from runtime.control.inference import ModelError
from runtime.transfer.interface import TransferScheme
from runtime.transfer.reference_models import ReferenceModel, build_reference


@dataclass(frozen=True)
class SchemeContext:
    """What a builder gets: the robot config, the transfer stage's settings (`runtime.transfer.stage
    .TransferSettings`: the reference model, the delay margin, ...), the scheme's own settings, and where the run's
    models get the robot's base from: `estimator` (the run's `KinematicEstimator`: robot-faithful) or, when
    `base_state` is given instead, the simulator's truth (a truth-fed diagnostic on the mock)."""

    config: RobotConfig
    name: str                  # as asked for: an alias stays itself (`pinn`)
    transfer: Any              # runtime.transfer.stage.TransferSettings
    settings: Any              # the scheme's settings class, filled in from transfer.<section>; None without one
    pinn_path: Path | None = None
    base_state: Callable | None = None
    estimator: Any = None
    twin_controller: Callable | None = None  # makes a second instance of the robot's nominal controller
    paced: bool = False                      # the loop runs on the wall clock: a scheme's helper may take a thread
    build: Callable[[str], TransferScheme] | None = None  # another scheme by name, on the same run (an inner scheme)

    def reference(self, lookahead: int = 0) -> ReferenceModel:
        """The reference model of `transfer.reference_model` (`lookahead`: PINN ticks rolled further ahead)."""
        kind = self.transfer.reference_model
        base = self.base_state if self.base_state is not None else (
            None if self.estimator is None else self.estimator.estimate)
        if kind == "nominal" and base is None:
            raise ModelError(f"--transfer {self.name} with transfer.reference_model nominal: the nominal model needs "
                             "the robot's base state, from the run's estimator (or, in a diagnostic, the simulator's "
                             "truth)")
        return build_reference(self.config, kind, self.pinn_path, base or (lambda: None), lookahead=lookahead,
                                scheme=self.name)


@dataclass(frozen=True)
class SchemeEntry:
    name: str
    settings: type | None                          # a dataclass of `runtime.transfer.settings.setting` fields
    build: Callable[[SchemeContext], TransferScheme]
    section: str                                   # its settings' YAML section: transfer.<section>.<field>
    aliases: tuple[str, ...] = ()
    help: str = ""                                 # one phrase for bruce-run --transfer's help
    uses_reference: bool = False                   # asks a reference model: --pinn and SCHEME@nominal apply


_SCHEMES: dict[str, SchemeEntry] = {}  # every name and alias -> its entry, in registration order
_generation = 0  # counts the changes of _SCHEMES: the sections a config's transfer settings were read with


def register_scheme(name: str, settings: type | None, build: Callable[[SchemeContext], TransferScheme], *,
                    section: str | None = None, aliases: tuple[str, ...] = (), help: str = "",
                    uses_reference: bool = False) -> SchemeEntry:
    """Make scheme `name` known (with `aliases`): built by `build(context)`, its settings `settings` read from
    transfer.<section> (default: the name; two schemes may share a section with the same settings class)."""
    entry = SchemeEntry(name, settings, build, section or name, tuple(aliases), help, uses_reference)
    for known in (*entry.aliases, name):
        if known in _SCHEMES:
            raise ValueError(f"transfer scheme {known!r} is registered twice")
    shared = next((e for e in _SCHEMES.values() if e.section == entry.section and e.settings is not None), None)
    if settings is not None and shared is not None and shared.settings is not settings:
        raise ValueError(f"transfer.{entry.section}: {name!r} and {shared.name!r} register different settings")
    global _generation
    for known in (*entry.aliases, name):  # an alias first: it is the older name (`pinn` for eq9)
        _SCHEMES[known] = entry
    _generation += 1
    return entry


def unregister_scheme(name: str) -> None:
    """Forget scheme `name` and its aliases (a test's own scheme, once the test is over)."""
    global _generation
    entry = _SCHEMES[name]
    for known in (*entry.aliases, entry.name):
        del _SCHEMES[known]
    _generation += 1


def registry_generation() -> int:
    return _generation


def scheme_names(aliases: bool = True) -> tuple[str, ...]:
    """Every scheme name, in registration order, each alias before its scheme (without `aliases`: one per scheme)."""
    return tuple(known for known, entry in _SCHEMES.items() if aliases or known == entry.name)


def scheme_entry(name: str) -> SchemeEntry:
    """The registration of `name` (a name or an alias); ValueError listing the names for an unknown one."""
    try:
        return _SCHEMES[name]
    except KeyError:
        raise ValueError(f"unknown transfer {name!r} (expected one of {', '.join(_SCHEMES)})") from None


def scheme_sections() -> Mapping[str, type]:
    """transfer.<section> -> its settings class, for every registered scheme that has settings."""
    return {entry.section: entry.settings for entry in _SCHEMES.values() if entry.settings is not None}


def listed_schemes(alias: str = " = ") -> str:
    """The schemes for a help text, an alias beside its scheme: "direct, pinn = eq9, shadow, ..."."""
    return ", ".join(alias.join((*_SCHEMES[name].aliases, name)) for name in scheme_names(aliases=False))


def scheme_help() -> tuple[tuple[str, ...], str]:
    """bruce-run --transfer's choices and help: "direct: Eq. 8 torques alone; pinn or eq9: the paper's Eq. 9, ..."."""
    parts = [f"{' or '.join((*_SCHEMES[name].aliases, name))}: {_SCHEMES[name].help}"
             for name in scheme_names(aliases=False)]
    return scheme_names(), "; ".join(parts)
