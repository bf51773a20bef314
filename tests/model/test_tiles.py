"""Rendering in tiles (``model/tiles.py``): the tiles cover the maps once, the plan fits the budget or
refuses up front, and the tiled image is the whole render's."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model import TABLE2
from skinlayers.model.illumination import Light
from skinlayers.model.maps import SkinMaps
from skinlayers.model.renderer import SkinRenderer
from skinlayers.model.tiles import TooLargeError, plan_render, render_tiled, tiles

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
    budget = whole.whole_bytes / 2
    tiled = plan_render((1, 512, 512), MM, 9, Light("uniform"), renderer, budget_bytes=budget)
    assert tiled.tile_px is not None and 64 <= tiled.tile_px < 512 and tiled.peak_bytes <= budget
    assert tiled.halo_px == 100  # the renderer's 5 mm of border at 0.05 mm a pixel
    assert plan_render((1, 512, 512), MM, 9, Light("uniform"), renderer, 1e12, tile_px=128).tile_px == 128


def test_what_cannot_fit_is_refused_with_the_estimate_the_budget_and_the_way_out(renderer):
    with pytest.raises(TooLargeError, match=r"needs about .* the budget is .*only uniform light renders in tiles"):
        plan_render((1, 4000, 4000), MM, 9, Light("window", size_mm=7.5), renderer, budget_bytes=2**30)
    with pytest.raises(TooLargeError, match=r"even in tiles of 64 px .*SKINLAYERS_MEMORY_BUDGET_MB"):
        plan_render((1, 5000, 5000), MM, 9, Light("uniform"), renderer, budget_bytes=2**29)


def test_tiles_of_uniform_skin_are_the_whole_render(renderer):
    maps = SkinMaps.uniform(TABLE2["III interior"], (96, 80), MM)
    with torch.no_grad():
        whole = renderer.render(maps, Light("uniform"), WL).image
    tiled = render_tiled(renderer, maps, Light("uniform"), WL, 32, 20)
    torch.testing.assert_close(tiled, whole.float(), rtol=2e-6, atol=0)


def test_tiles_refuse_other_lights(renderer):
    maps = SkinMaps.uniform(TABLE2["III interior"], (16, 16), MM)
    with pytest.raises(ValueError, match="uniform light"):
        render_tiled(renderer, maps, Light("window", size_mm=0.5), WL, 8, 4)
