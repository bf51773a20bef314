"""Typed settings of the map fit (``skinlayers reconstruct``), with an embedded default that runs.

YAML (``configs/fit.yaml``) overrides any subset of keys; unknown keys are refused with the key named.
The skin model's own settings sit under ``model`` (the same keys as ``configs/model.yaml``), so one
resolved file, saved beside every fit, re-makes it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from ..model import ModelSettings
from ..model.settings import load_settings

__all__ = ["FitSettings", "FitSettingsError", "load_fit_settings"]


class FitSettingsError(ValueError):
    """A fit settings file or value that cannot be used; the message names the file and key."""


class FitSettings(BaseModel):
    """Everything that shapes a map fit. Defaults are the measured choices (docs in each field)."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, protected_namespaces=())

    method: str = Field(
        "gn-hom",
        description=(
            "Optimiser (registry in reconstruct/optimizers.py): gn-hom (Gauss–Newton with each pixel's "
            "homogeneous Jacobian on the heterogeneous residual: forward renders only), gn (the same "
            "curvature with the exact gradient from one forward+backward), adam (autograd gradients), "
            "paper-fd (DWRR08 §6.3: gradient descent by forward differences, 6 renders a step)."
        ),
    )
    start: Literal["homogeneous", "paper"] = Field(
        "homogeneous",
        description="homogeneous: a point-spectrum fit of every pixel of the coarsest level; paper: DWRR08's pale skin.",
    )
    coarsest_px: int = Field(
        64, ge=0, description="Coarse-to-fine: halve the cube while its longer side exceeds this (0: fit the full grid only)."
    )
    border_mm: float = Field(
        3.0,
        ge=0,
        description=(
            "Occluded skin simulated beyond the window. Measured against 10 mm on the palest Table 2 skin at 64²: "
            "1 mm moves a window pixel by up to 1.6% (670 nm), 2 mm by 0.23%, 5 mm by 3.5·10⁻⁵; 3 mm keeps every "
            "visible pixel within ~6·10⁻⁴, a tenth of the camera noise."
        ),
    )
    view_angle_deg: float | None = Field(
        None, ge=0, lt=90, description="Camera angle off the flash axis; default: the cube's meta 'camera_angle_deg', else 30."
    )
    band_fwhm_nm: float | None = Field(
        None,
        ge=0,
        description=(
            "Width of each band's filter (Gaussian FWHM, nm), modelled by a per-pixel band-mean correction; "
            "default: the cube meta's 'band_fwhm_nm', else 10 (PHYSICS.md §7); 0: treat bands as lines."
        ),
    )
    free_scale: bool = Field(True, description="Fit one global radiometric scale (DWRR08 §6.4 found 1.02).")
    max_iterations: int = Field(60, ge=1, description="Iteration cap per level (a safety net: the convergence test stops first).")
    ftol: float = Field(
        1e-3,
        gt=0,
        description=(
            "Converged when an accepted step lowers the loss by less than this fraction. Measured: from 1e-3 to 1e-4 "
            "the iterations double (noise being fitted along poorly determined directions) and no parameter's median "
            "error changes by more than 1% of itself."
        ),
    )
    xtol: float = Field(
        2e-3,
        gt=0,
        description="… or when no pixel moves more than this in the unconstrained parameters (≈ relative change of a small fraction).",
    )
    anderson_memory: int = Field(
        0,
        ge=0,
        le=20,
        description=(
            "gn, gn-hom: Anderson acceleration over this many past steps (0: plain Levenberg–Marquardt). Measured on "
            "32² cubes: 5 steps doubled the rejected steps and stopped no sooner, hence off."
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
        from .optimizers import METHODS  # noqa: PLC0415 (the registry imports settings' users)

        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(sorted(METHODS))}, got {self.method!r}")
        return self


def load_fit_settings(path: str | Path | None = None, **overrides) -> FitSettings:
    """Embedded defaults, overridden by a YAML file if given, then by keyword ``overrides`` (None ignored).

    Raises ``FitSettingsError`` naming the file, the key and the problem.
    """
    return load_settings(FitSettings, path, FitSettingsError, "fit settings", {k: v for k, v in overrides.items() if v is not None})
