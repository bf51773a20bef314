"""The YAML settings shipped with skinlayers (model, and later rigs, fits and scenes)."""

from importlib import resources
from pathlib import Path


def config_path(name: str) -> Path:
    """Path of a shipped YAML file, e.g. ``config_path("model.yaml")``."""
    return Path(str(resources.files(__package__).joinpath(name)))
