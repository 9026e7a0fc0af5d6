"""SLAM configuration: nested frozen dataclasses (defaults in each part's module), loaded here.

``config_from_dict({"proposal": {"point_sigma_m": 0.03}})`` or ``apply_overrides(cfg,
["proposal.point_sigma_m=0.03"])``; an unknown section or key is an error that names it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from typing import Any

from robot_agent.slam.fastslam import SlamConfig


class ConfigError(ValueError):
    """An unknown or ill-typed configuration key."""


def _replace(obj: Any, values: Mapping[str, Any], where: str) -> Any:
    names = {f.name: f for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in values.items():
        if key not in names:
            raise ConfigError(f"unknown config key {where}{key!r}; known: {', '.join(sorted(names))}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ConfigError(f"config {where}{key} is a section; give a mapping, not {value!r}")
            changes[key] = _replace(current, value, f"{where}{key}.")
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
        try:
            return typ(value)
        except ValueError:
            raise ConfigError(f"config {name}: expected {typ.__name__}, got {value!r}") from None
    if typ is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, typ):
        raise ConfigError(f"config {name}: expected {typ.__name__}, got {type(value).__name__}")
    return value


def config_from_dict(values: Mapping[str, Any], base: SlamConfig | None = None) -> SlamConfig:
    return _replace(base or SlamConfig(), values, "")


def apply_overrides(cfg: SlamConfig, overrides: Iterable[str]) -> SlamConfig:
    """Apply ``section.key=value`` strings (``particles=50`` for top-level keys). ``compiled=false``
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
        node[parts[-1]] = value.strip()
    return config_from_dict(nested, cfg)


def command_line_config(overrides: Iterable[str] = (), particles: int | None = None) -> SlamConfig:
    """The defaults with ``--set`` overrides and ``--particles`` applied (the commands' one way)."""
    cfg = apply_overrides(SlamConfig(), overrides)
    if particles is not None:
        if particles < 1:
            raise ValueError(f"--particles must be at least 1, got {particles}")
        cfg = apply_overrides(cfg, [f"particles={particles}"])
    return cfg
