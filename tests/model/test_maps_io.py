"""The parameter-map format: round trips, and bad files refused with the channel and problem named."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from skinlayers.model.patch.edits import add_absorbance, apply_edit, scale_chromophore, swap_chromophore
from skinlayers.model.patch.maps import MapsError, SkinMaps
from skinlayers.formats.maps import read_absorbance
from skinlayers.model.patch.maps_io import read_maps, write_maps
from skinlayers.formats.exr import read_spectral, write_exr, write_spectral

GOOD = dict(C_m=0.02, beta_m=0.5, C_he=0.002, C_bc=0.001, C_hd=0.006)


def channels(h=6, w=5, **override):
    base = {k: np.full((h, w), v, np.float32) for k, v in GOOD.items()}
    base.update(override)
    return base


def test_round_trip(tmp_path):
    g = torch.Generator().manual_seed(0)
    maps = SkinMaps.uniform(GOOD | {"rho_s": 0.3}, (7, 9), 0.0293)
    maps = maps.replace(C_m=torch.rand(1, 7, 9, generator=g) * 0.1,
                        absorbance=torch.rand(1, 2, 7, 9, generator=g), absorbance_wavelength_nm=torch.tensor([450.0, 600.0]))
    path = write_maps(tmp_path / "m.exr", maps, extra={"residual_rms": torch.zeros(7, 9)})
    back = read_maps(path)
    assert back.mm_per_pixel == pytest.approx(0.0293, rel=1e-7)
    for name in ("C_m", "beta_m", "C_he", "C_bc", "C_hd", "rho_s", "absorbance"):
        torch.testing.assert_close(getattr(back, name), getattr(maps, name), rtol=0, atol=0)
    torch.testing.assert_close(back.absorbance_wavelength_nm, torch.tensor([450.0, 600.0], dtype=torch.float64))


def test_spectral_round_trip(tmp_path):
    img = torch.rand(3, 4, 5, dtype=torch.float64)
    write_spectral(tmp_path / "s.exr", img, torch.tensor([400.0, 500.5, 600.0]), 0.1)
    back, wl, header = read_spectral(tmp_path / "s.exr")
    torch.testing.assert_close(back, img.float())
    assert wl.tolist() == [400.0, 500.5, 600.0] and float(header["mm_per_pixel"]) == pytest.approx(0.1)


@pytest.mark.parametrize(
    "override, attrs, needle",
    [
        ({"C_he": None}, {"mm_per_pixel": 0.03}, "missing channel(s) C_he"),
        ({}, {}, "header attribute mm_per_pixel is missing"),
        ({"C_m": np.full((6, 5), np.nan, np.float32)}, {"mm_per_pixel": 0.03}, "channel C_m has 30 NaN"),
        ({"beta_m": np.full((6, 5), 1.5, np.float32)}, {"mm_per_pixel": 0.03}, "channel beta_m spans 1.5–1.5"),
        ({"C_hd": np.full((6, 5), -0.01, np.float32)}, {"mm_per_pixel": 0.03}, "channel C_hd spans -0.01"),
        ({"C_m": np.full((6, 5), 0.9, np.float32), "C_he": np.full((6, 5), 0.2, np.float32)}, {"mm_per_pixel": 0.03},
         "C_m + C_he + C_bc exceeds 1"),
        ({}, {"mm_per_pixel": -1.0}, "mm_per_pixel must be a pixel size of"),
    ],
)
def test_bad_map_files_are_refused(tmp_path, override, attrs, needle):
    data = channels(**{k: v for k, v in override.items() if v is not None})
    for k, v in override.items():
        if v is None:
            del data[k]
    path = write_exr(tmp_path / "bad.exr", data, attrs)
    with pytest.raises(MapsError) as err:
        read_maps(path)
    assert needle in str(err.value) and str(path) in str(err.value)


def test_unreadable_and_mismatched_files(tmp_path):
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"\x76\x2f\x31\x01 truncated")
    with pytest.raises(MapsError, match="not a readable OpenEXR"):
        read_maps(junk)
    with pytest.raises(MapsError, match="no such file"):
        read_maps(tmp_path / "none.exr")
    ink = write_exr(tmp_path / "ink.exr", {"P_450": np.ones((3, 3), np.float32)}, {"mm_per_pixel": 0.03})
    absorbance, wl, _ = read_absorbance(ink)
    maps = SkinMaps.uniform(GOOD, (6, 5), 0.03)
    with pytest.raises(MapsError, match="does not fit"):
        add_absorbance(maps, absorbance, wl)
    with pytest.raises(MapsError, match="no absorbance channels"):
        read_absorbance(write_exr(tmp_path / "x.exr", {"Q": np.ones((3, 3), np.float32)}, {"mm_per_pixel": 0.03}))


def test_edits():
    maps = SkinMaps.uniform(GOOD, (4, 4), 0.05)
    more_blood = apply_edit(maps, "hemoglobin*1.5")
    assert float(more_blood.C_he.mean()) == pytest.approx(0.003) and float(more_blood.C_hd.mean()) == pytest.approx(0.009)
    assert float(more_blood.C_m.mean()) == pytest.approx(0.02)
    tan = scale_chromophore(maps, "tan", 3.0)
    assert float(tan.C_m.mean()) == pytest.approx(0.06)
    donor = SkinMaps.uniform(GOOD | {"C_hd": 0.05}, (4, 4), 0.05)
    assert float(swap_chromophore(maps, donor, "C_hd").C_hd.mean()) == pytest.approx(0.05)
    inked = add_absorbance(maps, torch.ones(2, 4, 4), torch.tensor([450.0, 650.0]))
    assert inked.absorbance.shape == (1, 2, 4, 4)
    with pytest.raises(ValueError, match="NAME\\*FACTOR"):
        apply_edit(maps, "more blood")
    with pytest.raises(ValueError, match="unknown chromophore"):
        apply_edit(maps, "water*2")
    with pytest.raises(MapsError, match="channel C_m spans 2–2, outside its physical range"):
        apply_edit(maps, "melanin*100")


def test_render_refuses_a_non_numeric_pixel_size_in_one_line(tmp_path, run_cli):
    """The render's memory plan reads the maps' header before the maps' reader does: a non-numeric
    mm_per_pixel is refused there in the reader's words, not a traceback."""
    path = write_exr(tmp_path / "maps.exr", channels(), {"mm_per_pixel": "abc"})
    code, _, err = run_cli("render", str(path), "-o", str(tmp_path / "out"))
    assert code == 1 and "header attribute mm_per_pixel must be a number" in err and "Traceback" not in err
