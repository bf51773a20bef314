"""skinlayers: multi-spectral skin acquisition and inverse rendering with a layered, heterogeneous,
spectral skin model (Donner, Weyrich, d'Eon, Ramamoorthi, Rusinkiewicz 2008).

The public API re-exports what each part offers; the command line is ``skinlayers`` (``cli.py``).
"""

import logging
from importlib.metadata import PackageNotFoundError, version

from .model import TABLE2, ColourConverter, ModelSettings, SkinModel, SkinParams, load_model_settings
from .reconstruct import fit_spectra

# a library logs and leaves the showing to its user (the command line: ``skinlayers -v``)
logging.getLogger(__name__).addHandler(logging.NullHandler())

try:
    __version__ = version("skinlayers")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"

__all__ = [
    "TABLE2",
    "ColourConverter",
    "ModelSettings",
    "SkinModel",
    "SkinParams",
    "__version__",
    "fit_spectra",
    "load_model_settings",
]
