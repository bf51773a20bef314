"""Reconstruction: chromophore parameters from measured reflectance.

Today: point spectra fitted with the homogeneous model (``fit_spectra``). The per-pixel inverse
rendering of reflectance cubes lands here with the reconstruction issue.
"""

from .spectrum_fit import PAPER_START, SpectrumFit, fit_spectra

__all__ = ["PAPER_START", "SpectrumFit", "fit_spectra"]
