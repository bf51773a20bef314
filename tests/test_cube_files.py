"""Cubes from other cameras and tools (``formats/foreign/cubes.py``): ENVI, multi-page TIFF, NumPy and HDF5
read into the same ``Cube`` as ``cube.exr``, to the bit; a file without its wavelengths or its scale is
refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from skinlayers.formats.cube import Cube, CubeError, CubeHeader, write_cube
from skinlayers.formats.foreign.cubes import CUBE_READERS, read_cube_file, write_cube_file

WL = [450.0, 500.0, 550.0, 600.0, 650.0]


@pytest.fixture(scope="module")
def cube() -> Cube:
    g = torch.Generator().manual_seed(0)
    reflectance = torch.rand(len(WL), 12, 10, generator=g) * 0.6
    mask = torch.rand(12, 10, generator=g) > 0.2
    header = CubeHeader(wavelengths_nm=WL, band_fwhm_nm=[10.0, 12.0, 10.0, 8.0, 10.0], camera_angle_deg=15.0, mm_per_pixel=0.05)
    return Cube(reflectance, mask, header)


@pytest.mark.parametrize("suffix", sorted(CUBE_READERS))
def test_every_format_reads_back_the_cube_it_was_written_from(tmp_path, cube, suffix):
    back = read_cube_file(write_cube_file(tmp_path / f"cube{suffix}", cube))
    exr = read_cube_file(write_cube(tmp_path / "cube.exr", cube))
    for other in (back, exr):
        assert torch.equal(other.reflectance, cube.reflectance) and torch.equal(other.mask, cube.mask)
        for field in ("wavelengths_nm", "band_fwhm_nm", "camera_angle_deg", "mm_per_pixel"):
            assert getattr(other.header, field) == getattr(cube.header, field), field


def _npz(path, **fields):
    np.savez(path, **fields)
    return path


def test_integer_counts_are_divided_by_the_files_scale_and_widths_come_from_the_spacing(tmp_path):
    counts = np.full((3, 4, 4), 4000, dtype=np.uint16)
    counts[1, 0, 0] = 0
    path = _npz(tmp_path / "c.npz", reflectance=counts, wavelengths_nm=np.array([450.0, 470.0, 530.0]),
                reflectance_scale=10000.0, mm_per_pixel=0.1)
    cube = read_cube_file(path)
    assert torch.allclose(cube.reflectance[0], torch.full((4, 4), 0.4))
    assert cube.header.band_fwhm_nm == [20.0, 40.0, 60.0]  # the neighbours' mean distance; one neighbour at the ends
    assert cube.header.calibration["band_fwhm_from"] == "the bands' spacing"


def test_missing_pixels_are_masked_and_micrometres_become_nanometres(tmp_path):
    from spectral.io import envi

    data = np.full((4, 5, 3), 0.3, dtype=np.float32)  # (rows, cols, bands), as ENVI holds it
    data[1, 2, 0] = np.nan
    data[3, 3, 2] = -9999.0
    envi.save_image(str(tmp_path / "c.hdr"), data, metadata={"wavelength": [0.45, 0.55, 0.65], "mm per pixel": 0.1,
                                                            "data ignore value": -9999.0}, force=True, ext=".img")
    cube = read_cube_file(tmp_path / "c.hdr")
    assert cube.header.wavelengths_nm == pytest.approx([450.0, 550.0, 650.0])
    assert not cube.mask[1, 2] and not cube.mask[3, 3] and int(cube.mask.sum()) == 18
    assert bool(torch.isfinite(cube.reflectance).all())


@pytest.mark.parametrize("fields, message", [
    ({"reflectance": np.zeros((2, 3, 3), np.float32), "mm_per_pixel": 0.1}, "no 'wavelengths_nm'"),
    ({"reflectance": np.zeros((2, 3, 3), np.uint16), "wavelengths_nm": [500.0, 600.0], "mm_per_pixel": 0.1}, "no reflectance scale"),
    ({"reflectance": np.full((2, 3, 3), 40.0, np.float32), "wavelengths_nm": [500.0, 600.0], "mm_per_pixel": 0.1}, "values up to 40"),
    ({"reflectance": np.zeros((2, 3, 3), np.float32), "wavelengths_nm": [500.0, 600.0]}, "give --mm-per-pixel"),
    ({"reflectance": np.zeros((3, 3, 3), np.float32), "wavelengths_nm": [500.0, 600.0], "mm_per_pixel": 0.1}, "2 wavelengths for pixels"),
    ({"reflectance": np.zeros((2, 3, 3), np.float32), "wavelengths_nm": [600.0, 500.0], "mm_per_pixel": 0.1}, "must increase"),
])
def test_a_file_that_cannot_be_fitted_is_refused_in_one_line(tmp_path, fields, message):
    with pytest.raises(CubeError, match=message) as caught:
        read_cube_file(_npz(tmp_path / "c.npz", **fields))
    assert "\n" not in str(caught.value)


def test_the_pixel_side_comes_from_the_command_line_where_the_file_has_none(tmp_path):
    path = _npz(tmp_path / "c.npz", reflectance=np.zeros((2, 3, 3), np.float32), wavelengths_nm=[500.0, 600.0])
    assert read_cube_file(path, mm_per_pixel=0.07).mm_per_pixel == 0.07
    with_pixel = _npz(tmp_path / "d.npz", reflectance=np.zeros((2, 3, 3), np.float32), wavelengths_nm=[500.0, 600.0], mm_per_pixel=0.1)
    with pytest.raises(CubeError, match="says 0.1 mm a pixel, --mm-per-pixel 0.07"):
        read_cube_file(with_pixel, mm_per_pixel=0.07)
    with pytest.raises(CubeError, match="not a cube file skinlayers reads"):
        read_cube_file(tmp_path / "cube.png")


def test_tiff_without_wavelengths_is_refused(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "c.tif", np.zeros((2, 3, 3), np.float32), photometric="minisblack", metadata={"mm_per_pixel": 0.1})
    with pytest.raises(CubeError, match="no wavelengths_nm"):
        read_cube_file(tmp_path / "c.tif")


def test_an_envi_header_without_its_data_or_not_a_header_is_refused(tmp_path):
    (tmp_path / "bad.hdr").write_text("garbage\n")
    with pytest.raises(CubeError, match="not a readable ENVI cube"):
        read_cube_file(tmp_path / "bad.hdr")
    (tmp_path / "lonely.hdr").write_text("ENVI\nsamples = 3\nlines = 3\nbands = 1\ndata type = 4\ninterleave = bsq\n"
                                         "header offset = 0\nbyte order = 0\nwavelength = {500}\n")
    with pytest.raises(CubeError, match="not a readable ENVI cube"):
        read_cube_file(tmp_path / "lonely.hdr")
