"""Raw frames: linear photosite values from DNG and camera raws (rawpy / LibRaw), and 2×2 superpixels.

Decoding keeps the sensor's linear values: no demosaicing, no white balance, no gamma. The black level
is subtracted per photosite. rawpy lists black levels by *colour index* (``black_level_per_channel[c]``
for c in ``color_desc``, e.g. R, G, B, G2), not by position in the CFA cell, so the per-photosite black
is ``black_level_per_channel[raw_colors_visible]``; ``raw_pattern`` gives the colour index of each
position of the 2×2 cell.

**Superpixel.** Calibration works on the sum of the four photosites of each Bayer cell, one value per
cell ``(H/2, W/2)``. Under a 10-nm band-pass filter each colour channel sees the same narrow band with
a different sensitivity; summing the cell gives one value whose spectral weight is the *sum* of the
four channel sensitivities (the reflectance per band is defined with exactly that weight),
with four times the signal of a photosite and no demosaicing artefact: no colour channel is ever
interpolated into a position it was not measured at. The price is half the sampling frequency, which the
window's 512 → 256 resampling does not need. Any 2×2 block holds one photosite of every cell position,
so the sum does not depend on the pattern's phase (RGGB, GBRG, …).

Where a superpixel samples the scene depends on the band: its value weighs the four photosites by their
channel's sensitivity, so under blue light it leans towards the blue photosite. ``cell_centroid`` gives
that point from a flat frame (the Spectralon reference); positions found in superpixels convert back to
raw photosites through it (a fraction of a pixel off otherwise: docs/calibration.md, "From
calibration/raw.py"). The
footprint is lopsided too — under blue light mostly the one blue photosite — and ``cell_weights`` gives
it to the window's edge model.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import RawDecodeError

__all__ = ["RawImage", "cell_centroid", "cell_weights", "read_raw", "superpixel", "superpixel_any"]


@dataclass(frozen=True)
class RawImage:
    """One decoded raw frame.

    ``values`` ``(H, W)`` float32: photosite values minus their black level (DN, linear; may be
    negative from read noise). ``saturated`` ``(H, W)`` bool: at or above the saturation threshold.
    ``black_cell`` ``(2, 2)``: the black level of each position of the CFA cell; ``cfa``: the cell's
    colours by position, row-major, e.g. ``"RGGB"``; ``white_level``: the raw value of full scale.
    """

    path: Path
    values: np.ndarray
    saturated: np.ndarray
    black_cell: np.ndarray
    white_level: float
    cfa: str

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.values.shape)  # type: ignore[return-value]

    @property
    def full_scale_dn(self) -> float:
        """Largest signal above black a photosite can hold (DN), from the smallest black of the cell."""
        return float(self.white_level - self.black_cell.min())

    def superpixel(self) -> np.ndarray:
        """Sum of each 2×2 cell ``(H/2, W/2)`` float32 (DN above black)."""
        return superpixel(self.values)

    def superpixel_saturated(self) -> np.ndarray:
        """``(H/2, W/2)`` bool: a cell with any saturated photosite."""
        return superpixel_any(self.saturated)


def read_raw(path: str | Path, saturation_margin: float = 0.01, label: str | None = None) -> RawImage:
    """Decode a Bayer raw file (DNG, CR2, NEF, …) into linear values above black.

    ``saturation_margin``: a photosite whose raw value is at or above ``white − margin · white`` is
    saturated. ``label``: what the frame is (e.g. ``"skin frame, 430 nm"``), put beside the file's name
    in errors. Raises ``FileNotFoundError`` if the file is absent and ``RawDecodeError`` (naming the
    file) if it is corrupt, truncated, or not a 2×2 Bayer raw.
    """
    import rawpy  # noqa: PLC0415 (heavy; only decoding needs it)

    path = Path(path)
    name = f"{path} ({label})" if label else str(path)
    if not path.is_file():
        raise FileNotFoundError(f"{name}: raw file not found")
    try:
        with _quiet_stderr(), rawpy.imread(str(path)) as raw:
            pattern = raw.raw_pattern
            if pattern is None or np.asarray(pattern).shape != (2, 2):
                shape = None if pattern is None else np.asarray(pattern).shape
                raise RawDecodeError(f"{name}: not a 2×2 Bayer raw (CFA pattern {shape}); calibration needs a Bayer sensor")
            pattern = np.asarray(pattern)
            desc = raw.color_desc.decode("ascii", "replace")
            cfa = "".join(desc[int(c)] for c in pattern.reshape(-1))
            if sorted(cfa) != sorted("RGGB"):
                raise RawDecodeError(f"{name}: CFA cell {cfa!r} is not a Bayer R/G/G/B cell")
            black_by_colour = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            values = raw.raw_image_visible.astype(np.float32)
            colours = np.array(raw.raw_colors_visible, copy=True)
            white = float(raw.white_level)
    except RawDecodeError:
        raise
    except Exception as exc:  # noqa: BLE001 (LibRaw reports corrupt and truncated files with several exception types)
        message = exc.args[0].decode(errors="replace") if exc.args and isinstance(exc.args[0], bytes) else str(exc)
        raise RawDecodeError(
            f"{name}: cannot decode raw file ({type(exc).__name__}: {message or 'no detail'}); corrupt or truncated?"
        ) from None
    if values.ndim != 2 or values.shape[0] < 2 or values.shape[1] < 2:
        raise RawDecodeError(f"{name}: raw image has shape {values.shape}, expected a 2-D mosaic")
    if colours.max() >= black_by_colour.size:
        raise RawDecodeError(f"{name}: colour index {int(colours.max())} has no black level")
    black = black_by_colour[colours]
    if not white > float(black.max()):
        raise RawDecodeError(f"{name}: white level {white:g} is not above the black level {float(black.max()):g}")
    saturated = values >= white - saturation_margin * white
    values -= black.astype(np.float32)
    return RawImage(
        path=path,
        values=values,
        saturated=saturated,
        black_cell=black_by_colour[pattern],
        white_level=white,
        cfa=cfa,
    )


@contextmanager
def _quiet_stderr():
    """LibRaw writes its own complaint about a broken file to the process's stderr (file descriptor 2,
    past Python), beside the one-line error this module raises: keep it out of the user's terminal."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def superpixel(values: np.ndarray) -> np.ndarray:
    """Sum of the four photosites of each 2×2 cell: ``(H, W)`` → ``(H // 2, W // 2)`` float32.

    An odd last row or column (no full cell) is dropped.
    """
    h, w = values.shape[0] // 2 * 2, values.shape[1] // 2 * 2
    v = np.asarray(values[:h, :w], dtype=np.float32)
    return v[0::2, 0::2] + v[0::2, 1::2] + v[1::2, 0::2] + v[1::2, 1::2]


