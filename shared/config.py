"""Configuration overrides for nested frozen dataclasses (the SLAM's, the map server's): from a
mapping (``{"proposal": {"point_sigma_m": 0.03}}``) or from ``section.key=value`` strings (the
commands' ``--set``). An unknown section or key, or a value of the wrong type, is a
:class:`ConfigError` that names it."""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """An unknown or ill-typed configuration key."""


def replace_from(obj: T, values: Mapping[str, Any], where: str = "") -> T:
    """``obj`` with the (nested) ``values`` replaced; ``where``: the path of ``obj`` in messages."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"unknown config key {where + key!r}; known: {', '.join(sorted(names))}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ConfigError(f"config {where}{key} is a section; give a mapping, not {value!r}")
            changes[key] = replace_from(current, value, f"{where}{key}.")
        else:
            changes[key] = _coerce(current, value, f"{where}{key}")
    return dataclasses.replace(obj, **changes)


def _coerce(current: Any, value: Any, name: str) -> Any:
    typ = type(current)
    if isinstance(value, str) and typ is not str:
        if typ is bool:
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"config {name}: expected a boolean, got {value!r}")
        if not issubclass(typ, numbers.Real):  # a tuple of stages, an array: not from one string
            raise ConfigError(f"config {name} ({typ.__name__}) cannot be set from a string")
        try:
            return typ(value)
        except ValueError:
            raise ConfigError(f"config {name}: expected {typ.__name__}, got {value!r}") from None
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, typ):
        raise ConfigError(f"config {name}: expected {typ.__name__}, got {type(value).__name__}")
    return value


def apply_overrides(cfg: T, overrides: Iterable[str]) -> T:
    """Apply ``section.key=value`` strings (``key=value`` for top-level keys). ``compiled=false``
    sets every section's ``compiled`` (the numpy code instead of the compiled kernels)."""
    nested: dict[str, Any] = {}
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.key=value")
        path, value = item.split("=", 1)
        if path.strip() == "compiled":  # every section that has the switch
            for f in dataclasses.fields(cfg):
                section = getattr(cfg, f.name)
                if dataclasses.is_dataclass(section) and hasattr(section, "compiled"):
                    nested.setdefault(f.name, {})["compiled"] = value.strip()
            continue
        parts = path.strip().split(".")
        node = nested
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {p!r} is set as a value and as a section")
        node[parts[-1]] = value.strip()
    return replace_from(cfg, nested)
