"""One ``skinlayers render`` in this process, its memory plan against its measured peak:
``python render_memory_run.py JSON``.

JSON: ``maps`` (a maps EXR), ``mode`` (``whole``: a budget nothing exceeds; ``group:G``: the budget that
just admits G bands at a time whole; ``tile:T``: tiles of T px; ``budget:MB``: that budget;
``default``: the budget the command finds here), optional ``config`` (a model settings YAML).

The process's resident memory after its imports is read first; Linux's high-water mark (VmHWM) is then
reset (``/proc/self/clear_refs``) and read after the command. Prints one JSON line: the plan, the
estimate (``plan.peak_bytes``), the memory the command added at its peak, their ratio and the seconds.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import torch


def _status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"/proc/self/status has no {key}")


def _budget_mb(cfg: dict, settings, size: int, mm: float, bands: int) -> float | None:
    """The SKINLAYERS_MEMORY_BUDGET_MB that gives the mode's plan (None: the command's own default)."""
    from skinlayers.model.render.illumination import parse_light
    from skinlayers.model.render.renderer import SkinRenderer
    from skinlayers.formats.resources import USABLE_SHARE
    from skinlayers.model.render.tiles import TooLargeError, plan_render

    mode = cfg["mode"]
    if mode == "default":
        return None
    if mode.startswith("budget:"):
        return float(mode.split(":")[1])
    if mode == "whole" or mode.startswith("tile:"):
        return 1e9
    group = int(mode.split(":")[1])
    light, renderer = parse_light("uniform"), SkinRenderer(settings)
    low, high = 1.0, 1e9  # the least plan budget that still plans G bands a pass, by bisection on the plan itself
    for _ in range(60):
        mid = math.sqrt(low * high)
        try:
            plan = plan_render((1, size, size), mm, bands, light, renderer, mid * 2**20)
        except TooLargeError:
            plan = None
        fits = plan is not None and plan.tile_px is None and (plan.bands_per_pass or bands) >= group
        low, high = (low, mid) if fits else (mid, high)
    # SKINLAYERS_MEMORY_BUDGET_MB caps the whole process: the plan gets its usable share beside what this one holds
    return high / USABLE_SHARE + _status_mb("VmRSS")


def main(cfg: dict) -> dict:
    from skinlayers.formats.exr import float_attribute, read_exr_header
    from skinlayers.formats.maps import MapsError
    from skinlayers.model.cli import _memory_plan
    from skinlayers.model.render.illumination import parse_light
    from skinlayers.model.settings import load_model_settings
    from skinlayers.cli import app
    from typer.main import get_command

    maps = Path(cfg["maps"])
    settings = load_model_settings(Path(cfg["config"]) if cfg.get("config") else None)
    size, _, header = read_exr_header(maps, MapsError)
    mm = float_attribute(header, "mm_per_pixel", maps, MapsError)
    wl = torch.tensor(settings.render_wavelengths_nm, dtype=torch.float64)
    budget = _budget_mb(cfg, settings, size, mm, wl.numel())
    if budget is not None:
        os.environ["SKINLAYERS_MEMORY_BUDGET_MB"] = f"{budget:.3f}"
    tile = int(cfg["mode"].split(":")[1]) if cfg["mode"].startswith("tile:") else 0
    plan = _memory_plan(maps, parse_light("uniform"), wl, settings, torch.device("cpu"), tile, "diffusion")
    args = ["render", str(maps), "-o", str(maps.with_name(maps.stem + "_render")), "--force", "--device", "cpu"]
    args += ["--tile", str(tile)] if tile else []
    args += ["--config", cfg["config"]] if cfg.get("config") else []
    before_mb = _status_mb("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # the high-water mark from here on
    start = time.perf_counter()
    try:
        get_command(app).main(args, standalone_mode=False)
    except SystemExit as stop:
        if stop.code:
            raise
    seconds = time.perf_counter() - start
    added_mb = _status_mb("VmHWM") - before_mb
    estimate_mb = plan.peak_bytes / 2**20
    return {"size": size, "mode": cfg["mode"], "plan": plan.describe(), "tile_px": plan.tile_px,
            "bands_per_pass": plan.bands_per_pass or wl.numel(), "budget_mb": round(plan.budget_bytes / 2**20),
            "estimate_mb": round(estimate_mb), "added_peak_mb": round(added_mb), "resident_before_mb": round(before_mb),
            "ratio": round(added_mb / estimate_mb, 3), "seconds": round(seconds, 1)}


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1]))))
