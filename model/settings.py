"""Typed settings of the skin model, with the published constants as defaults.

Every number the physics uses lives here, once, with its source (Donner et al. 2008, "DWRR08" below,
and the primary references it builds on; each constant with its unit and source: docs/model.md,
"Constants and units"). YAML files (``configs/model.yaml``) override fields; unknown keys are refused.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from ..formats.errors import SettingsError as BaseSettingsError
from ..formats.settings import Strict, load_settings
from .optics.optics import SkinOptics

__all__ = ["ModelSettings", "RenderSettings", "SettingsError", "SkinOptics", "TableSettings", "TransportSettings", "load_model_settings"]

PAPER_RENDER_WAVELENGTHS_NM = [400.0 + 35.0 * i for i in range(8)]
#: The light transport a render can use: the diffusion model, or the Monte Carlo reference (model/transport).
PHYSICS = ("diffusion", "transport")
#: The layer responses the model combines: radiative transport's (adding-doubling totals by similarity,
#: model/column/layer_totals.py) or the paper's diffusion (dipole and multipole, DWRR08 §3).
PROFILES = ("transport", "diffusion")
#: Photons per wavelength a Monte Carlo render may take.
MIN_PHOTONS, MAX_PHOTONS = 1000, 10**10


class TableSettings(Strict):
    """Sum-of-Gaussians fits and σa lookup tables (DWRR08 §3 Eq. 4, §4.3, §4.5; d'Eon et al. 2007)."""

    n_gaussians: int = Field(
        21,
        ge=2,
        le=40,
        description=(
            "Gaussians per profile. The paper's 18 (std 0.01 mm · √2^k) extended down by three so that the "
            "profiles of the darkest epidermis, narrower than the paper's narrowest Gaussian, still fit "
            "(docs/model.md, \"The Gaussian basis\"); Gaussians under the identity threshold merge into the "
            "identity at render time, so the extension costs nothing there."
        ),
    )
    gaussian_std_min_mm: float = Field(
        0.01 / (2.0 * math.sqrt(2.0)), gt=0, description="Standard deviation of the narrowest Gaussian (mm)."
    )
    sigma_a_min_per_mm: float = Field(0.01, gt=0, description="Lowest tabulated σa (mm⁻¹).")
    sigma_a_max_per_mm: float = Field(200.0, gt=0, le=1e5, description="Highest tabulated σa (mm⁻¹).")
    n_sigma_a: int = Field(256, ge=8, le=4096, description="Log-spaced σa samples per table (DWRR08: 256).")
    multipole_tolerance: float = Field(1e-8, gt=0, lt=1e-2, description="Energy of dipole pairs left out.")
    fit_r_min_mm: float = Field(2e-4, gt=0, description="Innermost radius of the least-squares fit grid (mm).")
    fit_r_max_mm: float = Field(80.0, gt=0, le=1000, description="Outermost radius of the fit grid (mm).")
    fit_r_samples: int = Field(300, ge=50, le=10000, description="Log-spaced radii in the fit grid.")

    @model_validator(mode="after")
    def _ranges(self) -> "TableSettings":
        if self.sigma_a_max_per_mm <= self.sigma_a_min_per_mm:
            raise ValueError("sigma_a_max_per_mm must exceed sigma_a_min_per_mm")
        if self.fit_r_max_mm <= self.fit_r_min_mm:
            raise ValueError("fit_r_max_mm must exceed fit_r_min_mm")
        return self

    def gaussian_variances_mm2(self) -> list[float]:
        """v_k = v_0 2^k, so that G(v_{k+1}) = G(v_k) ∗ G(v_k)."""
        v0 = self.gaussian_std_min_mm**2
        return [v0 * 2.0**k for k in range(self.n_gaussians)]


class RenderSettings(Strict):
    """The heterogeneous renderer (DWRR08 §4.1–4.3, Eq. 5–9; docs/renderer.md)."""

    blur: Literal["pyramid", "fft", "chain"] = Field(
        "pyramid", description="How Gaussian blur stacks are computed (model/render/blur.py; their agreement: docs/renderer.md)."
    )
    identity_below_px: float = Field(
        0.25,
        ge=0,
        description=(
            "Gaussians narrower than this (std, pixels) act as the identity. A quarter pixel, not the "
            "half the paper suggests: merging 0.25–0.5 px Gaussians visibly moves a window's edge and a "
            "point light's centre pixel, below 0.25 px nothing does (docs/renderer.md)."
        ),
    )
    pyramid_min_px: float = Field(3.0, gt=0.5, description="Pyramid: go down a level once a blur is twice this wide (pixels).")
    series_tolerance: float = Field(
        2e-2,
        gt=0,
        lt=1,
        description=(
            "Inter-scattering terms are added until the rest of the series carries less than this of the light "
            "(worst pixel). With the closure on, the closed rest is small at this tolerance (docs/renderer.md); "
            "without it, use 1e-3 or less."
        ),
    )
    max_series_terms: int = Field(12, ge=1, le=100, description="Upper bound on inter-scattering terms (DWRR08 used 5–6).")
    series_closure: bool = Field(
        True,
        description=(
            "Close the truncated series with its geometric rest (the last term's light divided by 1 - A² R₁⁻ R₂⁺ "
            "per pixel): exact for homogeneous skin under uniform light, and it lets fewer terms reach the "
            "same accuracy (docs/renderer.md)."
        ),
    )
    weight_cache_mb: float = Field(
        1536.0, ge=0, le=1 << 20, description="Memory for per-pixel Gaussian weights kept across inter-scattering terms (0: none)."
    )
    checkpoint: bool = Field(
        True, description="Recompute blur stacks in the backward pass instead of storing them (memory for time)."
    )
    coupling: Literal["exit", "segment"] = Field(
        "exit",
        description=(
            "How neighbouring skin of different absorption couples: 'exit' (DWRR08 Eq. 9: each profile "
            "chosen by the absorption at the exit pixel) or 'segment' (each Gaussian's weight chosen by "
            "the absorption averaged over where its light went between entry and exit: model/render/renderer.py; "
            "both against the Monte Carlo in docs/transport.md)."
        ),
    )
    coupling_scale: float = Field(
        1.25, gt=0, le=16,  # refitted with the angular hand-over (the stripe: docs/transport.md)
        description="'segment', the dermis's profile: the segment's variance as a multiple of each Gaussian's (1: its own).",
    )
    coupling_scale_epidermis: float = Field(
        1.5, gt=0, le=16,  # refitted on the transport shapes (the step: docs/transport.md)
        description="'segment', the epidermis's profiles: the same multiple.",
    )
    coupling_bridge: float = Field(
        0.5, ge=0, le=8,
        description="'segment': the wander of the path about the straight segment (a Brownian bridge's t(1 - t), times this).",
    )
    coupling_power: float = Field(
        0.35, ge=0, le=1,
        description="'segment': σa averaged as a power mean of this exponent (0: geometric, 1: arithmetic).",
    )
    surface_roughness: float = Field(0.35, gt=0, description="Beckmann roughness of the Torrance–Sparrow surface term.")
    border_mm: float = Field(
        5.0,
        ge=0,
        le=20,
        description=(
            "Skin simulated beyond the maps (occluded by the tape for window light) unless the light names its "
            "own. DWRR08 uses 1 cm; 5 mm changes no pixel of a 7.5-mm window by more than 10⁻⁴ of 1 cm's "
            "(docs/renderer.md)."
        ),
    )


class TransportSettings(Strict):
    """The Monte Carlo transport reference (``model/transport``): the truth the diffusion model is measured against."""

    anisotropy: float = Field(
        0.0, ge=0.0, lt=1.0,
        description=(
            "Henyey–Greenstein g. 0 with σs = σs′: the similarity case diffusion rests on (the same medium as the "
            "model); skin's g ≈ 0.8 is the realistic one (σs = σs′ / (1 − g))."
        ),
    )
    photons: int = Field(1_000_000, ge=MIN_PHOTONS, le=MAX_PHOTONS, description="Photons per wavelength.")
    batch_photons: int = Field(1 << 18, ge=256, le=1 << 24, description="Photons walked at once (memory: about 1.1 kB each).")
    batches_min: int = Field(16, ge=4, le=1000, description="Batches at least (the standard error is the batches' spread).")
    roulette_weight: float = Field(1e-4, gt=0, lt=1, description="Below this weight a photon survives Russian roulette 1 in 10.")
    margin_mm: float = Field(
        3.0, ge=0, le=20,
        description="Uniform and striped light: also lit, this far beyond the maps (replicated skin), for the light that comes back into them.",
    )
    max_depth_mm: float = Field(50.0, gt=0, le=1000, description="A photon deeper than this in a semi-infinite dermis is dropped.")
    twin: bool = Field(
        True,
        description=(
            "Render a scene as a homogeneous twin's exact image plus the difference the same photons measure "
            "between the scene and the twin (a control variate: model/transport/walk.py). Unbiased either way; "
            "far less noise on skin near its mean (docs/transport.md, \"A homogeneous twin\")."
        ),
    )
    twin_kernel_share: float = Field(
        1.0, gt=0, le=4,
        description="twin: photons for the twin's exact image (its point response, pooled over the plane), as a share of the scene's.",
    )


class ModelSettings(Strict):
    """Everything that shapes the model's output; saved beside results so they can be re-made."""

    optics: SkinOptics = SkinOptics()
    tables: TableSettings = TableSettings()
    render: RenderSettings = RenderSettings()
    transport: TransportSettings = TransportSettings()
    profiles: Literal["transport", "diffusion"] = Field(
        "diffusion",
        description=(
            "The layer responses the model combines: 'transport' (each profile's plane integral from "
            "adding-doubling and its lateral shape from the project's Monte Carlo, both tabulated by "
            "similarity; the unscattered beam through the epidermis kept collimated: model/column/layer_totals.py, "
            "model/column/layer_shapes.py) or 'diffusion' (DWRR08's dipole and multipole, still the default: on "
            "sessions rendered by transport, transport fits melanin and epidermal blood better and dermal "
            "blood worse, as it does on its own physics at that noise). "
            "Both against the Monte Carlo: docs/transport.md, \"A forward model that matches transport\"."
        ),
    )
    handover: Literal["angular", "lambertian"] = Field(
        "angular",
        description=(
            "With profiles 'transport': how the layers hand light to each other. 'angular': the dermis's "
            "reflectance R₂⁺ times the factor κ that makes Eq. 7's scalar series give the two layers' total "
            "as adding-doubling stacks them angle by angle (model/column/layer_totals.py, handover_factor); "
            "'lambertian': Eq. 7 as DWRR08 has it, every hand-over Lambertian (0.3–1% too bright in the green "
            "on homogeneous skin: docs/transport.md). Diffusion profiles always hand over as the paper does."
        ),
    )
    render_wavelengths_nm: list[float] = Field(
        default_factory=lambda: list(PAPER_RENDER_WAVELENGTHS_NM),
        description="Wavelengths rendered for colour images (DWRR08 §7: 400, 435, …, 645 nm).",
    )
    illuminant: str = Field("D65", description="CIE illuminant for colour (any name colour-science knows).")

    @field_validator("render_wavelengths_nm")
    @classmethod
    def _wavelengths(cls, value: list[float]) -> list[float]:
        if not value:
            raise ValueError("at least one wavelength is needed")
        if len(value) > 512:
            raise ValueError(f"at most 512 wavelengths, got {len(value)}")
        if any(not (380.0 <= w <= 800.0) for w in value):
            raise ValueError("wavelengths must lie within 380–800 nm")
        return value

    @model_validator(mode="after")
    def _profiles(self) -> "ModelSettings":
        if self.profiles == "transport":
            from .column.layer_totals import check_optics  # noqa: PLC0415

            check_optics(self.optics)
        return self

    def digest(self, *parts: object) -> str:
        """A short stable hash of these settings and any extra parts (used as a cache key)."""
        blob = json.dumps([self.model_dump(mode="json"), *parts], sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]


class SettingsError(BaseSettingsError):
    """A model settings file or value that cannot be used; the message names the file, the key and the problem."""


def load_model_settings(path: str | Path | None = None) -> ModelSettings:
    """Embedded defaults, overridden by a YAML file if one is given.

    Raises ``SettingsError`` naming the file, the key and the problem.
    """
    return load_settings(ModelSettings, path, SettingsError, "model settings")
