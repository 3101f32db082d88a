"""Settings that a transfer-stage component declares itself: a frozen dataclass whose numeric fields each carry
their valid range (`setting(default, Bound)`), read from one section of the robot config's `transfer` section.

A field `NAME` of the settings of section `SECTION` is the YAML key `transfer.SECTION.NAME`; every key is optional
(the field's default). A class may narrow its bounds by other settings (`relations`, e.g. the observer's shortest
time constant from the delay margin): then a value given outside is refused naming the relation, and so is a default
that falls outside (naming the key that moved the bound, since the user never wrote the field).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from bruce_hw.yaml_reader import Bound, YamlReader


def setting(default: float, bound: Bound) -> Any:
    """A numeric settings field: its default and its valid range (the error's unit and reason)."""
    return dataclasses.field(default=default, metadata={"bound": bound})


def bounds_of(settings_class: type) -> dict[str, Bound]:
    """Field name -> Bound of every numeric field of a settings class, in declaration order."""
    return {f.name: f.metadata["bound"] for f in dataclasses.fields(settings_class) if "bound" in f.metadata}


@dataclass(frozen=True)
class Relation:
    """A bound narrowed by other settings (`bound.why` says by which) and the key whose value narrowed it: a default
    outside the narrowed bound is refused at that key (its value `got`), as `expected` ("a margin that the default
    ... keeps")."""

    bound: Bound
    depends_on: str          # e.g. "transfer.delay_margin_s"
    got: float
    expected: str = "a value"


def read_settings(r: YamlReader, key: str, settings_class: type, relations: Mapping[str, Relation] | None = None):
    """The settings at `key` (e.g. "transfer.twin"; absent: every default), each value inside its bound, or the one
    inside its relation's narrowed bound; unknown keys are refused."""
    bounds = bounds_of(settings_class)
    relations = relations or {}
    node = r.mapping(key, set(bounds)) if _present(r, key) else {}
    values = {name: r.number(f"{key}.{name}", bound=relations[name].bound if name in relations else bound)
              for name, bound in bounds.items() if name in node}
    defaults = settings_class()
    for name, relation in relations.items():
        default = getattr(defaults, name)
        if name not in values and not relation.bound.contains(default):
            unit = f" {bounds[name].unit}" if bounds[name].unit else ""
            raise r.fail(relation.depends_on, f"{relation.expected} that the default {key}.{name} ({default:g}{unit}) "
                         "keeps; set that key too", relation.got)
    return dataclasses.replace(defaults, **values)


def _present(r: YamlReader, key: str) -> bool:
    """Whether the tree has a value at `key` (a path of mapping keys)."""
    node = r.data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True

