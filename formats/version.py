"""The software version every output records (``software_version`` in manifests, cubes, maps, fit.json)."""

from __future__ import annotations

from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version

__all__ = ["software_version"]


@lru_cache(maxsize=1)
def software_version() -> str:
    """The installed ``skinlayers`` distribution's version, or ``0+unknown`` in a source tree that is not installed."""
    try:
        return version("skinlayers")
    except PackageNotFoundError:
        return "0+unknown"
