"""The physics of skinlayers: spectra, layer profiles, Gaussian tables, layered skin, colour.

Pure, differentiable functions on tensors (CPU or CUDA alike); imports nothing of the project but
its contracts (``formats``).
"""

from .optics.colour import ColourConverter, ita_degrees
from .optics.fresnel import diffuse_fresnel_reflectance, fresnel_reflectance, fresnel_transmittance
from .column.gaussians import fit_gaussian_weights, gaussian_sum_hankel, gaussian_sum_profile
from .column.layered import LayerTransforms, SkinModel, combine_layers, inverse_hankel
from .optics.params import (
    N_PARAMS,
    PARAMETER_BOUNDS,
    PARAMETER_NAMES,
    TABLE2,
    LayerAbsorption,
    SkinParams,
    layer_absorption,
    parameter_bounds,
)
from .column.profiles import (
    LayerProfiles,
    dipole_hankel,
    dipole_profile,
    dipole_total,
    multipole_hankel,
    multipole_profiles,
    multipole_totals,
)
from .settings import ModelSettings, SettingsError, SkinOptics, TableSettings, load_model_settings
from .optics.spectra import ChromophoreSpectra, chromophore_spectra, epidermis_scattering
from .column.tables import ProfileTables, build_profile_tables, load_profile_tables

__all__ = [
    "N_PARAMS",
    "PARAMETER_BOUNDS",
    "PARAMETER_NAMES",
    "TABLE2",
    "ChromophoreSpectra",
    "ColourConverter",
    "LayerAbsorption",
    "LayerProfiles",
    "LayerTransforms",
    "ModelSettings",
    "ProfileTables",
    "SettingsError",
    "SkinModel",
    "SkinOptics",
    "SkinParams",
    "TableSettings",
    "build_profile_tables",
    "chromophore_spectra",
    "combine_layers",
    "diffuse_fresnel_reflectance",
    "dipole_hankel",
    "dipole_profile",
    "dipole_total",
    "epidermis_scattering",
    "fit_gaussian_weights",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "gaussian_sum_hankel",
    "gaussian_sum_profile",
    "inverse_hankel",
    "ita_degrees",
    "layer_absorption",
    "load_model_settings",
    "load_profile_tables",
    "multipole_hankel",
    "multipole_profiles",
    "multipole_totals",
    "parameter_bounds",
]
