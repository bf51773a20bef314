"""One timed render in a fresh process (peak memory is per process): ``python render_run.py JSON``.

Prints one JSON line: seconds forward, seconds backward, peak resident memory (MB), device peak (MB).
"""

from __future__ import annotations

import json
import resource
import sys
import time

import torch

from skinlayers.model import ModelSettings, TableSettings
from skinlayers.model.render.illumination import Light
from skinlayers.model.render.memory import trim_heap_on_free
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.settings import RenderSettings


def example(size: int, mm: float, device: str) -> SkinMaps:
    g = torch.Generator().manual_seed(0)
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    c_m = 0.008 * (1 + 0.4 * torch.sin(5 * x + 1) * torch.cos(3 * y))
    for _ in range(12):
        cy, cx, r = torch.rand(3, generator=g)
        c_m = c_m + 0.05 * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (0.0004 + 0.002 * r))
    c_hd = 0.007 * (1 + 0.3 * y)
    full = lambda v: torch.full((1, size, size), v)  # noqa: E731
    return SkinMaps(c_m[None], full(0.4), full(0.002), full(0.0008), c_hd[None], mm).to(device)


def main(cfg: dict) -> dict:
    if cfg.get("trim", True):
        trim_heap_on_free()
    device = cfg.get("device", "cpu")
    render = RenderSettings(**cfg.get("render", {}))
    tables = TableSettings(**cfg.get("tables", {}))
    renderer = SkinRenderer(ModelSettings(render=render, tables=tables, profiles=cfg.get("profiles", "transport"),
                                          handover=cfg.get("handover", "angular")))
    wl = torch.linspace(cfg.get("wl_lo", 420.0), cfg.get("wl_hi", 680.0), cfg["bands"], dtype=torch.float64)
    maps = example(cfg["size"], cfg["mm"], device)
    light = Light("window", size_mm=cfg["size"] * cfg["mm"], border_mm=cfg.get("border_mm", 10.0))
    out = {}
    renderer.model.tables(wl)  # build or load tables outside the timing
    if renderer.settings.profiles == "transport" and renderer.settings.handover == "angular":
        t = time.perf_counter()
        renderer.model.handover_grid(wl)  # once per set of bands, like the tables
        out["handover_grid_s"] = time.perf_counter() - t
    if cfg.get("backward"):
        maps = maps.replace(C_m=maps.C_m.clone().requires_grad_(), C_hd=maps.C_hd.clone().requires_grad_())
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
        torch.cuda.synchronize()
    t = time.perf_counter()
    result = renderer.render(maps, light, wl, blur=cfg.get("blur"), series_terms=cfg.get("terms"))
    if device == "cuda":
        torch.cuda.synchronize()
    out["forward_s"] = time.perf_counter() - t
    if cfg.get("backward"):
        t = time.perf_counter()
        result.exitance.sum().backward()
        if device == "cuda":
            torch.cuda.synchronize()
        out["backward_s"] = time.perf_counter() - t
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if device == "cuda":
        out["peak_device_mb"] = torch.cuda.max_memory_allocated() / 2**20
    out["grid"] = list(result.exitance.shape)
    out["terms"] = result.terms[0]
    if cfg.get("save"):
        torch.save(result.exitance.detach().cpu(), cfg["save"])
    return out


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1]))))
