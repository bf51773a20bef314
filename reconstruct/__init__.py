"""Reconstruction: chromophore parameters from measured reflectance.

- ``fit_spectra``: point spectra fitted with the homogeneous model (batched Levenberg–Marquardt);
  ``select_spectrum_models``: the same, choosing per spectrum which fixed constants to free (BIC).
- ``fit_cube``: per-pixel inverse rendering of a reflectance cube with the heterogeneous renderer
  (DWRR08 §6.3): five maps and a global scale, coarse-to-fine, with residuals, flags and
  uncertainties; ``write_outputs`` writes maps.exr, fit.json, report.png and the resolved settings.
"""

from .mapfit.fit import FitEvent, MapFit, fit_cube
from .mapfit.optimizers import METHODS
from .results.outputs import fit_summary, reconstruct_cube, write_outputs
from .settings import FitSettings, FitSettingsError, load_fit_settings
from .spectrum.spectrum_fit import PAPER_START, SpectrumFit, fit_spectra
from .spectrum.spectrum_models import SpectrumModel, SpectrumSelection, select_spectrum_models

__all__ = [
    "METHODS",
    "PAPER_START",
    "FitEvent",
    "FitSettings",
    "FitSettingsError",
    "MapFit",
    "SpectrumFit",
    "SpectrumModel",
    "SpectrumSelection",
    "fit_cube",
    "fit_spectra",
    "fit_summary",
    "load_fit_settings",
    "reconstruct_cube",
    "select_spectrum_models",
    "write_outputs",
]
