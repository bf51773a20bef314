"""Typed settings of the map fit (``skinlayers reconstruct``), with an embedded default that runs.

YAML (``configs/fit.yaml``) overrides any subset of keys; unknown keys are refused with the key named.
The skin model's own settings sit under ``model`` (the same keys as ``configs/model.yaml``), so one
resolved file, saved beside every fit, re-makes it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from ..formats.errors import SettingsError
from ..formats.settings import Strict, load_settings
from ..model import ModelSettings
from .mapfit.optimizers import METHODS, PER_PIXEL_METHODS

__all__ = ["DEFAULT_MAP_CELL_MM", "MAP_CELL_MM_BY_PROFILES", "TRANSPORT_MAP_CELL_MM", "FitSettings", "FitSettingsError", "load_fit_settings"]


class FitSettingsError(SettingsError):
    """A fit settings file or value that cannot be used; the message names the file and key."""


#: Node spacing (mm) per map for gn-hom, measured (configs/fit.yaml, docs/reconstruct.md):
#: melanin and epidermal blood per pixel; β_m on 1.5-mm nodes; carotene one value per patch; dermal blood
#: on 0.375-mm nodes (20 across the 7.5-mm window).
DEFAULT_MAP_CELL_MM = {"C_m": 0.0, "beta_m": 1.5, "C_he": 0.0, "C_bc": 100.0, "C_hd": 0.375}
#: With transport profiles: a dermal-blood change spreads its light further over its neighbours than
#: diffusion draws it, so the data hold C_hd on coarser nodes, and epidermal blood (whose spectrum is
#: dermal blood's) on nodes too; the spacings chosen on the Monte Carlo's own sessions (docs/transport.md,
#: "Sessions at the size a user fits").
TRANSPORT_MAP_CELL_MM = {**DEFAULT_MAP_CELL_MM, "C_he": 0.25, "C_hd": 0.5}
#: gn-hom's node spacings by the model's ``profiles``.
MAP_CELL_MM_BY_PROFILES = {"diffusion": DEFAULT_MAP_CELL_MM, "transport": TRANSPORT_MAP_CELL_MM}
_PER_PIXEL = dict.fromkeys(DEFAULT_MAP_CELL_MM, 0.0)
#: How the loss weighs the bands, by the model's ``profiles`` (``band_weights`` left out): transport, close to
#: the Monte Carlo in every band, gains from trusting the quiet bands more; diffusion's error is largest in the
#: quiet blue and green bands, so weighing them up costs it melanin (docs/reconstruct.md, "Band weights").
BAND_WEIGHTS_BY_PROFILES = {"diffusion": "equal", "transport": "noise"}


class FitSettings(Strict):
    """Everything that shapes a map fit. Defaults are the measured choices (docs/reconstruct.md)."""

    method: str = Field(
        "gn-hom",
        description=(
            "Optimiser (the table in reconstruct/mapfit/optimizers.py): gn-hom (Gauss–Newton with each pixel's "
            "homogeneous Jacobian on the heterogeneous residual: forward renders only), gn (the same "
            "curvature with the exact gradient from one forward+backward), adam (autograd gradients), "
            "paper-fd (DWRR08 §6.3: gradient descent by forward differences, 1 + N_PARAMS renders a step)."
        ),
    )
    start: Literal["homogeneous", "paper"] = Field(
        "homogeneous",
        description=("homogeneous: a point-spectrum fit of every pixel of the coarsest level; paper: DWRR08's pale skin. "
                     "The renderer's fit starts there; forward: auto's homogeneous fit starts from a point fit of the "
                     "cube's mean spectrum."),
    )
    coarsest_px: int = Field(
        64, ge=0, le=4096, description="Coarse-to-fine: halve the cube while its longer side exceeds this (0: fit the full grid only)."
    )
    border_mm: float = Field(
        3.0,
        ge=0,
        le=20,
        description=(
            "Occluded skin simulated beyond the window (mm): light that enters through the window and travels under "
            "the tape comes back into the edge pixels. The default keeps every visible pixel within a tenth of the "
            "camera noise of a wider border (docs/reconstruct.md, \"Settings\")."
        ),
    )
    view_angle_deg: float | None = Field(
        None, ge=0, lt=90,
        description="Camera angle off the flash axis (°), replacing the cube header's (the rig's); default: the header's, else 30 (DWRR08 §6.1).",
    )
    band_fwhm_nm: float | None = Field(
        None,
        ge=0,
        le=100,
        description=(
            "Width of every band's filter (Gaussian FWHM, nm), replacing the cube header's per-band widths (the rig's), "
            "modelled by a per-pixel band-mean correction; default: the header's, else 10 (DWRR08 §6.1: 10-nm band-pass "
            "filters), which the fit reports; 0: treat bands as lines."
        ),
    )
    map_cell_mm: dict[str, float] | None = Field(
        None,
        description=(
            "Node spacing (mm) of each map's own grid, bilinearly interpolated onto the pixels; 0: per pixel; a "
            "spacing as large as the window: one value for the patch. Maps not named keep the default. "
            "None: the measured default for gn-hom and the model's profiles (MAP_CELL_MM_BY_PROFILES), per pixel for "
            "gn, adam and paper-fd."
        ),
    )
    map_grids: Literal["fixed", "auto"] = Field(
        "fixed",
        description=(
            "fixed: map_cell_mm as given (or its default); auto: each map's spacing chosen on the cube at the coarsest "
            "level, the candidate with the least Cramér–Rao variance + C_p bias² (reconstruct/choice/grid_choice.py), "
            "starting from map_cell_mm; the evidence goes into fit.json. gn-hom only."
        ),
    )
    forward: Literal["auto", "heterogeneous", "homogeneous"] = Field(
        "auto",
        description=(
            "The forward model: heterogeneous (the renderer, DWRR08 §4: every pixel lit by its neighbours), "
            "homogeneous (each pixel's own model under the window's light: no cross-talk, no render per step), or auto: "
            "the homogeneous fit first, kept where the renderer at its maps differs from it by at most half the cube's "
            "noise, else the heterogeneous fit (reconstruct/choice/fidelity.py; the evidence goes into fit.json)."
        ),
    )
    absorbers: Literal["auto", "none"] = Field(
        "none",
        description=(
            "auto: after the finest level, a grey interface absorbance (DWRR08 §4.2's thin layer) is fitted on the "
            "pixels whose residual stands out (hairs), kept per pixel where it lowers that pixel's chi2 by more than "
            "ln n (BIC, the cube's noise known), and the maps refitted with it (reconstruct/diagnosis/absorbers.py); none: never. "
            "The renderer's fit only (the homogeneous model holds no neighbour to shade)."
        ),
    )
    robust_passes: int = Field(
        1, ge=0, le=5,
        description=(
            "After each level's fit, refit this many times with each pixel weighted by a Cauchy weight of its "
            "residual (hairs, veins: what the model does not hold pulls the shared unknowns less)."
        ),
    )
    robust_finest: Literal["carry", "refit"] = Field(
        "carry",
        description=(
            "carry: the finest level is fitted once, each pixel weighted from the start by the robust weight of its "
            "parent pixel on the level above (one pass fewer: the demo's 256² fit 1.6× faster, no map worse by more "
            "than 5%); refit: fitted unweighted, then refitted robust_passes times with its own weights (better with "
            "hairs: beta_m 0.100 against 0.126 on the demo's scene with five hairs). docs/reconstruct.md, \"Settings\"."
        ),
    )
    band_weights: Literal["noise", "equal"] | None = Field(
        None,
        description=(
            "How the loss weighs the bands: noise, each band by the inverse of the cube's own noise there (measured "
            "on the cube, reconstruct/grid_choice.band_noise; a band's weight at most fit.NOISE_WEIGHT_MAX times the "
            "typical band's): the least-squares fit of unequal noise; equal: every band alike, as DWRR08 §6.3's fit. "
            "None: by the model's profiles (BAND_WEIGHTS_BY_PROFILES: noise with transport, equal with diffusion). "
            "docs/reconstruct.md, \"Band weights\"."
        ),
    )
    robust_scale: float = Field(2.0, gt=0, description="The Cauchy weight's scale, in multiples of the median pixel's residual RMS.")
    free_scale: bool = Field(
        False,
        description=(
            "Fit one global radiometric scale (DWRR08 §6.4 found 1.02). Off: the calibration's Spectralon sets the "
            "scale. With β_m and C_bc on nodes a free scale trades brightness against them, which costs β_m far "
            "more than a calibration error would (docs/reconstruct.md, \"Measured\")."
        ),
    )
    max_iterations: int = Field(60, ge=1, le=10000, description="Iteration cap per level (a safety net: the convergence test stops first).")
    ftol: float = Field(
        1e-3,
        gt=0,
        description=(
            "Converged when an accepted step lowers the loss by less than this fraction. Smaller values fit the noise "
            "along poorly determined directions: more iterations, the same errors (docs/reconstruct.md, \"Convergence and flags\")."
        ),
    )
    xtol: float = Field(
        2e-3,
        gt=0,
        description="… or when no pixel moves more than this in the unconstrained parameters (≈ relative change of a small fraction).",
    )
    renderer_retries: int = Field(
        1,
        ge=0,
        le=20,
        description=(
            "gn, gn-hom with the renderer: rejected steps in a row tolerated once a step of the pass has been kept, "
            "before the pass ends (each costs a render). 1 (the default since issue 58): the demo's 256² fit 1.9× "
            "faster than with 4 on clean skin and 1.24× with the demo scene's hairs, β_m within its target on both; "
            "0 costs β_m its target with hairs (docs/speed.md). Before any step is kept the damping may grow further."
        ),
    )
    anderson_memory: int = Field(
        0,
        ge=0,
        le=20,
        description=(
            "gn, gn-hom: Anderson acceleration over this many past steps (0: plain Levenberg–Marquardt). Off: it "
            "added rejected steps and stopped no sooner (docs/reconstruct.md, \"Settings\")."
        ),
    )
    learning_rate: float = Field(0.05, gt=0, description="adam and paper-fd: initial step in the unconstrained parameters.")
    fd_step: float = Field(1e-3, gt=0, description="paper-fd: forward-difference step in the unconstrained parameters.")
    saturated_reflectance: float = Field(
        0.95, gt=0, description="A pixel with any band at or above this is saturated: left out of the loss and flagged."
    )
    dead_band_reflectance: float = Field(
        2e-3, ge=0, description="A band whose median over the window is at or below this is dead: left out and reported."
    )
    high_residual_factor: float = Field(
        3.0, gt=1, description="Flag pixels whose residual RMS exceeds this multiple of the median pixel's."
    )
    at_bound_fraction: float = Field(1e-3, gt=0, lt=0.5, description="Flag a parameter within this fraction of its range of a bound.")
    dtype: Literal["float32", "float64"] = Field("float32", description="Precision of the renders.")
    model: ModelSettings = Field(default_factory=ModelSettings, description="The skin model (keys of configs/model.yaml).")

    @model_validator(mode="after")
    def _method(self) -> "FitSettings":
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(sorted(METHODS))}, got {self.method!r}")
        if self.map_cell_mm is not None:
            unknown = set(self.map_cell_mm) - set(DEFAULT_MAP_CELL_MM)
            if unknown:
                raise ValueError(f"map_cell_mm: unknown map(s) {', '.join(sorted(unknown))}; the maps are {', '.join(DEFAULT_MAP_CELL_MM)}")
            if any(v < 0 for v in self.map_cell_mm.values()):
                raise ValueError(f"map_cell_mm: a node spacing must be ≥ 0 mm (0: per pixel), got {self.map_cell_mm}")
            # a file names only the maps it changes; the others keep the method's and the physics' default
            # (the settings are frozen once made: this is their making)
            object.__setattr__(self, "map_cell_mm", {**self._default_cells(), **self.map_cell_mm})
        if self.map_grids == "auto" and self.method in PER_PIXEL_METHODS:
            raise ValueError(f"map_grids: auto chooses node grids, which method {self.method} does not fit (use gn-hom)")
        if self.coarse_maps and self.method in PER_PIXEL_METHODS:
            raise ValueError(
                f"method {self.method} fits every map per pixel; map_cell_mm puts {', '.join(self.coarse_maps)} on nodes "
                "(use gn-hom, or leave map_cell_mm out)"
            )
        return self

    @property
    def cells(self) -> dict[str, float]:
        """The node spacing of every map as the fit uses it (``map_cell_mm`` resolved)."""
        if self.map_cell_mm is not None:
            return dict(self.map_cell_mm)
        return self._default_cells()

    def _default_cells(self) -> dict[str, float]:
        return dict(_PER_PIXEL if self.method in PER_PIXEL_METHODS else MAP_CELL_MM_BY_PROFILES[self.model.profiles])

    @property
    def band_weighting(self) -> str:
        """How the loss weighs the bands as the fit does it (``band_weights`` resolved by the profiles)."""
        return self.band_weights or BAND_WEIGHTS_BY_PROFILES[self.model.profiles]

    @property
    def coarse_maps(self) -> list[str]:
        """The maps fitted on nodes rather than per pixel."""
        return [k for k, v in self.cells.items() if v > 0]


def load_fit_settings(path: str | Path | None = None, **overrides) -> FitSettings:
    """Embedded defaults, overridden by a YAML file if given, then by keyword ``overrides`` (None ignored).

    Raises ``FitSettingsError`` naming the file, the key and the problem.
    """
    return load_settings(FitSettings, path, FitSettingsError, "fit settings", {k: v for k, v in overrides.items() if v is not None})
