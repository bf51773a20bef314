"""Optics of the simulated bench: the 30° camera's projection of the skin plane, the warp onto the
sensor, lens blur, vignetting, and the spectra of flash, filters and Bayer channels.

Skin-plane coordinates in mm, origin at the window centre, x right, y down as the camera sees them
(z into the skin). The pinhole camera stands at distance D from the window centre, tilted by θ about
the x axis towards -y, looking at the centre; a skin point (x, y) lands at

    u = c_u + F x / (D + y sin θ),   v = c_v + F y cos θ / (D + y sin θ)

(raw pixels, F the focal length in pixels, (c_u, c_v) the sensor centre): the window is a trapezoid,
wider on the side nearer the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .simulation_settings import ChannelCurve

__all__: list[str] = []

CHANNELS = ("red", "green", "blue")
#: Bayer RGGB: the channel (index into CHANNELS) at raw positions (0,0), (0,1), (1,0), (1,1).
RGGB = (0, 1, 1, 2)
_PLANCK_C2_NM_K = 1.438776877e7  # hc/k in nm·K (CODATA 2018)


@dataclass(frozen=True)
class CameraGeometry:
    """The pinhole camera of the bench; ``focal_px`` / ``distance_mm`` is raw px per mm at the centre."""

    focal_px: float
    distance_mm: float
    angle_deg: float
    width_px: int
    height_px: int

    @property
    def centre(self) -> tuple[float, float]:
        return (self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0

    @property
    def px_per_mm(self) -> tuple[float, float]:
        """Image scale at the window centre along x and along y (foreshortened by cos θ)."""
        s = self.focal_px / self.distance_mm
        return s, s * math.cos(math.radians(self.angle_deg))

    def project(self, x_mm, y_mm):
        """Skin-plane points → raw pixel coordinates (u, v); arrays or tensors of any shape."""
        s, c = math.sin(math.radians(self.angle_deg)), math.cos(math.radians(self.angle_deg))
        z = self.distance_mm + y_mm * s
        cu, cv = self.centre
        return cu + self.focal_px * x_mm / z, cv + self.focal_px * c * y_mm / z

    def unproject(self, u, v):
        """Raw pixel coordinates → skin-plane points (x, y) in mm (the inverse of ``project``)."""
        s, c = math.sin(math.radians(self.angle_deg)), math.cos(math.radians(self.angle_deg))
        cu, cv = self.centre
        a, b = (u - cu) / self.focal_px, (v - cv) / self.focal_px
        y = b * self.distance_mm / (c - b * s)
        return a * (self.distance_mm + y * s), y


def sensor_geometry(window_mm: float, span_px: int, distance_mm: float, angle_deg: float,
                    field_of_view_mm: tuple[float, float]) -> CameraGeometry:
    """The camera whose window centre line spans ``span_px`` and whose sensor covers the field of view
    (rounded up to a multiple of 16 px, as TIFF tiles want)."""
    scale = span_px / window_mm
    width = 16 * math.ceil(field_of_view_mm[0] * scale / 16)
    height = 16 * math.ceil(field_of_view_mm[1] * scale * math.cos(math.radians(angle_deg)) / 16)
    return CameraGeometry(scale * distance_mm, distance_mm, angle_deg, width, height)


def sample_points(geom: CameraGeometry, supersample: int, rows: slice, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Skin-plane points (mm) of ``supersample²`` sub-pixel centres per raw pixel of ``rows``:
    ``(S², R, W)`` each, float64."""
    offsets = (torch.arange(supersample, dtype=torch.float64, device=device) + 0.5) / supersample - 0.5
    v = torch.arange(rows.start, rows.stop, dtype=torch.float64, device=device)
    u = torch.arange(geom.width_px, dtype=torch.float64, device=device)
    vv = (v[None, :, None] + offsets[:, None, None]).repeat_interleave(supersample, 0)  # (S², R, 1)
    uu = (u[None, None, :] + offsets.repeat(supersample)[:, None, None])  # (S², 1, W)
    vv, uu = torch.broadcast_tensors(vv, uu)
    return geom.unproject(uu, vv)


def to_subject(x_mm: torch.Tensor, y_mm: torch.Tensor, shift_mm: tuple[float, float], rotation_deg: float):
    """World skin-plane points → the subject's own coordinates, the subject moved by a rotation about
    the window centre and then a shift: p = R(-φ)(w - t)."""
    phi = math.radians(rotation_deg)
    dx, dy = x_mm - shift_mm[0], y_mm - shift_mm[1]
    return math.cos(phi) * dx + math.sin(phi) * dy, -math.sin(phi) * dx + math.cos(phi) * dy


