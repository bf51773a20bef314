"""The simulator's truth render before and after cut 3 (docs/speed.md), side by side in one run (on
demand: ``pytest -m bench tests/bench/test_bench_truth_render.py -s``; about three minutes at 256²).

Per band of the default rig, on the demo's scene at a ``SKINLAYERS_BENCH_CUBE``² cube (default 256: the
582² truth grid and its 3 mm border): the band's three wavelength nodes rendered at once with every
blur pass over the whole image (before), and one node at a time with the passes in cache-sized slabs
(after, ``SimulatedBench.render_band``'s path), alternating, before first. Both must give the same
image to float32 rounding. Writes ``truth_render.csv`` (wall seconds per band and the largest
difference).
"""

from __future__ import annotations

import os
import time

import pytest
import torch

from bench_io import write_csv

pytestmark = pytest.mark.bench


def test_truth_render_per_node_in_slabs_against_at_once(monkeypatch):
    from skinlayers.acquire.simulator.scene import SceneConfig
    from skinlayers.acquire.simulator.simulated import SimulatedBench
    from skinlayers.analyses.truths import demo_scene, session_rig
    from skinlayers.model.render import blur
    from skinlayers.model.render.illumination import Light

    cube = int(os.environ.get("SKINLAYERS_BENCH_CUBE", "256"))
    rig = session_rig(cube)
    bench = SimulatedBench(rig, SceneConfig(**demo_scene()), seed=0, device="cpu")
    maps = bench.scene_maps()
    light = Light("window", size_mm=rig.geometry.window_mm, border_mm=bench.settings.truth.border_mm)
    slab_above = blur.PASS_SLAB_ABOVE_BYTES
    rows = []
    with torch.no_grad():
        for band in rig.bands:
            nodes = torch.tensor(bench.spectra[band.wavelength_nm].nodes_nm)
            monkeypatch.setattr(blur, "PASS_SLAB_ABOVE_BYTES", 2**62)
            start = time.perf_counter()
            before = bench.renderer.render(maps, light, nodes, view_angle_deg=rig.camera.angle_deg).image[0]
            before_s = time.perf_counter() - start
            monkeypatch.setattr(blur, "PASS_SLAB_ABOVE_BYTES", slab_above)
            start = time.perf_counter()
            after = bench._render_nodes(light, nodes)
            after_s = time.perf_counter() - start
            diff = float((after - before).abs().max())
            rows.append({"cube_px": cube, "grid_px": before.shape[-1], "band_nm": band.wavelength_nm,
                         "before_s": round(before_s, 2), "after_s": round(after_s, 2),
                         "ratio": round(before_s / after_s, 2), "max_abs_diff": f"{diff:.1e}"})
    total = {"cube_px": cube, "band_nm": "all", "before_s": round(sum(r["before_s"] for r in rows), 1),
             "after_s": round(sum(r["after_s"] for r in rows), 1)}
    total["ratio"] = round(total["before_s"] / total["after_s"], 2)
    write_csv("truth_render.csv", rows + [total], "the truth's band renders: at once against per node in slabs")
    assert all(float(r["max_abs_diff"]) <= 1e-6 for r in rows)
