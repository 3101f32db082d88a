"""Typed, bounded reading of YAML settings files; every failure is one line "SOURCE: dotted.key: expected ..., got ...".

`YamlReader` walks a parsed tree by dotted keys ("buses.bear.ids[3]") and raises the caller's error class;
`Bound` is the valid range of one number, `bound_lookup` finds a concrete key's entry in a table of key patterns;
`read_yaml` loads a file; `apply_overrides` applies `--set KEY=VALUE` to a tree. It knows no schema: the robot
config (bruce_hw/config.py), the reality-gap profiles and the command scenarios bring theirs.
"""

from __future__ import annotations

import copy
import functools
import math
import re
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

ErrorClass = type[ValueError]


@dataclass(frozen=True, slots=True)
class Bound:
    """The valid range of one numeric setting, its unit and the physical reason. Both ends are finite, so a value
    inside is finite too."""

    low: float
    high: float
    unit: str = ""
    why: str = ""
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    step: float = 0.0  # > 0: only low + k * step

    def contains(self, value: float) -> bool:
        # Comparisons only: NaN fails every one, and a huge YAML integer is compared exactly (no float overflow).
        if not (value > self.low if self.low_open else value >= self.low):
            return False
        if not (value < self.high if self.high_open else value <= self.high):
            return False
        return not self.step or abs((value - self.low) / self.step - round((value - self.low) / self.step)) < 1e-6

    def interval(self, unit: bool = False) -> str:
        """The range, e.g. "(0, 10.5]" ("(0, 10.5] N·m" with `unit`); a two-value step reads "1 or -1"."""
        low, high = (f"{int(x)}" if self.integer else f"{x:g}" for x in (self.low, self.high))
        if self.step and self.high - self.low == self.step:
            return f"{high} or {low}"
        text = f"{'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"
        text += f" {self.unit}" if unit and self.unit else ""
        return text + (f" in steps of {self.step:g}" if self.step else "")

    def expected(self) -> str:
        """What an error says was expected, e.g. "a number in [0.2, 0.5] N·m/A (Koala BEAR rating)"."""
        text = self.interval(unit=True)
        if not (self.step and self.high - self.low == self.step):
            text = f"{'an integer' if self.integer else 'a number'} in {text}"
        return text + (f" ({self.why})" if self.why else "")

    def narrowed(self, why: str, low: float = -math.inf, high: float = math.inf, high_open: bool = False) -> Bound:
        """This range cut by a relation to another setting (`why` names it); the static ends still hold."""
        if low <= self.low and high >= self.high:
            return self
        return replace(self, why=why, low=max(self.low, low), high=min(self.high, high),
                       low_open=self.low_open and low <= self.low,
                       high_open=self.high_open if high >= self.high else high_open)


def shown(value: Any) -> str:
    """A value as an error quotes it: its repr, cut at 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def checked_number(source: Any, key: str, value: Any, bound: Bound, error: ErrorClass, also: str = "") -> Any:
    """`value` if it is a number (an int for integer bounds; never a YAML boolean) inside `bound`, as a float (int);
    otherwise one-line `error` "{source}: {key}: expected ..., got ...". `also` adds other accepted forms."""
    kind = int if bound.integer else int | float
    if isinstance(value, bool) or not isinstance(value, kind) or not bound.contains(value):
        hint = ""
        if isinstance(value, str):
            try:
                hint = " (YAML reads 1e-3 as text: write 1.0e-3)" if math.isfinite(float(value)) else ""
            except ValueError:
                pass
        raise error(f"{source}: {key}: expected {bound.expected()}{also}, got {shown(value)}{hint}")
    return value if bound.integer else float(value)


def _key_pattern(pattern: str) -> re.Pattern:
    return re.compile(re.escape(pattern).replace(r"\[\*\]", r"\[\d+\]").replace(r"\*", r"[^.\[\]]+"))


def bound_lookup(table: Mapping[str, Bound], name: str) -> Callable[[str], Bound]:
    """The lookup of a table of dotted key patterns ("*" one name, "[*]" one list index) -> Bound: called with a
    concrete key ("joints.velocity_limits.r_knee"), it returns the first matching entry (LookupError naming
    `name`, the table, when none matches)."""
    patterns = [(_key_pattern(pattern), bound) for pattern, bound in table.items()]

    @functools.lru_cache(maxsize=4096)
    def bound_for(key: str) -> Bound:
        for pattern, bound in patterns:
            if pattern.fullmatch(key):
                return bound
        raise LookupError(f"no {name} entry for {key}")

    return bound_for


def read_yaml(path: Path, error: ErrorClass, what: str = "file") -> Any:
    """The YAML tree of a text file; one-line `error` naming the file when it cannot be read, is not UTF-8 text or
    is not YAML."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        return yaml.safe_load(text)
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an integer too long to convert
        raise error(f"{path}: not valid YAML: {_yaml_problem(exc)}") from None


