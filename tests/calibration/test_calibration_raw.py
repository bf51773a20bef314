"""Raw decoding: linear values, black level per photosite through the CFA pattern, white level,
saturation, superpixels, and corrupt or truncated files named in the error."""

from __future__ import annotations

import numpy as np
import pytest

from skinlayers.calibration.errors import RawDecodeError
from skinlayers.calibration.raw import read_raw, superpixel, superpixel_any


@pytest.mark.parametrize("cfa", ["RGGB", "GBRG", "BGGR"])
@pytest.mark.parametrize("bits", [12, 16])
def test_black_level_follows_the_cfa_position_not_the_colour_index(synth, tmp_path, cfa, bits):
    # per-position black levels that differ everywhere: a mapping by colour index instead of position
    # (rawpy's black_level_per_channel) would subtract the wrong black from three of the four sites
    black = (100, 140, 180, 220)
    rng = np.random.default_rng(1)
    signal = rng.integers(0, 1500, (48, 64))
    cell = np.tile(np.array(black).reshape(2, 2), (24, 32))
    data = (signal + cell).astype(np.uint16)
    path = synth.write_dng(tmp_path / f"{cfa}.dng", data, bits=bits, black=black, cfa=cfa)
    raw = read_raw(path)
    assert raw.cfa == cfa
    np.testing.assert_array_equal(raw.black_cell, np.array(black).reshape(2, 2))
    np.testing.assert_array_equal(raw.values, signal.astype(np.float32))
    assert raw.white_level == (1 << bits) - 1


def test_saturation_mask_and_superpixel(synth, tmp_path):
    black = (64, 64, 64, 64)
    data = np.full((32, 40), 1064, np.uint16)
    data[2, 3] = 4095  # clipped
    data[5, 7] = 4095 - 30  # within the default 1% margin (41 DN) of the white level
    data[6, 0] = 4095 - 60  # below it
    raw = read_raw(synth.write_dng(tmp_path / "sat.dng", data, black=black), saturation_margin=0.01)
    assert set(zip(*np.nonzero(raw.saturated))) == {(2, 3), (5, 7)}
    sp = raw.superpixel()
    assert sp.shape == (16, 20)
    assert sp[0, 0] == pytest.approx(4 * 1000)
    assert set(zip(*np.nonzero(raw.superpixel_saturated()))) == {(1, 1), (2, 3)}
    assert raw.full_scale_dn == 4095 - 64


def test_superpixel_sums_each_cell_and_drops_an_odd_edge():
    values = np.arange(5 * 7, dtype=np.float32).reshape(5, 7)
    sp = superpixel(values)
    assert sp.shape == (2, 3)
    assert sp[1, 2] == values[2:4, 4:6].sum()
    mask = np.zeros((5, 7), bool)
    mask[3, 5] = True
    assert superpixel_any(mask).tolist() == [[False, False, False], [False, False, True]]


@pytest.mark.parametrize("keep", [0.5, 0.99, 0.0])
def test_truncated_or_corrupt_file_is_named(synth, tmp_path, keep):
    path = synth.write_dng(tmp_path / "frame.dng", np.full((32, 32), 500, np.uint16))
    data = path.read_bytes()
    broken = tmp_path / "broken.dng"
    broken.write_bytes(data[: int(len(data) * keep)] if keep else b"not a raw file at all" * 50)
    with pytest.raises(RawDecodeError, match="broken.dng"):
        read_raw(broken)


def test_missing_file_is_an_os_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.dng"):
        read_raw(tmp_path / "absent.dng")