def bilinear(image: torch.Tensor, x_mm: torch.Tensor, y_mm: torch.Tensor, mm_per_pixel: float) -> torch.Tensor:
    """Sample ``image`` ``(C, N, N)`` (a square grid centred on the origin) at points ``(...)`` → ``(C, ...)``."""
    n = image.shape[-1]
    half = n * mm_per_pixel / 2.0
    grid = torch.stack([x_mm / half, y_mm / half], dim=-1).reshape(1, -1, 1, 2).to(image.dtype)
    out = F.grid_sample(image[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, :, 0].reshape(image.shape[0], *x_mm.shape)


def gaussian_blur(image: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(C, H, W)`` with a kernel of ±4σ (normalised), edges replicated."""
    if sigma_px <= 0:
        return image
    r = max(1, math.ceil(4 * sigma_px))
    t = torch.arange(-r, r + 1, dtype=image.dtype, device=image.device)
    k = torch.exp(-0.5 * (t / sigma_px) ** 2)
    k = k / k.sum()
    x = F.pad(image[None], (r, r, r, r), mode="replicate")[0]
    h, w = image.shape[-2:]
    # weighted sums of shifted views: faster on the CPU than a grouped conv2d
    # (docs/calibration.md, "From acquire/simulator/_optics.py")
    rows = sum(k[i] * x[:, :, i:i + w] for i in range(2 * r + 1))
    return sum(k[i] * rows[:, i:i + h, :] for i in range(2 * r + 1))


def vignetting(geom: CameraGeometry, strength: float, dtype=torch.float32, device=None) -> torch.Tensor:
    """Relative illumination ``(H, W)``: 1 at the centre, 1 - strength at the corners (quadratic in r)."""
    cu, cv = geom.centre
    v = torch.arange(geom.height_px, dtype=torch.float64, device=device)[:, None] - cv
    u = torch.arange(geom.width_px, dtype=torch.float64, device=device)[None, :] - cu
    return (1.0 - strength * (u**2 + v**2) / (cu**2 + cv**2)).to(dtype)


# -- spectra -----------------------------------------------------------------------------------------
def blackbody(wavelength_nm: np.ndarray, temperature_k: float, reference_nm: float = 560.0) -> np.ndarray:
    """Planck's spectral radiance, relative to its value at ``reference_nm``."""

    def planck(w):
        return w**-5.0 / np.expm1(_PLANCK_C2_NM_K / (w * temperature_k))

    return planck(np.asarray(wavelength_nm, dtype=np.float64)) / planck(reference_nm)


def channel_sensitivity(curve: ChannelCurve, wavelength_nm: np.ndarray) -> np.ndarray:
    """The closed form of ``ChannelCurve`` at ``wavelength_nm``."""
    w = np.asarray(wavelength_nm, dtype=np.float64)
    sigma = np.where(w < curve.centre_nm, curve.sigma_left_nm, curve.sigma_right_nm)
    main = curve.peak * np.exp(-0.5 * ((w - curve.centre_nm) / sigma) ** 2)
    return main + curve.side_peak * np.exp(-0.5 * ((w - curve.side_centre_nm) / curve.side_sigma_nm) ** 2)


@dataclass(frozen=True)
class BandSpectrum:
    """A band's quadrature: nodes ``(K,)`` in nm and per channel the weights ``(3, K)`` of
    filter × flash × sensitivity (their row sums are the channels' relative signals)."""

    nodes_nm: np.ndarray
    weights: np.ndarray

    @property
    def channel_signal(self) -> np.ndarray:
        return self.weights.sum(axis=1)

    def truth_weights(self) -> np.ndarray:
        """Weights of the four Bayer positions together (R + 2G + B), normalised ``(K,)``."""
        w = self.weights[0] + 2.0 * self.weights[1] + self.weights[2]
        return w / w.sum()


def band_spectrum(centre_nm: float, fwhm_nm: float, samples: int, temperature_k: float,
                  sensitivity: dict[str, ChannelCurve]) -> BandSpectrum:
    """Gauss–Hermite quadrature of a Gaussian band-pass of ``fwhm_nm`` (∫ filter f dλ ≈ Σ W_i f(λ_i),
    exact for f a polynomial of degree < 2·samples), times the flash and each channel's sensitivity."""
    sigma = fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    x, w = np.polynomial.hermite.hermgauss(samples)
    nodes = centre_nm + math.sqrt(2.0) * sigma * x
    filt = w * math.sqrt(2.0) * sigma  # ∫ exp(-(λ-c)²/2σ²) f(λ) dλ
    flash = blackbody(nodes, temperature_k)
    weights = np.stack([filt * flash * channel_sensitivity(sensitivity[c], nodes) for c in CHANNELS])
    return BandSpectrum(nodes, weights)