def _yaml_problem(exc: Exception) -> str:
    mark = getattr(exc, "problem_mark", None)
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    return " ".join(f"{getattr(exc, 'problem', None) or exc}{where}".split())


def apply_overrides(data: dict, overrides: list[str], source: Any, error: ErrorClass) -> dict:
    """Apply `KEY=VALUE` overrides (dotted key paths, VALUE parsed as YAML) to a copy of the raw tree.

    Only existing keys can be set, so a typo fails instead of being ignored.
    """
    data = copy.deepcopy(data)
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise error(f"{source}: --set {item!r}: expected KEY=VALUE with a dotted key path")
        parts = key.split(".")
        node = data
        for depth, part in enumerate(parts):
            if not isinstance(node, dict) or part not in node:
                parent = ".".join(parts[:depth]) or "<top>"
                raise error(f"{source}: {key}: no such key to --set (nothing named {part!r} under {parent})")
            if depth == len(parts) - 1:
                try:
                    node[part] = yaml.safe_load(text) if text else ""
                except (yaml.YAMLError, ValueError) as exc:
                    raise error(f"{source}: --set {key}: not a valid YAML value: {_yaml_problem(exc)}") from None
            else:
                node = node[part]
    return data


_KEY_PART = re.compile(r"[^.\[\]]+|\[\d+\]")  # "a.b[2]" -> "a", "b", "[2]"
_LOOK_UP = object()  # "read the value at the key", distinct from a YAML null


def _listed(names: Collection) -> list:
    """Names as an error lists them: a set sorted, a sequence in its order."""
    return sorted(names, key=str) if isinstance(names, set | frozenset) else list(names)


