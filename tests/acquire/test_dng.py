"""DNG files: rawpy reads back every pixel, the pattern, the black level per channel and the white
level exactly as written; what pidng cannot write is refused with a clear message."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy

from skinlayers.acquire.hardware.dng import write_dng

#: rawpy's colour indices of an RGGB sensor: R=0, G=1, B=2, second G=3.
RGGB_PATTERN = [[0, 1], [3, 2]]


@pytest.mark.parametrize("bits, white, shape", [(12, 4095, (64, 96)), (16, 16383, (50, 70)), (16, 65535, (32, 48))])
def test_rawpy_reads_back_exactly_what_was_written(tmp_path, bits, white, shape):
    rng = np.random.default_rng(bits + shape[0])
    raw = rng.integers(0, white + 1, shape).astype(np.uint16)
    raw[0, 0], raw[-1, -1] = 0, white  # both ends of the range
    black = [100, 101, 102, 103]  # positions (0,0), (0,1), (1,0), (1,1)
    path = write_dng(tmp_path / "frame.dng", raw, bits=bits, black_level=black, white_level=white, iso=400, exposure_s=0.01,
                     f_number=10.0)
    with rawpy.imread(str(path)) as r:
        assert r.raw_image.shape == shape
        assert np.array_equal(r.raw_image, raw)
        assert r.raw_pattern.tolist() == RGGB_PATTERN
        assert r.color_desc == b"RGBG"
        assert r.white_level == white
        for row in range(2):
            for col in range(2):
                assert r.black_level_per_channel[r.raw_pattern[row][col]] == black[2 * row + col]
    assert [p.name for p in tmp_path.iterdir()] == ["frame.dng"]  # no temporary file left behind


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"bits": 14}, "12 or 16"),
        ({"raw": np.zeros((5, 8), np.uint16)}, "even sides"),
        ({"raw": np.zeros((4, 8), np.int32)}, "uint16"),
        ({"raw": np.full((4, 8), 5000, np.uint16), "bits": 12, "white_level": 4095}, "do not fit 12 bits"),
        ({"white_level": 70000}, "white level"),
        ({"black_level": [1, 2, 3]}, "four values"),
        ({"black_level": [0, 0, 0, 20000]}, "four values"),
    ],
)
def test_what_cannot_be_written_is_refused(tmp_path, kwargs, match):
    args = {"raw": np.zeros((4, 8), np.uint16), "bits": 16, "black_level": [0, 0, 0, 0], "white_level": 16383, **kwargs}
    with pytest.raises(ValueError, match=match):
        write_dng(tmp_path / "x.dng", args.pop("raw"), **args)
    assert not list(tmp_path.iterdir())
