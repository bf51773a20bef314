"""The rig configuration from YAML: ``load_rig`` (the embedded ``configs/rig.yaml`` by default).

The rig's typed description is a contract between acquisition and calibration and lives in
``formats/rig.py``; it is re-exported here, where a capture reads it.
"""

from __future__ import annotations

from pathlib import Path

from ...formats.rig import (
    BandConfig,
    CameraConfig,
    GeometryConfig,
    PolarizationConfig,
    RigConfig,
    RigError,
    TargetsConfig,
    WheelConfig,
    rig_from_dict,
)
from ...formats.settings import load_settings

__all__ = ["BandConfig", "CameraConfig", "GeometryConfig", "PolarizationConfig", "RigConfig", "RigError",
           "TargetsConfig", "WheelConfig", "default_rig_path", "load_rig", "rig_from_dict"]


def default_rig_path() -> Path:
    from ...configs import config_path  # noqa: PLC0415

    return config_path("rig.yaml")


def load_rig(path: str | Path | None = None, **overrides) -> RigConfig:
    """The rig of a YAML file (the embedded ``configs/rig.yaml`` when ``path`` is None), with
    ``overrides`` merged in (e.g. ``camera={"driver": "simulated"}``). Raises ``RigError`` naming the
    file, the key and the problem."""
    return load_settings(RigConfig, path, RigError, "rig", overrides, default_path=default_rig_path())