class YamlReader:
    """Typed access to a parsed YAML tree `data` read from `source` (a path, or a name for values built in code).

    Keys are dotted paths with list indexes, "" the whole tree; every failure is one `error` that names the source
    and the key. `bounds` maps a concrete key to its `Bound` (see `bound_lookup`): the default range of `number`.
    """

    def __init__(self, source: Any, data: Any, error: ErrorClass,
                 bounds: Callable[[str], Bound] | None = None):
        self.source = source
        self.data = data
        self.error = error
        self.bounds = bounds

    def fail(self, key: str, expected: str, got: Any = None, *, show_got: bool = True) -> ValueError:
        """The error "{source}: {key}: expected {expected}, got {got}" (without the got part: `show_got=False`)."""
        tail = f", got {shown(got)}" if show_got else ""
        return self.error(f"{self.source}: {key or '<top>'}: expected {expected}{tail}")

    def node(self, key: str) -> Any:
        """The value at `key`; a missing key or a step into a non-mapping (non-list) is an error."""
        node, walked = self.data, ""
        for part in _KEY_PART.findall(key):
            if part.startswith("["):
                index = int(part[1:-1])
                if not isinstance(node, list):
                    raise self.fail(walked, "a list", node)
                if index >= len(node):
                    raise self.fail(walked, f"a list of more than {index} entries, got {len(node)}", show_got=False)
                node = node[index]
                walked += part
            else:
                if not isinstance(node, dict):
                    raise self.fail(walked, "a mapping", node)
                if part not in node:
                    raise self.error(f"{self.source}: {key}: missing key (expected under '{walked or '<top>'}')")
                node = node[part]
                walked = f"{walked}.{part}" if walked else part
        return node

    def check_keys(self, key: str, node: Mapping, allowed: Collection, required: Collection = (), *,
                   what: str = "key", missing: str = "") -> None:
        """The keys of `node` (the mapping at `key`) are among `allowed` and include `required`; errors say "unknown
        {what}" / "missing {what}", `missing` adds why it is needed."""
        unknown = [name for name in node if name not in allowed]
        if unknown:
            raise self.error(f"{self.source}: {_child(key, unknown[0])}: unknown {what} (expected one of "
                             f"{_listed(allowed)})")
        absent = [name for name in _listed(required) if name not in node]
        if absent:
            why = missing or f" (expected under '{key or '<top>'}')"
            raise self.error(f"{self.source}: {_child(key, absent[0])}: missing {what}{why}")

    def mapping(self, key: str, allowed: Collection | None = None, required: Collection = ()) -> dict:
        """The mapping at `key`; with `allowed`, its keys are among them and include `required`."""
        node = self.node(key)
        if not isinstance(node, dict):
            raise self.fail(key, "a mapping" if allowed is None else f"a mapping with keys among {_listed(allowed)}",
                            node)
        if allowed is not None:
            self.check_keys(key, node, allowed, required)
        return node

    def number(self, key: str, value: Any = _LOOK_UP, bound: Bound | None = None, also: str = "") -> Any:
        """The number at `key` (or `value`, already looked up) inside `bound`, by default `bounds(key)`."""
        value = self.node(key) if value is _LOOK_UP else value
        if bound is None:
            if self.bounds is None:
                raise LookupError(f"no bound for {key}: pass one or give the reader a table")
            bound = self.bounds(key)
        return checked_number(self.source, key, value, bound, self.error, also)

    def string(self, key: str) -> str:
        value = self.node(key)
        if not isinstance(value, str) or not value:
            raise self.fail(key, "a non-empty string", value)
        return value

    def choice(self, key: str, choices: Collection[str]) -> str:
        value = self.node(key)
        if value not in choices:
            raise self.fail(key, f"one of {', '.join(choices)}", value)
        return value

    def names(self, key: str, length: int | None = None) -> tuple[str, ...]:
        """A list of unique non-empty strings (of `length`, when given)."""
        value = self.node(key)
        if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
            raise self.fail(key, "a list of names", value)
        if length is not None and len(value) != length:
            raise self.fail(key, f"a list of {length} names, got {len(value)}", show_got=False)
        if len(set(value)) != len(value):
            raise self.fail(key, "unique names", value)
        return tuple(value)

    def vector(self, key: str, length: int, value: Any = _LOOK_UP, bound: Bound | None = None,
               axes: tuple[str, ...] | None = None) -> np.ndarray:
        """A list of `length` numbers at `key` (or `value`, already looked up, reported as `key`), each inside
        `bound` (by default its own key's). Its entries are keys "{key}[i]", or "{key}.{axis}" with `axes`."""
        value = self.node(key) if value is _LOOK_UP else value
        expected = f"[{', '.join(axes)}] ({length} numbers)" if axes else f"a list of {length} numbers"
        if not isinstance(value, list):
            raise self.fail(key, expected, value)
        if len(value) != length:
            raise self.fail(key, f"{expected}, got {len(value)} entries", show_got=False)
        return np.array([self.number(f"{key}.{axes[i]}" if axes else f"{key}[{i}]", v, bound)
                         for i, v in enumerate(value)], dtype=np.float64)

    def per_joint(self, key: str, joints: tuple[str, ...], width: int = 1,
                  bounds: list[Bound] | None = None) -> np.ndarray:
        """A mapping joint name -> number (or [numbers] of `width`), every joint of `joints` and no other, returned
        in `joints` order; `bounds`: one per joint, instead of each key's own."""
        node = self.mapping(key)
        self.check_keys(key, node, joints, joints, what="joint",
                        missing=f" (every joint of {list(joints)} needs a value)")
        if width == 1:
            return np.array([self.number(f"{key}.{name}", bound=bounds[i] if bounds else None)
                             for i, name in enumerate(joints)])
        return np.stack([self.vector(f"{key}.{name}", width) for name in joints])


def _child(key: str, name: Any) -> str:
    return f"{key}.{name}" if key else str(name)
