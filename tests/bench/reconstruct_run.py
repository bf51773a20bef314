"""One timed map fit in a fresh process (peak memory is per process): ``python reconstruct_run.py JSON``.

JSON keys: ``size`` (cube side, px), ``preset`` (Table 2 row), ``seed``, ``noise`` (multiple of
``synthetic_cubes``' camera noise), ``truth_blur`` (fft or pyramid), ``settings`` (FitSettings
overrides), ``threads``, ``device``, ``cube_cache`` (a folder where made cubes are kept between runs).
Prints one JSON line: CPU and wall seconds of the fit, renders, iterations per level, residual RMS,
noise RMS, scale, median errors per parameter (away from the vein), peak resident memory (MB), the
loss history (CPU s, loss, level).
"""

from __future__ import annotations

import importlib.util
import json
import os
import resource
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch

SYNTHETIC = Path(__file__).resolve().parents[1] / "reconstruct" / "synthetic_cubes.py"


def synthetic():
    """The tests' ``synthetic_cubes`` module, loaded by path (test folders are not packages)."""
    spec = importlib.util.spec_from_file_location("skinlayers_tests_synthetic_cubes", SYNTHETIC)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def cube_for(cfg: dict):
    sc = synthetic()
    key = f"cube_{cfg['size']}_{cfg['preset'].replace(' ', '_')}_s{cfg.get('seed', 0)}_n{cfg.get('noise', 1.0)}_{cfg.get('truth_blur', 'pyramid')}.pt"
    cache = cfg.get("cube_cache")
    if cache and (Path(cache) / key).exists():
        return torch.load(Path(cache) / key, weights_only=False)
    syn = sc.make_cube(cfg["size"], seed=cfg.get("seed", 0), preset=cfg["preset"], noise=cfg.get("noise", 1.0),
                       blur=cfg.get("truth_blur", "pyramid"))
    if cache:
        Path(cache).mkdir(parents=True, exist_ok=True)
        torch.save(syn, Path(cache) / key)
    return syn


def main(cfg: dict) -> dict:
    from skinlayers.model import PARAMETER_NAMES
    from skinlayers.reconstruct.mapfit.fit import fit_cube
    from skinlayers.reconstruct.settings import FitSettings

    torch.set_num_threads(int(cfg.get("threads", torch.get_num_threads())))
    syn = cube_for(cfg)
    settings = FitSettings(**cfg.get("settings", {}))
    if cfg.get("warm_tables", True):  # table building is a one-off cost (cached on disk), not the fit's
        from skinlayers.model.render.renderer import SkinRenderer

        SkinRenderer(settings.model).model.tables(syn.cube.wavelength_nm)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    fit = fit_cube(syn.cube, settings, device=cfg.get("device", "cpu"))
    keep = syn.cube.mask & ~syn.vein
    errors = {}
    for n in PARAMETER_NAMES:
        t, f = getattr(syn.truth, n)[0][keep], getattr(fit.maps, n)[0][keep].cpu()
        errors[n] = float((f - t).abs().median()) if n == "beta_m" else float(((f - t).abs() / t).median())
    mask = syn.cube.mask
    return {
        "size": cfg["size"], "preset": cfg["preset"], "method": settings.method, "start": settings.start,
        "coarsest_px": settings.coarsest_px, "threads": torch.get_num_threads(),
        "cpu_s": fit.cpu_s, "wall_s": fit.wall_s, "renders": fit.counter.as_dict(),
        "levels": [(lv["shape"][0], lv["iterations"], lv["converged"], lv["cpu_s"]) for lv in fit.kept_levels],
        "residual_rms": float(fit.residual[:, mask].pow(2).mean().sqrt()),
        "noise_rms": float(syn.noise[:, mask].pow(2).mean().sqrt()),
        "scale": fit.scale, "errors": errors,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rss_before_fit_mb": base_rss,
        "history": [(round(t, 3), loss, lv) for t, loss, lv in fit.history],
    }


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1]))))
