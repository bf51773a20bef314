"""Raw Bayer mosaics as uncompressed DNG files (pidng), read back exactly by rawpy/LibRaw.

12 or 16 bits per sample only: pidng's 14-bit packing and its lossless-JPEG compression are broken,
and a 14-bit camera's data fits a 16-bit container with its white level stated. The CFA is RGGB
(red at row 0, column 0); the black level is given per position of the 2×2 pattern
(BlackLevelRepeatDim 2×2), in the order (0,0), (0,1), (1,0), (1,1). The file is written atomically
(a temporary file in the folder, then a rename), so a broken write never leaves a file that looks done.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Sequence

import numpy as np

from ...formats.files import atomic_write

__all__ = ["DNG_BIT_DEPTHS", "write_dng"]

DNG_BIT_DEPTHS = (12, 16)


def _rational(value: float) -> list[int]:
    f = Fraction(value).limit_denominator(100000)
    return [f.numerator, f.denominator]


def write_dng(
    path: str | Path,
    raw: np.ndarray,
    *,
    bits: int,
    black_level: Sequence[int],
    white_level: int,
    iso: int | None = None,
    exposure_s: float | None = None,
    f_number: float | None = None,
    make: str = "skinlayers",
    model: str = "simulated camera",
    description: str | None = None,
) -> Path:
    """Write ``raw`` ``(H, W)`` uint16 (H, W even) as an uncompressed RGGB DNG; return the path."""
    from pidng.core import RAW2DNG  # noqa: PLC0415 (heavy import kept local)
    from pidng.dng import DNGTags, Tag  # noqa: PLC0415

    path = Path(path)
    raw = np.ascontiguousarray(raw)
    _check_raw(path, raw, bits, black_level, white_level)
    height, width = raw.shape
    t = DNGTags()
    for tag, value in _dng_tags(width, height, bits, black_level, white_level, make, model).items():
        t.set(getattr(Tag, tag), value)
    if iso is not None:
        t.set(Tag.PhotographicSensitivity, [int(iso)])
    if exposure_s is not None:
        t.set(Tag.ExposureTime, [_rational(exposure_s)])
    if f_number is not None:
        t.set(Tag.FNumber, [_rational(f_number)])
    if description:
        t.set(Tag.ImageDescription, description)
    writer = RAW2DNG()
    writer.options(t, path="", compress=False)
    data = bytes(writer.convert(raw))
    return atomic_write(path, data)


def _check_raw(path: Path, raw: np.ndarray, bits: int, black_level: Sequence[int], white_level: int) -> None:
    """Refuse what a DNG of ``bits`` cannot hold, naming the file."""
    if bits not in DNG_BIT_DEPTHS:
        raise ValueError(f"{path}: DNG bit depth must be 12 or 16 (pidng's 14-bit path is broken), got {bits}")
    if raw.dtype != np.uint16 or raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise ValueError(f"{path}: raw data must be a 2-D uint16 array with even sides, got {raw.dtype} {raw.shape}")
    top = (1 << bits) - 1
    if not 0 < white_level <= top:
        raise ValueError(f"{path}: white level {white_level} does not fit {bits} bits")
    if len(black_level) != 4 or any(not 0 <= int(b) < white_level for b in black_level):
        raise ValueError(f"{path}: black level needs four values within 0 … {white_level - 1}, got {list(black_level)}")
    if int(raw.max(initial=0)) > top:
        raise ValueError(f"{path}: raw values up to {int(raw.max())} do not fit {bits} bits")


def _dng_tags(width: int, height: int, bits: int, black_level: Sequence[int], white_level: int, make: str,
              model: str) -> dict:
    """The DNG tags of one uncompressed RGGB tile, by pidng's ``Tag`` name, in the order they are set."""
    from pidng.defs import CFAPattern, CalibrationIlluminant, DNGVersion, Orientation, PhotometricInterpretation  # noqa: PLC0415

    return {
        "ImageWidth": width, "ImageLength": height, "TileWidth": width, "TileLength": height,
        "Orientation": Orientation.Horizontal,
        "PhotometricInterpretation": PhotometricInterpretation.Color_Filter_Array,
        "SamplesPerPixel": 1, "BitsPerSample": bits,
        "CFARepeatPatternDim": [2, 2], "CFAPattern": CFAPattern.RGGB,
        "BlackLevelRepeatDim": [2, 2], "BlackLevel": [int(b) for b in black_level], "WhiteLevel": int(white_level),
        # an identity colour matrix: the data are radiometric, not colour-managed; readers need one
        "ColorMatrix1": [[1, 1], [0, 1], [0, 1], [0, 1], [1, 1], [0, 1], [0, 1], [0, 1], [1, 1]],
        "CalibrationIlluminant1": CalibrationIlluminant.Flash,
        "AsShotNeutral": [[1, 1], [1, 1], [1, 1]],
        "Make": make, "Model": model, "UniqueCameraModel": f"{make} {model}",
        "DNGVersion": DNGVersion.V1_4, "DNGBackwardVersion": DNGVersion.V1_2,
    }
