"""SLAM configuration: nested frozen dataclasses (defaults in each part's module), loaded here.

``config_from_dict({"proposal": {"point_sigma_m": 0.03}})`` or ``apply_overrides(cfg,
["proposal.point_sigma_m=0.03"])``; an unknown section or key is an error that names it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from robot_agent.slam.fastslam import SlamConfig
from shared.config import ConfigError, apply_overrides, replace_from

__all__ = ["ConfigError", "apply_overrides", "command_line_config", "config_from_dict"]


def config_from_dict(values: Mapping[str, Any], base: SlamConfig | None = None) -> SlamConfig:
    return replace_from(base or SlamConfig(), values)


def command_line_config(overrides: Iterable[str] = (), particles: int | None = None) -> SlamConfig:
    """The defaults with ``--set`` overrides and ``--particles`` applied (the commands' one way)."""
    cfg = apply_overrides(SlamConfig(), overrides)
    if particles is not None:
        if particles < 1:
            raise ValueError(f"--particles must be at least 1, got {particles}")
        cfg = apply_overrides(cfg, [f"particles={particles}"])
    return cfg
