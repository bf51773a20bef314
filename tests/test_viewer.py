"""Issue 59: the napari plugin (skinlayers/viewer), headless.

A simulated session (16², the demo's scene and rig), its calibration and its fit, opened as a user opens
them (``napari maps.exr``, ``napari cube.exr``, ``napari SESSION``): through npe2, the plugin's manifest
found among the installed packages, the layers added to napari's ``ViewerModel``. The dock widget runs in
Qt's offscreen platform. napari's ``Viewer`` (its canvas) needs OpenGL, which Qt's offscreen platform does
not give on these machines: the viewer's model holds the same layers, cursor and events without it.
"""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # before Qt loads

import numpy as np
import pytest
import torch

import npe2
from napari.components import ViewerModel

from skinlayers.analyses.tradeoff import make_session
from skinlayers.analyses.tradeoff_plan import SessionSpec
from skinlayers.model import PARAMETER_NAMES
from skinlayers.reconstruct.results.outputs import reconstruct_cube
from skinlayers.reconstruct.settings import load_fit_settings

SIZE_PX = 16
#: One wavelength node a band in the truth (the simulator's default: three): the viewer is tested, not the fit.
FAST_TRUTH = {"filters": {"wavelength_samples": 1}}


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """(session folder, cube path, maps path, the fit)."""
    root = tmp_path_factory.mktemp("viewer")
    make_session(SessionSpec("diffusion", 61, SIZE_PX), root, simulation_over=FAST_TRUTH)
    cube = root / "calibrated" / "cube.exr"
    fit, paths = reconstruct_cube(cube, root / "reconstruction", load_fit_settings(None, coarsest_px=0), device="cpu")
    return root / "session", cube, paths["maps"], fit


def _opened(path) -> ViewerModel:
    """``path`` opened through npe2 with the plugin skinlayers, into a viewer's model."""
    npe2.PluginManager.instance().discover()  # as napari does at its start
    viewer = ViewerModel()
    for data, kwargs, kind in npe2.read([str(path)], stack=False, plugin_name="skinlayers"):
        viewer._add_layer_from_data(data, kwargs, kind)
    return viewer


@pytest.fixture(scope="module")
def qt_app():
    from qtpy.QtWidgets import QApplication

    return QApplication.instance() or QApplication([])


def test_the_plugin_is_found_by_napari():
    manager = npe2.PluginManager.instance()
    manager.discover()
    manifest = manager.get_manifest("skinlayers")
    assert {w.display_name for w in manifest.contributions.widgets} == {"Pixel inspector"}
    assert any(r.accepts_directories for r in manifest.contributions.readers)


def test_maps_open_as_named_layers_in_their_units_and_scale(done):
    _, _, maps, fit = done
    viewer = _opened(maps)
    mm = fit.maps.mm_per_pixel
    for name in ("melanin C_m", "eumelanin share β_m", "epidermal blood C_he", "carotene C_bc", "dermal blood C_hd"):
        layer = viewer.layers[name]
        assert tuple(layer.scale) == (mm, mm) and [str(u) for u in layer.units] == ["millimeter", "millimeter"]
        assert layer.metadata["skinlayers"]["unit"] in ("volume fraction", "fraction of the melanin")
    assert np.array_equal(viewer.layers["melanin C_m"].data, fit.maps.C_m[0].numpy())
    assert np.array_equal(viewer.layers["σ dermal blood C_hd"].data, fit.sigma[PARAMETER_NAMES.index("C_hd")].numpy(), equal_nan=True)
    residual = viewer.layers["fit − measured"]
    assert residual.data.shape == (9, SIZE_PX, SIZE_PX) and tuple(residual.translate)[0] == 430.0
    assert tuple(residual.scale)[0] == 30.0 and str(residual.units[0]) == "nanometer"  # the slider reads nm
    flags = viewer.layers["flags (first set)"]
    assert flags.__class__.__name__ == "Labels" and list(flags.features["flag"])[:2] == ["none", "masked"]


def test_a_cube_opens_as_a_stack_on_its_wavelength_axis(done):
    _, cube, _, fit = done
    viewer = _opened(cube)
    layer = viewer.layers["reflectance"]
    assert layer.data.shape == (9, SIZE_PX, SIZE_PX)
    assert tuple(layer.scale) == (30.0, fit.maps.mm_per_pixel, fit.maps.mm_per_pixel)
    assert tuple(layer.translate)[0] == 430.0 and layer.axis_labels[0] == "wavelength"
    assert "masked" in viewer.layers


def test_a_session_opens_as_its_frames_per_band(done):
    session, *_ = done
    viewer = _opened(session)
    for role in ("skin", "reference"):
        layer = viewer.layers[f"{role} frames"]
        assert layer.data.shape[0] == 9 and layer.metadata["skinlayers"]["wavelengths_nm"][0] == 430.0
        assert float(layer.data.max()) > 0


def test_without_a_cube_of_this_fit_the_inspector_shows_the_maps_and_says_why(done, tmp_path):
    from skinlayers.formats.cube import read_cube
    from skinlayers.formats.foreign.cubes import write_cube_file
    from skinlayers.viewer.inspector import FitAtPixels

    _, cube_path, maps, fit = done
    cube = read_cube(cube_path)
    other = write_cube_file(tmp_path / "other.npz", type(cube)(cube.reflectance[:6], cube.mask,
                                                               cube.header.model_copy(update={"wavelengths_nm": cube.header.wavelengths_nm[:6], "band_fwhm_nm": None})))
    at = FitAtPixels(maps, cube=other)
    report = at.at(8, 8)
    assert report.measured is None and report.fitted is None and "does not match" in at.cube_problem
    assert report.parameters["C_m"][0] == pytest.approx(float(fit.maps.C_m[0, 8, 8]))


def test_the_inspector_shows_the_fits_render_at_the_cursors_pixel(done, qt_app):
    from skinlayers.viewer.widget import PixelInspector

    _, _, maps, fit = done
    viewer = _opened(maps)
    widget = PixelInspector(viewer)
    mm = fit.maps.mm_per_pixel
    for row, col in ((8, 8), (3, 11)):
        viewer.cursor.position = (row * mm + 0.2 * mm, col * mm - 0.3 * mm)  # within the pixel, off its centre
        report = widget.report
        assert (report.row, report.col) == (row, col)
        assert np.allclose(report.fitted, fit.image[:, row, col].double().numpy(), rtol=0, atol=1e-6)
        for i, n in enumerate(PARAMETER_NAMES):
            assert report.parameters[n] == pytest.approx((float(getattr(fit.maps, n)[0, row, col]), float(fit.sigma[i, row, col])))
        set_bits = int(fit.flags[row, col])
        assert len(report.flags) == bin(set_bits).count("1")
        assert report.noise_sigma.shape == (9,) and bool((torch.as_tensor(report.noise_sigma) > 0).all())
    assert "C_hd =" in widget.text.text() and "flags:" in widget.text.text()
    viewer.cursor.position = (-5.0, -5.0)  # off the maps: the last pixel's report stays
    assert (widget.report.row, widget.report.col) == (3, 11)


def test_each_pixel_is_labelled_by_its_lowest_flag():
    from skinlayers.reconstruct.diagnosis.checks import FLAG_BITS, first_flag

    flags = np.array([0, (1 << FLAG_BITS["hair"]) | 1, 1 << FLAG_BITS["structure"]])
    assert first_flag(flags).tolist() == [0, 1, FLAG_BITS["structure"] + 1]
    assert first_flag(torch.tensor([0, 4, 128, 132]), {"a": 2, "b": 7}).tolist() == [0, 3, 8, 3]
