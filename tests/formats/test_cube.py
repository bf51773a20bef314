"""The cube's contract: its typed header survives the file, disagreements with the pixels are refused,
and cubes written before the typed header still read."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from skinlayers.formats.cube import Cube, CubeError, CubeHeader, read_cube, write_cube
from skinlayers.formats.exr import read_exr, write_exr


def _cube(bands=(450.0, 550.0, 650.0), fwhm=(12.0, 10.0, 8.0), size=6) -> Cube:
    g = torch.Generator().manual_seed(0)
    header = CubeHeader(wavelengths_nm=list(bands), band_fwhm_nm=list(fwhm), camera_angle_deg=25.0, mm_per_pixel=0.1,
                        provenance={"session": "/data/S01", "made_by": "test", "rig": "bench"}, calibration={"note": 1})
    mask = torch.ones(size, size, dtype=torch.bool)
    mask[0] = False
    return Cube(torch.rand(len(bands), size, size, generator=g), mask, header)


def test_the_header_survives_the_file(tmp_path):
    cube = _cube()
    back = read_cube(write_cube(tmp_path / "cube.exr", cube))
    assert back.header == cube.header
    assert torch.equal(back.reflectance, cube.reflectance) and torch.equal(back.mask, cube.mask)
    assert back.wavelength_nm.tolist() == [450.0, 550.0, 650.0] and back.mm_per_pixel == 0.1
    _, attributes = read_exr(tmp_path / "cube.exr")  # other EXR readers see the plain attributes too
    assert float(attributes["mm_per_pixel"]) == pytest.approx(0.1) and list(attributes["wavelengths_nm"]) == [450.0, 550.0, 650.0]


def test_a_cube_without_the_typed_header_reads_with_what_it_recorded(tmp_path):
    """A cube written before the typed header: its camera angle from ``meta``; its filters unknown (None)."""
    channels = {f"R_{w}": np.full((4, 4), 0.3, np.float32) for w in (450, 550)}
    channels["mask"] = np.ones((4, 4), np.float32)
    write_exr(tmp_path / "old.exr", channels, {"wavelengths_nm": [450.0, 550.0], "mm_per_pixel": 0.1, "software_version": "0.1.0",
                                               "meta": json.dumps({"camera_angle_deg": 32.0, "session": "/data/S02"})})
    header = read_cube(tmp_path / "old.exr").header
    assert header.camera_angle_deg == 32.0 and header.band_fwhm_nm is None
    assert header.provenance.session == "/data/S02" and header.mm_per_pixel == pytest.approx(0.1)


def _parts(path):
    """A cube file's channels and its own attributes (not the EXR's layout attributes)."""
    channels, attributes = read_exr(path)
    return channels, {k: attributes[k] for k in ("skinlayers_cube", "wavelengths_nm", "mm_per_pixel")}


def test_a_header_that_disagrees_with_the_pixels_is_refused(tmp_path):
    path = write_cube(tmp_path / "cube.exr", _cube())
    channels, attributes = _parts(path)
    header = json.loads(attributes["skinlayers_cube"])
    header["wavelengths_nm"] = [450.0, 560.0, 650.0]
    write_exr(tmp_path / "moved.exr", channels, {**attributes, "skinlayers_cube": json.dumps(header)})
    with pytest.raises(CubeError, match="differ from the channels"):
        read_cube(tmp_path / "moved.exr")
    header["wavelengths_nm"] = [450.0, 550.0]
    write_exr(tmp_path / "fewer.exr", channels, {**attributes, "skinlayers_cube": json.dumps(header)})
    with pytest.raises(CubeError, match="lists 2 bands, the file has 3"):
        read_cube(tmp_path / "fewer.exr")


@pytest.mark.parametrize(
    "change, needle",
    [
        ({"band_fwhm_nm": [10.0, 10.0]}, "2 values for 3 bands"),
        ({"wavelengths_nm": [550.0, 450.0, 650.0]}, "must increase"),
        ({"mm_per_pixel": 0.0}, "mm_per_pixel"),
        ({"camera_angle_deg": 95.0}, "camera_angle_deg"),
        ({"colour": "red"}, "unknown key"),
    ],
)
def test_a_bad_header_is_named(tmp_path, change, needle):
    path = write_cube(tmp_path / "cube.exr", _cube())
    channels, attributes = _parts(path)
    header = {**json.loads(attributes["skinlayers_cube"]), **change}
    write_exr(tmp_path / "bad.exr", channels, {**attributes, "skinlayers_cube": json.dumps(header)})
    with pytest.raises(CubeError) as err:
        read_cube(tmp_path / "bad.exr")
    assert needle in str(err.value) and str(tmp_path / "bad.exr") in str(err.value)


def test_shapes_are_checked():
    cube = _cube()
    with pytest.raises(CubeError, match="wavelengths for"):
        Cube(cube.reflectance[:2], cube.mask, cube.header)
    with pytest.raises(CubeError, match="mask has shape"):
        Cube(cube.reflectance, cube.mask[:3], cube.header)
