"""Issue 59: a session through a hyperspectral rig (31 bands of 10 nm, 400–700 nm, Hyper-Skin's layout),
calibrated to ``cube.exr`` and written as ENVI, multi-page TIFF and NumPy: ``skinlayers reconstruct``
fits each copy to the maps of the ``cube.exr`` to the bit.

The session is the simulator's (the demo's scene, a 16² cube: small, so the suite stays quick); how well
31 bands fit against the simulation's truth at the size a user fits is measured in the tradeoff chart's
row "31 bands" (docs/tradeoff.md) and docs/formats.md.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from skinlayers.acquire.hardware.simdevices import SimulatedTunableFilter, SimulatedWheel
from skinlayers.analyses.tradeoff import make_session
from skinlayers.analyses.tradeoff_plan import SessionSpec
from skinlayers.analyses.truths import HYPERSPECTRAL_BANDS, session_rig
from skinlayers.cli import app
from skinlayers.formats.cube import read_cube
from skinlayers.formats.foreign.cubes import read_cube_file, write_cube_file
from skinlayers.formats.manifest import read_manifest
from skinlayers.model import PARAMETER_NAMES
from skinlayers.model.patch.maps_io import read_maps

SIZE_PX = 16
#: One wavelength node a band in the truth's render (the simulator's default takes three): this test asks
#: whether the formats fit alike, not how close the fit comes to the truth, and 93 renders cost half a minute.
FAST_TRUTH = {"filters": {"wavelength_samples": 1}}
#: The fit at 16² (0.47-mm pixels) on one level, so four fits take seconds.
FIT_CONFIG = "coarsest_px: 0\n"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hyper") / "session"
    make_session(SessionSpec("diffusion", 61, SIZE_PX, HYPERSPECTRAL_BANDS), folder, simulation_over=FAST_TRUTH)
    return folder


@pytest.fixture(scope="module")
def fits(session, tmp_path_factory):
    """The cube.exr and each foreign copy fitted by the command a user runs: ``{suffix: fit folder}``."""
    root = tmp_path_factory.mktemp("hyperfits")
    cube = read_cube(session / "calibrated" / "cube.exr")
    config = root / "fit.yaml"
    config.write_text(FIT_CONFIG)
    inputs = {".exr": session / "calibrated" / "cube.exr"}
    for suffix in (".hdr", ".tif", ".npz"):
        inputs[suffix] = write_cube_file(root / f"arm{suffix}", cube)
    out = {}
    for suffix, path in inputs.items():
        out[suffix] = root / f"rec{suffix[1:]}"
        result = CliRunner().invoke(app, ["reconstruct", str(path), "--config", str(config), "--device", "cpu",
                                          "-o", str(out[suffix])])
        assert result.exit_code == 0, (result.output, result.exception)
    return out


def test_the_rig_takes_31_bands_of_10_nm_through_a_tunable_filter(session):
    rig = session_rig(SIZE_PX, HYPERSPECTRAL_BANDS)
    assert [b.wavelength_nm for b in rig.bands] == [400.0 + 10.0 * i for i in range(31)]
    assert {b.fwhm_nm for b in rig.bands} == {10.0}
    manifest = read_manifest(session / "session")
    assert manifest.rig["wheel"]["position_count"] == 32
    assert {f.band_nm for f in manifest.frames if f.role == "skin"} == {b.wavelength_nm for b in rig.bands}


def test_a_tunable_filter_takes_what_no_wheel_holds():
    tunable = SimulatedTunableFilter(32, time_scale=0.0)
    tunable.move_to(32)
    assert tunable.position() == 32 and "32 settings" in tunable.identify()
    with pytest.raises(ValueError, match="tunable filter has 2–65 positions"):
        SimulatedTunableFilter(66)
    with pytest.raises(ValueError, match="wheel has 6 or 12 positions"):
        SimulatedWheel(32)


def test_the_cube_says_its_bands_and_widths_in_every_format(session, tmp_path):
    cube = read_cube(session / "calibrated" / "cube.exr")
    assert cube.reflectance.shape == (31, SIZE_PX, SIZE_PX)
    for suffix in (".hdr", ".tif", ".npz"):
        back = read_cube_file(write_cube_file(tmp_path / f"c{suffix}", cube))
        assert back.header.wavelengths_nm == cube.header.wavelengths_nm
        assert back.header.band_fwhm_nm == [10.0] * 31
        assert torch.equal(back.reflectance, cube.reflectance) and torch.equal(back.mask, cube.mask)


def test_every_format_fits_to_the_maps_of_its_cube_exr(fits):
    reference = read_maps(fits[".exr"] / "maps.exr")
    scale = json.loads((fits[".exr"] / "fit.json").read_text())["scale"]
    assert math.isfinite(scale)
    for suffix in (".hdr", ".tif", ".npz"):
        maps = read_maps(fits[suffix] / "maps.exr")
        for n in PARAMETER_NAMES:
            assert torch.equal(getattr(maps, n), getattr(reference, n)), (suffix, n)
        assert json.loads((fits[suffix] / "fit.json").read_text())["scale"] == scale


def test_the_fit_models_each_band_by_its_width(fits):
    """The fit's band model from the file's FWHM: three wavelength nodes a band (problem.band_nodes)."""
    fit = json.loads((fits[".hdr"] / "fit.json").read_text())
    assert fit["wavelengths_nm"] == [400.0 + 10.0 * i for i in range(31)]
    assert np.allclose(fit["band_fwhm_nm"], 10.0) and fit["band_fwhm_source"] == "cube header"


def test_the_report_draws_nine_bands_the_worst_among_them():
    from skinlayers.reconstruct.results.report import REPORT_BANDS, report_bands

    rms = np.ones(31)
    rms[5] = 3.0
    shown = report_bands(rms)
    assert len(shown) == REPORT_BANDS and shown[0] == 0 and shown[-1] == 30 and 5 in shown
    assert shown == sorted(set(shown))
    assert report_bands(np.ones(9)) == list(range(9))
    rms[1] = 6.0  # the worst beside the first band: an inner pick gives way, the ends stay
    assert report_bands(rms)[:2] == [0, 1] and report_bands(rms)[-1] == 30
    rms[30] = 9.0  # the worst already among the spread: nothing replaced
    assert report_bands(rms) == [int(round(v)) for v in np.linspace(0, 30, REPORT_BANDS)]
