"""Reflectance spectra to colour: CIE XYZ (1931 2° observer), CIELAB, sRGB (DWRR08 §7; CIE 1931;
sRGB as IEC 61966-2-1).

The tristimulus integral is linear in the reflectance, so for a fixed set of sample wavelengths it is
a ``(3, L)`` matrix: built once per wavelength set from colour-science's observer and illuminant data
by pushing unit spectra through colour-science's linear interpolator (constant extrapolation) onto
its 1 nm grid. Linear, not Sprague or spline: with the paper's 8 render samples 35 nm apart, the
smooth interpolators overshoot between samples and raise the colour error against 151 samples
(docs/model.md). Everything after is tensor maths,
batched and differentiable, on any device.

XYZ is normalised so that the perfect white under the illuminant has Y = 1; sRGB is reached by
Bradford adaptation from the illuminant's white to D65 when they differ.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from ...formats.errors import InputError

__all__ = ["ColourConverter", "delta_e_2000", "ita_degrees", "srgb_encode"]

OBSERVER = "CIE 1931 2 Degree Standard Observer"


def _colour():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour  # noqa: PLC0415 (heavy import, deferred)
    return colour


def srgb_encode(linear: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 transfer function; input clamped to [0, 1]."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055)


def ita_degrees(lab: torch.Tensor) -> torch.Tensor:
    """Individual typology angle ITA° = arctan((L* - 50) / b*) · 180/π, ``(...,)`` from ``(..., 3)``."""
    return torch.rad2deg(torch.atan((lab[..., 0] - 50.0) / lab[..., 2]))


class ColourConverter:
    """Spectra sampled at fixed wavelengths ``(L,)`` → XYZ, Lab, linear and encoded sRGB, each ``(..., 3)``."""

    def __init__(self, wavelength_nm, illuminant: str = "D65") -> None:
        colour = _colour()
        w = np.asarray(torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1).cpu())
        if w.size < 2 or np.any(np.diff(w) <= 0):
            raise InputError("colour needs at least two increasing wavelengths")
        if illuminant not in colour.SDS_ILLUMINANTS:
            raise InputError(f"unknown illuminant {illuminant!r}; try D65, D50, A, E or F2")
        self.wavelength_nm = torch.from_numpy(w)
        self.illuminant = illuminant
        with warnings.catch_warnings():
            # colour-science warns about aligning shapes and non-uniform samples: both are intended here
            warnings.simplefilter("ignore")
            self._build(colour, w, illuminant)

    def _build(self, colour, w: np.ndarray, illuminant: str) -> None:
        shape = colour.SpectralShape(360, 830, 1)
        cmfs = colour.MSDS_CMFS[OBSERVER].copy().align(shape).values  # (471, 3)
        light = colour.SDS_ILLUMINANTS[illuminant].copy().align(shape).values  # (471,)
        weights = cmfs * light[:, None]
        weights /= weights[:, 1].sum()
        resample = np.zeros((shape.range().size, w.size))
        for j in range(w.size):
            unit = np.zeros(w.size)
            unit[j] = 1.0
            sd = colour.SpectralDistribution(unit, w, interpolator=colour.LinearInterpolator)
            resample[:, j] = sd.align(shape, interpolator=colour.LinearInterpolator).values
        self.matrix = torch.from_numpy(weights.T @ resample)  # (3, L)
        self.white_xyz = torch.from_numpy(weights.sum(0))
        rgb = colour.RGB_COLOURSPACES["sRGB"]
        d65 = colour.xy_to_XYZ(rgb.whitepoint)
        white = self.white_xyz.numpy() / self.white_xyz.numpy()[1]
        cat = np.eye(3)
        if np.abs(white - d65).max() > 1e-4:
            cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(white, d65, transform="Bradford")
        self.xyz_to_linear_srgb = torch.from_numpy(rgb.matrix_XYZ_to_RGB @ cat)

    def xyz(self, reflectance: torch.Tensor) -> torch.Tensor:
        """``(..., L)`` → ``(..., 3)``; a perfect white gives the illuminant's white with Y = 1."""
        if reflectance.shape[-1] != self.matrix.shape[1]:
            raise ValueError(f"expected spectra with {self.matrix.shape[1]} samples, got {reflectance.shape[-1]}")
        return reflectance @ self.matrix.to(reflectance).T

    def lab(self, reflectance: torch.Tensor) -> torch.Tensor:
        """CIELAB relative to the illuminant's white."""
        t = self.xyz(reflectance) / self.white_xyz.to(reflectance)
        d = 6.0 / 29.0
        f = torch.where(t > d**3, t.clamp_min(1e-12) ** (1.0 / 3.0), t / (3.0 * d * d) + 4.0 / 29.0)
        return torch.stack(
            [116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], dim=-1
        )

    def linear_srgb(self, reflectance: torch.Tensor) -> torch.Tensor:
        return self.xyz(reflectance) @ self.xyz_to_linear_srgb.to(reflectance).T

    def srgb(self, reflectance: torch.Tensor) -> torch.Tensor:
        """Display-encoded sRGB in [0, 1]."""
        return srgb_encode(self.linear_srgb(reflectance))


def delta_e_2000(lab_a: torch.Tensor, lab_b: torch.Tensor) -> torch.Tensor:
    """CIEDE2000 colour difference (colour-science's implementation), ``(...,)``."""
    colour = _colour()
    return torch.from_numpy(np.asarray(colour.delta_E(lab_a.detach().cpu().numpy(), lab_b.detach().cpu().numpy(), method="CIE 2000")))