def superpixel_any(mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool → ``(H // 2, W // 2)`` bool: true where any photosite of the cell is."""
    h, w = mask.shape[0] // 2 * 2, mask.shape[1] // 2 * 2
    m = mask[:h, :w]
    return m[0::2, 0::2] | m[0::2, 1::2] | m[1::2, 0::2] | m[1::2, 1::2]


def cell_weights(flat: np.ndarray) -> np.ndarray:
    """How much each position of the 2×2 cell weighs in a superpixel of this band ``(2, 2)`` (rows, then
    columns of the cell; sum 1), from a flat frame's values above black ``(H, W)``: each position's mean
    signal (its channel's sensitivity to the band). Equal weights where the frame holds no signal."""
    h, w = flat.shape[0] // 2 * 2, flat.shape[1] // 2 * 2
    weights = np.array([[np.mean(flat[dy:h:2, dx:w:2], dtype=np.float64) for dx in (0, 1)] for dy in (0, 1)])
    weights = np.clip(weights, 0.0, None)
    total = weights.sum()
    return weights / total if total > 0 else np.full((2, 2), 0.25)


def cell_centroid(flat: np.ndarray) -> tuple[float, float]:
    """Where in its 2×2 cell a superpixel of this band samples, ``(x, y)`` in photosites (0.5, 0.5 = the
    cell's centre), from a flat frame's values above black ``(H, W)``: the photosite positions weighted by
    ``cell_weights``."""
    weights = cell_weights(flat)
    return float(weights[:, 1].sum()), float(weights[1, :].sum())
