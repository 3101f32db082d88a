"""The transfer stage's settings: the robot config's `transfer` section, read by the runtime (bruce_hw keeps it
unread in `RobotConfig.raw`).

The stage's own keys (`TransferSettings`: the scheme without --transfer, the reference model, the delay and phase
margins the feedback schemes are designed for) and its sections: `gap_monitor` and each registered scheme's
(`transfer.<section>.<field>`, runtime/transfer/registry.py). `settings_for(config)` reads and checks them once per
config; a bad value is one `ConfigError` naming the file and the key, as for the rest of the config.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from bruce_hw.config import ConfigError, RobotConfig
from bruce_hw.yaml_reader import Bound, YamlReader
from runtime.transfer.gap_monitor import GapMonitorSettings
from runtime.transfer.reference_models import REFERENCE_MODELS
from runtime.transfer.registry import registry_generation, scheme_names, scheme_sections
from runtime.transfer.settings import bounds_of, read_settings, setting


@dataclass(frozen=True)
class TransferSettings:
    """transfer: every key optional (these defaults)."""

    scheme: str = "direct"
    reference_model: str = "pinn"
    # the loop delay the feedback schemes are designed to tolerate ... with this phase margin left
    # (runtime/transfer/gains.py)
    delay_margin_s: float = setting(0.009, Bound(0.001, 0.05, "s", "loop delay the transfer feedback must tolerate"))
    phase_margin_deg: float = setting(45.0, Bound(10.0, 70.0, "deg",
                                                  "left at that delay; a PD leads by at most 71.6 deg"))
    gap_monitor: GapMonitorSettings = GapMonitorSettings()
    schemes: Mapping[str, Any] = field(default_factory=dict)  # section -> that scheme's settings

    def of(self, section: str) -> Any:
        """The settings of scheme section `section` (e.g. "twin")."""
        return self.schemes[section]


def sections() -> dict[str, type]:
    """transfer.<section> -> its settings class: the gap monitor's, then each registered scheme's."""
    return {"gap_monitor": GapMonitorSettings, **scheme_sections()}


def transfer_bounds() -> dict[str, Bound]:
    """Every numeric key of the transfer section ("transfer.twin.resync_s") -> its Bound: docs/config_bounds.md's
    transfer rows."""
    table = {f"transfer.{name}": bound for name, bound in bounds_of(TransferSettings).items()}
    for section, settings_class in sections().items():
        table.update({f"transfer.{section}.{name}": bound for name, bound in bounds_of(settings_class).items()})
    return table


def parse_transfer(config: RobotConfig) -> TransferSettings:
    """The `transfer` section of `config`'s YAML, checked; ConfigError naming the file and the key."""
    r = YamlReader(config.path, config.raw, ConfigError)
    if "transfer" not in config.raw:
        return _with_defaults(TransferSettings(), config, r)
    own = bounds_of(TransferSettings)
    node = r.mapping("transfer", {"scheme", "reference_model", *own, *sections()})
    values: dict[str, Any] = {}
    if "scheme" in node:
        values["scheme"] = r.choice("transfer.scheme", scheme_names())
    if "reference_model" in node:
        values["reference_model"] = r.choice("transfer.reference_model", REFERENCE_MODELS)
    values.update({name: r.number(f"transfer.{name}", bound=bound) for name, bound in own.items() if name in node})
    return _with_defaults(TransferSettings(**values), config, r)


def _with_defaults(stage: TransferSettings, config: RobotConfig, r: YamlReader) -> TransferSettings:
    """`stage` with every section read (absent: its defaults), each checked against its relations to the stage's
    own keys and the robot config."""
    read = {}
    for section, settings_class in sections().items():
        relations = getattr(settings_class, "relations", None)
        read[section] = read_settings(r, f"transfer.{section}", settings_class,
                                      relations(stage, config) if relations is not None else None)
    return replace(stage, gap_monitor=read.pop("gap_monitor"), schemes=read)


# id(config) -> (config, the registry's generation it was read under, its settings); the entry holds its config, so
# the id is not reused while it is cached. Configs are few per process.
_CACHE: OrderedDict[int, tuple[RobotConfig, int, TransferSettings]] = OrderedDict()
_CACHE_SIZE = 16


def settings_for(config: RobotConfig) -> TransferSettings:
    """The transfer settings of `config` (read once per config object and set of registered schemes); ConfigError
    naming the file and the key for a bad value."""
    key, generation = id(config), registry_generation()
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is config and hit[1] == generation:
        _CACHE.move_to_end(key)
        return hit[2]
    settings = parse_transfer(config)
    _CACHE[key] = (config, generation, settings)
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return settings

