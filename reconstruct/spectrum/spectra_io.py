"""Reading measured reflectance spectra from CSV.

Format: optional ``#`` comment lines, then a header row, then one row per wavelength. The first
column is the wavelength in nm (increasing); every further column is one spectrum, named by its
header, holding reflectance as a fraction 0–1. (The NIST skin reflectance file is such a file.)
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from ...formats.errors import InputError

__all__ = ["MeasuredSpectra", "SpectraFileError", "read_spectra_csv"]


class SpectraFileError(InputError):
    """A spectra file that cannot be used; the message names the file, line and column."""


@dataclass(frozen=True)
class MeasuredSpectra:
    """``names`` (B,), ``wavelength_nm`` (L,), ``reflectance`` (B, L)."""

    names: list[str]
    wavelength_nm: torch.Tensor
    reflectance: torch.Tensor

    def select(self, lo_nm: float, hi_nm: float) -> "MeasuredSpectra":
        keep = (self.wavelength_nm >= lo_nm) & (self.wavelength_nm <= hi_nm)
        if int(keep.sum()) < 6:
            raise SpectraFileError(f"fewer than 6 samples lie within {lo_nm:g}–{hi_nm:g} nm")
        return MeasuredSpectra(self.names, self.wavelength_nm[keep], self.reflectance[:, keep])


def read_spectra_csv(path: str | Path) -> MeasuredSpectra:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise SpectraFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise SpectraFileError(f"{path}: not a text (CSV) file") from None
    lines = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")]
    if len(lines) < 2:
        raise SpectraFileError(f"{path}: expected a header row and at least one data row")
    header_no, header_line = lines[0]
    header = next(csv.reader(io.StringIO(header_line)))
    if len(header) < 2:
        raise SpectraFileError(f"{path}: line {header_no}: expected 'wavelength_nm,<spectrum>,...' with at least two columns")
    names = [h.strip() or f"spectrum_{j}" for j, h in enumerate(header[1:], start=1)]
    wavelengths, rows = [], []
    for line_no, line in lines[1:]:
        cells = next(csv.reader(io.StringIO(line)))
        if len(cells) != len(header):
            raise SpectraFileError(f"{path}: line {line_no}: {len(cells)} columns, the header has {len(header)}")
        values = []
        for j, cell in enumerate(cells):
            try:
                v = float(cell)
            except ValueError:
                col = header[j] if j < len(header) else str(j)
                raise SpectraFileError(f"{path}: line {line_no}, column {col!r}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                col = header[j]
                raise SpectraFileError(f"{path}: line {line_no}, column {col!r}: {cell.strip()} (NaN or infinite)")
            values.append(v)
        wavelengths.append(values[0])
        rows.append(values[1:])
    w = torch.tensor(wavelengths, dtype=torch.float64)
    if bool((torch.diff(w) <= 0).any()):
        raise SpectraFileError(f"{path}: wavelengths in the first column must increase")
    refl = torch.tensor(rows, dtype=torch.float64).T.contiguous()
    if bool((refl < -0.05).any()) or bool((refl > 1.5).any()):
        raise SpectraFileError(
            f"{path}: reflectance must be a fraction 0–1 (found {float(refl.min()):g}–{float(refl.max()):g}; "
            "percent values? divide by 100)"
        )
    return MeasuredSpectra(names, w, refl)
