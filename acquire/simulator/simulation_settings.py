"""Settings of the simulated bench: camera geometry, flash, filters, sensor, and the true skin render.

Typed and validated (``configs/simulation.yaml`` is the embedded default). The rig (bands, exposures,
window, targets, camera angle) comes from the rig config; these settings say how the simulator turns
it into pictures.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional

from pydantic import Field, model_validator

from ...formats.errors import SettingsError
from ...formats.settings import Strict, load_settings, validate_settings
from ...model.settings import MAX_PHOTONS, MIN_PHOTONS
from ...model.transport import check_physics_options

__all__ = ["ChannelCurve", "SimulationError", "SimulationSettings", "load_simulation_settings", "simulation_from_dict",
           "truth_overrides"]


class SimulationError(SettingsError):
    """Simulation settings that cannot be used; the message names the file or key and the problem."""


class SimCamera(Strict):
    distance_mm: float = Field(270.0, gt=10, le=10000, description="Centre of projection to the window centre (mm).")
    window_span_px: Optional[int] = Field(None, ge=16, le=8192, description="Raw px across the window's centre line; None: 2 × rectify_px.")
    field_of_view_mm: tuple[Annotated[float, Field(gt=0, le=200)], Annotated[float, Field(gt=0, le=200)]] = Field(
        (12.0, 10.0), description="Skin-plane width × height the sensor covers (mm)."
    )
    psf_sigma_px: float = Field(1.0, ge=0, le=10, description="Gaussian lens blur (raw px).")
    vignetting: float = Field(0.30, ge=0, lt=1, description="Fall-off at the sensor corners (0.3: 30%).")
    supersample: int = Field(2, ge=1, le=8, description="Samples per raw pixel per axis in the warp.")


class SimScene(Strict):
    tape_reflectance: float = Field(0.03, ge=0, le=1, description="Reflectance of the black tape (flat).")
    gray_card_mm: tuple[float, float, float, float] = Field(
        (-5.8, -1.5, -4.3, 1.5), description="Gray card, fixed to the rig: [x0, y0, x1, y1] in skin-plane mm."
    )

    @model_validator(mode="after")
    def _card(self) -> "SimScene":
        x0, y0, x1, y1 = self.gray_card_mm
        if not (x0 < x1 and y0 < y1):
            raise ValueError(f"gray_card_mm must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1, got {list(self.gray_card_mm)}")
        return self


class SimFlash(Strict):
    temperature_k: float = Field(6000.0, ge=1000, le=20000, description="Blackbody temperature of the xenon continuum (K).")
    jitter: float = Field(0.05, ge=0, lt=1, description="Flash energy uniform within ± this fraction.")


class SimMotion(Strict):
    max_shift_px: float = Field(10.0, ge=0, le=1000, description="Largest subject shift between frames (raw px at the window centre).")
    max_rotation_deg: float = Field(0.2, ge=0, le=10, description="Largest subject rotation about the window centre.")


class SimFilters(Strict):
    wavelength_samples: int = Field(3, ge=1, le=15, description="Gauss–Hermite nodes across each band-pass.")


class ChannelCurve(Strict):
    """One Bayer channel's relative spectral sensitivity: an asymmetric Gaussian main lobe plus a
    Gaussian side lobe (fitted to measured camera curves; see ``SimSensor.sensitivity``)."""

    peak: float = Field(..., ge=0)
    centre_nm: float
    sigma_left_nm: float = Field(..., gt=0)
    sigma_right_nm: float = Field(..., gt=0)
    side_peak: float = Field(0.0, ge=0)
    side_centre_nm: float = 500.0
    side_sigma_nm: float = Field(30.0, gt=0)


def _nikon_d5100() -> dict[str, ChannelCurve]:
    return {
        "red": ChannelCurve(peak=0.952, centre_nm=589.6, sigma_left_nm=8.59, sigma_right_nm=39.4,
                            side_peak=0.074, side_centre_nm=511.2, side_sigma_nm=63.7),
        "green": ChannelCurve(peak=0.949, centre_nm=534.5, sigma_left_nm=26.2, sigma_right_nm=38.7,
                              side_peak=0.316, side_centre_nm=476.6, side_sigma_nm=30.6),
        "blue": ChannelCurve(peak=0.646, centre_nm=427.7, sigma_left_nm=5.90, sigma_right_nm=56.0,
                             side_peak=0.512, side_centre_nm=472.3, side_sigma_nm=25.5),
    }


class SimSensor(Strict):
    bit_depth: Literal[12, 16] = Field(16, description="Bits per sample in the DNG (pidng's 14-bit path is broken).")
    white_level: int = Field(16383, gt=0, description="Largest DN the converter gives (saturation).")
    black_level: tuple[int, int, int, int] = Field(
        (1024, 1024, 1024, 1024), description="Black level (DN) at the RGGB positions R, G (R row), G (B row), B."
    )
    full_well_e: float = Field(25000.0, gt=0, le=1e12, description="Electrons a pixel holds.")
    e_per_dn_iso100: float = Field(1.6, gt=0, description="Electrons per DN at ISO 100; ISO n divides it by n/100.")
    read_noise_e: float = Field(2.5, ge=0, le=1e4, description="Read noise before the gain (electrons, rms).")
    read_noise_dn: float = Field(1.0, ge=0, le=1e4, description="Read noise after the gain (DN, rms).")
    white_electrons: Optional[float] = Field(
        None, gt=0, le=1e12,
        description=(
            "Flash power, as the electrons of a green pixel at the image centre from a white diffuser through a 10-nm "
            "filter at 550 nm at f/10. None: set as an operator sets the flash, so that the brightest reference "
            "frame of the rig (Spectralon at the centre, the flash at its strongest) fills reference_fill of the range."
        ),
    )
    reference_fill: float = Field(0.8, gt=0, le=1, description="Fraction of white - black the brightest reference reaches.")
    sensitivity: dict[Literal["red", "green", "blue"], ChannelCurve] = Field(
        default_factory=_nikon_d5100,
        description=(
            "Per-channel spectral sensitivity: closed forms least-squares fitted (400–700 nm) to the Nikon D5100 "
            "curves measured by the UK National Physical Laboratory (colour-science's MSDS_CAMERA_SENSITIVITIES); "
            "within 0.053 of the channel peak everywhere."
        ),
    )
    iso_values: list[int] = Field(
        [100, 125, 160, 200, 250, 320, 400, 500, 640, 800, 1000, 1250, 1600, 2000, 2500, 3200, 4000, 5000, 6400],
        description="ISO settings the camera accepts (third stops); others are ignored, as a camera does.",
    )
    shutter_values_s: list[float] = Field(
        [1 / 4000, 1 / 3200, 1 / 2500, 1 / 2000, 1 / 1600, 1 / 1250, 1 / 1000, 1 / 800, 1 / 640, 1 / 500, 1 / 400,
         1 / 320, 1 / 250, 1 / 200, 1 / 160, 1 / 125, 1 / 100, 1 / 80, 1 / 60, 1 / 50, 1 / 40, 1 / 30, 1 / 25, 1 / 20,
         1 / 15, 1 / 13, 1 / 10, 1 / 8, 1 / 6, 1 / 5, 1 / 4, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 2.5, 3.2, 4.0,
         5.0, 6.0, 8.0, 10.0, 13.0, 15.0, 20.0, 25.0, 30.0],
        description="Shutter times the camera accepts (s).",
    )
    aperture_values: list[float] = Field(
        [2.8, 3.2, 3.5, 4.0, 4.5, 5.0, 5.6, 6.3, 7.1, 8.0, 9.0, 10.0, 11.0, 13.0, 14.0, 16.0, 18.0, 20.0, 22.0, 25.0,
         29.0, 32.0],
        description="f-numbers the lens accepts.",
    )

    @model_validator(mode="after")
    def _levels(self) -> "SimSensor":
        top = (1 << self.bit_depth) - 1
        if self.white_level > top:
            raise ValueError(f"white_level {self.white_level} exceeds {top}, the largest {self.bit_depth}-bit value")
        if any(not 0 <= b < self.white_level for b in self.black_level):
            raise ValueError(f"black_level {list(self.black_level)} must lie within 0 … white_level - 1 ({self.white_level - 1})")
        return self


class SimTruth(Strict):
    oversample: int = Field(2, ge=2, le=8, description="Truth grid = cube grid / oversample (at least 2× finer).")
    margin_mm: float = Field(0.5, ge=0.05, le=20, description="Skin mapped beyond the window on every side (mm).")
    border_mm: float = Field(3.0, ge=0, le=20, description="Renderer border beyond the maps for the window light (mm).")
    blur: Literal["fft", "pyramid", "chain"] = Field(
        "pyramid", description="Renderer blur strategy for the truth (pyramid: its agreement with fft, docs/renderer.md)."
    )
    identity_below_px: float = Field(0.0, ge=0, description="Gaussians narrower than this act as the identity.")
    series_tolerance: float = Field(1e-2, gt=0, lt=1, description="Light left in the inter-scattering series (closed by its geometric rest).")
    physics: Literal["diffusion", "transport"] = Field(
        "diffusion",
        description=(
            "The light transport of the truth: diffusion (the model's renderer, at the settings above) or transport "
            "(the Monte Carlo reference, model/transport: physics the fit's model did not make; its noise is recorded "
            "in the truth)."
        ),
    )
    photons: int = Field(
        1_000_000, ge=MIN_PHOTONS, le=MAX_PHOTONS,
        description="physics transport: photons per wavelength node of each band (a node's pixel noise falls as 1/√photons).",
    )


class SimulationSettings(Strict):
    """How the simulated bench turns the rig and a scene into raw frames."""

    camera: SimCamera = SimCamera()
    scene: SimScene = SimScene()
    flash: SimFlash = SimFlash()
    motion: SimMotion = SimMotion()
    filters: SimFilters = SimFilters()
    sensor: SimSensor = SimSensor()
    truth: SimTruth = SimTruth()


def default_simulation_path() -> Path:
    from ...configs import config_path  # noqa: PLC0415

    return config_path("simulation.yaml")


def truth_overrides(physics: str | None, photons: int | None) -> dict:
    """The ``truth`` settings a command's ``--physics`` and ``--photons`` change (for ``open_devices``)."""
    check_physics_options(physics, photons)
    return {k: v for k, v in (("physics", physics), ("photons", photons)) if v is not None}


def load_simulation_settings(path: str | Path | None = None, **overrides) -> SimulationSettings:
    """Settings of a YAML file (the embedded ``configs/simulation.yaml`` when ``path`` is None), with
    ``overrides`` merged in (e.g. ``truth={"physics": "transport"}``)."""
    return load_settings(SimulationSettings, path, SimulationError, "simulation settings", overrides,
                         default_path=default_simulation_path())


def simulation_from_dict(data: dict, source: str = "simulation settings") -> SimulationSettings:
    return validate_settings(SimulationSettings, data, SimulationError, source)
