"""Rendering in tiles (``model/render/tiles.py``): the tiles cover the maps once, the plan fits the budget or
refuses up front, and the tiled image is the whole render's."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model import TABLE2
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.render.tiles import TooLargeError, plan_render, render_tiled, tiles

WL = torch.tensor([450.0, 560.0, 670.0], dtype=torch.float64)
MM = 0.05


@pytest.fixture(scope="module")
def renderer(tmp_path_factory) -> SkinRenderer:
    return SkinRenderer(cache_dir=str(tmp_path_factory.mktemp("tables")))


def test_tile_cores_cover_every_pixel_once_and_halos_stay_inside():
    count = torch.zeros(70, 45, dtype=torch.int32)
    for t in tiles(70, 45, 32, 5):
        count[t.y0:t.y1, t.x0:t.x1] += 1
        assert 0 <= t.ya <= t.y0 < t.y1 <= t.yb <= 70 and 0 <= t.xa <= t.x0 < t.x1 <= t.xb <= 45
        assert t.y0 - t.ya == min(5, t.y0) and t.yb - t.y1 == min(5, 70 - t.y1)
    assert bool((count == 1).all())


def test_the_plan_is_whole_when_it_fits_and_tiles_when_it_does_not(renderer):
    whole = plan_render((1, 512, 512), MM, 9, Light("uniform"), renderer, budget_bytes=1e12)
    assert whole.tile_px is None and whole.peak_bytes == whole.whole_bytes
    for light in (Light("uniform"), Light("window", size_mm=7.5)):  # whole in fewer band passes, any light
        passes = plan_render((1, 512, 512), MM, 9, light, renderer, budget_bytes=whole.whole_bytes / 2)
        assert passes.tile_px is None and passes.bands_per_pass < 9 and passes.peak_bytes <= whole.whole_bytes / 2
    one_band = plan_render((1, 512, 512), MM, 1, Light("uniform"), renderer, budget_bytes=1e12).peak_bytes
    budget = 0.9 * (one_band + 512 * 512 * 8 * 8)  # not even one band whole, the image of nine kept
    tiled = plan_render((1, 512, 512), MM, 9, Light("uniform"), renderer, budget_bytes=budget)
    assert tiled.tile_px is not None and tiled.tile_px < 512 and tiled.peak_bytes <= budget
    assert tiled.halo_px == 100  # the renderer's 5 mm of border at 0.05 mm a pixel
    assert plan_render((1, 512, 512), MM, 9, Light("uniform"), renderer, 1e12, tile_px=128).tile_px == 128


def test_what_cannot_fit_is_refused_with_the_estimate_the_budget_and_the_way_out(renderer):
    with pytest.raises(TooLargeError, match=r"needs about .* the budget is .*only uniform light renders in tiles"):
        plan_render((1, 4000, 4000), MM, 9, Light("window", size_mm=7.5), renderer, budget_bytes=2**30)
    with pytest.raises(TooLargeError, match=r"even in tiles of 64 px .*SKINLAYERS_MEMORY_BUDGET_MB"):
        plan_render((1, 5000, 5000), MM, 9, Light("uniform"), renderer, budget_bytes=2**29)


@pytest.mark.parametrize("bands_per_pass", [None, 1, 2])
def test_tiles_of_uniform_skin_are_the_whole_render(renderer, bands_per_pass):
    maps = SkinMaps.uniform(TABLE2["III interior"], (96, 80), MM)
    with torch.no_grad():
        whole = renderer.render(maps, Light("uniform"), WL).image
    tiled = render_tiled(renderer, maps, Light("uniform"), WL, 32, 20, bands_per_pass=bands_per_pass)
    torch.testing.assert_close(tiled, whole.float(), rtol=2e-6, atol=0)


def test_tiles_refuse_other_lights(renderer):
    maps = SkinMaps.uniform(TABLE2["III interior"], (16, 16), MM)
    with pytest.raises(ValueError, match="uniform light"):
        render_tiled(renderer, maps, Light("window", size_mm=0.5), WL, 8, 4)


def _scene_maps(size: int, mm_per_pixel: float) -> SkinMaps:
    from skinlayers.acquire.simulator.scene import SkinScene, load_scene

    wavelengths = torch.arange(400.0, 701.0, 25.0, dtype=torch.float64)
    return SkinScene(load_scene(None), 0).maps(mm_per_pixel, size, wavelengths)


#: The largest relative difference allowed between the tiled and the whole render of a scene with the
#: default halo (the renderer's 5 mm border): the light that travels farther than the halo
#: (docs/renderer.md, "Tiles").
TILE_TOLERANCE = 3e-4


def _tiled_against_whole(renderer, maps, tile_px, halo_px):
    with torch.no_grad():
        whole = renderer.render(maps, Light("uniform"), WL).image.float()
    tiled = render_tiled(renderer, maps, Light("uniform"), WL, tile_px, halo_px)
    return float(((tiled - whole).abs() / whole.abs()).max())


def test_tiles_of_a_scene_differ_from_the_whole_render_only_by_the_light_beyond_the_halo(renderer):
    """Freckles, a scar, veins and hairs, 24 mm across in 192² px: tiles of 64 px with a 5 mm halo."""
    maps = _scene_maps(192, 0.125)
    halo = plan_render(maps.shape, maps.mm_per_pixel, 3, Light("uniform"), renderer, float("inf"), tile_px=64).halo_px
    assert halo == 40
    close = _tiled_against_whole(renderer, maps, 64, halo)
    near = _tiled_against_whole(renderer, maps, 64, 4)  # a halo of half a millimetre: the neighbours' light is missed
    assert close < TILE_TOLERANCE and near > 10 * close, (close, near)


@pytest.mark.slow
def test_tiles_of_a_camera_sized_patch_match_the_whole_render_on_a_512_crop(renderer):
    """The issue's check at the rig's pixel size (0.0293 mm): a 512² crop in tiles of 256 px, default halo."""
    maps = _scene_maps(512, 7.5 / 256)
    halo = plan_render(maps.shape, maps.mm_per_pixel, 3, Light("uniform"), renderer, float("inf"), tile_px=256).halo_px
    assert _tiled_against_whole(renderer, maps, 256, halo) < TILE_TOLERANCE


def _uniform_maps_file(path, size: int, mm_per_pixel: float):
    from skinlayers.model.patch.maps_io import write_maps

    write_maps(path, SkinMaps.uniform(TABLE2["III interior"], (size, size), mm_per_pixel))
    return path


def test_render_refuses_maps_too_large_for_the_budget_before_reading_them(tmp_path, run_cli, monkeypatch):
    maps = _uniform_maps_file(tmp_path / "maps.exr", 64, 0.1)
    monkeypatch.setenv("SKINLAYERS_MEMORY_BUDGET_MB", "1")
    monkeypatch.setattr("skinlayers.model.patch.maps_io.read_maps", lambda *a, **k: pytest.fail("the maps were read"))
    code, _, err = run_cli("render", str(maps), "-o", str(tmp_path / "out"), "--bands", "560")
    assert code == 1 and "needs about" in err and "even in tiles of 64 px" in err, err
    assert not list(tmp_path.glob("out*")), "nothing written"


def test_render_goes_to_tiles_when_the_whole_does_not_fit(tmp_path, run_cli, monkeypatch):
    from skinlayers.formats.exr import read_spectral

    maps = _uniform_maps_file(tmp_path / "maps.exr", 96, 0.1)
    code, _, err = run_cli("render", str(maps), "-o", str(tmp_path / "whole"), "--bands", "470,560,650")
    assert code == 0, err
    code, out, err = run_cli("render", str(maps), "-o", str(tmp_path / "tiled"), "--bands", "470,560,650", "--tile", "32")
    assert code == 0 and "tiles of 32 px with a 50-px halo" in out, out + err
    whole, _, _ = read_spectral(tmp_path / "whole.exr")
    tiled, _, header = read_spectral(tmp_path / "tiled.exr")
    assert header["tile_px"] == "32"
    torch.testing.assert_close(tiled, whole, rtol=2e-6, atol=0)


def test_the_terms_of_a_large_frame_are_found_a_chunk_of_pixels_at_a_time(renderer, monkeypatch):
    """``series_terms_for`` takes the pixels ``SERIES_TERMS_CHUNK_PX`` at a time (all of a camera's frame at
    once took more memory than the render it plans): any chunk gives the worst pixel's terms, the ones a
    render of all bands at once takes."""
    import skinlayers.model.render.renderer as module

    maps = _scene_maps(48, 0.125)
    with torch.no_grad():
        at_once = renderer.render(maps, Light("uniform"), WL).terms[0]
    whole = renderer.series_terms_for(maps, WL)
    monkeypatch.setattr(module, "SERIES_TERMS_CHUNK_PX", 7)  # many chunks, the last one short
    assert renderer.series_terms_for(maps, WL) == whole == at_once


def test_a_budget_set_by_hand_caps_the_whole_process(monkeypatch):
    """``SKINLAYERS_MEMORY_BUDGET_MB`` is the process's whole budget: a render plans within the usable
    share of what this process leaves of it (its peak lies within about 10% of the estimate)."""
    from skinlayers.formats.resources import USABLE_SHARE, _resident_bytes, memory_budget_bytes, plan_budget_bytes

    monkeypatch.setenv("SKINLAYERS_MEMORY_BUDGET_MB", "4096")
    resident = _resident_bytes()
    assert resident > 50 * 2**20  # this process, torch imported
    assert memory_budget_bytes() == 4096 * 2**20
    assert plan_budget_bytes() == pytest.approx(USABLE_SHARE * (4096 * 2**20 - resident), rel=0.02)
    monkeypatch.setenv("SKINLAYERS_MEMORY_BUDGET_MB", "1")
    assert plan_budget_bytes() == 0.0
    monkeypatch.delenv("SKINLAYERS_MEMORY_BUDGET_MB")
    assert plan_budget_bytes() == pytest.approx(memory_budget_bytes(), rel=0.05)  # the memory available, read twice
